"""RDL (Luft et al. 2018; docs/rdl.md) checked step by step against what the paper claims:

- two platforms: the pair's joint covariance is all there is, so RDL is the centralized filter
  (UKF-CCL) exactly, tick after tick;
- three platforms, a pair (1, 2) updating while 1 is correlated with 3 and 2 is not: the pair's
  means and covariances and the cross-covariance Sigma_13 (the paper's approximation
  P_11+ P_11^-1 Sigma_13) equal the centralized filter's; what RDL gives up is platform 3's
  share (its mean, covariance and the cross-covariance Sigma_23 the update creates);
- over random swarms, in lockstep through netsim's radio: every range used, NEES not above its
  95 % bound, and the accuracy between UKF-CCL and bounded UKF-DCL.
"""

import collections
import math

import numpy as np
import pytest
from scipy.stats import chi2
from test_ukf_dcl_bounded import scenario as bounded_scenario

from netsim.sim import Simulation
from swarmloc import wire
from swarmloc.estimators import make_nodes
from swarmloc.estimators.rdl.node import RdlNode
from swarmloc.estimators.ukf.ccl import CentralizedUKF
from swarmloc.experiment.results import compute_references, nees_series, position_errors
from swarmloc.experiment.runner import InProcessRunner
from swarmloc.experiment.scenario import parse
from swarmloc.node import Send
from swarmloc.wire.messages import OdometryMsg, RangeMsg, RdlRequest, Sensors

MODEL = "planar-speed-heading"
P0 = np.eye(2) * 4.0


class Swarm:
    """RDL nodes and the centralized filter on the same hand-made sensor frames; the nodes'
    frames go through the wire codec and are delivered in lockstep rounds (a broadcast to all)."""

    def __init__(self, x0: dict, seed: int = 0):
        self.nodes = {a: RdlNode(a, x, P0, MODEL) for a, x in x0.items()}
        self.ccl = CentralizedUKF(x0, P0, MODEL)
        self.truth = {a: np.asarray(x, float) + np.array([1.0, -1.5]) for a, x in x0.items()}
        self.rng = np.random.default_rng(seed)
        self.k = -1

    def tick(self, ranges=()):
        """One tick: every platform moves; (m, n) in `ranges` is a range m -> n, noise 0.5 m."""
        self.k += 1
        frames = {}
        for a in sorted(self.nodes):
            heading = 0.3 * a
            self.truth[a] = self.truth[a] + 0.5 * np.array([math.cos(heading), math.sin(heading)])
            odo = OdometryMsg(0.5, 1.0 + self.rng.normal(0, 0.1), heading + self.rng.normal(0, 0.05), 0.1, 0.05)
            rs = [RangeMsg(n, float(np.linalg.norm(self.truth[m] - self.truth[n]) + self.rng.normal(0, 0.5)), 0.5)
                  for m, n in ranges if m == a]
            frames[a] = Sensors(self.k, 0.5 * self.k, odo, rs)
        queue = [(a, s) for a in sorted(self.nodes) for s in self.nodes[a].step(frames[a])]
        self._deliver(queue)
        self.ccl.step(frames)

    def _deliver(self, queue):
        queue = [(src, s) for src, s in queue if isinstance(s, Send)]
        while queue:
            src, s = queue.pop(0)
            for dst in [s.dst] if s.dst is not None else [j for j in sorted(self.nodes) if j != src]:
                msg = wire.decode(wire.encode(s.msg, src, 1, dst)).body
                queue += [(dst, x) for x in self.nodes[dst].receive(src, msg) if isinstance(x, Send)]
        assert not any(n.waiting for n in self.nodes.values())

    def cross(self, i, j) -> np.ndarray:
        """Sigma_ij as RDL holds it: the product of i's side and j's (zero where either is missing)."""
        si, sj = self.nodes[i].factors.get(j), self.nodes[j].factors.get(i)
        return np.zeros((2, 2)) if si is None or sj is None else si @ sj.T

    def ccl_block(self, i, j) -> np.ndarray:
        return self.ccl.P[self.ccl.block(i), self.ccl.block(j)]


def assert_same(a, b, what):
    np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-10, err_msg=what)


def test_two_platforms_are_the_centralized_filter():
    s = Swarm({1: np.array([0.0, 0.0]), 2: np.array([30.0, 10.0])})
    s.tick()  # tick 0: beacons only, so each knows the other is in reach
    for k in range(12):
        s.tick([(1, 2), (2, 1)] if k % 3 else [(2, 1)])
        for a in (1, 2):
            assert_same(s.nodes[a].x, s.ccl.x[s.ccl.block(a)], f"x_{a}, tick {s.k}")
            assert_same(s.nodes[a].P, s.ccl_block(a, a), f"P_{a}{a}, tick {s.k}")
        assert_same(s.cross(1, 2), s.ccl_block(1, 2), f"Sigma_12, tick {s.k}")
    assert np.abs(s.ccl_block(1, 2)).max() > 1e-3  # the pair is correlated: the test compared something
    assert s.nodes[1].stats["measurements_used"] + s.nodes[2].stats["measurements_used"] == 20


def test_a_pair_update_is_exact_except_for_the_third_platform_s_share():
    s = Swarm({1: np.array([0.0, 0.0]), 2: np.array([30.0, 10.0]), 3: np.array([-20.0, 25.0])})
    s.tick()
    s.tick([(1, 3)])  # 1 and 3 become correlated, 2 is correlated with no one
    for a in (1, 3):
        assert_same(s.nodes[a].P, s.ccl_block(a, a), f"P_{a}{a} after the first pair")
    assert_same(s.cross(1, 3), s.ccl_block(1, 3), "Sigma_13 after the first pair")
    s.tick([(2, 1)])  # the pair (1, 2), with Sigma_12 = 0 and Sigma_23 = 0 before it
    for a in (1, 2):
        assert_same(s.nodes[a].x, s.ccl.x[s.ccl.block(a)], f"x_{a}")
        assert_same(s.nodes[a].P, s.ccl_block(a, a), f"P_{a}{a}")
    assert_same(s.cross(1, 2), s.ccl_block(1, 2), "Sigma_12")
    # The paper's approximation of the cross-covariance with a platform not involved is exact here.
    assert_same(s.cross(1, 3), s.ccl_block(1, 3), "Sigma_13 = P_11+ P_11^-1 Sigma_13")
    # What RDL gives up: platform 3 hears nothing, so its mean and covariance only took the time
    # update, and the correlation the update creates between 2 and 3 is not kept.
    assert not np.allclose(s.nodes[3].P, s.ccl_block(3, 3), rtol=1e-6, atol=1e-9)
    assert not np.allclose(s.nodes[3].x, s.ccl.x[s.ccl.block(3)], rtol=1e-9, atol=1e-9)
    assert np.abs(s.ccl_block(2, 3)).max() > 1e-4 and not s.cross(2, 3).any()


def test_an_undeliverable_request_is_given_up_and_counted():
    a = RdlNode(1, np.zeros(2), P0, MODEL)
    a.beacons.hear(2, wire.messages.Beacon(0, np.array([10.0, 0.0]), np.eye(2), {}))
    a.step(Sensors(0, 0.0, OdometryMsg(0.5, 1.0, 0.0, 0.1, 0.05), []))
    out = a.step(Sensors(1, 0.5, OdometryMsg(0.5, 1.0, 0.0, 0.1, 0.05), [RangeMsg(2, 9.0, 0.5)]))
    req = next(s.msg for s in out if isinstance(s, Send) and isinstance(s.msg, RdlRequest))
    x, P = a.x.copy(), a.P.copy()
    for _ in range(a.max_retries):
        assert [s.msg for s in a.link_failed(2, req)] == [req]  # sent again
    a.link_failed(2, req)
    assert a.waiting is None and a.stats["measurements_dropped"] == 1 and a.stats["measurements_used"] == 0
    assert_same(a.x, x, "x after a lost request")
    assert_same(a.P, P, "P after a lost request")


def test_a_wait_in_real_time_holds_the_next_tick_and_is_given_up_within_it():
    from swarmloc.estimators.rdl.node import WAIT_TICKS
    from swarmloc.node import Timer

    assert 0.5 < WAIT_TICKS < 1  # a round trip is two hops; one boundary at most (docs/rdl.md)
    a = RdlNode(1, np.zeros(2), P0, MODEL)
    a.synchronous = False
    a.beacons.hear(2, wire.messages.Beacon(0, np.array([10.0, 0.0]), np.eye(2), {}))
    a.step(Sensors(0, 0.0, OdometryMsg(0.5, 1.0, 0.0, 0.1, 0.05), []))
    out = a.step(Sensors(1, 0.5, OdometryMsg(0.5, 1.0, 0.0, 0.1, 0.05), [RangeMsg(2, 9.0, 0.5)]))
    timers = [s for s in out if isinstance(s, Timer)]
    assert len(timers) == 1 and timers[0].delay == pytest.approx(WAIT_TICKS * 0.5)
    x, P = a.x.copy(), a.P.copy()
    # The next tick's frame comes during the wait: held, not run, not skipped.
    assert a.step(Sensors(2, 1.0, OdometryMsg(0.5, 1.0, 0.0, 0.1, 0.05), [])) == []
    assert a.k == 1 and a.deferred is not None and a.drops["tick-skipped"] == 0
    a.on_timer(timers[0].tag, 0.5 + timers[0].delay)  # no commit: the measurement is given up
    assert a.drops["tick-skipped"] == 0 and a.drops["no-commit"] == 1
    assert a.waiting is None and a.stats["waits_expired"] == 1 and a.stats["measurements_dropped"] == 1
    assert a.k == 2 and a.deferred is None  # the held tick ran when the wait ended
    assert_same(a.x, x + 0.5 * np.array([1.0, 0.0]), "x: tick 2's motion alone, no half of a pair")
    assert np.all(np.linalg.eigvalsh(a.P - P) > 0), "P: tick 2's process noise added, nothing taken"


RUNS, N = 3, 10


def run(estimator: str, seed: int):
    sc = bounded_scenario(seed, N)
    if estimator == "rdl":
        sc = parse({**sc.model_dump(mode="json", exclude_none=True), "estimator": {"name": "rdl"}}, source="test")
    nodes = make_nodes(estimator, sc)
    record = InProcessRunner(Simulation(sc), nodes).run()
    compute_references(sc, record)
    return nodes, record


@pytest.fixture(scope="module")
def monte_carlo():
    nees, err, stats = collections.defaultdict(list), collections.defaultdict(list), collections.Counter()
    for seed in range(RUNS):
        for estimator in ("rdl", "ukf-dcl"):
            nodes, record = run(estimator, seed)
            algs = (estimator, "ukf-ccl", "il") if estimator == "rdl" else (estimator,)
            for alg in algs:
                tr = record.trace(alg)
                nees[alg].append(nees_series(record, tr)[1:])
                err[alg].append(position_errors(record, tr)[1:].mean())
            if estimator == "rdl":
                for n in nodes.values():
                    stats.update({k: v for k, v in n.stats.items() if k.startswith("measurements")})
    return {a: np.stack(v) for a, v in nees.items()}, {a: float(np.mean(v)) for a, v in err.items()}, stats


@pytest.mark.slow
def test_every_range_is_used_in_lockstep(monte_carlo):
    *_, stats = monte_carlo
    assert stats["measurements_used"] > 100 * RUNS, stats
    assert stats["measurements_dropped"] == 0 and stats["measurements_gated"] == 0, stats


@pytest.mark.slow
def test_rdl_is_consistent_and_between_the_centralized_filter_and_bounded_ukf_dcl(monte_carlo):
    nees, err, _ = monte_carlo
    n = RUNS * N
    hi = chi2.ppf(0.975, 2 * n) / n  # the 95 % bound of a tick's average over runs and platforms
    per_tick = nees["rdl"].mean(axis=(0, 2))
    assert per_tick.mean() <= hi, f"RDL overconfident: NEES {per_tick.mean():.2f} > {hi:.2f}"
    assert err["ukf-ccl"] < err["rdl"] < err["ukf-dcl"] < err["il"], err


def test_a_beacon_every_few_ticks_changes_no_estimate_and_sends_fewer_frames():
    """`estimator.params.beacon_every` (issue 29: at 256 platforms the beacons are most of the
    deliveries): a beacon only says who is in reach, and a neighbour stays known for 3 ticks, so
    on a lossless radio every 2 or 3 ticks (staggered by id) gives the same estimates, bit for
    bit, and every range is still used, with fewer radio frames."""
    from swarmloc.experiment import scenario as S

    got = {}
    for n in (1, 2, 3):
        sc = S.load("swarm32").with_overrides(**{"clock.duration": 15.0,
                                                  "estimator": {"name": "rdl", "params": {"beacon_every": n}}})
        nodes = make_nodes("rdl", sc)
        runner = InProcessRunner(Simulation(sc), nodes)
        record = runner.run()
        used = sum(nd.stats["measurements_used"] for nd in nodes.values())
        dropped = sum(nd.stats["measurements_dropped"] for nd in nodes.values())
        got[n] = (record.trace("rdl"), runner.frames, used, dropped)
    (ref, frames1, used1, _) = got[1]
    assert used1 > 300 and all(g[3] == 0 for g in got.values())
    for n in (2, 3):
        tr, frames, used, _ = got[n]
        assert np.array_equal(tr.mean, ref.mean) and np.array_equal(tr.cov, ref.cov), n
        assert used == used1
        beacons1 = 32 * 31  # one a platform a tick over 31 ticks
        assert frames <= frames1 - beacons1 * (1 - 1 / n) * 0.9, (n, frames, frames1)
    with pytest.raises(Exception, match="beacon_every"):
        S.load("swarm32").with_overrides(estimator={"name": "rdl", "params": {"beacon_every": 4}})
