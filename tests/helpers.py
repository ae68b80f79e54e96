"""Shared test helpers (plain functions; fixtures live in conftest.py)."""

import numpy as np

from netsim.sim import Simulation
from swarmloc.estimators.ukf.ccl import CentralizedUKF
from swarmloc.experiment.runner import InProcessRunner, make_nodes
from swarmloc.wire.messages import Sensors


def centralized(sc):
    """UKF-CCL from the scenario's prior, the reference every distributed run is compared with."""
    return CentralizedUKF({a: sc.prior(a)[0] for a in sc.agent_ids}, sc.prior(sc.agent_ids[0])[1],
                          spread=sc.estimation.spread)


def ccl_without(sc, sensors, skip):
    """UKF-CCL means (T, N, d) over a recorded sensor stream, leaving out the ranges skip(k, m, n) names."""
    ccl = centralized(sc)
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
