"""The run directory, metrics and plots of a swarm of mixed state sizes (planar robots and UAS,
a ground station left out): padding, dims, NEES in each model's own error coordinates."""

import json

import numpy as np

from swarmloc import ins
from swarmloc import scenario as S
from swarmloc.messages import OdometryMsg, Sensors
from swarmloc.models import UasIns
from swarmloc.node import Estimate
from swarmloc.results import RunRecord, Trace, write_run


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
