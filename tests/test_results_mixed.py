"""The run directory, metrics and plots of a swarm of mixed state sizes (planar robots and UAS,
a ground station left out): padding, dims, NEES in each model's own error coordinates."""

import json

import numpy as np
import pytest

from swarmloc.experiment import scenario as S
from swarmloc.experiment.results import RunRecord, Trace
from swarmloc.experiment.rundir import write_run
from swarmloc.models import ins
from swarmloc.models.motion import UasIns
from swarmloc.node import Estimate
from swarmloc.wire.messages import OdometryMsg, Sensors


def test_a_mixed_swarm_round_trips_through_the_run_directory(tmp_path):
    rng = np.random.default_rng(1)
    record = RunRecord([1, 2], {1: "planar-speed-heading", 2: "uas-ins"})
    assert record.d == 16 and list(record.dims) == [2, 16]
    uas = UasIns()
    P1, P2 = np.eye(2) * 0.25, np.eye(16) * 0.01
    for k in range(30):
        truth = {1: np.array([k, 0.0]), 2: uas.pack(ins.InsState([k, 1.0, 50.0], [1.0, 0, 0], [1, 0, 0, 0]))}
        frames = {a: Sensors(k, 0.5 * k, OdometryMsg(0.5, 1.0, 0.0, 0.1, 0.0) if a == 1 else None, []) for a in (1, 2)}
        record.add_tick(k, 0.5 * k, frames, truth | {100: np.zeros(0)})
        e2 = rng.multivariate_normal(np.zeros(16), P2)  # an error drawn from the claimed covariance
        est2 = uas.pack(ins.inject(uas.unpack(truth[2]), -e2))
        record.add_estimate("x", 1, Estimate(k, truth[1] + rng.multivariate_normal(np.zeros(2), P1), P1, ((1.0, 1),)))
        record.add_estimate("x", 2, Estimate(k, est2, P2))
        record.add_estimate("x", 100, Estimate(k, np.zeros(0), np.zeros((0, 0))))  # a ground station: ignored
    sc = S.load("wang2019")
    m = write_run(tmp_path, sc, record, ["x"], plots=True)
    tr = Trace.load(tmp_path / "estimates" / "x.npz")
    assert tr.mean.shape == (30, 2, 16) and list(tr.dims) == [2, 16]
    assert np.isnan(tr.mean[:, 0, 2:]).all() and not np.isnan(tr.mean[:, 1]).any()
    with np.load(tmp_path / "truth.npz") as t:
        assert list(t["dims"]) == [2, 16] and np.isnan(t["state"][:, 0, 2:]).all()
    x = m["estimators"]["x"]["agents"]
    # NEES of the UAS in its error coordinates: chi-square(16) draws, so about 16 on average.
    assert 10 < x["2"]["mean_nees"] < 22 and 0.5 < x["1"]["mean_nees"] < 4
    assert x["1"]["nis"]["n"] == 30 and x["2"]["nis"] is None
    assert json.loads((tmp_path / "metrics.json").read_text())["models"] == {"1": "planar-speed-heading", "2": "uas-ins"}
    assert {p.name for p in (tmp_path / "plots").iterdir()} >= {"trajectories.png", "position_error.png", "nees.png"}


def _planar_record(errors, fixes):
    """Two planar robots over 41 ticks of 0.1 s at the origin; agent a's estimate is off by
    errors[a][k] along x; fixes[a]: the ticks its frame carries a GNSS fix."""
    from swarmloc.wire.messages import GnssMsg

    record = RunRecord([1, 2], {1: "planar-speed-heading", 2: "planar-speed-heading"})
    P = np.eye(2) * 0.01
    for k in range(41):
        frames = {a: Sensors(k, 0.1 * k, OdometryMsg(0.1, 1.0, 0.0, 0.1, 0.0), [],
                             GnssMsg([0.0, 0.0], 1.0) if k in fixes[a] else None) for a in (1, 2)}
        record.add_tick(k, 0.1 * k, frames, {1: np.zeros(2), 2: np.zeros(2)})
        for a in (1, 2):
            record.add_estimate("x", a, Estimate(k, np.array([errors[a][k], 0.0]), P))
    return record


def test_gnss_denied_means_no_fix_within_an_epoch_and_since_leaves_the_start_out():
    from swarmloc.experiment.results import gnss_covered, metrics

    # Agent 1: a fix every second (10 ticks), as a UAS with 1 Hz GNSS. Agent 2: fixes at 1 s and
    # 4 s only, so from 2.0 s to 3.0 s it is more than an epoch from any fix.
    fixes = {1: set(range(10, 41, 10)), 2: {10, 40}}
    err = {1: np.full(41, 0.1), 2: np.where((np.arange(41) >= 20) & (np.arange(41) <= 30), 5.0, 0.2)}
    err[1][0] = err[2][0] = 9.0  # tick 0 never counts
    record = _planar_record(err, fixes)
    cov = gnss_covered(record)
    assert cov[1:, 0].all() and not cov[0, 0]
    assert list(np.flatnonzero(~cov[:, 1])) == [0, *range(20, 31)]
    m = metrics(record, ["x"])["estimators"]["x"]
    assert m["no_gnss_mean_error_m"] == pytest.approx(5.0) and m["no_gnss_max_error_m"] == pytest.approx(5.0)
    assert m["max_error_m"] == pytest.approx(5.0)
    late = metrics(record, ["x"], since=3.05)["estimators"]["x"]  # ticks 31..40: agent 2 covered again
    assert late["no_gnss_mean_error_m"] is None and late["max_error_m"] == pytest.approx(0.2)
    assert late["agents"]["2"]["mean_error_m"] == pytest.approx(0.2)
    assert late["agents"]["2"]["final_error_m"] == pytest.approx(0.2)
    # A fix every tick (the planar world): a tick counts as covered only if it carries one.
    every = _planar_record(err, {1: set(range(41)), 2: set(range(0, 41, 2))})
    assert list(np.flatnonzero(~gnss_covered(every)[:, 1])) == list(range(1, 41, 2))


def test_jitter_is_the_rms_tick_to_tick_change_of_the_error():
    from swarmloc.experiment.results import metrics

    a = 0.03
    err = {1: a * (-1.0) ** np.arange(41), 2: np.linspace(0.0, 4.0, 41)}  # white-ish against a smooth drift
    m = metrics(_planar_record(err, {1: set(), 2: set()}), ["x"])["estimators"]["x"]
    assert m["agents"]["1"]["jitter_m"] == pytest.approx(2 * a)
    assert m["agents"]["2"]["jitter_m"] == pytest.approx(0.1)
    assert m["jitter_m"] == pytest.approx(np.sqrt(((2 * a) ** 2 + 0.1**2) / 2))
    assert "no_gnss_mean_error_m" not in m  # no GNSS in the swarm
