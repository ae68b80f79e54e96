"""swarmloc calibrate: noise models of a recording fitted against its ground truth, noise.yaml,
the replay through them, and the default replay scoring what its noise was not fitted to."""

import math
from pathlib import Path

import mrclam_synth
import numpy as np
import pytest

from netsim.sim import Simulation
from netsim.world.recorded import ReplayWorld
from swarmloc.datasets import calibrate, mrclam
from swarmloc.experiment import replay, scenario
from swarmloc.experiment.results import RunRecord, compute_references, metrics
from swarmloc.experiment.runner import InProcessRunner

ROOT = Path(__file__).resolve().parents[1]
FULL = ROOT.parent / "shared" / "data" / "mrclam" / "MRCLAM_Dataset6"
DT = 0.1
SPEED_SCALE, RANGE_BIAS, BEARING_BIAS, RANGE_REL, BEARING_STD = 0.9, (0.05, -0.1), 0.01, 0.01, 0.01


@pytest.fixture(scope="module")
def biased(tmp_path_factory):
    """Known systematic errors and white noise of known sizes (mrclam_synth)."""
    return mrclam_synth.write(tmp_path_factory.mktemp("biased") / "MRCLAM_Biased", duration=120.0, seed=7,
                              speed_scale=SPEED_SCALE, range_bias=RANGE_BIAS, bearing_bias=BEARING_BIAS,
                              range_rel_std=RANGE_REL, bearing_std=BEARING_STD)


@pytest.fixture(scope="module")
def coloured(tmp_path_factory):
    """A speed error correlated over a second, six times the white one per tick."""
    return mrclam_synth.write(tmp_path_factory.mktemp("coloured") / "MRCLAM_Coloured", duration=120.0, seed=3,
                              colour_std=0.03, colour_tau=1.0)


def lstsq_se(X: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Standard errors of weighted least-squares coefficients with residual stds sigma."""
    W = X / sigma[:, None]
    return np.sqrt(np.diag(np.linalg.inv(W.T @ W)))


def test_calibrate_recovers_a_known_noise_model(biased):
    rec = mrclam.load(biased)
    T, horizon = rec.duration, 1.0
    # In sample (folds 1): the stds of the fit's own residuals, which a known model's white noise
    # sets; cross-validated, they also hold what the corrections miss on data they did not see.
    model = calibrate.calibrate(rec, dt=DT, horizon=horizon, folds=1)
    crossed = calibrate.calibrate(rec, dt=DT, horizon=horizon, folds=2)
    for r in model.robots:
        assert crossed.robots[r].odometry.speed_std >= model.robots[r].odometry.speed_std
    # The std of an overlapping-batch-means std over T s at horizon H: about sqrt(H / (3 T)) of it.
    std_tol = 4 * math.sqrt(horizon / (3 * T))
    full = [r for r, n in model.robots.items() if n.landmarks.range_bias[3] != 0]
    assert len(full) >= 2  # a robot whose halves see other bearings keeps a simpler model: its own fit is not this
    for r, n in model.robots.items():
        o = n.odometry
        # The lag is mrclam.estimate_odometry_lag's (tested in test_mrclam.py); this recording's
        # slowly varying commands pin it only to about 0.1 s, its turn rate (in proportion to the
        # speed) not at all better: the turn rate keeps the speed's lag.
        assert o.speed_lag == pytest.approx(mrclam.estimate_odometry_lag(rec, r), abs=1e-6)
        assert o.turn_rate_lag == o.speed_lag
        # The table: the robot moves at SPEED_SCALE times its command; each cell within 4 standard
        # errors of its median (1.25 sigma / sqrt(n), sigma the tick mean's white noise) plus half
        # a cell's spread of the scale error.
        sigma_tick = 0.005 / math.sqrt(40 * DT)  # mrclam_synth's speed_std per 40 Hz row
        assert len(o.table) >= 3
        for i, _, dv, _, count in o.table:
            expected = (SPEED_SCALE - 1) * i * o.speed_step
            assert abs(dv - expected) <= 4 * 1.2533 * sigma_tick / math.sqrt(count) + abs(SPEED_SCALE - 1) * o.speed_step / 2
        # What is left: the white noise, and the scale error of the commands in no cell of the
        # table (fewer than MIN_CELL ticks: left as commanded), drifting over the horizon.
        s = calibrate._Samples(rec, r, [(0.0, T)], DT, o.speed_lag, o.turn_rate_lag)
        i, j = calibrate._cells(s.v, s.w, o.speed_step, o.turn_rate_step)
        cells = {(a, b) for a, b, *_ in o.table}
        missed = np.array([key not in cells for key in zip(i.tolist(), j.tolist())])
        assert missed.mean() < 0.1
        scale_error = np.where(missed, (SPEED_SCALE - 1) * s.v, 0.0) + 0 * s.vt  # no truth, no residual
        left = calibrate.batch_std(scale_error, s.t, horizon, s.seg)
        assert sigma_tick * (1 - std_tol - 0.1) <= o.speed_std <= math.hypot(sigma_tick, left) * (1 + std_tol + 0.1)
        assert o.speed_std < 0.2 * calibrate.batch_std(s.vt - s.v, s.t, horizon, s.seg)  # the table corrects
        if r not in full:
            continue
        cam = n.landmarks
        obs = s.obs["landmarks"]
        se_r = lstsq_se(calibrate.range_features(obs["r"], obs["b"]), RANGE_REL * obs["tr"])
        se_b = lstsq_se(calibrate.bearing_features(obs["b"]), np.full(obs["b"].size, BEARING_STD))
        # The generator's a3 r b^2 is in the true range; the fit's in the measured one, which
        # differs by the bias itself: |a3| (|a0| + |a3| r) b^2 at most, on top of 4 standard errors.
        slack = abs(RANGE_BIAS[1]) * (abs(RANGE_BIAS[0]) + abs(RANGE_BIAS[1]) * 5.0) * 0.36
        assert cam.range_bias[0] == pytest.approx(RANGE_BIAS[0], abs=4 * se_r[0] + slack)
        assert cam.range_bias[3] == pytest.approx(RANGE_BIAS[1], abs=4 * se_r[3] + slack)
        assert cam.bearing_bias[0] == pytest.approx(BEARING_BIAS, abs=4 * se_b[0])
        assert cam.range_std_per_m == pytest.approx(RANGE_REL, rel=std_tol + 0.1)
        assert cam.bearing_std == pytest.approx(BEARING_STD, rel=std_tol + 0.1)


def test_noise_yaml_round_trips_and_bad_files_are_one_line(biased, tmp_path):
    rec = mrclam.load(biased)
    model = calibrate.calibrate(rec, [(0.0, 60.0)], dt=DT)
    path = model.save(tmp_path / "noise.yaml")
    assert calibrate.NoiseModel.load(path) == model
    assert path.read_text().startswith("# swarmloc noise model")
    (tmp_path / "bad.yaml").write_text("format: swarmloc-noise/1\nrecording: x\n")
    with pytest.raises(calibrate.CalibrationError, match=r"bad.yaml: windows: Field required"):
        calibrate.NoiseModel.load(tmp_path / "bad.yaml")
    (tmp_path / "bad.yaml").write_text("[1, 2")
    with pytest.raises(calibrate.CalibrationError, match="not valid YAML"):
        calibrate.NoiseModel.load(tmp_path / "bad.yaml")
    with pytest.raises(calibrate.CalibrationError, match="is not inside the recording"):
        calibrate.calibrate(rec, [(50.0, 500.0)])
    with pytest.raises(calibrate.CalibrationError, match="shorter than"):
        calibrate.calibrate(rec, [(0.0, 5.0)])
    with pytest.raises(calibrate.CalibrationError, match="the recording has robots"):
        calibrate.calibrate(rec, robots=[1, 9])


def test_batch_means_find_the_long_run_variance_of_a_correlated_error():
    """AR(1) residuals of correlation phi per tick: the white noise that drifts as they do has
    variance sigma^2 (1 + phi) / (1 - phi); the per-tick RMS says sigma."""
    rng = np.random.default_rng(0)
    phi, n = 0.8, 40_000
    x = np.zeros(n)
    shocks = math.sqrt(1 - phi**2) * rng.standard_normal(n)
    for k in range(1, n):
        x[k] = phi * x[k - 1] + shocks[k]
    t = DT * np.arange(n)
    long_run, horizon = math.sqrt((1 + phi) / (1 - phi)), 10.0
    # Batches of 100 ticks lose the correlation across their ends: 2 phi / ((1 - phi)^2 n) of it.
    expected = math.sqrt(long_run**2 - 2 * phi / ((1 - phi) ** 2 * horizon / DT))
    assert calibrate.batch_std(x, t, horizon) == pytest.approx(expected, rel=4 * math.sqrt(horizon / (3 * n * DT)))
    assert calibrate.batch_std(x, t, 0) == pytest.approx(1.0, rel=0.05)


def test_the_replay_plays_the_recording_through_the_noise_model(biased):
    rec = mrclam.load(biased)
    model = calibrate.calibrate(rec, [(0.0, 60.0)], dt=DT)
    sc = replay.replay_scenario(biased, estimator="il", noise=model)
    assert sc.world.noise == model and sc.world.offset == pytest.approx(60.0)
    world = ReplayWorld(sc)
    frames = [world.step() for _ in range(sc.clock.steps + 1)]
    for r in sc.agent_ids:
        n = model.robots[r]
        tk = mrclam.ticked(rec, r, rec.t0 + sc.world.offset, DT, sc.clock.steps, n.odometry.speed_lag,
                           n.odometry.turn_rate_lag)
        v, w = n.odometry.correct(tk.v, tk.w)
        assert [f[r].odometry.speed for f in frames[1:]] == pytest.approx(v[1:])
        assert [f[r].odometry.turn_rate for f in frames[1:]] == pytest.approx(w[1:])
        assert {f[r].odometry.speed_std for f in frames} == {n.odometry.speed_std}
        sent = [(m.range, m.bearing, m.range_std, m.bearing_std) for f in frames for m in f[r].landmarks]
        mark = np.isin(tk.subject, list(rec.landmarks))
        expected = np.column_stack(n.landmarks.correct(tk.range[mark], tk.bearing[mark]))  # frame order is tick order
        assert len(sent) == mark.sum() > 50
        assert np.array(sent) == pytest.approx(expected)


def test_a_camera_kind_the_calibration_never_saw_keeps_its_readings(coloured):
    """A robot that saw no other robot in the calibration windows has no `robots` model: its
    robot observations in the scored span go out with its landmark camera's stds (the same
    camera), none dropped (a zero std would be)."""
    sc = replay.replay_scenario(coloured, estimator="il")
    unseen = [r for r, n in sc.world.noise.robots.items() if n.robots is None and n.landmarks is not None]
    assert unseen  # this recording's first half: robots 2 and 3 see no robot
    world = ReplayWorld(sc)
    frames = [world.step() for _ in range(sc.clock.steps + 1)]
    assert world.dropped["negative range"] == 0
    for r in unseen:
        cam = sc.world.noise.robots[r].landmarks
        sent = [m for f in frames for m in f[r].rb]
        assert sent and all(m.bearing_std == cam.bearing_std and m.range_std == pytest.approx(cam.range_std_per_m * m.range)
                            for m in sent)


def test_the_default_replay_scores_what_its_noise_was_not_fitted_to(biased):
    rec = mrclam.load(biased)
    T = rec.duration
    sc = replay.replay_scenario(biased, estimator="il")
    assert sc.world.offset == pytest.approx(T / 2) and sc.world.noise.windows == [(0.0, pytest.approx(T / 2))]
    label = replay.replay_label(sc)
    assert "held out" in label and "fitted on the scored data" not in label and label in sc.description
    # A span given: calibrated on what it leaves.
    sc = replay.replay_scenario(biased, estimator="il", offset=20.0, duration=30.0)
    assert sc.world.noise.windows == [(0.0, 20.0), (50.0, pytest.approx(T))] and "held out" in replay.replay_label(sc)
    # Fitting on the scored data is asked for, and said.
    sc = replay.replay_scenario(biased, estimator="il", calibration="scored")
    assert sc.world.noise.windows == [(0.0, pytest.approx(T))]
    assert replay.replay_label(sc).startswith("noise fitted on the scored data")
    # A noise model of part of the recording scores the rest; one of all of it is labelled.
    first = calibrate.calibrate(rec, [(0.0, 80.0)], dt=DT)
    sc = replay.replay_scenario(biased, estimator="il", noise=first)
    assert sc.world.offset == pytest.approx(80.0) and "held out" in replay.replay_label(sc)
    sc = replay.replay_scenario(biased, estimator="il", noise=first, offset=0.0, duration=60.0)
    assert replay.replay_label(sc).startswith("noise fitted on the scored data")
    # The white fit of before calibration is fitted on the scored data, and says so.
    sc = replay.replay_scenario(biased, estimator="il", calibration="none")
    assert sc.world.noise is None and replay.replay_label(sc).startswith("noise fitted on the scored data")
    with pytest.raises(scenario.ScenarioError, match="too little to calibrate on"):
        replay.replay_scenario(biased, estimator="il", offset=0.0, duration=T - 20)


def test_a_noise_model_names_the_robots_it_lacks(biased):
    rec = mrclam.load(biased)
    model = calibrate.calibrate(rec, [(0.0, 60.0)], dt=DT, robots=[1, 2])
    with pytest.raises(scenario.ScenarioError, match="noise model has no robot 3"):
        replay.replay_scenario(biased, estimator="il", noise=model)
    # A simulated world has no readings to correct: a noise model there is refused, not ignored.
    data = scenario.load("wang2019").model_dump(mode="json")
    data["world"]["noise"] = model.model_dump(mode="json")
    with pytest.raises(scenario.ScenarioError, match="for a recorded source"):
        scenario.parse(data)


def _nees(sc, names) -> dict:
    record = InProcessRunner(Simulation(sc), {}).run(RunRecord.for_scenario(sc))
    compute_references(sc, record, names)
    return {n: m for n, m in metrics(record, list(names))["estimators"].items()}


def test_coloured_odometry_noise_is_consistent_with_the_model_and_not_without(coloured):
    """The speed error is correlated over a second: white noise of its per-tick size lets dead
    reckoning claim a drift far below the real one. The calibrated model, fitted on the first
    half and scored on the second, stays within twice the state dimension; the white fit of
    before (fitted on the scored data, even) does not."""
    names = ("il", "ekf-ccl")
    sc = replay.replay_scenario(coloured, estimator="il")
    with_model = _nees(sc, names)
    # The same half scored: RMSEs of other spans do not compare.
    without = _nees(replay.replay_scenario(coloured, estimator="il", calibration="none", offset=sc.world.offset,
                                           duration=sc.clock.duration), names)
    for n in names:
        assert with_model[n]["nees"]["mean"] <= 6.0, n
        assert without[n]["nees"]["mean"] > 6.0, n
        assert with_model[n]["rmse_m"] <= 1.05 * without[n]["rmse_m"], n


def test_calibrate_command_writes_noise_yaml(cli, biased, tmp_path):
    out = tmp_path / "noise.yaml"
    p = cli.run("calibrate", str(biased), "-o", str(out), "--window", "0:60", check=True)
    assert f"wrote {out}" in p.stdout.replace("\n", "")
    model = calibrate.NoiseModel.load(out)
    assert model.windows == [(0.0, 60.0)] and sorted(model.robots) == [1, 2, 3]


def test_calibrate_and_replay_noise_errors_are_one_line(biased, tmp_path):
    from typer.testing import CliRunner

    from agents.cli import app

    def run(*args):
        result = CliRunner().invoke(app, list(args))
        return result.exit_code, result.stderr

    (tmp_path / "there.yaml").write_text("")
    for args, what in ((("calibrate", str(biased), "-o", str(tmp_path / "there.yaml")), "exists"),
                       (("calibrate", str(biased), "-o", str(tmp_path / "x.yaml"), "--window", "sixty"), "--window"),
                       (("calibrate", str(tmp_path / "nothing"), "-o", str(tmp_path / "x.yaml")), "no such directory"),
                       (("replay", str(biased), "--noise", str(tmp_path / "missing.yaml")), "cannot read"),
                       (("replay", str(biased), "--noise", str(tmp_path / "there.yaml"), "--fit-on-scored"), "one of")):
        code, err = run(*args)
        assert code == 2 and err.startswith("error:") and what in err and len(err.strip().splitlines()) == 1, (args, err)


@pytest.mark.slow
@pytest.mark.skipif(not FULL.is_dir(), reason="the shared MR.CLAM Dataset6 is not beside the repository")
def test_dataset6_held_out_replay_is_consistent_and_no_less_accurate():
    """docs/replay.md: the default replay (calibrated on the first half, scoring the second) keeps
    every reference's mean NEES within twice the state dimension, and its position RMSE within
    5 % of the white noise of before on the same half."""
    names = ("il", "ekf", "ekf-ccl")
    after = _nees(replay.replay_scenario(FULL, estimator="ukf-dcl"), names)
    rec = mrclam.load(FULL)
    half = rec.duration / 2
    before = _nees(replay.replay_scenario(FULL, estimator="ukf-dcl", calibration="none", offset=half,
                                          duration=rec.duration - half), names)
    for n in names:
        assert after[n]["nees"]["mean"] <= 6.0, (n, after[n]["nees"]["mean"])
        assert after[n]["rmse_m"] <= 1.05 * before[n]["rmse_m"], (n, after[n]["rmse_m"], before[n]["rmse_m"])
