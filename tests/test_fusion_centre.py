"""The centralized EKF of Goel et al. 2016, section 3: JointEkf / CentralizedEkf (offline
reference "ekf-ccl") and the fusion-centre roles (FusionCentre on a ground station,
CentreClient on each UAS, "ekf-centre"), on synthetic UAS data made here with netsim/world/uas_sensors.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
from msgspec.structs import replace

from netsim.world import uas_sensors as uas
from swarmloc import wire
from swarmloc.estimators.ekf.ccl import CentralizedEkf, JointEkf
from swarmloc.estimators.ekf.centre import CentreClient, FusionCentre
from swarmloc.estimators.ekf.local import EkfNode, placeholder_prior
from swarmloc.estimators.settings import CentreSettings
from swarmloc.models import ins
from swarmloc.models.motion import MOTION_MODELS
from swarmloc.node import Send, Timer
from swarmloc.wire.messages import AlignMsg, CentreData, CentreEstimate, GnssMsg, ImuMsg, RelPosMsg, Sensors

UAS_MODEL = MOTION_MODELS["uas-ins"]
IMU = ins.ImuSpec()
DT, IMU_RATE, EPOCH = 0.1, 100, 10  # tick (s), IMU samples per second, ticks per GNSS / relpos epoch


def p0_diag() -> np.ndarray:
    return np.concatenate([[1.0] * 3, [0.1**2] * 3, [math.radians(1.0) ** 2] * 3,
                           [IMU.gyro_bias_sigma0**2] * 3, [IMU.accel_bias_sigma0**2] * 3, [1.0]])


class Flight:
    """N UAS on figure-8s side by side: truth, and per tick each one's sensor frame.

    Frame k carries the IMU intervals of (t_{k-1}, t_k] (none at tick 0, which carries the
    alignment instead), a GNSS fix every EPOCH ticks for the UAS in `gnss`, and, every EPOCH
    ticks, the relative position of every other UAS if `relpos`."""

    def __init__(self, n: int, gnss=None, relpos: bool = True, seed: int = 0, gnss_std: float = 2.0,
                 relpos_std: float = 0.05, spacing: float = 30.0):
        self.ids = list(range(1, n + 1))
        self.gnss = set(self.ids if gnss is None else gnss)
        self.relpos, self.gnss_std, self.relpos_std = relpos, gnss_std, relpos_std
        self.rng = np.random.default_rng(seed)
        self.traj = {a: uas.figure8(center=(spacing * i, 0.0), width=120.0, period=40.0, phase=0.3 * i)
                     for i, a in enumerate(self.ids)}
        self.imu = {a: uas.ImuSimulator(self.traj[a], 1.0 / IMU_RATE, IMU, rng=seed * 1000 + a) for a in self.ids}
        self.k = -1

    def true_state(self, a: int, t: float) -> ins.InsState:
        tr = self.traj[a].truth(t)
        sim = self.imu[a]
        return ins.InsState(tr.position, tr.velocity, tr.quaternion, sim.gyro_bias, sim.accel_bias)

    def truth(self, t: float) -> dict[int, np.ndarray]:
        return {a: UAS_MODEL.pack(self.true_state(a, t)) for a in self.ids}

    def frames(self) -> dict[int, Sensors]:
        self.k += 1
        k, t = self.k, self.k * DT
        pos = {a: self.traj[a].position(t) for a in self.ids}
        out = {}
        for a in self.ids:
            align = imu = gnss = None
            if k == 0:
                P0 = np.diag(p0_diag())
                e = self.rng.standard_normal(16) * np.sqrt(p0_diag())
                align = AlignMsg(UAS_MODEL.pack(ins.inject(self.true_state(a, t), e)), P0)
            else:
                rec = self.imu[a].run(int(round(DT * IMU_RATE)))
                imu = ImuMsg(1.0 / IMU_RATE, np.hstack([rec.gyro, rec.accel]))
            epoch = k % EPOCH == 0
            if epoch and a in self.gnss:
                gnss = GnssMsg(pos[a] + self.rng.normal(0.0, self.gnss_std, 3), self.gnss_std)
            rel = [RelPosMsg(b, uas.relative_position(pos[b], pos[a], self.relpos_std, self.rng), self.relpos_std)
                   for b in self.ids if b != a] if epoch and self.relpos else []
            out[a] = Sensors(k, t, None, [], gnss=gnss, imu=imu, relpos=rel, align=align)
        return out


def position_error(x: np.ndarray, truth: np.ndarray) -> float:
    return float(np.linalg.norm(x[:3] - truth[:3]))


def ccl_run(flight: Flight, ticks: int):
    """CentralizedEkf over the flight: per tick the frames, the estimates and the truth."""
    ref = CentralizedEkf(flight.ids, IMU)
    out = []
    for _ in range(ticks):
        fr = flight.frames()
        ref.step(fr)
        out.append((fr, {a: ref.estimate(a) for a in flight.ids}, flight.truth(fr[flight.ids[0]].t)))
    return ref, out


# --------------------------------------------------------------------------- the joint filter


def test_joint_ekf_of_one_uas_is_the_uas_alone():
    """N = 1: the joint filter is InsEkf (the node, EkfNode, stepped on the same frames)."""
    flight = Flight(1, relpos=False)
    ref = CentralizedEkf(flight.ids, IMU)
    node = EkfNode(1, *placeholder_prior(np.zeros(3), np.eye(3), IMU), imu=IMU)
    for _ in range(120):
        fr = flight.frames()
        ref.step(fr)
        node.step(fr[1])
        est = ref.estimate(1)
        assert est.k == node.k == fr[1].k
        np.testing.assert_allclose(est.mean, node.x, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(est.cov, node.P, rtol=1e-9, atol=1e-12)
        assert len(ref.nis[1]) == len(node.nis)
        for (a, da), (b, db) in zip(ref.nis[1], node.nis):
            assert da == db and a == pytest.approx(b, rel=1e-6)


def test_joint_ekf_members_come_and_go_in_id_order():
    joint = JointEkf(IMU)
    P = {a: np.diag(p0_diag()) * a for a in (1, 2, 3)}
    for a in (3, 1, 2):
        joint.add(a, np.full(16, float(a)) * 0.01, P[a])
    assert joint.ids == [1, 2, 3]
    joint.P[joint.block(1), joint.block(3)] = 0.5  # a cross-covariance must follow its members
    joint.remove(2)
    assert joint.ids == [1, 3] and joint.P.shape == (32, 32)
    assert np.all(joint.P[0:16, 16:32] == 0.5)
    np.testing.assert_allclose(joint.estimate(3)[1], P[3])
    np.testing.assert_allclose(joint.estimate(1)[0][:3], 0.01)
    with pytest.raises(ValueError):
        joint.add(4, np.zeros(15), np.eye(16))


@pytest.mark.slow
def test_relative_positions_bound_a_uas_without_gnss():
    """The paper's section 5.1 / fig. 7 case: UAS 2 has no GNSS, UAS 1 has; sharing relative
    positions in the joint filter keeps UAS 2 near UAS 1's accuracy, while alone its INS drifts."""
    flight = Flight(2, gnss=[1])
    alone = EkfNode(2, *placeholder_prior(np.zeros(3), np.eye(3), IMU), imu=IMU)
    ref = CentralizedEkf(flight.ids, IMU)
    err_ccl, err_alone, nis = [], [], []
    for _ in range(300):
        fr = flight.frames()
        ref.step(fr)
        alone.step(fr[2])
        truth = flight.truth(fr[1].t)
        err_ccl.append(position_error(ref.estimate(2).mean, truth[2]))
        err_alone.append(position_error(alone.x, truth[2]))
        nis += [v for vs in ref.nis.values() for v in vs]
    late = slice(200, None)
    rms = lambda e: float(np.sqrt(np.mean(np.square(e[late]))))
    assert rms(err_ccl) < 4.0  # UAS 1's GNSS, 2 m per axis, once a second, sets the scale
    assert rms(err_ccl) < 0.3 * rms(err_alone)
    # Consistent: the mean NIS per degree of freedom near 1.
    total, dof = sum(v for v, _ in nis), sum(d for _, d in nis)
    assert 0.5 < total / dof < 1.6


# --------------------------------------------------------------------------- the centre over the radio

CENTRE = 0


class Swarm:
    """A lockstep radio in-process, as the runner and netsim run it: at the start of a tick the
    timers due fire, then every node steps on its frame, then messages are delivered in rounds
    until none is left. Every message goes through the wire codec. While `centre_up` is False
    the centre is dead: nothing reaches it, it sends nothing, and a unicast to it comes back to
    its sender as a NACK (link_failed)."""

    def __init__(self, flight: Flight, forget_after: int = 20, reach=None):
        self.flight = flight
        self.centre = self.new_centre(forget_after)
        self.clients = {a: CentreClient(a, *placeholder_prior(np.zeros(3), np.eye(3), IMU), imu=IMU, centre=CENTRE)
                        for a in flight.ids}
        self.centre_up = True
        self.reach = reach or (lambda k, a: True)  # whether UAS a and the centre hear each other in tick k
        self.timers: dict[str, float] = {}
        self.seq = 0
        self.k, self.t = -1, 0.0

    def new_centre(self, forget_after: int = 20) -> FusionCentre:
        self.timers = {}
        return FusionCentre(CENTRE, self.flight.ids, IMU, wait=0.05, forget_after=forget_after)

    def node(self, a):
        return self.centre if a == CENTRE else self.clients[a]

    def tick(self) -> dict[int, Sensors]:
        frames = self.flight.frames()
        self.k, self.t = frames[self.flight.ids[0]].k, frames[self.flight.ids[0]].t
        queue = []
        if self.centre_up:
            for tag, due in sorted(self.timers.items()):
                if due <= self.t + 1e-9:
                    del self.timers[tag]
                    queue += [(CENTRE, o) for o in self.centre.on_timer(tag, self.t)]
            queue += [(CENTRE, o) for o in self.centre.step(Sensors(self.k, self.t, None, []))]
        for a in self.flight.ids:
            queue += [(a, o) for o in self.clients[a].step(frames[a])]
        while queue:
            queue = [out for src, o in queue for out in self.deliver(src, o)]
        return frames

    def deliver(self, src, out):
        if isinstance(out, Timer):
            self.timers[out.tag] = self.t + out.delay
            return []
        assert isinstance(out, Send) and out.dst is not None, "the centre's roles only unicast"
        self.seq += 1
        data = wire.encode(out.msg, src, self.seq, out.dst)
        assert len(data) <= wire.MAX_FRAME_BYTES
        uas_end = out.dst if src == CENTRE else src
        if not (self.centre_up and self.reach(self.k, uas_end)):
            if src == CENTRE and not self.centre_up:
                return []  # a dead centre hears no NACK
            return [(src, o) for o in self.node(src).link_failed(out.dst, out.msg)]
        return [(out.dst, o) for o in self.node(out.dst).receive(src, wire.decode(data).body)]


def test_centre_equals_the_offline_reference_falls_back_and_takes_uas_back():
    flight = Flight(3, gnss=[1], seed=1)
    ref = CentralizedEkf(flight.ids, IMU)
    swarm = Swarm(flight)
    ids = flight.ids
    history = {}
    for k in range(80):
        if k == 30:
            swarm.centre_up = False  # (b) the ground station is lost
        if k == 60:
            swarm.centre, swarm.centre_up = swarm.new_centre(), True  # (c) a new centre process, empty
        frames = swarm.tick()
        ref.step(frames)
        history[k] = {a: swarm.clients[a].estimate() for a in ids}
        for a in ids:
            c = swarm.clients[a]
            assert c.k == k and np.all(np.isfinite(c.x)) and np.all(np.isfinite(c.P))
            if k < 30:  # (a) on the centre: the offline reference's estimates
                assert c.adopted == k
                e = ref.estimate(a)
                np.testing.assert_allclose(c.x, e.mean, rtol=1e-9, atol=1e-9)
                np.testing.assert_allclose(c.P, e.cov, rtol=1e-9, atol=1e-12)
            elif k < 60:
                assert c.adopted is None
            else:
                assert c.adopted == k
        if k == 29:
            assert swarm.centre.stats["ticks_run"] == 30 and swarm.centre.stats["joined"] == 3
            assert all(c.stats["state_sent"] == 1 for c in swarm.clients.values())  # tick 0 only
    for a in ids:
        c = swarm.clients[a]
        assert c.stats["centre_ticks"] == 50 and c.stats["own_ticks"] == 30
        assert c.stats["centre_unreachable"] == 30 and c.stats["stale"] == 0
        assert c.stats["state_sent"] == 1 + 29 + 1  # tick 0, ticks 31-59 (not 30: it held 29's answer), 60
        assert not c.drops
    # (b) in the outage each UAS ran its own EKF from the centre's estimate of tick 29.
    flight2 = Flight(3, gnss=[1], seed=1)
    frames = [flight2.frames() for _ in range(60)]
    for a in ids:
        own = EkfNode(a, *placeholder_prior(np.zeros(3), np.eye(3), IMU), imu=IMU)
        e29 = history[29][a]
        own.resume(29, e29.mean, e29.cov)
        for k in range(30, 60):
            own.step(frames[k][a])
        np.testing.assert_allclose(history[59][a].mean, own.x, rtol=1e-12, atol=1e-12)
    # (c) the new centre took everyone in at tick 60 from their own estimates; relative positions
    # to UAS 1 (GNSS) pin down UAS 3 (no GNSS) again at once.
    assert swarm.centre.stats["joined"] == 3 and swarm.centre.stats["left"] == 0
    pos = lambda e: float(np.trace(e.cov[:3, :3]))
    assert pos(history[60][3]) < 0.5 * pos(history[59][3])
    assert not swarm.centre.drops


def test_a_uas_out_of_the_centres_reach():
    """UAS 3 cannot reach the centre from tick 10. The centre waits for it (its timer, so in
    lockstep the answers of those ticks reach the others one tick late: each adopts it as the
    previous tick's estimate and redoes its own step on top) until
    forget_after ticks have passed without its data; then the others are on the centre again.
    UAS 3 runs on its own all along, and is taken back in from its x, P when back in reach."""
    flight = Flight(3, gnss=[1, 2], seed=2)
    swarm = Swarm(flight, forget_after=3, reach=lambda k, a: not (a == 3 and 10 <= k < 25))
    adopted = {a: [] for a in flight.ids}
    for k in range(35):
        swarm.tick()
        for a in flight.ids:
            adopted[a].append(swarm.clients[a].adopted == k)
    c1, c3 = swarm.clients[1], swarm.clients[3]
    # Ticks 10-12: the centre still expects UAS 3 and runs on its timer at the next tick's start;
    # from tick 13, three ticks without its data, it no longer waits.
    assert adopted[1][:10] == [True] * 10 and adopted[1][10:13] == [False] * 3 and all(adopted[1][13:])
    assert c1.stats["stale"] == 0 and c1.stats["late_adopted"] == 3  # taken one tick late, under tick k's own step
    # Back at tick 25, its data arrive after the others', which were all the centre waited for:
    # late. From tick 26 the centre waits for it again and takes it in from its x, P.
    assert not any(adopted[3][10:26]) and all(adopted[3][26:])
    assert swarm.centre.stats["late"] == 1
    assert c3.stats["centre_unreachable"] == 15
    assert swarm.centre.stats["left"] == 1 and swarm.centre.stats["joined"] == 4
    assert all(np.isfinite(c.x).all() for c in swarm.clients.values())


def test_bad_messages_are_dropped_and_counted():
    flight = Flight(2, seed=3)
    swarm = Swarm(flight)
    for _ in range(3):
        last = swarm.tick()
    centre, client = swarm.centre, swarm.clients[1]
    good = replace(last[1], k=3)  # a frame of the next tick, as it could be
    x, P = client.x.copy(), client.P.copy()
    nan_x = x.copy()
    nan_x[4] = np.nan
    bad_P = P.copy()
    bad_P[0, 1] += 1.0  # not symmetric
    neg_P = -np.eye(16)
    bad_data = [
        CentreData(3, good, nan_x, P),
        CentreData(3, good, x[:15], P),
        CentreData(3, good, x, bad_P),
        CentreData(3, good, x, neg_P),
        CentreData(3, good, x, None),
        CentreData(3, good, x * 1e12, P),
        CentreData(4, good, None, None),  # the frame is of tick 3
        CentreData(3, Sensors(3, good.t, None, [], imu=ImuMsg(0.01, np.full((10, 6), np.inf)))),
        CentreData(3, Sensors(3, good.t, None, [], imu=ImuMsg(0.01, np.zeros((10, 5))))),
        CentreData(3, Sensors(3, good.t, None, [], imu=good.imu, gnss=GnssMsg(np.zeros(3), 0.0))),
        CentreData(3, Sensors(3, good.t, None, [], imu=good.imu, relpos=[RelPosMsg(2, np.zeros(2), 0.1)])),
        CentreData(3, Sensors(3, good.t, None, [], imu=good.imu, relpos=[RelPosMsg(2, np.zeros(3), 1e-12)])),
        CentreData(3, Sensors(3, good.t, None, [], imu=ImuMsg(5.0, good.imu.samples))),
    ]
    for msg in bad_data:
        assert centre.receive(1, msg) == []
    assert centre.receive(1, CentreEstimate(3, x, P)) == []  # not a message for the centre
    assert centre.receive(7, CentreData(3, good)) == []  # not a UAS of the swarm
    assert centre.pending is None and sum(centre.drops.values()) == len(bad_data) + 2

    k = client.k
    bad_estimates = [CentreEstimate(k, nan_x, P), CentreEstimate(k, x[:3], P), CentreEstimate(k, x, bad_P),
                     CentreEstimate(k, x, neg_P), CentreEstimate(k, x, P * 1e20), CentreEstimate(k + 1, x, P)]
    before = client.estimate()
    for msg in bad_estimates:
        assert client.receive(CENTRE, msg) == []
    assert client.receive(2, CentreEstimate(k, x, P)) == []  # not from the centre
    assert client.receive(CENTRE, CentreData(k, good)) == []
    assert sum(client.drops.values()) == len(bad_estimates) + 2
    assert client.drops["future"] == 1 and client.stats["stale"] == 0
    np.testing.assert_array_equal(client.estimate().mean, before.mean)
    np.testing.assert_array_equal(client.estimate().cov, before.cov)
    # Non-finite numbers do not even get through the wire: the receiving daemon drops the frame.
    with pytest.raises(wire.WireError):
        wire.decode(wire.encode(CentreEstimate(k, nan_x, P), CENTRE, 1, 1))
    # After all that, both carry on as before.
    swarm.tick()
    assert all(c.adopted == swarm.k for c in swarm.clients.values())


def test_the_centre_is_deterministic():
    runs = []
    for _ in range(2):
        flight = Flight(3, gnss=[1], seed=4)
        swarm = Swarm(flight, forget_after=2, reach=lambda k, a: not (a == 2 and 5 <= k < 9))
        for _ in range(15):
            swarm.tick()
        runs.append([(c.x.copy(), c.P.copy(), dict(c.stats)) for c in swarm.clients.values()])
    for (x1, P1, s1), (x2, P2, s2) in zip(*runs):
        np.testing.assert_array_equal(x1, x2)
        np.testing.assert_array_equal(P1, P2)
        assert s1 == s2


def uas_scenario(stations=(0,), **params):
    from swarmloc.experiment import scenario

    agents = [{"id": s, "model": "ground-station", "start": [0.0, 0.0, 0.0]} for s in stations]
    agents += [{"id": a, "model": "uas-ins", "start": [30.0 * a, 0.0, 50.0]} for a in (1, 2)]
    return scenario.parse({"version": 1, "name": "centre", "clock": {"dt": 0.1, "duration": 1.0},
                           "world": {"agents": agents}, "estimator": {"name": "ekf-centre", "params": params}})


def test_roles_from_the_scenario():
    from swarmloc.estimators import REGISTRY, make_nodes
    from swarmloc.node import Idle

    nodes = make_nodes("ekf-centre", uas_scenario(wait=0.02, forget_after=5))
    assert isinstance(nodes[0], FusionCentre) and nodes[0].wait == 0.02 and nodes[0].forget_after == 5
    assert nodes[0].roster == {1, 2} and nodes[0].model.state_dim == 0
    assert all(isinstance(nodes[a], CentreClient) and nodes[a].centre == 0 for a in (1, 2))
    nodes = make_nodes("ekf-centre", uas_scenario((0, 9), centre=9))
    assert isinstance(nodes[9], FusionCentre) and isinstance(nodes[0], Idle) and nodes[1].centre == 9
    for stations, params in (((), {}), ((0, 9), {}), ((0,), {"centre": 1})):
        with pytest.raises(ValueError, match="ground-station"):
            make_nodes("ekf-centre", uas_scenario(stations, **params))
    with pytest.raises(ValueError, match="wait"):
        REGISTRY["ekf-centre"].settings({"wait": -1.0})
    with pytest.raises(ValueError, match="typo"):
        REGISTRY["ekf-centre"].settings({"typo": 1})
    assert CentreSettings() == REGISTRY["ekf-centre"].settings()
    ref = REGISTRY["ekf-ccl"].make_reference(uas_scenario(), [0, 1, 2])
    assert isinstance(ref, CentralizedEkf) and ref.ids == [1, 2]  # the ground station is not localized


def test_a_tick_whose_arithmetic_fails_changes_nothing(monkeypatch):
    """If the joint update fails anyway, the centre keeps its state of the tick before, answers
    nobody (the UAS carry on on their own) and takes them back in from their x, P next tick."""
    flight = Flight(2, seed=5)
    swarm = Swarm(flight)
    for _ in range(4):
        swarm.tick()
    centre = swarm.centre
    before = (list(centre.joint.ids), centre.joint.P.copy())

    def broken(frames):
        raise np.linalg.LinAlgError("singular")

    monkeypatch.setattr(centre.joint, "update", broken)
    swarm.tick()
    assert centre.stats["numerical"] == 1 and centre.drops["numerical"] == 1
    assert centre.joint.ids == before[0] and np.array_equal(centre.joint.P, before[1])
    assert all(c.adopted is None for c in swarm.clients.values())
    monkeypatch.undo()
    swarm.tick()
    assert all(c.adopted == swarm.k for c in swarm.clients.values())
    assert centre.stats["left"] == 2 and centre.stats["joined"] == 4


def test_relative_positions_in_information_form_are_the_stacked_update():
    """JointEkf's one information-form update of a tick's relative positions equals the stacked
    EKF update of the same rows (one batch), state and covariance, to rounding."""
    import copy

    from netsim.sim import Simulation
    from swarmloc.estimators.ekf.ccl import CentralizedEkf
    from swarmloc.experiment import scenario as S

    sc = S.load("goel10").with_overrides(**{"clock.duration": 2.0, "sensors.gnss.agents": [2, 4, 6, 8, 10]})
    sim = Simulation(sc)
    frames = [sim.tick()[2] for _ in range(sim.steps + 1)]
    ccl = CentralizedEkf.from_scenario(sc, sc.localized_ids)
    for fr in frames[:10]:
        ccl.step(fr)
    joint = ccl.joint
    joint.predict({a: frames[10][a].imu for a in joint.ids})
    batches = joint.batches(frames[10])
    assert [len(b) for b in batches] == [5, 90]  # 5 fixes, then every relative position at once
    fast, stacked = copy.deepcopy(joint), copy.deepcopy(joint)
    fast.nis = {a: [] for a in joint.ids}
    stacked.nis = {a: [] for a in joint.ids}
    for f in (fast, stacked):
        f._update(batches[0])
    fast._update_linear(batches[1])
    stacked._update(batches[1])
    x = lambda f: np.concatenate([f.estimate(a)[0] for a in f.ids])
    assert np.abs(x(fast) - x(stacked)).max() < 1e-12
    assert np.abs(fast.P - stacked.P).max() < 1e-12 * np.abs(stacked.P).max()
    assert np.allclose([v for a in fast.ids for v, _ in fast.nis[a]], [v for a in fast.ids for v, _ in stacked.nis[a]])
