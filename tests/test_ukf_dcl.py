"""UKF-DCL in process: step by step against UKF-CCL, side by side (FilterPy-test style)."""

import concurrent.futures
import multiprocessing
from pathlib import Path

import numpy as np
import pytest
from helpers import ccl_without, centralized

from netsim.sim import Simulation
from swarmloc import wire
from swarmloc.estimators.ukf.dcl import UkfDclNode
from swarmloc.experiment import scenario as S
from swarmloc.experiment.results import compute_references, metrics
from swarmloc.experiment.runner import InProcessRunner, make_nodes
from swarmloc.wire.messages import DclCommit, DclToken

TOL = 1e-9


def lockstep_compare(sc, check_connected=False):
    """Run UKF-DCL nodes and UKF-CCL side by side; after every tick every node's mean and
    whole covariance row must equal the centralized ones."""
    sim = Simulation(sc)
    nodes = make_nodes("ukf-dcl", sc)
    ccl = centralized(sc)
    worst = {"mean": 0.0, "row": 0.0}
    chains = []

    def on_tick(k, frames):
        if check_connected:
            assert connected(sim), f"precondition: swarm connected at tick {k}"
        ccl.step(frames)
        for a, node in nodes.items():
            worst["mean"] = max(worst["mean"], np.abs(node.x - ccl.x[ccl.block(a)]).max())
            for b in sc.agent_ids:
                block = node.row.get(b, np.zeros((2, 2)))
                worst["row"] = max(worst["row"], np.abs(block - ccl.P[ccl.block(a), ccl.block(b)]).max())
        chains.append(sum(len(f.ranges) for f in frames.values()))
        assert worst["mean"] < TOL and worst["row"] < TOL, f"tick {k}: diverged {worst}"
        for a, node in nodes.items():  # the measurer's NIS of each range, as the centralized filter's
            assert [d for _, d in node.nis] == [d for _, d in ccl.nis[a]], f"tick {k}: agent {a}'s NIS"
            assert np.allclose([v for v, _ in node.nis], [v for v, _ in ccl.nis[a]], rtol=0, atol=TOL)

    InProcessRunner(sim, nodes).run(on_tick=on_tick)
    return nodes, worst, chains


def connected(sim):
    ids = sim.ids
    seen, todo = {ids[0]}, [ids[0]]
    while todo:
        a = todo.pop()
        for b in ids:
            if b not in seen and sim.link_state(a, b)[0]:
                seen.add(b)
                todo.append(b)
    return len(seen) == len(ids)


def test_wang2019_equals_centralized_every_tick():
    nodes, worst, chains = lockstep_compare(S.load("wang2019"))
    assert sum(chains) > 300  # about 400 measurements at p = 0.5 over 800 steps
    assert all(n.stats["measurements_dropped"] == 0 for n in nodes.values())
    assert sum(n.stats["measurements_used"] for n in nodes.values()) == sum(chains)


@pytest.mark.slow
def test_seven_agents_random_motion_limited_radio_equals_centralized():
    nodes, worst, chains = lockstep_compare(S.load("random7"), check_connected=True)
    assert max(chains) >= 2, "scenario must exercise several chains in one tick"
    assert sum(n.stats["measurements_used"] for n in nodes.values()) == sum(chains)


def run(sc):
    sim = Simulation(sc)
    nodes = make_nodes("ukf-dcl", sc)
    record = InProcessRunner(sim, nodes).run()
    compute_references(sc, record)
    return metrics(record, ["il", "ukf-dcl", "ukf-ccl"]), nodes


@pytest.mark.slow
def test_cooperation_beats_dead_reckoning_for_every_platform():
    m, _ = run(S.load("wang2019"))
    il, dcl = m["estimators"]["il"]["agents"], m["estimators"]["ukf-dcl"]["agents"]
    for a in il:
        assert dcl[a]["mean_error_m"] < il[a]["mean_error_m"], f"A{a}"


def dcl_error(p: float, seed: int) -> float:
    sc = S.load("wang2019").with_overrides(**{"clock.duration": 200.0, "sensors.range.probability": p, "seed": seed})
    return run(sc)[0]["estimators"]["ukf-dcl"]["mean_error_m"]


@pytest.mark.slow
def test_error_falls_as_measurement_probability_rises():
    """Fig. 7 trend: averaged over seeds, the mean error decreases with p."""
    ps = [0.05, 0.1, 0.2, 0.5]
    cases = [(p, s) for p in ps for s in (1, 2, 3)]
    # Two worker processes (forkserver: no copied Zenoh threads from earlier tests).
    with concurrent.futures.ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("forkserver")) as pool:
        e = list(pool.map(dcl_error, *zip(*cases)))
    errs = [np.mean(e[3 * i:3 * i + 3]) for i in range(len(ps))]
    assert all(a > b for a, b in zip(errs, errs[1:])), dict(zip(ps, errs))


def partitioned_run(seed: int) -> tuple[dict, int]:
    """One seed of the partitioned swarm (a worker's task), its nodes checked at the end: every
    covariance PSD, equal versions holding equal cross-covariances."""
    sc = S.load("random7").with_overrides(**{"radio.range_m": 60.0, "seed": seed})
    m, nodes = run(sc)
    for n in nodes.values():
        P = n.estimate().cov
        assert np.allclose(P, P.T) and np.linalg.eigvalsh(P).min() > 0
        for j in nodes:  # nodes that applied the same commits hold the same cross-covariances
            if nodes[j].version == n.version:
                np.testing.assert_allclose(nodes[j]._block(n.id), n._block(j).T, atol=1e-9)
    return m, sum(n.stats["outsider_commits"] for n in nodes.values())


@pytest.mark.slow
def test_partitioned_swarm_stays_consistent():
    """Radio range shorter than the swarm (60 m): parts cooperate inside themselves, nodes out
    of a chain's reach take its commit later as outsiders, and over 6 seeds UKF-DCL is as
    consistent as the centralized filter (average NEES), never positive-indefinite, and between
    the centralized filter and dead reckoning in accuracy."""
    nees = {"ukf-dcl": [], "ukf-ccl": []}
    err = {"il": [], "ukf-dcl": [], "ukf-ccl": []}
    with concurrent.futures.ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("forkserver")) as pool:
        runs = list(pool.map(partitioned_run, range(1, 7)))
    for m, outsiders in runs:
        for a in err:
            err[a].append(m["estimators"][a]["mean_error_m"])
        for a in nees:
            nees[a] += [v["mean_nees"] for v in m["estimators"][a]["agents"].values()]
    assert sum(o for _, o in runs) > 0
    mean = {a: np.mean(v) for a, v in nees.items()}
    assert abs(mean["ukf-dcl"] - mean["ukf-ccl"]) <= 0.1 * mean["ukf-ccl"], mean
    assert np.mean(err["ukf-ccl"]) < np.mean(err["ukf-dcl"]) < np.mean(err["il"]), {a: np.mean(v) for a, v in err.items()}


def test_restarted_node_is_removed_as_an_orphan_and_rejoins():
    """A node that lost its cross-covariances (restart from a checkpoint) is dropped from the
    others' rows with a covariance-intersection bound by the next chain that touches it, then
    cooperates again; copies agree at equal versions throughout."""
    sc = S.load("wang2019").with_overrides(**{"clock.duration": 60.0, "sensors.range.probability": 1.0})
    nodes = make_nodes("ukf-dcl", sc)
    seen = {}

    def on_tick(k, frames):
        if k == 40:
            n = nodes[3]
            seen["before"] = {a: nodes[a].row[a].copy() for a in nodes}
            n.resume(n.k, n.x, n.row[3])
            assert n.orphan and list(n.row) == [3]
        if k == 41:
            # the removal: every holder scaled its row by |G| / (|G| - 1), the orphan by |G|
            seen["after"] = {a: nodes[a].row[a].copy() for a in nodes}
        for a in nodes:
            for b in nodes:
                if nodes[a].version == nodes[b].version and not (nodes[a].orphan or nodes[b].orphan):
                    np.testing.assert_allclose(nodes[a]._block(b), nodes[b]._block(a).T, atol=1e-9)

    InProcessRunner(Simulation(sc), nodes).run(on_tick=on_tick)
    assert sum(n.stats["orphans_removed"] for n in nodes.values()) == 3
    assert not any(n.orphan for n in nodes.values())
    assert set(nodes[3].row) == {1, 2, 3, 4}  # correlated with everyone again
    assert len({tuple(sorted(n.version.items())) for n in nodes.values()}) == 1
    for a, n in nodes.items():
        assert np.linalg.eigvalsh(n.row[a]).min() > 0
    # Covariance intersection over the 4 agents: the restarted node's own block took weight 1/4.
    assert np.trace(seen["after"][3]) > 3 * np.trace(seen["before"][3])


class Capture:
    """Drive 3 nodes by hand, keeping every frame, to replay old ones later."""

    def __init__(self):
        self.sc = S.load("wang2019").with_overrides(**{"sensors.range.probability": 1.0})
        self.sim = Simulation(self.sc)
        self.nodes = make_nodes("ukf-dcl", self.sc)
        self.frames = []
        self.runner = InProcessRunner(self.sim, self.nodes)

    def ticks(self, n):
        original = self.runner._encode

        def spy(src, sends):
            self.frames += [(src, send) for send in sends]
            return original(src, sends)

        self.runner._encode = spy
        self.sim.steps = n - 1
        self.runner.run()


def test_stale_and_replayed_frames_never_change_state():
    cap = Capture()
    cap.ticks(6)
    snapshot = {a: (n.x.copy(), {j: b.copy() for j, b in n.row.items()}) for a, n in cap.nodes.items()}
    replayed = 0
    for src, send in cap.frames:
        if isinstance(send.msg, (DclToken, DclCommit)):
            node = cap.nodes[send.dst]
            before = node.drops["stale"] + node.drops["duplicate"]
            node.receive(src, wire.decode(wire.encode(send.msg, src, 1, send.dst)).body)
            # A copy of a frame handled this tick, an old chain frame, or a commit already
            # applied (its seq is within our version).
            assert node.drops["stale"] + node.drops["duplicate"] == before + 1
            replayed += 1
    assert replayed > 10
    for a, n in cap.nodes.items():
        x, row = snapshot[a]
        assert np.array_equal(n.x, x)
        assert all(np.array_equal(row[j], n.row[j]) for j in row)


def test_malformed_but_decodable_chain_frames_are_dropped():
    cap = Capture()
    cap.ticks(3)
    node = cap.nodes[2]
    x = node.x.copy()
    key = [1, 0, 2, 0]
    def token(**over):
        f = dict(k=node.k, epoch=node.epoch, key=key, status=0, L=np.eye(4), Y=np.ones((4, 1)), Pz=np.eye(1),
                 nu=np.zeros(1), order=[1], parent={}, gains={1: np.zeros((2, 1))}, versions={1: {}}, orphans=[],
                 pending=[])
        f.update(over)
        return DclToken(**f)

    def commit(**over):
        f = dict(k=node.k, epoch=node.epoch, key=key, seq=1, version={}, L=np.eye(4), Y=np.ones((4, 1)),
                 Pz=np.eye(1), nu=np.zeros(1), parent={2: 1}, gains={2: np.zeros((2, 1))}, participants=[2],
                 removed=[], finished=True, pending=[])
        f.update(over)
        return DclCommit(**f)

    assert node.receive(1, token(L=np.eye(3))) == []
    assert node.receive(1, token(L=np.zeros((4, 4)))) == []  # not a Cholesky factor
    assert node.receive(1, token(Pz=-np.eye(1))) == []
    assert node.receive(1, token(gains={1: np.zeros((3, 1))})) == []
    assert node.receive(1, commit(gains={9: np.zeros((2, 1))}, participants=[9], parent={9: 1})) == []  # not ours
    assert node.receive(1, commit(participants=[2, 3])) == []  # a participant without a gain
    assert node.receive(1, commit(seq=7)) == []  # seq must follow the measurer's own count
    assert node.receive(1, commit(gains={}, participants=[], removed=[[0, 3]])) == []
    assert sum(node.drops.values()) >= 7
    assert np.array_equal(node.x, x)


def test_node_needs_matching_model_dimensions():
    with pytest.raises(ValueError, match="state_dim"):
        UkfDclNode(1, np.zeros(3), np.eye(3))


CUTS = {
    "wang2019": [[1, 2], [2, 3], [1, 4]],
    "random7": [[1, 2], [2, 6], [3, 4], [5, 1], [7, 3], [6, 7]],
}


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CUTS))
def test_cut_links_chains_route_around_them(name):
    """Links cut and restored at many ticks: chains meet freshly cut links (the radio NACKs
    them) and route around; only ranges between a cut pair are lost, from the cut tick to the
    restore tick inclusive (neighbour tables lag the radio by one tick)."""
    base = S.load(name)
    faults, windows = [], []
    for i, link in enumerate(CUTS[name] * 3):
        t0 = 10.0 + 13.5 * i
        faults += [{"at": t0, "action": "cut", "link": link}, {"at": t0 + 6.0, "action": "restore", "link": link}]
        windows.append((set(link), int(round(t0 / base.clock.dt)), int(round((t0 + 6.0) / base.clock.dt))))
    sc = base.with_overrides(faults=faults, **{"clock.duration": min(base.clock.duration, 10.0 + 13.5 * len(windows))})
    sim = Simulation(sc)
    nodes = make_nodes("ukf-dcl", sc)
    record = InProcessRunner(sim, nodes).run()
    during = lambda k, m, n: any({m, n} == pair and kc <= k <= kr for pair, kc, kr in windows)
    expected = ccl_without(sc, record.sensors, during)
    got = record.trace("ukf-dcl").mean
    assert np.abs(got - expected).max() < TOL
    assert sum(n.drops["undeliverable"] for n in nodes.values()) == 0
    # No frame crossed a link while it was cut; every link carried frames at other times.
    crossed = [(k, {s, r}) for k, s, r, _, why in sim.radio_log if why == ""]
    assert not [c for c in crossed if any(c[1] == pair and kc <= c[0] < kr for pair, kc, kr in windows)]
    assert sum(1 for *_, why in sim.radio_log if why == "fault") > 0


class DuplicatingRadio:
    """The scenario's radio, except every frame (and NACK) is delivered twice in a row."""

    def __init__(self, sim):
        self.sim = sim

    def __getattr__(self, name):
        return getattr(self.sim, name)

    def exchange(self, frames):
        return [rx for rx in self.sim.exchange(frames) for rx in (rx, rx)]


@pytest.mark.slow
@pytest.mark.parametrize("name", ["wang2019", "random7"])
def test_duplicated_frames_are_recognised_and_change_nothing(name):
    """A radio that delivers every frame twice: the copies are counted and dropped, and the
    estimates are bit for bit those of a clean run (before the fix a copy of an early token
    raised inside the node and cost the tick its chains)."""
    sc = S.load(name).with_overrides(**{"clock.duration": 60.0})
    clean = make_nodes("ukf-dcl", sc)
    ref = InProcessRunner(Simulation(sc), clean).run()
    nodes = make_nodes("ukf-dcl", sc)
    got = InProcessRunner(DuplicatingRadio(Simulation(sc)), nodes).run()
    assert np.array_equal(got.trace("ukf-dcl").mean, ref.trace("ukf-dcl").mean)
    assert np.array_equal(got.trace("ukf-dcl").cov, ref.trace("ukf-dcl").cov)
    assert sum(n.drops["duplicate"] for n in nodes.values()) > 100
    assert all("invalid" not in n.drops for n in nodes.values())


class Dead:
    """A killed agent: hears nothing, says nothing, estimates nothing."""

    def __init__(self, node):
        self.id, self.model, self.algorithm = node.id, node.model, node.algorithm

    def step(self, frames):
        return []

    def receive(self, src, msg):
        return []

    def link_failed(self, dst, msg):
        return []

    def estimate(self):
        from swarmloc.node import Estimate

        d = self.model.state_dim
        return Estimate(-1, np.full(d, np.nan), np.full((d, d), np.nan))


def run_with_restart(sc, victim, killed_at, restarted_at):
    """In process, as `swarmloc run` does with a kill fault: the victim's process dies at
    `killed_at` (the radio reports it down) and a new one resumes from its last checkpoint."""
    sim = Simulation(sc)
    nodes = make_nodes("ukf-dcl", sc)
    checkpoint = {}

    def on_tick(k, frames):
        if k == killed_at:
            checkpoint["e"] = nodes[victim].estimate()
            nodes[victim] = Dead(nodes[victim])
            sim.down.add(victim)
        if k == restarted_at:
            node = make_nodes("ukf-dcl", sc, [victim])[victim]
            e = checkpoint["e"]
            node.resume(e.k, e.mean, e.cov)
            nodes[victim] = node
            sim.down.discard(victim)

    record = InProcessRunner(sim, nodes).run(on_tick=on_tick)
    compute_references(sc, record, ["il"])
    return record, nodes


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_restarted_agent_finds_itself_and_beats_dead_reckoning(seed):
    """The docs' example (3 agents; agents 1 and 2 circle mirror-symmetrically, so a range to
    either cannot tell a position from its mirror image): agent 3 dies for 80 s and comes back
    with a checkpoint 80 s stale, inflated to ~100 m. Lost, it fuses no range until a window
    of ranges pins it down; over the last 75 s it must beat dead reckoning and be consistent.
    (Fusing ranges at once, it ended 36 to 80 m off against 5 to 12 m for dead reckoning.)"""
    sc = S.load(str(Path(__file__).with_name("data") / "example-3.yaml")).with_overrides(seed=seed)
    record, nodes = run_with_restart(sc, victim=3, killed_at=160, restarted_at=320)
    assert nodes[3].stats["lost"] >= 1 and nodes[3].stats["refound"] >= 1
    truth = record.truth_array()[-150:, 2]
    dcl, il = record.trace("ukf-dcl"), record.trace("il")
    err_dcl = dcl.mean[-150:, 2] - truth
    err_il = il.mean[-150:, 2] - truth
    assert np.linalg.norm(err_dcl, axis=1).mean() < np.linalg.norm(err_il, axis=1).mean()
    nees = np.einsum("ti,tij,tj->t", err_dcl, np.linalg.inv(dcl.cov[-150:, 2]), err_dcl)
    assert nees.mean() < 8  # chi-square with 2 dof averages 2; overconfident runs were in the hundreds
    # The others were not dragged off: they also beat dead reckoning.
    for i in (0, 1):
        e = np.linalg.norm(dcl.mean[-150:, i] - record.truth_array()[-150:, i], axis=1).mean()
        assert e < np.linalg.norm(il.mean[-150:, i] - record.truth_array()[-150:, i], axis=1).mean()


class LateCommits:
    """The scenario's radio, except that commits to `victim` arrive one tick late, after the
    next tick's chains are already under way: what a starved process sees in real time."""

    def __init__(self, sim, victim):
        self.sim, self.victim = sim, victim
        self.late, self.calls, self.k = [], 0, None

    def __getattr__(self, name):
        return getattr(self.sim, name)

    def exchange(self, frames):
        if self.sim.k != self.k:
            self.k, self.calls, due = self.sim.k, 0, self.late
            self.late = []
        else:
            due = []
        self.calls += 1
        out = []
        for rx in self.sim.exchange(frames):
            if rx.receiver == self.victim and rx.data is not None and isinstance(wire.decode(rx.data).body, DclCommit):
                self.late.append(rx)
            else:
                out.append(rx)
        if self.calls == 2:  # the new tick's chains have started: now the old commits come
            out += due
        return out


@pytest.mark.parametrize("synchronous, orphans", [(False, False), (True, True)])
def test_late_commit_after_a_new_tick_orphans_nobody(synchronous, orphans):
    """A node that reported to a chain and moved to the next tick before the chain's commit
    came holds (refuses new chains, is an outsider to others) until it comes: no orphan.
    Treating the tick as over (synchronous, right only in lockstep) orphans it."""
    sc = S.load("wang2019").with_overrides(**{"clock.duration": 40.0, "sensors.range.probability": 1.0})
    nodes = make_nodes("ukf-dcl", sc)
    for n in nodes.values():
        n.synchronous = synchronous
    InProcessRunner(LateCommits(Simulation(sc), victim=2), nodes).run()
    orphaned = sum(n.stats["orphaned"] for n in nodes.values())
    assert (orphaned > 0) == orphans, orphaned
    if not orphans:
        assert sum(n.stats["refused_holding"] for n in nodes.values()) > 0
        assert sum(n.stats["measurements_used"] for n in nodes.values()) > 40
        for a in nodes:
            for b in nodes:
                if nodes[a].version == nodes[b].version:
                    np.testing.assert_allclose(nodes[a]._block(b), nodes[b]._block(a).T, atol=1e-9)
