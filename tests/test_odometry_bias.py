"""Odometry bias states (swarmloc.models.motion.PlanarPoseBias, the `odometry_bias` setting of
ekf-ccl and ukf-ccl): the augmented model's Jacobian, and both centralized filters recovering a
speed scale and a turn-rate bias injected into synthetic odometry."""

from pathlib import Path

import numpy as np
import pytest

from swarmloc.estimators import REGISTRY
from swarmloc.estimators.ekf.pose import PoseCentralizedEkf
from swarmloc.estimators.ukf.ccl import CentralizedUKF
from swarmloc.models.motion import Odometry, PlanarPose, PlanarPoseBias, reported_dim
from swarmloc.wire.messages import OdometryMsg, RangeBearingMsg, Sensors

SCALE, BIAS = 0.06, 0.03  # injected: the robot moves 6 % faster and turns 0.03 rad/s more than it reports
DT, STEPS = 0.1, 3000
MARKS = {6: (0.0, 0.0), 7: (4.0, 0.0), 8: (4.0, 4.0), 9: (0.0, 4.0)}
SPEED_STD, TURN_STD, RANGE_STD, BEARING_STD = 0.005, 0.01, 0.05, 0.02


def model(walk=(1e-6, 1e-7)) -> PlanarPoseBias:
    return PlanarPoseBias(*walk, speed_scale_std=0.1, turn_rate_bias_std=0.05)


def test_the_jacobian_is_the_derivative_and_without_bias_it_is_planar_pose():
    m = model()
    u = Odometry(DT, 0.3, 0.0, 0.01, 0.0, turn_rate=0.2, turn_rate_std=0.02)
    x = np.array([1.0, -2.0, 0.7, 0.04, -0.01])
    fx, F, Q = m.predict(x, u)
    num = np.column_stack([(m.predict(x + e, u)[0] - m.predict(x - e, u)[0]) / 2e-6 for e in 1e-6 * np.eye(5)])
    np.testing.assert_allclose(F, num, atol=1e-8)
    assert np.all(np.linalg.eigvalsh(Q) >= -1e-15) and Q[3, 3] == pytest.approx(1e-6 * DT)
    base = PlanarPose().predict(x[:3], u)
    zero = m.predict(np.r_[x[:3], 0.0, 0.0], u)
    np.testing.assert_allclose(zero[0][:3], base[0])
    np.testing.assert_allclose(zero[1][:3, :3], base[1])
    np.testing.assert_allclose(zero[2][:3, :3], base[2])
    assert reported_dim(m) == 3 and reported_dim(PlanarPose()) == 3


def frames(seed=3):
    """A robot driving loops among four landmarks at v (1 + SCALE), turning at w + BIAS, while its
    odometry reports v and w with white noise; it sees every landmark within 3.5 m every tick."""
    rng = np.random.default_rng(seed)
    x = np.array([2.0, 0.5, 0.0])
    out, truth = [], []
    for k in range(STEPS):
        v, w = 0.25, 0.25 * np.sin(2 * np.pi * k / 900)
        x = x + np.array([DT * v * (1 + SCALE) * np.cos(x[2]), DT * v * (1 + SCALE) * np.sin(x[2]), DT * (w + BIAS)])
        odo = OdometryMsg(DT, v + SPEED_STD * rng.standard_normal(), 0.0, SPEED_STD, 0.0,
                          w + TURN_STD * rng.standard_normal(), TURN_STD)
        seen = []
        for mid, p in MARKS.items():
            d = np.subtract(p, x[:2])
            r = float(np.hypot(*d))
            if r < 3.5:
                b = float(np.arctan2(d[1], d[0]) - x[2] + BEARING_STD * rng.standard_normal())
                seen.append(RangeBearingMsg(mid, r + RANGE_STD * rng.standard_normal(), (b + np.pi) % (2 * np.pi) - np.pi,
                                            RANGE_STD, BEARING_STD))
        out.append({1: Sensors(k, k * DT, odo, [], landmarks=seen)})
        truth.append(x.copy())
    return out, np.array(truth)


def run(filt, data, state):
    """Feed the filter; (final full state of robot 1, its covariance, mean pose NEES)."""
    stream, truth = data
    nees = []
    for f, xt in zip(stream, truth):
        filt.step(f)
        e = filt.estimate(1)
        assert e.mean.shape == (3,) and e.cov.shape == (3, 3)
        err = xt - e.mean
        err[2] = (err[2] + np.pi) % (2 * np.pi) - np.pi
        nees.append(err @ np.linalg.solve(e.cov, err))
    x, P = state(filt)
    return x, P, float(np.mean(nees[100:]))


@pytest.fixture(scope="module")
def data():
    return frames()


X0, P0 = np.array([2.0, 0.5, 0.0]), np.diag([0.01, 0.01, 0.001])
FILTERS = {
    "ekf-ccl": (lambda bias: PoseCentralizedEkf({1: X0}, {1: P0}, [[i, *p] for i, p in MARKS.items()], bias=bias),
                lambda f: (f.filter.x, f.filter.P)),
    "ukf-ccl": (lambda bias: CentralizedUKF({1: X0 if bias is None else bias.augment(X0, P0)[0]},
                                            P0 if bias is None else bias.augment(X0, P0)[1], bias or "planar-pose",
                                            landmarks=MARKS),
                lambda f: (f.x, f.P)),
}


@pytest.mark.parametrize("name", FILTERS)
def test_the_bias_states_recover_an_injected_scale_and_turn_rate_bias(data, name):
    make, state = FILTERS[name]
    x, P, nees = run(make(model()), data, state)
    sd = np.sqrt(np.diag(P))
    # Each within 3 of its own stds, and those stds small beside the biases: recovered, not guessed.
    assert abs(x[3] - SCALE) < 3 * sd[3] and sd[3] < SCALE / 4, (x[3], sd[3])
    assert abs(x[4] - BIAS) < 3 * sd[4] and sd[4] < BIAS / 4, (x[4], sd[4])
    _, _, plain = run(make(None), data, state)
    # White noise alone is overconfident against a bias that lasts; the states make it consistent.
    assert nees < 6.0 < plain, (nees, plain)


@pytest.mark.parametrize("name", FILTERS)
def test_the_setting_augments_the_centralized_filters_of_a_replay(tmp_path_factory, name):
    """The registry's settings reach both filters from a scenario: blocks of 5 with the setting,
    of 3 without, estimates of the pose alone either way; odometry_bias is refused elsewhere."""
    import mrclam_synth

    from netsim.sim import Simulation
    from swarmloc.experiment import replay
    from swarmloc.experiment.results import RunRecord
    from swarmloc.experiment.runner import InProcessRunner

    path = mrclam_synth.write(tmp_path_factory.mktemp("synth") / "MRCLAM_Synthetic", seed=4)
    sc = replay.replay_scenario(path, estimator="ukf-dcl", duration=20.0, calibration="none")
    record = InProcessRunner(Simulation(sc), {}).run(RunRecord.for_scenario(sc))
    info = REGISTRY[name]
    for on, dim in ((False, 3), (True, 5)):
        ref = info.make_reference(sc, record.ids, info.settings({"odometry_bias": on}))
        for f in record.sensors:
            ref.step(f)
        full = ref.filter.x if name == "ekf-ccl" else ref.x
        assert full.shape == (dim * len(record.ids),)
        e = ref.estimate(record.ids[0])
        assert e.mean.shape == (3,) and e.cov.shape == (3, 3) and np.isfinite(e.cov).all()
    with pytest.raises(ValueError, match="odometry_bias"):
        REGISTRY["ekf-ci"].settings({"odometry_bias": True})


def test_a_scenario_names_a_references_settings_and_the_run_uses_them(tmp_path_factory):
    """reference_params reaches compute_references: ekf-ccl with odometry_bias gives other
    estimates than without, ukf-ccl unnamed keeps its defaults; a bad name or setting is
    refused naming it. `replay_scenario(odometry_bias=True)` (the CLI's --odometry-bias) sets
    it for both centralized filters and says so in its label."""
    import mrclam_synth

    from netsim.sim import Simulation
    from swarmloc.experiment import replay, scenario
    from swarmloc.experiment.results import RunRecord, compute_references
    from swarmloc.experiment.runner import InProcessRunner

    path = mrclam_synth.write(tmp_path_factory.mktemp("synth") / "MRCLAM_Synthetic", seed=4)
    plain = replay.replay_scenario(path, estimator="ukf-dcl", duration=20.0, calibration="none")
    biased = plain.with_overrides(reference_params={"ekf-ccl": {"odometry_bias": True}})
    record = InProcessRunner(Simulation(plain), {}).run(RunRecord.for_scenario(plain))
    traces = {}
    for sc in (plain, biased):
        record.est.pop("ekf-ccl", None), record.est.pop("ukf-ccl", None)
        compute_references(sc, record, ["ekf-ccl", "ukf-ccl"])
        traces[sc is biased] = {n: record.trace(n).mean.copy() for n in ("ekf-ccl", "ukf-ccl")}
    assert not np.array_equal(traces[True]["ekf-ccl"], traces[False]["ekf-ccl"])
    assert np.array_equal(traces[True]["ukf-ccl"], traces[False]["ukf-ccl"])
    with pytest.raises(scenario.ScenarioError, match="reference_params.*kalman"):
        plain.with_overrides(reference_params={"kalman": {}})
    with pytest.raises(scenario.ScenarioError, match="reference_params.*odometry_bias"):
        plain.with_overrides(reference_params={"ekf": {"odometry_bias": True}})
    sc = replay.replay_scenario(path, estimator="ukf-dcl", duration=20.0, calibration="scored", odometry_bias=True)
    assert sc.reference_params == {"ekf-ccl": {"odometry_bias": True}, "ukf-ccl": {"odometry_bias": True}}
    assert sc.estimator.params == {"odometry_bias": True}  # the agents' ukf-dcl with the model of its references
    assert replay.replay_label(sc).endswith("; ukf-dcl, ekf-ccl and ukf-ccl with odometry bias states")
    import yaml

    assert scenario.parse(yaml.safe_load(sc.to_yaml())).reference_params == sc.reference_params


FULL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "mrclam" / "MRCLAM_Dataset6"


@pytest.mark.slow
@pytest.mark.skipif(not FULL.is_dir(), reason="the shared MR.CLAM Dataset6 is not beside the repository")
def test_dataset6_robots_only_bias_states_are_consistent_on_held_out_data():
    """docs/mrclam.md: robots only, each half scored with the noise model and the walk setting
    picked on the other half, EKF-CCL and UKF-CCL with bias states keep their mean NEES within
    twice the state dimension and their position RMSE within 5 % of the white noise of before
    (which was even fitted on the scored data), where the calibrated model without them is
    more than 5 % worse and less consistent."""
    from netsim.study import odometry_bias
    from swarmloc.datasets import calibrate, mrclam
    from swarmloc.experiment import replay

    rec = mrclam.load(FULL)
    halves = calibrate.held_out_split(rec.duration)
    names = odometry_bias.ESTIMATORS
    got = {(n, kind): [] for n in names for kind in ("picked", "off", "before")}
    for fit, scored in (halves, halves[::-1]):
        model = calibrate.calibrate(rec, [fit], 0.1)

        def sc(span, **kw):
            return replay.replay_scenario(FULL, estimator="ukf-dcl", offset=span[0], duration=span[1] - span[0],
                                          landmarks=False, **kw)

        choice = odometry_bias.pick(odometry_bias.score(sc(fit, noise=model), odometry_bias.grid()))
        for n in names:
            rows = odometry_bias.score(sc(scored, noise=model), [choice[n], odometry_bias.OFF], [n])
            got[(n, "picked")].append(rows[0][2]), got[(n, "off")].append(rows[1][2])
        for n, _, m, _ in odometry_bias.score(sc(scored, calibration="none"), [odometry_bias.OFF]):
            got[(n, "before")].append(m)
    for n in names:
        p, o, b = (odometry_bias.pooled(got[(n, kind)]) for kind in ("picked", "off", "before"))
        assert p["nees"]["mean"] <= odometry_bias.NEES_TARGET, (n, p)
        assert p["rmse_m"] <= 1.05 * b["rmse_m"], (n, p, b)
        assert o["rmse_m"] > 1.05 * b["rmse_m"] and p["nees"]["mean"] < o["nees"]["mean"], (n, o, b)


def replay_cli(monkeypatch, *args):
    """`swarmloc replay ARGS` in this process with the swarm's run replaced: (the scenario it would
    run, its output). Nothing is launched."""
    from typer.testing import CliRunner

    import agents.launcher
    from agents.cli import app

    got = []
    monkeypatch.setattr(agents.launcher, "run_swarm", lambda scenario, *a, **kw: got.append(scenario))
    result = CliRunner().invoke(app, ["replay", *map(str, args)])
    assert result.exit_code == 0 and len(got) == 1, (result.output, result.exception)
    return got[0], result.output


BIASED = {"ekf-ccl": {"odometry_bias": True}, "ukf-ccl": {"odometry_bias": True}}


def test_replay_without_landmarks_turns_the_bias_states_on_by_default(tmp_path, monkeypatch):
    """docs/replay.md: without landmarks `swarmloc replay` gives ekf-ccl and ukf-ccl their bias
    states unless told not to, and its label says it is the default; with landmarks, or with the
    uncalibrated white noise of before, they stay off unless asked for."""
    import mrclam_synth

    path = mrclam_synth.write(tmp_path / "MRCLAM_Synthetic", seed=4)
    span = ("--duration", "20", "--fit-on-scored")
    for flags, want, default in ((("--no-landmarks",), BIASED, True),
                                 (("--no-landmarks", "--no-odometry-bias"), {}, False),
                                 (("--no-landmarks", "--odometry-bias"), BIASED, False),
                                 ((), {}, False),
                                 (("--odometry-bias",), BIASED, False),
                                 (("--no-landmarks", "--duration", "20", "--odometry-horizon", "10"), {}, False)):
        sc, out = replay_cli(monkeypatch, path, *(flags if "--odometry-horizon" in flags else (*flags, *span)))
        text = " ".join(out.split())  # rich wraps the label at the terminal's width
        assert sc.reference_params == want, flags
        assert sc.estimator.params.get("odometry_bias", False) == bool(want), flags
        assert ("with odometry bias states" in text) == bool(want), (flags, text)
        assert ("the default without landmarks" in text) == default, (flags, text)


@pytest.mark.slow  # a minute on 2 shared cores: "several seconds or more" (pyproject.toml's markers)
@pytest.mark.skipif(not FULL.is_dir(), reason="the shared MR.CLAM Dataset6 is not beside the repository")
def test_dataset6_the_default_robots_only_replay_is_consistent(monkeypatch):
    """`swarmloc replay Dataset6 --no-landmarks` as it is, scored on the half it scores (the second,
    the noise calibrated on the first): the agents' ukf-dcl and the references ekf-ccl and ukf-ccl
    with the default bias states within a mean NEES of 6 and a position RMSE within 5 % of the
    white noise of before (fitted on the scored data even) (docs/replay.md: 4.2 and 4.3, 0.249
    and 0.250 m against 0.296 and 0.291), ukf-dcl equal to ukf-ccl."""
    from netsim.sim import Simulation
    from swarmloc.experiment.replay import replay_scenario
    from swarmloc.experiment.results import RunRecord, compute_references, metrics
    from swarmloc.experiment.runner import InProcessRunner, make_nodes

    sc, _ = replay_cli(monkeypatch, FULL, "--no-landmarks")
    assert sc.reference_params == BIASED and sc.world.offset > 400  # the second half
    assert sc.estimator.name == "ukf-dcl" and sc.estimator.params == {"odometry_bias": True}
    before = replay_scenario(FULL, offset=sc.world.offset, duration=sc.clock.duration, landmarks=False,
                             calibration="none")
    names = ["ukf-dcl", *BIASED]
    got = {}
    for s in (sc, before):
        record = InProcessRunner(Simulation(s), make_nodes("ukf-dcl", s)).run(RunRecord.for_scenario(s))
        compute_references(s.with_overrides(bound=False), record, list(BIASED))
        got[s is sc] = metrics(record, names)["estimators"]
    assert abs(got[True]["ukf-dcl"]["rmse_m"] - got[True]["ukf-ccl"]["rmse_m"]) < 1e-9
    for name in names:
        now, then = got[True][name], got[False][name]
        assert now["nees"]["mean"] <= 6.0, (name, now["nees"])
        assert now["rmse_m"] <= 1.05 * then["rmse_m"], (name, now["rmse_m"], then["rmse_m"])


def test_ukf_dcl_with_the_bias_states_equals_ukf_ccl_with_them(tmp_path_factory):
    """The same setting gives UKF-DCL the model of its centralized twin: 5-dimensional blocks in
    its chains, estimates of the pose alone, and UKF-CCL's estimates tick by tick (robots only, a
    synthetic recording); a checkpoint (the pose alone) resumes with the biases at their prior."""
    import mrclam_synth

    from netsim.sim import Simulation
    from swarmloc.experiment import replay
    from swarmloc.experiment.results import RunRecord, compute_references
    from swarmloc.experiment.runner import InProcessRunner, make_nodes

    path = mrclam_synth.write(tmp_path_factory.mktemp("synth") / "MRCLAM_Synthetic", seed=4)
    sc = replay.replay_scenario(path, estimator="ukf-dcl", duration=20.0, calibration="none", landmarks=False,
                                odometry_bias=True)
    nodes = make_nodes("ukf-dcl", sc)
    record = InProcessRunner(Simulation(sc), nodes).run(RunRecord.for_scenario(sc))
    compute_references(sc.with_overrides(bound=False), record, ["ukf-ccl"])
    dcl, ccl = record.est["ukf-dcl"], record.est["ukf-ccl"]
    assert len(dcl) > 150 and all(n.x.shape == (5,) for n in nodes.values())
    for k in dcl:
        for a, e in dcl[k].items():
            assert e.mean.shape == (3,) and e.cov.shape == (3, 3)
            assert np.abs(e.mean - ccl[k][a].mean).max() < 1e-10 and np.abs(e.cov - ccl[k][a].cov).max() < 1e-10
    plain = make_nodes("ukf-dcl", sc.with_overrides(**{"estimator.params": {}}))
    assert all(n.x.shape == (3,) for n in plain.values())
    node = nodes[record.ids[0]]
    e = node.estimate()
    node.resume(e.k, e.mean, e.cov)
    assert node.x.shape == (5,) and np.array_equal(node.x[:3], e.mean) and node.x[3:].tolist() == [0.0, 0.0]
