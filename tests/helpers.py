"""Shared test helpers (plain functions; fixtures live in conftest.py)."""

import numpy as np

from netsim.sim import Simulation
from swarmloc.estimators import CentralizedUKF
from swarmloc.messages import Sensors
from swarmloc.runner import InProcessRunner, make_nodes


def ccl_without(sc, sensors, skip):
    """UKF-CCL means (T, N, d) over a recorded sensor stream, leaving out the ranges skip(k, m, n) names."""
    x0 = {a: np.array(sc.agent(a).start, float) for a in sc.agent_ids}
    ccl = CentralizedUKF(x0, np.eye(2) * sc.estimation.initial_std**2, spread=sc.estimation.spread)
    means = []
    for frames in sensors:
        kept = {a: Sensors(f.k, f.t, f.odometry, [r for r in f.ranges if not skip(f.k, a, r.target)]) for a, f in frames.items()}
        ccl.step(kept)
        means.append(np.stack([ccl.x[ccl.block(a)] for a in sc.agent_ids]))
    return np.stack(means)


def in_process(sc, algorithm="ukf-dcl"):
    sim = Simulation(sc)
    nodes = make_nodes(algorithm, sc)
    return InProcessRunner(sim, nodes).run(), nodes, sim
