"""UKF-DCL on the unicycle pose model (F != I) with range-bearing to agents and landmarks, step by
step against UKF-CCL (FilterPy-test style), with and without the chi-square gate."""


import numpy as np
import pytest
from msgspec.structs import replace

from netsim.sim import Simulation
from swarmloc.estimators.ukf.ccl import CentralizedUKF
from swarmloc.experiment import scenario as S
from swarmloc.experiment.runner import InProcessRunner, make_nodes
from swarmloc.node import LANDMARK
from swarmloc.wire.messages import RangeBearingMsg

TOL = 1e-9
LANDMARKS = [{"id": 0, "position": [20.0, 30.0]}, {"id": 1, "position": [-30.0, 10.0]},
             {"id": 2, "position": [10.0, -40.0]}, {"id": 3, "position": [60.0, 0.0]}]


def pose_swarm(**over):
    """Five unicycles wandering inside ~100 m, seeing each other and four landmarks within 60 m
    by range and bearing, a few ranges besides; one radio hop for everyone."""
    agents = [{"id": i + 1, "model": "planar-pose", "start": s, "heading": h,
               "motion": {"kind": "random", "speed": 1.0, "turn_rate_std": 0.1}}
              for i, (s, h) in enumerate([([0.0, 0.0], 0.3), ([40.0, 10.0], 1.9), ([20.0, 45.0], 4.0),
                                          ([-30.0, 25.0], 5.5), ([-10.0, -35.0], 1.0)])]
    sc = S.parse({
        "version": 1, "name": "pose5", "seed": 5,
        "clock": {"mode": "lockstep", "dt": 0.5, "duration": 15.0},
        "world": {"agents": agents, "landmarks": LANDMARKS},
        "sensors": {"odometry": {"speed_noise": 0.2, "turn_rate_noise": 0.05},
                    "range": {"noise": 0.5, "probability": 0.3, "max_per_step": 2, "max_range": 60},
                    "range_bearing": {"enabled": True, "max_range": 60.0, "range_noise": 0.3, "bearing_noise": 0.03}},
        "radio": {"model": "unit-disk", "range_m": 1000},
        "estimation": {"initial_std": 0.5, "initial_heading_std": 0.05},
        "estimator": {"name": "ukf-dcl"},
        "references": ["ukf-ccl"],
    })
    return sc.with_overrides(**over) if over else sc


class Tampered:
    """netsim's Simulation with some measurements rewritten before anyone sees them."""

    def __init__(self, sim, tamper):
        self.sim, self.tamper = sim, tamper
        self.ids, self.steps = sim.ids, sim.steps

    def tick(self):
        k, t, frames = self.sim.tick()
        return k, t, {a: self.tamper(k, a, f) for a, f in frames.items()}

    def truth(self):
        return self.sim.truth()

    def targets(self):
        return self.sim.targets()

    def exchange(self, frames):
        return self.sim.exchange(frames)


def lockstep_compare(sc, tamper=None):
    """UKF-DCL nodes and UKF-CCL side by side; after every tick each node's mean, own block and
    (Phi_i C_ij Phi_j^T) cross-covariances must equal the centralized ones, and so must the NIS
    of what each measurer committed."""
    sim = Simulation(sc)
    env = Tampered(sim, tamper) if tamper else sim
    nodes = make_nodes("ukf-dcl", sc)
    ccl = CentralizedUKF.from_scenario(sc, sc.agent_ids)
    worst = {"mean": 0.0, "own": 0.0, "cross": 0.0}
    counts = {"rb": 0, "landmarks": 0, "ranges": 0}

    def on_tick(k, frames):
        ccl.step(frames)
        for a, node in nodes.items():
            b = ccl.block(a)
            worst["mean"] = max(worst["mean"], np.abs(node.x - ccl.x[b]).max())
            worst["own"] = max(worst["own"], np.abs(node.row[a] - ccl.P[b, b]).max())
            for j, C in node.row.items():
                if j != a:
                    real = C if node.phi is None else node.phi @ C @ nodes[j].phi.T
                    worst["cross"] = max(worst["cross"], np.abs(real - ccl.P[b, ccl.block(j)]).max())
            assert [d for _, d in node.nis] == [d for _, d in ccl.nis[a]], f"tick {k}: agent {a}'s NIS"
            assert np.allclose([v for v, _ in node.nis], [v for v, _ in ccl.nis[a]], rtol=0, atol=TOL)
        for f in frames.values():
            counts["rb"] += len(f.rb)
            counts["landmarks"] += len(f.landmarks)
            counts["ranges"] += len(f.ranges)
        assert max(worst.values()) < TOL, f"tick {k}: diverged {worst}"

    InProcessRunner(env, nodes).run(on_tick=on_tick)
    return nodes, ccl, worst, counts


@pytest.mark.slow
@pytest.mark.parametrize("gate", [None, 0.95])
def test_pose_swarm_with_range_bearing_and_landmarks_equals_centralized_every_tick(gate):
    nodes, ccl, worst, counts = lockstep_compare(pose_swarm(**{"estimation.gate": gate}))
    assert counts["rb"] > 300 and counts["landmarks"] > 300 and counts["ranges"] > 10
    gated = sum(n.stats["measurements_gated"] for n in nodes.values())
    assert gated == ccl.gated and (gated > 0) == (gate is not None)
    assert all(n.stats["measurements_dropped"] == 0 for n in nodes.values())
    assert sum(n.stats["measurements_used"] for n in nodes.values()) + gated == sum(counts.values())
    assert all(n.phi is not None and not np.allclose(n.phi, np.eye(3)) for n in nodes.values())  # F != I at work


@pytest.mark.slow
def test_landmarks_alone_equal_centralized():
    """Only landmark sightings: every chain has one platform; the estimates stay uncorrelated."""
    sc = pose_swarm(**{"sensors.range_bearing.robots": False, "sensors.range.probability": 0.0})
    nodes, ccl, worst, counts = lockstep_compare(sc)
    assert counts["landmarks"] > 100 and counts["rb"] == counts["ranges"] == 0
    assert all(list(n.row) == [a] for a, n in nodes.items())
    assert sum(n.stats["measurements_used"] for n in nodes.values()) == counts["landmarks"]


@pytest.mark.slow
def test_landmark_gain_reaches_the_platforms_correlated_with_the_measurer():
    """Only agent 2 sees landmarks. Once correlated with the others (through their range-bearing
    of it), its landmark chains carry gains for them too, applied as in the centralized filter."""
    def tamper(k, a, f):
        return f if a == 2 else replace(f, landmarks=[])

    nodes, *_ = lockstep_compare(pose_swarm(), tamper)
    reach = [len(c.gains) for c in nodes[2].log if c.key[0] == 2 and c.key[1] == LANDMARK and c.gains]
    assert reach and max(reach) == len(nodes)


@pytest.mark.slow
def test_gate_rejects_an_outlier_identically():
    """One range-bearing 25 m long at tick 12: rejected by agent 2 and by UKF-CCL, and nothing else is."""
    def tamper(k, a, f):
        if k == 12 and a == 2:
            return replace(f, rb=[replace(f.rb[0], range=f.rb[0].range + 25.0)] + f.rb[1:])
        return f

    nodes, ccl, *_ = lockstep_compare(pose_swarm(**{"estimation.gate": 0.9999, "clock.duration": 8.0}), tamper)
    assert nodes[2].gate.rejected == 1 and ccl.gate.rejected == 1 and ccl.gated == 1
    assert nodes[2].stats["measurements_gated"] == 1
    assert sum(n.stats["measurements_gated"] for n in nodes.values()) == 1


@pytest.mark.slow
def test_gate_opens_after_a_streak_in_both_filters():
    """Agent 1's sightings of landmark 0 read 15 m long from tick 10: rejected three times, then
    the gate stands open for that key, in the distributed and the centralized filter alike."""
    def tamper(k, a, f):
        if k >= 10 and a == 1:
            return replace(f, landmarks=[replace(m, range=m.range + 15.0) if m.target == 0
                                                     else m for m in f.landmarks])
        return f

    sc = pose_swarm(**{"estimation.gate": 0.999, "estimation.gate_open_after": 3, "clock.duration": 8.0})
    nodes, ccl, *_ = lockstep_compare(sc, tamper)
    assert nodes[1].gate.forced > 0 and ccl.gate.forced == sum(n.gate.forced for n in nodes.values())
    assert ccl.gate.rejected == sum(n.gate.rejected for n in nodes.values())


def test_speed_heading_swarm_drops_range_bearing_and_stays_exact():
    """planar-speed-heading has no heading to read a body-frame bearing with: both filters
    leave range-bearing frames out and run on ranges as before (no Phi: rows are real)."""
    def tamper(k, a, f):
        return replace(f, rb=[RangeBearingMsg(b, 10.0, 0.1, 0.3, 0.03) for b in (1, 2) if b != a])

    sc = S.load("wang2019").with_overrides(**{"clock.duration": 40.0})
    nodes, ccl, worst, counts = lockstep_compare(sc, tamper)
    assert all(n.phi is None for n in nodes.values())
    assert counts["ranges"] > 20 and counts["rb"] > 0
    assert sum(n.stats["measurements_dropped"] for n in nodes.values()) == counts["rb"]
    assert sum(n.stats["measurements_used"] for n in nodes.values()) == counts["ranges"]


@pytest.mark.slow
def test_partitioned_pose_swarm_keeps_equal_copies():
    """A 35 m radio splits the swarm: outsiders take commits late, parts replay each other's
    logs when they meet. With F != I that works on core rows: nodes at equal versions hold
    transposed copies of each core block, and every joint covariance stays positive definite."""
    sc = pose_swarm(**{"radio.range_m": 35.0, "clock.duration": 30.0})
    sim = Simulation(sc)
    nodes = make_nodes("ukf-dcl", sc)
    InProcessRunner(sim, nodes).run()
    assert sum(n.stats["outsider_commits"] for n in nodes.values()) > 0
    assert sum(n.stats["commits_replayed"] for n in nodes.values()) > 0
    for a, n in nodes.items():
        assert np.linalg.eigvalsh(n.row[a]).min() > 0 and not n.orphan
        for j, m in nodes.items():
            if j != a and m.version == n.version:
                np.testing.assert_allclose(m._block(a), n._block(j).T, atol=1e-9)
    ids = sorted(nodes)
    P = np.block([[nodes[i].row[i] if i == j else nodes[i].phi @ nodes[i]._block(j) @ nodes[j].phi.T for j in ids]
                  for i in ids])
    assert np.linalg.eigvalsh((P + P.T) / 2).min() > 0
