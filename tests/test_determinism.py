"""Lockstep is deterministic for a seed: two runs over Zenoh, bit for bit, at 16 agents with a
partition that heals, on the unit-disk radio (which can route a frame the moment it arrives,
and once did: whether a node caught up on the other half's commits before or after a token
visited it then depended on timing)."""

import json

import numpy as np
import pytest
import yaml
from helpers import in_process

from swarmloc.experiment import scenario as S

pytestmark = pytest.mark.slow


def sixteen_agents(tmp_path, duration=22.0):
    """16 agents on a 4x4 grid, 40 m apart, a 100 m unit-disk radio; the grid splits into its
    left and right halves from 6 s to 16 s."""
    agents = [{"id": i + 1, "start": [40.0 * (i % 4), 40.0 * (i // 4)], "heading": 0.4 * i,
               "motion": {"kind": "random", "speed": 1.0, "turn_rate_std": 0.08}} for i in range(16)]
    left = [i + 1 for i in range(16) if i % 4 < 2]
    right = [i + 1 for i in range(16) if i % 4 >= 2]
    doc = {"version": 1, "name": "grid16", "description": "16 agents, partition that heals", "seed": 5,
           "clock": {"mode": "lockstep", "dt": 0.5, "duration": duration},
           "world": {"agents": agents},
           "sensors": {"odometry": {"speed_noise": 0.5, "turn_rate_noise": 0.001},
                       "range": {"noise": 1.0, "probability": 0.5, "max_per_step": 2, "max_range": 90}},
           "radio": {"model": "unit-disk", "range_m": 100},
           "estimators": ["il", "ukf-dcl", "ukf-ccl"],
           "faults": [{"at": 6, "action": "partition", "groups": [left, right], "duration": 10}]}
    path = tmp_path / "grid16.yaml"
    path.write_text(yaml.safe_dump(doc))
    S.load(str(path))  # valid before two processes' worth of time is spent on it
    return path


def test_two_lockstep_runs_are_bit_identical(cli, tmp_path):
    path = sixteen_agents(tmp_path)
    runs = []
    for i in range(2):
        out = tmp_path / f"run{i}"
        cli.run("run", str(path), "--out", str(out), "--port", str(cli.port), "--swarm", cli.swarm, "--no-plots",
                check=True, timeout=400)
        with np.load(out / "estimates" / "ukf-dcl.npz") as f:
            runs.append({k: f[k] for k in f.files})
        runs[-1]["metrics"] = json.loads((out / "metrics.json").read_text())
    a, b = runs
    ma, mb = a.pop("metrics"), b.pop("metrics")
    # The partition really split and healed the chains: commits crossed as outsider updates.
    outsider = sum(s["outsider_commits"] for s in ma["agent_stats"].values())
    assert outsider > 0
    assert ma["radio"]["delivered"] == mb["radio"]["delivered"]
    assert outsider == sum(s["outsider_commits"] for s in mb["agent_stats"].values())
    for key in a:
        assert np.array_equal(a[key], b[key], equal_nan=True), key
    # ... and both are the in-process run of the same scenario.
    record, _, _ = in_process(S.load(str(path)))
    assert np.array_equal(a["mean"], record.trace("ukf-dcl").mean)
    assert np.array_equal(a["cov"], record.trace("ukf-dcl").cov)
