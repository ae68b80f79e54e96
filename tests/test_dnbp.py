"""dNBP between agents (Wan et al. 2014): the paper's schedule walked through with real nodes,
the world's GNSS Markov chain and ranges, the least-squares baseline, and runs of wan2014."""

import numpy as np
import pytest
from helpers import in_process

from netsim.sim import Simulation
from swarmloc import wire
from swarmloc.estimators.nbp.dnbp import DnbpNode, LeastSquaresReference
from swarmloc.experiment import scenario as S
from swarmloc.wire.messages import GnssMsg, NbpBelief, OdometryMsg, RangeMsg, Sensors

# Fig. 3: UAV1-3 normal, UAV4-6 fault. UAV4 ranges 1, 2, 3; UAV5 ranges 1, 2 and 4; UAV6 ranges
# 3, 4 and 5 (and nobody else). Positions are ours; the links are the figure's.
POS = {1: (0.0, 0.0), 2: (200.0, 0.0), 3: (100.0, 180.0), 4: (110.0, 60.0), 5: (240.0, 130.0), 6: (190.0, 260.0)}
LINKS = {(1, 4), (2, 4), (3, 4), (1, 5), (2, 5), (4, 5), (3, 6), (4, 6), (5, 6)}


def fig3_frames(rng):
    nbrs = {a: sorted({b for l in LINKS for b in l if a in l} - {a}) for a in POS}
    frames = {}
    for a, p in POS.items():
        ranges = [RangeMsg(b, float(np.hypot(*np.subtract(POS[b], p)) + rng.normal(0, 1.0)), 1.0) for b in nbrs[a]]
        gnss = GnssMsg(np.array(p) + rng.normal(0, 1.0, 2), 1.0) if a <= 3 else None
        frames[a] = Sensors(1, 1.0, OdometryMsg(1.0, 0.0, 0.0, 0.1, 0.0), ranges, gnss)
    return frames


def walk(nodes, frames):
    """One slice as lockstep runs it: every agent steps, then rounds of broadcasts (through the
    real codec) until nobody sends; returns the fault agents that sent, round by round."""
    sent = [(a, s.msg) for a in sorted(nodes) for s in nodes[a].step(frames[a]) if hasattr(s, "msg")]
    rounds = []
    while sent:
        rounds.append(sorted({a for a, m in sent if not m.normal}))
        nxt = []
        for src, msg in sent:
            data = wire.encode(msg, src, 1)
            for a in sorted(nodes):
                if a != src:
                    nxt += [(a, s.msg) for s in nodes[a].receive(src, wire.decode(data).body) if hasattr(s, "msg")]
        sent = nxt
    return [r for r in rounds if r]


def fig3_nodes(M=300, seed=0, iterations=1):
    # Priors: the normal agents' near the truth; the fault agents' 300 m wide around (150, 100).
    return {a: DnbpNode(a, np.array(POS[a]) if a <= 3 else np.array([150.0, 100.0]),
                        np.eye(2) * (1.0 if a <= 3 else 300.0**2), M=M, iterations=iterations, seed=seed) for a in POS}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_schedule_of_fig_3_4_with_real_nodes(seed):
    """UAV4 sends first (3 normal neighbours), then UAV5 (2 normal + UAV4), then UAV6 (UAV3,
    UAV4, UAV5); with refinements (3 sends each) UAV4, with 3 exact anchors, localizes to a few
    metres (GPS and range noise 1 m) from a 300 m wide prior, and UAV5 and UAV6, each resting on
    a fault UAV's belief, to within three standard deviations of their own beliefs."""
    assert walk(fig3_nodes(seed=seed), fig3_frames(np.random.default_rng(seed))) == [[4], [5], [6]]
    nodes = fig3_nodes(seed=seed, iterations=3)
    rounds = walk(nodes, fig3_frames(np.random.default_rng(seed)))
    first = {a: next(i for i, r in enumerate(rounds) if a in r) for a in (4, 5, 6)}
    assert first == {4: 0, 5: 1, 6: 2}
    for a in (4, 5, 6):
        e = nodes[a].estimate()
        err, std = np.linalg.norm(e.mean - POS[a]), np.sqrt(np.trace(e.cov) / 2)
        assert err < (5.0 if a == 4 else min(3 * std, 15.0)), (a, err, std)
    # A normal agent takes no beliefs of fault agents, and counts them.
    assert nodes[1].drops["ignored"] >= 2 and nodes[1].estimate().mean == pytest.approx(POS[1], abs=5.0)


def test_a_lone_fault_agent_forms_its_belief_at_the_slice_end_and_starts_the_next_relaxed():
    rng = np.random.default_rng(2)
    frames = fig3_frames(rng)
    nodes = {a: n for a, n in fig3_nodes().items() if a in (1, 2, 5)}  # UAV5 hears only UAV1 and UAV2
    for a in (5,):
        frames[a] = Sensors(1, 1.0, frames[a].odometry, [r for r in frames[a].ranges if r.target in (1, 2)], None)
    assert walk(nodes, frames) == []  # 2 < 3: it never sends in this slice
    f2 = {a: Sensors(2, 2.0, f.odometry, f.ranges, f.gnss) for a, f in frames.items()}
    nodes[5].on_timer("nbp-relax", 2.0)  # lockstep: the quiet timer fires at the next tick
    assert nodes[5].stats["formed_late"] == 1 and nodes[5].carry == 1  # 2 messages: next slice needs 2
    assert walk(nodes, f2) == [[5]]


def test_bad_beliefs_are_counted_and_change_nothing():
    node = fig3_nodes()[4]
    frames = fig3_frames(np.random.default_rng(3))
    node.step(frames[4])
    before = node.estimate().mean.copy()
    good = np.zeros((5, 2), np.float32)
    for src, msg in [(1, NbpBelief(0, 0, True, good, np.ones(5, np.float32), np.eye(2))),  # stale
                     (1, NbpBelief(2, 0, True, good, np.ones(5, np.float32), np.eye(2))),  # early
                     (9, NbpBelief(1, 0, True, good, np.ones(5, np.float32), np.eye(2))),  # not ranged
                     (1, NbpBelief(1, 0, True, np.zeros((5, 3), np.float32), np.ones(5, np.float32), np.eye(3))),
                     (1, NbpBelief(1, 0, True, good, np.zeros(5, np.float32), np.eye(2)))]:  # zero weights
        node.receive(src, msg)
    assert node.drops == {"stale": 1, "early": 1, "not-ranged": 1, "invalid": 2}
    assert np.array_equal(node.estimate().mean, before)


# --------------------------------------------------------------------------- world and baseline


def test_gnss_switches_as_a_markov_chain_with_its_stationary_share():
    sc = S.load("wan2014").with_overrides(**{"clock.duration": 400.0})
    sim = Simulation(sc)
    fixes, switches, last = [], 0, None
    for _ in range(sim.steps + 1):
        k, _, frames = sim.tick()
        have = np.array([frames[a].gnss is not None for a in sc.agent_ids])
        if k >= 1:
            fixes.append(have.mean())
            switches += 0 if last is None else int((have != last).sum())
            last = have
    assert abs(np.mean(fixes) - 1 / 3) < 0.06  # stationary share to_normal / (to_fault + to_normal)
    assert switches > 100
    fixed = S.load("wan2014").with_overrides(**{"sensors.gnss.to_fault": 0.0, "sensors.gnss.to_normal": 0.0,
                                                "sensors.gnss.agents": [1, 2, 3], "clock.duration": 5.0})
    sim = Simulation(fixed)
    for _ in range(sim.steps + 1):
        k, _, frames = sim.tick()
        if k:
            assert sorted(a for a, f in frames.items() if f.gnss is not None) == [1, 2, 3]
    share = S.load("wan2014").with_overrides(**{"sensors.gnss.to_fault": 0.0, "sensors.gnss.to_normal": 0.0,
                                                "sensors.gnss.normal_share": 0.25, "clock.duration": 5.0})
    sim, normal = Simulation(share), []
    for _ in range(sim.steps + 1):
        k, _, frames = sim.tick()
        if k:
            normal.append(sorted(a for a, f in frames.items() if f.gnss is not None))
    assert len(normal[0]) == 5 and all(n == normal[0] for n in normal)  # a quarter of 20, fixed


def test_every_uav_ranges_every_other_within_r():
    sc = S.load("wan2014").with_overrides(**{"clock.duration": 3.0})
    sim = Simulation(sc)
    for _ in range(sim.steps + 1):
        k, _, frames = sim.tick()
    pos = sim.world.positions()
    for a, f in frames.items():
        within = sorted(b for b in pos if b != a and np.linalg.norm(pos[a] - pos[b]) <= 300.0)
        assert sorted(r.target for r in f.ranges) == within


def test_least_squares_takes_three_exact_anchors_and_dead_reckons_with_fewer():
    sc = S.load("wan2014")
    ref = LeastSquaresReference(sc, [1, 2, 3, 4, 5])
    odo = OdometryMsg(1.0, 0.0, 0.0, 0.1, 0.0)
    anchors = {1: (0.0, 0.0), 2: (300.0, 0.0), 3: (0.0, 300.0)}
    truth = np.array([120.0, 90.0])
    frames = {a: Sensors(1, 1.0, odo, [], GnssMsg(np.array(p), 0.5)) for a, p in anchors.items()}
    frames[4] = Sensors(1, 1.0, odo, [RangeMsg(a, float(np.linalg.norm(truth - p)), 0.5) for a, p in anchors.items()])
    frames[5] = Sensors(1, 1.0, odo, [RangeMsg(1, 150.0, 0.5)])
    ref.step(frames)
    assert np.allclose(ref.estimate(4).mean, truth, atol=1e-6)
    assert np.array_equal(ref.estimate(5).mean, sc.prior(5)[0])  # one anchor: dead reckoning (zero speed)
    assert ref.stats == {"fixes": 3, "multilaterated": 1, "dead_reckoned": 1}


def test_dnbp_beats_least_squares_on_wan2014():
    """A short wan2014 run in process: over the GNSS-denied agents and ticks, dNBP's error is
    below the baseline's (which dead-reckons from a 300 m prior without 3 normal neighbours)."""
    from swarmloc.experiment.results import compute_references, metrics

    sc = S.load("wan2014").with_overrides(**{"clock.duration": 12.0, "estimator.params": {"M": 150}})
    record, nodes, _ = in_process(sc, "dnbp")
    compute_references(sc, record, ["ls"])
    m = metrics(record, ["dnbp", "ls"])["estimators"]
    assert m["dnbp"]["no_gnss_mean_error_m"] < m["ls"]["no_gnss_mean_error_m"]
    assert sum(n.stats["fault_sent"] for n in nodes.values()) > 0


@pytest.mark.slow
def test_lockstep_over_zenoh_equals_in_process(cli, tmp_path):
    sc = S.load("wan2014").with_overrides(**{"clock.duration": 4.0, "estimator.params": {"M": 100}})
    path = tmp_path / "w.yaml"
    path.write_text(sc.to_yaml())
    out = tmp_path / "run"
    cli.run("run", str(path), "--out", str(out), "--port", str(cli.port), "--swarm", cli.swarm, "--no-plots",
            check=True, timeout=300)
    with np.load(out / "estimates" / "dnbp.npz") as f:
        zen = f["mean"]
    record, _, _ = in_process(sc, "dnbp")
    assert np.array_equal(zen, record.trace("dnbp").mean)


@pytest.mark.slow
def test_real_time_with_loss_still_localizes(cli, tmp_path):
    """Real time, 10% frame loss: no agent falls behind, every agent reports, and the
    GNSS-denied agents end far better than their 300 m prior."""
    import json

    sc = S.load("wan2014").with_overrides(**{"clock.mode": "realtime", "clock.duration": 6.0,
                                             "estimator.params": {"M": 100},
                                             "faults": [{"at": 0.0, "action": "loss", "probability": 0.1}]})
    path = tmp_path / "w.yaml"
    path.write_text(sc.to_yaml())
    out = tmp_path / "run"
    cli.run("run", str(path), "--out", str(out), "--port", str(cli.port), "--swarm", cli.swarm, "--no-plots",
            check=True, timeout=300)
    m = json.loads((out / "metrics.json").read_text())
    assert m["unresponsive_agents"] == [] and m["radio"]["dropped"].get("loss", 0) > 0
    e = m["estimators"]["dnbp"]
    assert e["no_gnss_mean_error_m"] is not None and e["no_gnss_mean_error_m"] < 150.0
    assert all(a["ticks_missing"] <= 2 for a in e["agents"].values())


# --------------------------------------------------------------------------- the paper's own setup


def paper_run(seed, R, duration=12.0, M=150):
    from swarmloc.experiment.results import compute_references, metrics

    sc = S.load("wan2014-paper").with_overrides(**{"clock.duration": duration, "seed": seed, "estimator.params": {"M": M},
                                                   "radio.range_m": R, "sensors.range.max_range": R})
    record, _, _ = in_process(sc, "dnbp")
    compute_references(sc, record, ["ls"])
    return metrics(record, ["dnbp", "ls"])["estimators"]


def test_the_paper_scenario_starts_known_with_a_weak_motion_model():
    """wan2014-paper: wan2014 with each UAV's start known to its GPS's 3 m instead of 300 m, and
    odometry four times noisier in speed and five times in heading rate."""
    paper, ours = S.load("wan2014-paper"), S.load("wan2014")
    assert paper.estimation.initial_std == paper.sensors.gnss.noise == 3.0
    assert paper.sensors.odometry.speed_noise >= 4 * ours.sensors.odometry.speed_noise
    assert paper.sensors.odometry.turn_rate_noise >= 5 * ours.sensors.odometry.turn_rate_noise
    assert [a.start for a in paper.world.agents] == [a.start for a in ours.world.agents]
    assert paper.estimator.params["M"] == 300
    errs = [np.linalg.norm(paper.prior(a)[0] - paper.agent(a).start) for a in paper.agent_ids]
    assert max(errs) < 5 * 3.0  # 20 draws of a 3 m std in 2D


@pytest.mark.slow
def test_dnbp_beats_least_squares_at_short_range_from_known_starts():
    """The paper's ordering at R = 300 m (Fig. 6(b), 200-350 m): over 3 seeds of 12 s of
    wan2014-paper, dNBP's GNSS-denied error is below the baseline's in every seed, the baseline
    dead-reckoning on the weak motion model whenever it lacks 3 normal neighbours."""
    for seed in range(3):
        m = paper_run(seed, 300.0)
        assert m["dnbp"]["no_gnss_mean_error_m"] < m["ls"]["no_gnss_mean_error_m"], seed


@pytest.mark.slow
def test_least_squares_is_as_good_as_dnbp_at_long_range_from_known_starts():
    """The paper's claim for R > 500 m: with every UAV in reach of 3 normal ones, least squares
    is near optimal. Over 3 seeds of 12 s at R = 700 m (M = 150), its GNSS-denied error is below dNBP's
    on average (dNBP's M samples and weak prediction add their own noise)."""
    runs = [paper_run(seed, 700.0) for seed in range(3)]
    assert np.mean([m["ls"]["no_gnss_mean_error_m"] for m in runs]) < np.mean([m["dnbp"]["no_gnss_mean_error_m"] for m in runs])
