"""UKF-DCL with bounded chains (estimator.params.max_chain), in process, lockstep: a chain
visits at most max_chain platforms, chains run concurrently, and the rest of the swarm applies
each commit as outsiders. The filter stays the one it claims to be: equal copies of every
cross-covariance at equal versions, a PSD joint covariance, NEES not above its bounds; and it
sits between the centralized filter and dead reckoning."""

import collections
import math

import numpy as np
import pytest
from scipy.stats import chi2
from test_lossy import check_versions

from netsim.sim import Simulation
from swarmloc.estimators import make_nodes
from swarmloc.experiment.results import compute_references, nees_series, position_errors
from swarmloc.experiment.runner import InProcessRunner
from swarmloc.experiment.scenario import parse

N, BOUND, RUNS = 10, 3, 4


def scenario(seed: int, n: int = N, duration: float = 40.0):
    rng = np.random.default_rng(seed)
    side = 40.0 * math.sqrt(n)
    pts, heads = rng.uniform(0, side, (n, 2)), rng.uniform(0, 2 * np.pi, n)
    agents = [{"id": i + 1, "start": [float(x), float(y)], "heading": float(h),
               "motion": {"kind": "random", "speed": 1.0, "turn_rate_std": 0.08}} for i, ((x, y), h) in enumerate(zip(pts, heads))]
    # A perfect gyro makes the position-only model exact, so a consistent filter has NEES 2.
    return parse({"version": 1, "name": f"bounded{n}", "seed": seed,
                  "clock": {"mode": "lockstep", "dt": 0.5, "duration": duration}, "world": {"agents": agents},
                  "sensors": {"odometry": {"turn_rate_noise": 0.0},
                              "range": {"probability": 0.5, "max_per_step": n, "max_range": 80.0}},
                  "radio": {"model": "unit-disk", "range_m": 120.0},
                  "estimator": {"name": "ukf-dcl", "params": {"max_chain": BOUND}}, "references": ["il", "ukf-ccl"]},
                 source="test")


def run(seed: int, check=None):
    sc = scenario(seed)
    nodes = make_nodes("ukf-dcl", sc)
    record = InProcessRunner(Simulation(sc), nodes).run(on_tick=(lambda k, f: check(nodes, k)) if check else None)
    compute_references(sc, record)
    return sc, nodes, record


@pytest.fixture(scope="module")
def monte_carlo():
    nees, err, used, visited = collections.defaultdict(list), collections.defaultdict(list), 0, collections.Counter()
    for seed in range(RUNS):
        sc, nodes, record = run(seed, check=check_versions)
        for alg in ("ukf-dcl", "ukf-ccl", "il"):
            tr = record.trace(alg)
            nees[alg].append(nees_series(record, tr)[1:])
            err[alg].append(position_errors(record, tr)[1:].mean())
        used += sum(n.stats["measurements_used"] for n in nodes.values())
        for n in nodes.values():
            for c in n.log:
                if c.gains:
                    visited[len({c.key[0], *c.parent})] += 1
    return {a: np.stack(v) for a, v in nees.items()}, {a: float(np.mean(v)) for a, v in err.items()}, used, visited


@pytest.mark.slow
def test_no_chain_visits_more_than_the_bound(monte_carlo):
    *_, used, visited = monte_carlo
    assert used > 50 * RUNS, used
    assert max(visited) == BOUND, visited  # the bound binds, and is never exceeded


@pytest.mark.slow
def test_bounded_chains_are_consistent_and_cooperate(monte_carlo):
    nees, err, *_ = monte_carlo
    n = nees["ukf-dcl"][..., :].size // nees["ukf-dcl"].shape[1]  # runs x agents per tick
    hi = chi2.ppf(0.975, 2 * n) / n
    per_tick = nees["ukf-dcl"].mean(axis=(0, 2))
    assert per_tick.mean() <= hi, f"bounded UKF-DCL overconfident: NEES {per_tick.mean():.2f} > {hi:.2f}"
    assert err["ukf-ccl"] < err["ukf-dcl"] < err["il"], err


@pytest.mark.slow
def test_bounded_chains_are_deterministic_for_a_seed():
    a, b = run(3)[2], run(3)[2]
    ta, tb = a.trace("ukf-dcl"), b.trace("ukf-dcl")
    assert np.array_equal(ta.mean, tb.mean) and np.array_equal(ta.cov, tb.cov)


def test_unbounded_chains_still_equal_the_centralized_filter():
    sc = scenario(1, n=6, duration=10.0).with_overrides(estimator={"name": "ukf-dcl", "params": {}})
    nodes = make_nodes("ukf-dcl", sc)
    record = InProcessRunner(Simulation(sc), nodes).run()
    compute_references(sc, record)
    dcl, ccl = record.trace("ukf-dcl"), record.trace("ukf-ccl")
    assert np.abs(dcl.mean - ccl.mean).max() < 1e-9


def test_max_chain_is_validated():
    with pytest.raises(Exception, match="max_chain"):
        scenario(1).with_overrides(estimator={"name": "ukf-dcl", "params": {"max_chain": 1}})
