"""netsim/world/uas.py: the truth and sensor frames of a scenario's UAS (UasFleet)."""

import math

import numpy as np
import pytest

from netsim.world import uas as uas_world
from netsim.world.uas import UasFleet
from swarmloc.experiment.scenario import parse
from swarmloc.models import ins
from swarmloc.models.motion import UasIns

MOTIONS = ({"kind": "figure8", "width": 150.0, "climb": 5.0, "phase": 0.7, "heading": 0.3},
           {"kind": "orbit", "radius": 40.0, "speed": 8.0, "phase": 1.0, "clockwise": True},
           {"kind": "random3d"})
NO_NOISE = {"gyro_arw": 0.0, "accel_vrw": 0.0, "gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}


def scenario(n=3, sensors=None, clock=None, estimation=None, seed=0):
    agents = [{"id": i, "model": "uas-ins", "start": [30.0 * i, -20.0 * i, 50.0 + 5.0 * i],
               "motion": MOTIONS[i % len(MOTIONS)]} for i in range(n)]
    return parse({"version": 1, "name": "fleet", "seed": seed, "clock": clock or {"dt": 0.1, "duration": 10},
                  "world": {"agents": agents}, "sensors": sensors or {}, "estimation": estimation or {},
                  "estimator": {"name": "ekf"}})


def fleet(sc, seed=0, ids=None):
    return UasFleet(sc, sc.localized_ids if ids is None else ids, seed)


def run(f, ticks, gnss_ok=lambda a: True):
    return [f.step(k, gnss_ok) for k in range(ticks + 1)]


def test_trajectories_start_at_start_and_tick0_is_alignment_only():
    sc = scenario(6)
    f = fleet(sc)
    frames = f.step(0)
    for a in sc.agent_ids:
        start = np.array(sc.agent(a).start)
        np.testing.assert_allclose(f.positions()[a], start, atol=1e-9)
        np.testing.assert_allclose(f.states()[a][:3], start, atol=1e-9)
        fr = frames[a]
        assert fr["imu"] is None and fr["gnss"] is None and fr["pseudoranges"] is None
        assert fr["relpos"] == [] and fr["ranges"] == [] and fr["align"] is not None
    assert f.dt == 0.1
    frames = f.step(1)
    assert frames[0]["align"] is None and frames[0]["imu"].samples.shape == (10, 6) and frames[0]["imu"].dt == 0.01
    with pytest.raises(ValueError, match="expected tick 2"):
        f.step(3)


def test_imu_samples_are_consistent_with_the_truth():
    """Mechanizing the samples from the true initial state (true biases included) stays on the
    true trajectory: the samples, the truth and the biases in `states` agree."""
    sc = scenario(3, sensors={"imu": {**NO_NOISE}})  # turn-on biases kept, no noise or bias walk
    f = fleet(sc, seed=3)
    f.step(0)
    est = {a: UasIns.unpack(f.states()[a]) for a in f.ids}
    assert any(np.abs(e.accel_bias).max() > 1e-3 for e in est.values())
    for k in range(1, 101):
        frames = f.step(k)
        for a in f.ids:
            m = frames[a]["imu"]
            for row in m.samples:
                est[a] = ins.mechanize(est[a], ins.ImuSample(row[:3], row[3:]), m.dt)
    for a in f.ids:
        err = UasIns().error(f.states()[a], UasIns.pack(est[a]))
        assert np.linalg.norm(err[ins.POS]) < 1e-3, a  # 10 s of flight, tens of m/s
        assert np.linalg.norm(err[ins.VEL]) < 1e-3
        assert np.linalg.norm(err[ins.ATT]) < 1e-5
        # The truth moves: more than 50 m along the path in 10 s.
        assert np.linalg.norm(f.positions()[a] - sc.agent(a).start) > 20.0


def test_truth_biases_are_those_of_the_next_imu_interval():
    """With only biases (walking) on the IMU, a sample minus the perfect IMU's sample is the
    bias in force; the biases in `states` at tick k are those of tick k + 1's first interval."""
    walk = {"gyro_arw": 0.0, "accel_vrw": 0.0, "gyro_bias_rw": 1e-3, "accel_bias_rw": 1e-2}
    perfect = {**NO_NOISE, "gyro_bias_sigma0": 0.0, "accel_bias_sigma0": 0.0}
    biased, ideal = fleet(scenario(3, sensors={"imu": walk})), fleet(scenario(3, sensors={"imu": perfect}))
    biased.step(0)
    ideal.step(0)
    assert all(np.all(x[9:15] == 0.0) for x in ideal.states().values())
    for k in range(1, 31):
        before = biased.states()
        fb, fi = biased.step(k), ideal.step(k)
        for a in biased.ids:
            d = fb[a]["imu"].samples - fi[a]["imu"].samples
            np.testing.assert_allclose(d[0], before[a][9:15], atol=1e-9)
            assert np.abs(d[-1] - d[0]).max() > 0  # it walks within the tick


def test_gnss_fix_cadence_receivers_and_noise():
    sensors = {"gnss": {"enabled": True, "noise": 1.5, "noise_vertical": 3.0, "agents": [0, 2]}, "epoch": 0.5}
    sc = scenario(3, sensors=sensors)
    frames = run(fleet(sc), 100)
    for k, fr in enumerate(frames):
        has = {a for a in fr if fr[a]["gnss"] is not None}
        assert has == ({0, 2} if k >= 1 and k % 5 == 0 else set()), k
        assert all(fr[a]["pseudoranges"] is None for a in fr)
    g = frames[5][0]["gnss"]
    assert g.std == 1.5 and g.std_vertical == 3.0 and g.position.shape == (3,)
    # Errors against the truth: per-axis std as specified (20 epochs x 2 receivers x many seeds).
    errs = []
    for seed in range(15):
        f = fleet(sc, seed=seed)
        f.step(0)
        for k in range(1, 101):
            fr = f.step(k)
            for a in (0, 2):
                if fr[a]["gnss"] is not None:
                    errs.append(fr[a]["gnss"].position - f.positions()[a])
    errs = np.array(errs)
    np.testing.assert_allclose(errs.std(axis=0), [1.5, 1.5, 3.0], rtol=0.15)
    assert np.all(np.abs(errs.mean(axis=0)) < 0.3)


def test_gnss_outage_shifts_no_draw():
    """An outage of agent 2 removes its fixes and changes nothing else, during or after it."""
    sc = scenario(3, sensors={"gnss": {"enabled": True}, "epoch": 0.5})
    base = run(fleet(sc), 100)
    f = fleet(sc)
    frames = []
    for k in range(101):
        frames.append(f.step(k, lambda a, k=k: not (a == 2 and 20 <= k < 60)))
    for k in range(101):
        for a in (0, 1, 2):
            g, g0 = frames[k][a]["gnss"], base[k][a]["gnss"]
            if a == 2 and 20 <= k < 60:
                assert g is None
            elif g0 is None:
                assert g is None
            else:
                np.testing.assert_array_equal(g.position, g0.position)


def test_pseudoranges_carry_geometry_clock_and_noise():
    sensors = {"gnss": {"enabled": True, "kind": "pseudorange", "pseudorange_noise": 0.8, "mask_deg": 15.0}}
    sc = scenario(4, sensors=sensors, clock={"dt": 0.2, "duration": 10})
    f = fleet(sc, seed=5)
    f.step(0)
    res, clocks = [], []
    for k in range(1, 51):
        fr = f.step(k)
        for a in f.ids:
            pr = fr[a]["pseudoranges"]
            if k % 5:
                assert pr is None and fr[a]["gnss"] is None
                continue
            p, clock = f.positions()[a], f.states()[a][15]
            assert pr.std == 0.8 and len(pr.rho) >= 4 and pr.sats.shape == (len(pr.rho), 3)
            d = pr.sats - p
            assert np.all(np.degrees(np.arcsin(d[:, 2] / np.linalg.norm(d, axis=1))) >= 15.0)
            res.extend(pr.rho - np.linalg.norm(d, axis=1) - clock)
            clocks.append(clock)
    res = np.array(res)
    assert len(res) > 150
    assert abs(res.mean()) < 4 * 0.8 / math.sqrt(len(res))
    assert res.std() == pytest.approx(0.8, rel=0.15)
    assert np.ptp(clocks) > 1.0  # the clock is arbitrary, not zero


def test_relative_positions_and_all_pairs_ranges():
    sensors = {"relpos": {"enabled": True, "noise": 0.05, "max_range": 60.0},
               "range": {"all_pairs": True, "noise": 0.3, "max_range": 80.0}}
    sc = scenario(5, sensors=sensors)
    f = fleet(sc)
    f.step(0)
    seen_rel = seen_rng = 0
    for k in range(1, 51):
        fr = f.step(k)
        P = f.positions()
        for a in f.ids:
            if k % 10:
                assert fr[a]["relpos"] == [] and fr[a]["ranges"] == []
                continue
            rel, rng = fr[a]["relpos"], fr[a]["ranges"]
            assert [m.target for m in rel] == [b for b in f.ids if b != a and np.linalg.norm(P[b] - P[a]) <= 60.0]
            assert [m.target for m in rng] == [b for b in f.ids if b != a and np.linalg.norm(P[b] - P[a]) <= 80.0]
            for m in rel:
                assert m.std == 0.05
                np.testing.assert_allclose(m.z, P[m.target] - P[a], atol=5 * 0.05)
            for m in rng:
                assert m.std == 0.3 and m.range == pytest.approx(np.linalg.norm(P[m.target] - P[a]), abs=5 * 0.3)
            seen_rel += len(rel)
            seen_rng += len(rng)
    assert seen_rel > 0 and seen_rng > seen_rel  # the range reaches farther
    # Without all_pairs, UAS do not range.
    f = fleet(scenario(3, sensors={"relpos": {"enabled": True}}))
    assert all(fr[a]["ranges"] == [] for fr in run(f, 20) for a in fr)


def test_ranges_once_per_pair_draw_what_both_ends_drew():
    """both_ends: false keeps, of each pair, the lower id's range, the very draw it had with both
    ends measuring (a full row is drawn either way)."""
    both = {"range": {"all_pairs": True, "noise": 0.3}}
    once = {"range": {"all_pairs": True, "noise": 0.3, "both_ends": False}}
    fb, fo = fleet(scenario(4, sensors=both)), fleet(scenario(4, sensors=once))
    fb.step(0)
    fo.step(0)
    for k in range(1, 21):
        rb, ro = fb.step(k), fo.step(k)
        for a in fo.ids:
            assert [m.target for m in ro[a]["ranges"]] == ([b for b in fo.ids if b > a] if k % 10 == 0 else [])
            kept = {m.target: m.range for m in rb[a]["ranges"] if m.target > a}
            assert {m.target: m.range for m in ro[a]["ranges"]} == kept


def test_relative_epoch_runs_ranges_and_relative_positions_on_their_own_clock():
    sensors = {"gnss": {"enabled": True, "kind": "position", "noise": 0.02}, "relpos": {"enabled": True},
               "range": {"all_pairs": True, "noise": 0.02}, "epoch": 1.0, "relative_epoch": 0.3}
    f = fleet(scenario(3, sensors=sensors))
    for k, fr in enumerate(run(f, 30)):
        for a in f.ids:
            assert (fr[a]["gnss"] is not None) == (k > 0 and k % 10 == 0)
            assert bool(fr[a]["ranges"]) == bool(fr[a]["relpos"]) == (k > 0 and k % 3 == 0)
    # The GNSS draws do not depend on when the relative measurements come.
    g = fleet(scenario(3, sensors={**sensors, "relative_epoch": None}))
    fixes = [fr[0]["gnss"].position for fr in run(g, 30) if fr[0]["gnss"] is not None]
    f2 = fleet(scenario(3, sensors=sensors))
    np.testing.assert_array_equal(fixes, [fr[0]["gnss"].position for fr in run(f2, 30) if fr[0]["gnss"] is not None])
    with pytest.raises(Exception, match="relative_epoch"):
        scenario(3, sensors={**sensors, "relative_epoch": 0.25})


def _flat(frames, states):
    out = []
    for fr, st in zip(frames, states):
        for a in sorted(fr):
            d = fr[a]
            out.append(st[a])
            if d["imu"] is not None:
                out.append(d["imu"].samples)
            for key in ("gnss",):
                if d[key] is not None:
                    out.append(d[key].position)
            if d["pseudoranges"] is not None:
                out.extend([d["pseudoranges"].sats, d["pseudoranges"].rho])
            out.extend(m.z for m in d["relpos"])
            out.extend(np.array([m.range]) for m in d["ranges"])
            if d["align"] is not None:
                out.extend([d["align"].x, d["align"].P])
    return out


def _record(f, ticks):
    frames, states = [], []
    for k in range(ticks + 1):
        frames.append(f.step(k))
        states.append(f.states())
    return _flat(frames, states)


def test_deterministic_for_a_seed_and_streams_independent():
    sensors = {"gnss": {"enabled": True, "kind": "pseudorange"}, "relpos": {"enabled": True},
               "range": {"all_pairs": True}, "epoch": 0.5}
    sc = scenario(4, sensors=sensors)
    a, b = _record(fleet(sc, seed=11), 30), _record(fleet(sc, seed=11), 30)
    assert len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b))
    c = _record(fleet(sc, seed=12), 30)
    assert not all(np.array_equal(x, y) for x, y in zip(a, c))
    # Agent order does not matter, and enabling relative sensors does not change the IMU or truth.
    rev = _record(UasFleet(sc, list(reversed(sc.localized_ids)), 11), 30)
    assert all(np.array_equal(x, y) for x, y in zip(a, rev))
    plain = fleet(scenario(4, sensors={"gnss": {"enabled": True, "kind": "pseudorange"}, "epoch": 0.5}), seed=11)
    full = fleet(sc, seed=11)
    for k in range(31):
        p, q = plain.step(k), full.step(k)
        for i in plain.ids:
            if k:
                np.testing.assert_array_equal(p[i]["imu"].samples, q[i]["imu"].samples)
        for i in plain.ids:
            np.testing.assert_array_equal(plain.states()[i], full.states()[i])
    # A subset fleet flies the same agents the same way.
    sub = UasFleet(sc, [1, 3], 11)
    whole = fleet(sc, seed=11)
    for k in range(11):
        s, w = sub.step(k), whole.step(k)
    np.testing.assert_array_equal(s[3]["imu"].samples, w[3]["imu"].samples)


def test_batching_changes_numbers_only_by_rounding(monkeypatch):
    sc = scenario(2, sensors={"gnss": {"enabled": True}})
    a = _record(fleet(sc, seed=4), 45)
    monkeypatch.setattr(uas_world, "CHUNK_SECONDS", 0.3)
    b = _record(fleet(sc, seed=4), 45)
    assert len(a) == len(b)
    for x, y in zip(a, b):
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12)


def test_alignment_error_matches_its_covariance():
    n = 150
    sc = scenario(n, estimation={"initial_std": 0.5})
    seed = 7
    f = fleet(sc, seed=seed)
    frames = f.step(0)
    P = frames[0]["align"].P
    std = np.sqrt(np.diag(P))
    np.testing.assert_allclose(std[:9], [0.5] * 3 + [0.1] * 3 + [math.radians(0.5)] * 3)
    np.testing.assert_allclose(std[9:], [4.85e-4] * 3 + [2.94e-2] * 3 + [10.0])
    model = UasIns()
    z = []
    for a in f.ids:
        x = frames[a]["align"].x
        err = model.error(f.states()[a], x)
        # The error is the alignment stream's draw, exactly (attitude included).
        draw = std * uas_world.stream(seed, "align", a).standard_normal(16)
        np.testing.assert_allclose(err, draw, rtol=1e-9, atol=1e-12)
        z.append(err / std)
    z = np.array(z)
    assert np.all(np.abs(z.mean(axis=0)) < 4 / math.sqrt(n))
    np.testing.assert_allclose(z.std(axis=0), 1.0, atol=0.2)
    nees = np.mean(np.sum(z**2, axis=1))
    assert nees == pytest.approx(16.0, abs=1.5)
    # The truth's clock at turn-on is arbitrary: N(0, 10^2).
    clocks = np.array([f.states()[a][15] for a in f.ids])
    assert clocks.std() == pytest.approx(10.0, rel=0.2)
    # initial_error false: the alignment is the truth.
    sc = scenario(3, estimation={"initial_error": False})
    f = fleet(sc)
    frames = f.step(0)
    for a in f.ids:
        np.testing.assert_allclose(frames[a]["align"].x, f.states()[a], atol=1e-12)


def test_clear_errors():
    with pytest.raises(ValueError, match=r"clock.dt \* sensors.imu.rate_hz"):
        fleet(scenario(1, sensors={"imu": {"rate_hz": 95.0}}))
    with pytest.raises(ValueError, match=r"sensors.epoch / clock.dt"):
        fleet(scenario(1, sensors={"epoch": 0.25}))
    sc = parse({"version": 1, "name": "mix", "world": {"agents": [
        {"id": 0, "model": "uas-ins", "start": [0, 0, 50]}, {"id": 1, "model": "ground-station", "start": [0, 0, 0]}]},
        "estimator": {"name": "ekf"}})
    with pytest.raises(ValueError, match=r"\[1\] are not uas-ins"):
        UasFleet(sc, [0, 1], 0)
    UasFleet(sc, [0], 0).step(0)
