"""The posterior Cramér-Rao bound (swarmloc/experiment/bounds.py): the recursion against closed forms and a
Kalman filter, against the error of the centralized reference over Monte Carlo seeds, against
each family's centralized filter, and where a run reports it (metrics.json, the summary, studies)."""

import io
import json

import numpy as np
import pytest
import scipy.stats

from netsim.sim import Simulation
from swarmloc.experiment import scenario as S
from swarmloc.experiment.bounds import InformationRecursion, pcrb
from swarmloc.experiment.replay import replay_scenario
from swarmloc.experiment.results import compute_references, position_errors
from swarmloc.experiment.rundir import write_run
from swarmloc.experiment.runner import InProcessRunner, make_nodes
from swarmloc.filters import kalman
from swarmloc.models.motion import MOTION_MODELS
from swarmloc.node import odometry_of


def run(sc, estimator="il", references=None):
    record = InProcessRunner(Simulation(sc), make_nodes(estimator, sc)).run()
    compute_references(sc, record, references if references is not None else [])
    return record


def gnss_swarm(**changes):
    """Planar platforms with position fixes and nothing relative: F = I, H = I, Gaussian noise,
    a linear-Gaussian problem whose bound is the Kalman filter's covariance."""
    data = {"version": 1, "name": "linear", "seed": 3, "clock": {"dt": 0.5, "duration": 40.0},
            "world": {"agents": [{"id": i, "start": [30.0 * i, 5.0 * i], "heading": 0.4 * i,
                                  "motion": {"kind": "random", "speed": 1.0 + 0.2 * i}} for i in (1, 2, 3)]},
            "sensors": {"odometry": {"speed_noise": 0.3, "turn_rate_noise": 0.01},
                        "range": {"probability": 0.0},
                        "gnss": {"enabled": True, "noise": 2.0, "to_fault": 0.3, "to_normal": 0.3}},
            "estimation": {"initial_std": 1.5}, "estimator": {"name": "il"}, "references": []}
    return S.parse(data).with_overrides(**changes) if changes else S.parse(data)


# --------------------------------------------------------------------------- the recursion


def test_a_static_platform_with_a_fix_every_tick_has_the_closed_form_bound():
    # No motion noise at all (Q = 0, the singular case) and a 2 m fix every tick: the information
    # of each coordinate after k fixes is 1/s0^2 + k/s^2, exactly.
    sc = gnss_swarm(**{"world.agents": [{"id": 1, "start": [0.0, 0.0], "motion": {"kind": "circle", "speed": 0.0}}],
                       "sensors.odometry.speed_noise": 0.0, "sensors.odometry.turn_rate_noise": 0.0,
                       "sensors.gnss.to_fault": 0.0, "sensors.gnss.to_normal": 0.0})
    record = run(sc)
    b = record.bound
    k = np.arange(len(record.k))  # tick 0 has no fix
    want = np.sqrt(2.0 / (1 / 1.5**2 + k / 2.0**2))
    np.testing.assert_allclose(b.position[:, 0], want, rtol=1e-12)
    assert b.counts["gnss"] == k[-1]


def test_a_linear_gaussian_swarm_has_the_kalman_filters_covariance_as_its_bound():
    sc = gnss_swarm()
    record = run(sc)
    b = record.bound
    assert b.counts["gnss"] > 50 and b.counts["gnss"] < 3 * (len(record.k) - 1)  # outages: fixes come and go
    model = MOTION_MODELS["planar-speed-heading"]
    ids = record.ids
    P = kalman.block_diag([sc.prior(a)[1] for a in ids])
    x = np.zeros(2 * len(ids))
    for ti, frames in enumerate(record.sensors):
        if ti:
            Qs = [model.predict(np.zeros(2), odometry_of(frames[a]))[2] for a in ids]
            x, P = kalman.predict(x, P, np.eye(len(x)), kalman.block_diag(Qs))
        for i, a in enumerate(ids):
            g = frames[a].gnss
            if g is not None:
                H = np.zeros((2, len(x)))
                H[:, 2 * i:2 * i + 2] = np.eye(2)
                x, P, _ = kalman.update(x, P, P @ H.T, H @ P @ H.T + np.eye(2) * g.std**2, np.zeros(2))
        want = [np.sqrt(np.trace(P[2 * i:2 * i + 2, 2 * i:2 * i + 2])) for i in range(len(ids))]
        np.testing.assert_allclose(b.position[ti], want, rtol=1e-9)


def test_the_information_recursion_is_the_kalman_filter_and_the_d_form_on_a_coupled_linear_system():
    rng, other = np.random.default_rng(5), np.random.default_rng(6)
    blocks = {"a": 3, "b": 2, "c": 4}
    n = 9
    rec = InformationRecursion(blocks)
    P = np.diag(rng.uniform(0.5, 2.0, n))
    for name in blocks:
        i = rec.idx(name)
        rec.set_prior(name, P[np.ix_(i, i)])
    for step in range(40):
        Fs = {name: np.eye(s) + 0.3 * rng.standard_normal((s, s)) for name, s in blocks.items()}
        # Rank-deficient process noise on two blocks, none on the third: singular Q.
        Qs = {}
        for name, s in blocks.items():
            G = rng.standard_normal((s, 1 if name != "c" else 0))
            Qs[name] = G @ G.T * 0.2
        F, Q = kalman.block_diag(list(Fs.values())), kalman.block_diag(list(Qs.values()))
        J_prev = rec.J.copy()
        rec.predict({name: (Fs[name], Qs[name]) for name in blocks})
        P = F @ P @ F.T + Q
        Qr = Q + 1e-3 * np.eye(n)
        if step < 3:  # the D-form of Tichavský et al. needs Q^-1: with a regular Q the two agree
            check = InformationRecursion(blocks)
            check.J = J_prev.copy()
            check.predict({name: (Fs[name], Qr[np.ix_(check.idx(name), check.idx(name))]) for name in blocks})
            Qi = np.linalg.inv(Qr)
            D11, D12, D22 = F.T @ Qi @ F, -F.T @ Qi, Qi
            np.testing.assert_allclose(check.J, D22 - D12.T @ np.linalg.solve(J_prev + D11, D12), rtol=1e-8, atol=1e-10)
        rows = []
        for _ in range(2):  # relative measurements between two blocks, and one of a single block
            u, v = rng.choice(list(blocks), 2, replace=False)
            Hu, Hv = rng.standard_normal((2, blocks[u])), rng.standard_normal((2, blocks[v]))
            R = np.diag(rng.uniform(0.2, 1.0, 2))
            rows.append(([u, v], [Hu, Hv], R))
        rows.append((["c"], [rng.standard_normal((1, 4))], np.array([[0.5]])))
        A = other.standard_normal((2, 2))  # and one with correlated noise, from its own draws
        rows.append((["a", "b"], [other.standard_normal((2, 3)), other.standard_normal((2, 2))], A @ A.T + np.eye(2)))
        rec.add(rows)
        for names, Hs, R in rows:
            H = np.zeros((R.shape[0], n))
            for name, Hi in zip(names, Hs):
                H[:, rec.idx(name)] = Hi
            _, P, _ = kalman.update(np.zeros(n), P, P @ H.T, H @ P @ H.T + R, np.zeros(R.shape[0]))
        np.testing.assert_allclose(rec.covariance(), P, rtol=1e-9, atol=1e-12)
        groups = [rec.idx("a")[:2], rec.idx("b"), rec.idx("c")[1:]]  # what pcrb asks: traces of some blocks
        want = [np.sqrt(np.trace(P[np.ix_(g, g)])) for g in groups]
        np.testing.assert_allclose(rec.position_bounds(groups), want, rtol=1e-9)


def test_a_block_without_information_is_left_out_and_couples_to_nothing():
    rec = InformationRecursion({"agent": 2, "target": 2})
    rec.set_prior("agent", np.eye(2))
    rec.add([(["agent", "target"], [np.array([[1.0, 0.0]]), np.array([[-1.0, 0.0]])], np.array([[0.25]]))])
    P = rec.covariance(["target"])
    # One range-like row on a target with no prior: the agent learns nothing, the target is unknown.
    np.testing.assert_allclose(P[:2, :2], np.eye(2), atol=1e-12)
    assert np.isnan(P[2:, 2:]).all()
    rec.add([(["agent", "target"], [np.array([[0.0, 1.0]]), np.array([[0.0, -1.0]])], np.array([[0.25]]))])
    P = rec.covariance(["target"])
    np.testing.assert_allclose(P[2:, 2:], np.eye(2) + 0.25 * np.eye(2), atol=1e-12)  # target = agent + offset


def test_unusable_measurement_rows_are_left_out_and_named():
    rec = InformationRecursion({"a": 2, "b": 2})
    rec.set_prior("a", np.eye(2))
    rec.set_prior("b", np.eye(2))
    good = (["a", "b"], [np.array([[1.0, 0.0]]), np.array([[-1.0, 0.0]])], np.array([[0.25]]))
    rows = [(["a"], [np.array([[np.nan, 1.0]])], np.array([[1.0]])), good,
            (["b"], [np.eye(2)], np.array([[1.0, 2.0], [2.0, 1.0]])),  # R not positive definite
            (["b"], [np.array([[0.0, 1.0]])], np.array([[0.0]]))]  # zero std: infinite weight
    assert rec.add(rows) == [0, 2, 3]
    alone = InformationRecursion({"a": 2, "b": 2})
    alone.set_prior("a", np.eye(2))
    alone.set_prior("b", np.eye(2))
    alone.add([good])
    np.testing.assert_array_equal(rec.J, alone.J)


# --------------------------------------------------------------------------- against estimators


@pytest.mark.slow  # several seconds on two busy cores
def test_the_centralized_references_mse_is_not_below_the_bound_over_seeds():
    """wang2019 (ranges among four planar platforms), 24 seeds of 40 s: per seed the ratio r of
    the summed squared error of UKF-CCL to the summed squared bound over ticks and agents. If the
    bound holds, E[r] >= 1 (to first order; the UKF is close to efficient here, so not far above).
    One seed's r varies a lot (its errors drift together over the run: few independent values),
    so the check is on the seeds' mean, one-sided: it may not fall below 1 by more than the 99%
    t quantile of its own spread, t(0.99, n-1) s / sqrt(n) (about 0.2 here: a bound claiming
    twice the achievable variance, r near 0.5, fails)."""
    base = S.load("wang2019").with_overrides(**{"clock.duration": 40.0})
    r, r_il = [], []
    for seed in range(24):
        record = run(base.with_overrides(seed=100 + seed), "il", ["ukf-ccl"])
        B2 = record.bound.position[1:] ** 2
        for alg, out in (("ukf-ccl", r), ("il", r_il)):
            e2 = position_errors(record, record.trace(alg))[1:] ** 2
            out.append(float(e2.sum() / B2.sum()))
    r, r_il = np.array(r), np.array(r_il)
    n = r.size
    margin = scipy.stats.t.ppf(0.99, n - 1) * r.std(ddof=1) / np.sqrt(n)
    assert r.mean() >= 1.0 - margin, (r, margin)
    assert r_il.mean() > r.mean()  # dead reckoning, which ignores the ranges, sits farther above


def test_the_centralized_filters_covariance_is_the_bound_when_it_linearises_near_the_truth():
    """At small errors an EKF's (or UKF's) covariance is the bound's recursion linearised at its
    estimate instead of the truth: they differ by the Jacobians' change over the error, a few
    percent here (planar: 1-3 m errors at 20-250 m ranges)."""
    sc = S.load("wang2019").with_overrides(**{"clock.duration": 100.0})
    record = run(sc, "il", ["ukf-ccl"])
    tr = record.trace("ukf-ccl")
    std = np.sqrt(np.trace(tr.cov[1:, :, :2, :2], axis1=2, axis2=3))
    ratio = std / record.bound.position[1:]
    assert np.all(np.abs(np.median(ratio, axis=0) - 1.0) < 0.02) and np.all(np.abs(ratio - 1.0) < 0.2)


@pytest.mark.slow  # several seconds on two busy cores
def test_pose_robots_observing_landmarks_and_each_other_have_the_pose_ekfs_covariance_as_bound():
    data = {"version": 1, "name": "pose", "seed": 2, "clock": {"dt": 0.2, "duration": 30.0},
            "world": {"agents": [{"id": i, "model": "planar-pose", "start": [2.0 * i, 0.5 * i], "heading": 0.7 * i,
                                  "motion": {"kind": "random", "speed": 0.3, "turn_rate_std": 0.2}} for i in (1, 2, 3)],
                      "landmarks": [{"id": 50 + j, "position": p} for j, p in enumerate([[-5, -5], [10, -4], [12, 8], [-3, 9]])]},
            "sensors": {"odometry": {"speed_noise": 0.05, "turn_rate_noise": 0.02},
                        "range_bearing": {"enabled": True, "max_range": 8.0, "range_noise": 0.1, "bearing_noise": 0.03}},
            "estimation": {"initial_std": 0.05, "initial_heading_std": 0.02}, "estimator": {"name": "ekf"},
            "references": []}
    sc = S.parse(data)
    record = run(sc, "ekf", ["ekf-ccl"])
    b = record.bound
    assert b.counts["landmark"] > 100 and b.counts["range_bearing"] > 100
    tr = record.trace("ekf-ccl")
    ratio = np.sqrt(np.trace(tr.cov[1:, :, :2, :2], axis1=2, axis2=3)) / b.position[1:]
    assert np.all(np.abs(np.median(ratio, axis=0) - 1.0) < 0.03)
    alone = position_errors(record, record.trace("ekf"))[1:] ** 2
    assert alone.sum() > (b.position[1:] ** 2).sum()  # each robot's own EKF, without the others


@pytest.mark.slow  # several seconds on two busy cores
def test_targets_have_no_bound_until_ranged_from_two_directions_and_then_bound_the_agents_too():
    sc = S.load("wang2022").with_overrides(**{"clock.duration": 160.0})
    record = run(sc, "il")
    b = record.bound
    T = b.target_position[:, 0]
    first = int(np.argmax(np.isfinite(T)))
    seen = [ti for ti, f in enumerate(record.sensors) if any(f[a].targets for a in record.ids)]
    assert seen and first >= seen[0] and np.isnan(T[:first]).all() and np.isfinite(T[first:]).all()
    assert T[-1] < T[first]  # ranging goes on: the target's bound shrinks
    # Without the targets' ranges the agents' own bound would be larger (they anchor the swarm).
    without = S.load("wang2022").with_overrides(**{"clock.duration": 160.0, "sensors.target_range.probability": 0.0})
    b0 = run(without, "il").bound
    assert np.all(b.position[-1] < b0.position[-1])


# --------------------------------------------------------------------------- families over their filters


def test_uas_bound_is_the_joint_ekfs_covariance_with_gnss():
    sc = S.load("goel2node").with_overrides(**{"clock.duration": 8.0, "faults": []})
    record = run(sc, "ekf", ["ekf-ccl"])
    b = record.bound
    assert b.families == {1: "uas-ins", 2: "uas-ins"} and b.counts["gnss"] == 2 * 8 and b.counts["range"] == 2 * 8
    tr = record.trace("ekf-ccl")
    ratio = np.sqrt(np.trace(tr.cov[1:, :, :3, :3], axis1=2, axis2=3)) / b.position[1:]
    assert np.all(np.abs(ratio - 1.0) < 0.01)  # cm-level errors: the Jacobians hardly move


@pytest.mark.slow  # several seconds on two busy cores
def test_vehicle_bound_is_the_ekf_cl_covariance():
    sc = S.load("oliveros3").with_overrides(**{"clock.duration": 4.0})
    record = run(sc, "ekf-cl")
    b = record.bound
    assert b.families == {1: "quadrotor", 2: "quadrotor", 3: "ground-robot"}
    T = len(record.k)  # tick 0's frame has the IMU's attitude and a fix too
    assert b.counts["attitude"] == 3 * T and b.counts["vehicle_relpos"] > 0 and b.counts["gnss"] == T
    tr = record.trace("ekf-cl")
    ratio = np.sqrt(np.trace(tr.cov[1:, :, :3, :3], axis1=2, axis2=3)) / b.position[1:]
    # The EKF adds Q_FLOOR (1e-10 per tick) the world does not have: its covariance may only be
    # larger, by at most what 200 ticks of that floor add to the smallest variance here.
    floor = np.sqrt(1.0 + 3 * T * 1e-10 / np.min(b.position[1:] ** 2))
    assert np.all(ratio > 0.99) and np.all(np.median(ratio, axis=0) < floor + 0.01)


@pytest.mark.slow  # several seconds on two busy cores
def test_a_replay_with_a_vicon_gap_leaves_those_ticks_and_their_measurements_out(tmp_path):
    import mrclam_synth

    path = mrclam_synth.write(tmp_path / "MRCLAM_Synthetic", seed=4, duration=30.0)
    sc = replay_scenario(path, estimator="il", dt=0.1, gate=None)
    record = run(sc, "il", ["ekf-ccl"])
    b = record.bound
    truth_missing = np.isnan(record.truth_array()[:, :, 0])
    assert truth_missing.any() and np.array_equal(np.isnan(b.position), truth_missing)
    assert all("without truth" in k for k in b.skipped)
    assert np.isfinite(b.position[~truth_missing]).all()
    err = position_errors(record, record.trace("ekf-ccl"))[1:]
    ok = np.isfinite(err)
    assert np.sqrt(np.mean(err[ok] ** 2)) > 0.5 * np.sqrt(np.mean(b.position[1:][ok] ** 2))


# --------------------------------------------------------------------------- where the bound is reported


@pytest.mark.slow  # several seconds on two busy cores
def test_metrics_summary_and_plots_carry_the_bound(tmp_path):
    from rich.console import Console

    from agents import summary

    sc = S.load("wang2019").with_overrides(**{"clock.duration": 20.0})
    record = run(sc, "il", ["ukf-ccl"])
    m = write_run(tmp_path, sc, record, ["il", "ukf-ccl"], extra={"wall_time_s": 1.0, "ticks_per_s": 41.0})
    on_disk = json.loads((tmp_path / "metrics.json").read_text())
    T = len(record.k)
    assert set(on_disk["pcrb"]["position_m"]) == {"1", "2", "3", "4"}
    assert all(len(v) == T for v in on_disk["pcrb"]["position_m"].values())
    assert on_disk["pcrb"]["families"] == {str(a): "planar-speed-heading" for a in (1, 2, 3, 4)}
    for alg in ("il", "ukf-ccl"):
        e = m["estimators"][alg]
        assert e["pcrb_m"] > 0 and e["rmse_over_pcrb"] == pytest.approx(e["rmse_m"] / e["pcrb_m"])
        assert all(v["pcrb_m"] > 0 and v["rmse_over_pcrb"] > 0 for v in e["agents"].values())
    assert m["estimators"]["il"]["pcrb_m"] == m["estimators"]["ukf-ccl"]["pcrb_m"]  # one problem, one bound
    buf = io.StringIO()
    summary.print_summary(tmp_path, [], ui=Console(file=buf, width=250))
    assert "RMSE / PCRB" in buf.getvalue() and "PCRB" in buf.getvalue()
    assert (tmp_path / "plots" / "position_error.png").is_file()


def copy_record(record, truth=None):
    from swarmloc.experiment.results import RunRecord

    out = RunRecord(record.ids, record.dims[0].item())
    for ti, (k, t, frames) in enumerate(zip(record.k, record.t, record.sensors)):
        x = record.truth[ti] if truth is None else truth[ti]
        out.add_tick(k, t, frames, {a: x[i] for i, a in enumerate(record.ids)})
    return out


def test_measurements_of_an_agent_without_truth_are_left_out():
    sc = S.load("wang2019").with_overrides(**{"clock.duration": 60.0, "sensors.range.probability": 1.0})
    record = run(sc)
    truth = record.truth_array().copy()
    truth[40:60, 1] = np.nan  # agent 2 untracked for 20 ticks
    gap = copy_record(record, truth)
    b = pcrb(sc, gap)
    involved = sum(1 for f in record.sensors[40:60] for a, s in f.items() for r in s.ranges if 2 in (a, r.target))
    assert involved > 0 and b.skipped["range of an agent without truth"] == involved
    assert np.isnan(b.position[40:60, 1]).all() and np.isfinite(b.position[40:60, [0, 2, 3]]).all()
    full = record.bound
    assert np.all(b.position[60:] >= full.position[60:] - 1e-12)  # less information: a bound at least as large


def test_a_bound_that_cannot_be_computed_is_reported_not_raised():
    from swarmloc.experiment.results import compute_bound, metrics

    sc = S.load("wang2019").with_overrides(**{"clock.duration": 2.0})
    broken = copy_record(run(sc))
    bad = sc.with_overrides(**{"estimation.initial_std": 1e-200})  # a prior whose inverse overflows
    compute_bound(bad, broken)
    assert broken.bound is None and "LinAlgError" in broken.bound_error
    pcrb_part = metrics(broken, [])["pcrb"]
    assert pcrb_part["error"] == broken.bound_error and set(pcrb_part) == {"error", "wall_s", "cpu_s"}


@pytest.mark.slow  # several seconds on two busy cores
def test_a_run_whose_bound_fails_keeps_every_number_plot_and_summary_line(tmp_path, monkeypatch):
    # Any failure inside the bound, not only the linear algebra's: the run is written as without it.
    from rich.console import Console

    from agents import summary
    from swarmloc.experiment import bounds

    sc = S.load("wang2019").with_overrides(**{"clock.duration": 10.0})
    plain = run(sc.with_overrides(bound=False), "il", ["ukf-ccl"])
    assert plain.bound is None and plain.bound_error is None and plain.bound_time is None  # bound: false skips it

    def broken(*_):
        raise RuntimeError("a bug in the bound")
    monkeypatch.setattr(bounds, "pcrb", broken)
    failed = run(sc, "il", ["ukf-ccl"])
    assert failed.bound is None and failed.bound_error == "RuntimeError: a bug in the bound"
    extra = {"wall_time_s": 1.0, "ticks_per_s": 21.0}
    m_plain = write_run(tmp_path / "plain", sc, plain, ["il", "ukf-ccl"], extra=extra, plots=False)
    m_failed = write_run(tmp_path / "failed", sc, failed, ["il", "ukf-ccl"], extra=extra)
    assert "pcrb" not in m_plain and m_failed["pcrb"]["error"] == failed.bound_error
    assert m_failed["estimators"] == m_plain["estimators"]  # same numbers, none missing
    assert all("pcrb_m" not in e for e in m_failed["estimators"].values())
    assert (tmp_path / "failed" / "plots" / "position_error.png").is_file()
    for name, warned in (("plain", False), ("failed", True)):
        buf = io.StringIO()
        summary.print_summary(tmp_path / name, [], ui=Console(file=buf, width=250))
        out = buf.getvalue()
        assert "RMSE / PCRB" not in out and "il" in out and "ukf-ccl" in out
        assert ("no PCRB for this run (RuntimeError: a bug in the bound)" in out) == warned


def test_the_ratio_is_taken_over_the_ticks_the_metrics_keep():
    from swarmloc.experiment.results import metrics

    sc = S.load("wang2019").with_overrides(**{"clock.duration": 10.0})
    record = run(sc)
    kept = np.asarray(record.t) >= 5.0 - 1e-9  # metrics(since=5): ticks with t >= 5 s
    m = metrics(record, ["il"], since=5.0)
    err = position_errors(record, record.trace("il"))
    for ci, a in enumerate(record.ids):
        e = m["estimators"]["il"]["agents"][str(a)]
        b = record.bound.position[kept, ci]
        assert e["pcrb_m"] == pytest.approx(np.sqrt(np.mean(b**2)))
        assert e["rmse_over_pcrb"] == pytest.approx(np.sqrt(np.mean(err[kept, ci] ** 2)) / e["pcrb_m"])
        assert m["pcrb"]["rms_m"][str(a)] == pytest.approx(e["pcrb_m"])
