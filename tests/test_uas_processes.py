"""The EKF family as agent processes over netsim: lockstep equals the in-process runner, and
the fusion centre's loss is survived in both clock modes."""

import json

import numpy as np
import pytest
from helpers import in_process

from swarmloc.experiment import scenario as S
from swarmloc.experiment.results import metrics

pytestmark = pytest.mark.slow


def load_npz(path):
    with np.load(path, allow_pickle=False) as f:
        return {k: f[k] for k in f.files}


def short(name, tmp_path, duration, **changes):
    sc = S.load(name).with_overrides(**{"clock.duration": duration, **changes})
    path = tmp_path / f"{name}.yaml"
    path.write_text(sc.to_yaml())
    return sc, path


@pytest.mark.parametrize("name, estimator", [("goel-dist", "ekf-ci"), ("goel2node", "ekf-centre")])
def test_lockstep_over_zenoh_equals_in_process(cli, tmp_path, name, estimator):
    sc, path = short(name, tmp_path, 12.0, faults=[])
    out = tmp_path / "run"
    p = cli.run("run", str(path), "--out", str(out), "--port", str(cli.port), "--swarm", cli.swarm, "--no-plots",
                check=True, timeout=300)
    assert "Consistency" in p.stdout and estimator in p.stdout
    zen = load_npz(out / "estimates" / f"{estimator}.npz")
    record, _, _ = in_process(sc, estimator)
    ref = record.trace(estimator)
    assert zen["mean"].shape == ref.mean.shape == (121, 2, 16)
    assert np.array_equal(zen["mean"], ref.mean) and np.array_equal(zen["cov"], ref.cov)
    m = json.loads((out / "metrics.json").read_text())
    assert m["estimators"][estimator]["nees"]["n"] == 2 * 120
    assert m["models"] == {"1": "uas-ins", "2": "uas-ins"}
    # NIS too: an agent that publishes its estimate of a tick twice (its own, then the
    # centre's) counts that tick's innovations once, as in process.
    assert m["estimators"][estimator]["nis"] == metrics(record, [estimator])["estimators"][estimator]["nis"]


def test_a_ground_station_without_a_role_is_idle(tmp_path):
    sc = S.load("goel2node").with_overrides(**{"clock.duration": 3.0, "estimator": {"name": "ekf", "params": {}}})
    record, nodes, _ = in_process(sc, "ekf")
    assert nodes[100].model.state_dim == 0 and record.ids == [1, 2]
    assert not np.isnan(record.trace("ekf").mean).any()


@pytest.mark.parametrize("mode", ["lockstep", "realtime"])
def test_the_fusion_centres_loss_is_survived(cli, tmp_path, mode):
    """Centre (agent 100) killed at t = 4 s and restarted at t = 8 s: the UAS carry on on their
    own filters, then the new centre takes them back in. In real time the restarted process
    needs a moment to start: the run is long enough that it still runs ticks afterwards."""
    sc, path = short("goel2node", tmp_path, 20.0, **{"clock.mode": mode, "clock.speed": 2.0,
                     "faults": [{"at": 4.0, "action": "kill", "node": 100, "duration": 4.0}]})
    out = tmp_path / "run"
    cli.run("run", str(path), "--out", str(out), "--port", str(cli.port), "--swarm", cli.swarm, "--no-plots",
            check=True, timeout=300)
    m = json.loads((out / "metrics.json").read_text())
    for aid in ("1", "2"):
        stats = m["agent_stats"][aid]
        # On the centre's answers before the kill (40 ticks), on their own while it was gone.
        assert stats["own_ticks"] >= 30 and stats["centre_ticks"] >= 30, stats
        assert m["estimators"]["ekf-centre"]["agents"][aid]["ticks_missing"] == 0
        assert m["estimators"]["ekf-centre"]["agents"][aid]["max_error_m"] < 1.0
    centre = m["agent_stats"]["100"]  # the restarted process's own counters
    assert centre["joined"] >= 2 and centre["ticks_run"] >= 10, centre
    est = load_npz(out / "estimates" / "ekf-centre.npz")
    assert np.isfinite(est["mean"][1:]).all()
