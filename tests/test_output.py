"""What the daemon sends its flight controller (agents/companion/output.py) and the peers' clock
offsets (agents/timesync.py), without sockets: the estimate propagated between ticks with the
estimator's own time update, the reset counter, setpoints and their hold, NTP's offset."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from agents.companion.mavlink import Link, OutputRate
from agents.companion.output import (
    COPTER_HOLD,
    COPTER_TRACK,
    ROVER_VELOCITY,
    EstimateStream,
    FcOutputs,
    SetpointStream,
)
from agents.timesync import PeerClocks
from swarmloc.models.motion import MOTION_MODELS, Odometry
from swarmloc.models.vehicles import MODELS
from swarmloc.wire.messages import TimeSync


class StubFc:
    """A FlightController's sending side: records what would go out."""

    def __init__(self):
        self.output_rate = OutputRate(1e6)
        self.estimates, self.targets = [], []
        self.state, self.fc = Link.ALIVE, (1, 1)

    def send_estimate(self, t, position, cov, velocity=None, cov_velocity=None, yaw=None, yaw_var=None,
                      reset_counter=0):
        self.estimates.append((t, np.array(position), np.array(cov), reset_counter))
        return True

    def send_position_target(self, t, mask, p, v, a, yaw, rate):
        self.targets.append((t, mask, p, v, a, yaw, rate))
        return True


def ticks_of(tick=0.1, **kw):
    cfg = SimpleNamespace(tick=tick, speed_std=0.1, heading_std=0.02, turn_rate_std=0.01)
    return SimpleNamespace(fc=StubFc(), cfg=cfg, listeners=[], height=10.0, base=0.0, last_t=0.0,
                           time_of=lambda k: k * tick, position=None, yaw=None, u=None, **kw)


def stream(model: str, gate: float = 5.0, node=None, **kw):
    ticks = ticks_of(**kw)
    node = node or SimpleNamespace(model=MOTION_MODELS[model])
    return EstimateStream(node, ticks, SimpleNamespace(reset_gate=gate)), ticks


def planar_row(speed, heading, rate=0.0):
    return (speed, math.cos(heading), math.sin(heading), rate)


def test_between_ticks_the_estimate_moves_with_the_fc_samples_and_grows_at_the_nodes_rate():
    """A planar estimate propagated over a tick of 50 Hz FC samples lands where the motion
    model's one-tick step puts it, with the covariance that step adds (Q grows linearly in
    time at the node's rate, whatever the sample rate); each sample's state goes out once,
    stamped with the sample's FC time."""
    out, ticks = stream("planar-speed-heading")
    x0, P0 = np.array([1.0, 2.0]), np.diag([0.04, 0.09])
    out.estimate(x0, P0, 12.0)
    times = [12.02, 12.04, 12.06, 12.08, 12.10]
    for t in times:
        out.sample(t, planar_row(2.0, 0.3))
        out.poll(0.0)
        out.poll(0.0)  # nothing new since: not sent again
    x, F, Q = MOTION_MODELS["planar-speed-heading"].predict(x0, Odometry(0.1, 2.0, 0.3, 0.1, 0.02))
    mean, cov, t = out.chain
    np.testing.assert_allclose(mean, x, atol=1e-12)
    np.testing.assert_allclose(cov, P0 + Q, atol=1e-12)
    assert t == 12.10 and [s[0] for s in ticks.fc.estimates] == times
    assert all(s[2][2, 2] == pytest.approx(100.0**2) and s[1][2] == 10.0 for s in ticks.fc.estimates)  # the FC's height


def test_a_new_estimate_restarts_from_its_tick_and_a_jump_changes_the_reset_counter():
    out, ticks = stream("planar-speed-heading")
    P = np.eye(2) * 0.01
    out.estimate(np.zeros(2), P, 0.0)
    for t in (0.02, 0.04, 0.06, 0.08, 0.10, 0.12, 0.14):
        out.sample(t, planar_row(1.0, 0.0))
    # Tick 1's estimate (t = 0.1), corrected by a std: the samples after it move it on.
    out.estimate(np.array([0.2, 0.1]), P, 0.1)
    mean, _, t = out.chain
    assert t == 0.14 and mean == pytest.approx([0.24, 0.1])
    assert out.reset_counter == 0
    # A rejoin: 30 std away from where the stream had it.
    out.estimate(np.array([3.2, 0.1]), P, 0.1)
    assert out.reset_counter == 1 and out.resets == 1
    out.poll(0.0)
    assert ticks.fc.estimates[-1][3] == 1


def test_uas_ins_between_ticks_is_the_nodes_own_time_update():
    """uas-ins: the chain over a tick's IMU rows, one row at a time, equals the node's filter
    stepping over all of them at once (its batched mechanization)."""
    from swarmloc.estimators.ekf.local import InsEkf
    from swarmloc.models import ins
    from swarmloc.wire.messages import ImuMsg

    imu = ins.ImuSpec()
    node = SimpleNamespace(model=MOTION_MODELS["uas-ins"], filter=SimpleNamespace(imu=imu))
    out, _ = stream("uas-ins", node=node)
    x0 = np.zeros(16)
    x0[2], x0[3] = 10.0, 5.0
    P0 = np.eye(16) * 0.01
    rng = np.random.default_rng(0)
    rows = [np.r_[0.01 * rng.standard_normal(3), [0.1, 0.2, 9.81]] for _ in range(10)]
    out.estimate(x0, P0, 1.0)
    for i, r in enumerate(rows):
        out.sample(1.0 + 0.01 * (i + 1), (1.0 + 0.01 * (i + 1), r))
    f = InsEkf(x0, P0, imu)
    f.predict(ImuMsg(0.01, np.array(rows)))
    mean, cov, _ = out.chain
    np.testing.assert_allclose(mean, f.vector(), atol=1e-9)
    np.testing.assert_allclose(cov, f.P, rtol=1e-9, atol=1e-15)


def test_a_vehicle_is_propagated_by_its_model_under_the_command_in_force():
    """A ground robot's chain over a tick of samples is its model's prediction under the
    command in force (set by the daemon when the command goes out), and over a whole tick its
    covariance grows about as much as the node's one-tick predict adds."""
    from swarmloc.estimators.vehicles.filters import VehicleEkf

    dyn = MODELS["ground-robot"]
    std = np.array([0.3, 3e-3])
    node = SimpleNamespace(model=MOTION_MODELS["ground-robot"], actuator_std=std)
    out, _ = stream("ground-robot", node=node, tick=0.05)
    x0 = dyn.initial_state([1.0, 2.0, 0.0], 0.4)
    x0[4] = 0.5  # rolling at 0.5 m/s
    P0 = np.eye(7) * 1e-8  # small: what the tick adds dominates
    u = np.array([0.8, 0.01])
    out.set_command(u)
    out.estimate(x0, P0, 3.0)
    for i in range(1, 6):
        out.sample(3.0 + 0.01 * i, None)
    f = VehicleEkf(dyn, x0, P0, std)
    f.predict(u, 0.05)
    mean, cov, _ = out.chain
    np.testing.assert_allclose(mean, f.x, atol=1e-6)  # RK4 in 5 steps or in 1
    # Not equal: noise injected early in the tick reaches the position through the dynamics by
    # its end, which the node's single step leaves to the next tick (a tenth more here).
    grown, node_grown = np.trace(cov - P0), np.trace(f.P - P0)
    assert 0.8 < grown / node_grown < 1.25, (grown, node_grown)
    # Coasting on the hover input (no force) instead is another path: the command matters.
    still, _ = stream("ground-robot", node=node, tick=0.05)
    still.estimate(x0, P0, 3.0)
    for i in range(1, 6):
        still.sample(3.0 + 0.01 * i, None)
    assert abs(still.chain[0][4] - mean[4]) > 0.02  # 0.8 N on 1.75 kg for 50 ms


# --------------------------------------------------------------------------- setpoints


def setpoints(model: str, stale_after=0.5, rate_hz=20.0):
    ticks = ticks_of(tick=0.05)
    node = SimpleNamespace(model=MOTION_MODELS[model])
    return SetpointStream(node, ticks, SimpleNamespace(rate_hz=rate_hz, stale_after=stale_after)), ticks


def test_a_command_becomes_where_the_model_goes_in_one_tick():
    """A quadrotor hovering on its hover command: the setpoint is where it is, at rest, with no
    acceleration and its yaw (position, velocity, acceleration and yaw used). A ground robot:
    the velocity its model reaches under the command, velocity alone used."""
    quad = MODELS["quadrotor"]
    sp, ticks = setpoints("quadrotor")
    x = quad.initial_state([1.0, 2.0, 3.0], 0.5)
    sp.command(quad.hover_input(), x, now=10.0)
    sp.poll(10.01)
    t, mask, p, v, a, yaw, rate = ticks.fc.targets[-1]
    assert mask == COPTER_TRACK
    np.testing.assert_allclose(p, [1.0, 2.0, 3.0], atol=1e-9)
    np.testing.assert_allclose(v, 0.0, atol=1e-9)
    np.testing.assert_allclose(a, 0.0, atol=1e-9)
    assert yaw == pytest.approx(0.5) and rate is None

    ground = MODELS["ground-robot"]
    sp, ticks = setpoints("ground-robot")
    x = ground.initial_state([0.0, 0.0, 0.0], 0.3)
    x[4] = 0.5
    sp.command(np.array([0.0, 0.0]), x, now=10.0)  # no force, no moment: it rolls on
    sp.poll(10.01)
    t, mask, p, v, a, yaw, rate = ticks.fc.targets[-1]
    assert mask == ROVER_VELOCITY and p is None and a is None
    np.testing.assert_allclose(v[:2], 0.5 * np.array([math.cos(0.3), math.sin(0.3)]), atol=1e-3)


def test_setpoints_hold_when_estimates_go_stale_or_the_link_is_lost():
    sp, ticks = setpoints("ground-robot", stale_after=0.5, rate_hz=20.0)
    ground = MODELS["ground-robot"]
    x = ground.initial_state([0.0, 0.0, 0.0], 0.0)
    x[4] = 1.0
    sent = ticks.fc.targets

    def speed():
        return float(np.linalg.norm(sent[-1][3]))

    sp.poll(0.0)  # no command yet: a hold, so the operator can switch to offboard
    assert speed() == 0.0
    sp.command(np.zeros(2), x, now=0.05)
    sp.poll(0.1)
    assert speed() == pytest.approx(1.0, abs=1e-3)
    sp.poll(0.54)
    assert speed() > 0.9  # 0.49 s after the estimate: still fresh
    sp.poll(0.62)
    assert speed() == 0.0 and sp.holding  # stale: stop
    sp.command(np.zeros(2), x, now=0.65)
    ticks.fc.state = Link.LOST
    sp.poll(0.7)
    assert speed() == 0.0  # fresh, but the FC's heartbeat is gone
    ticks.fc.state = Link.ALIVE
    sp.poll(0.75)
    assert speed() > 0.9 and not sp.holding
    # At most rate_hz a second, however often the loop polls.
    n = len(sent)
    for i in range(1000):
        sp.poll(1.0 + i * 1e-3)
    assert len(sent) - n == 20


def test_a_copter_holds_where_its_fc_says_it_is():
    sp, ticks = setpoints("quadrotor")
    sp.poll(0.0)
    assert ticks.fc.targets == [] and sp.counts["hold-without-position"] == 1  # no FC position yet
    ticks.position, ticks.yaw = np.array([4.0, 5.0, 6.0]), 1.2
    sp.poll(1.0)
    t, mask, p, v, a, yaw, rate = ticks.fc.targets[-1]
    assert mask == COPTER_HOLD and p.tolist() == [4.0, 5.0, 6.0] and v.tolist() == [0.0, 0.0, 0.0] and yaw == 1.2


def test_no_setpoint_unless_enabled():
    ticks = ticks_of(tick=0.05)
    node = SimpleNamespace(model=MOTION_MODELS["ground-robot"], actuator_std=np.array([0.3, 3e-3]))
    off = FcOutputs(node, ticks, None, SimpleNamespace(enabled=False, rate_hz=20.0, stale_after=0.5))
    assert off.setpoints is None
    off.command(np.array([1.0, 0.0]), MODELS["ground-robot"].initial_state([0, 0, 0]))
    off.poll(0.0)
    assert ticks.fc.targets == [] and ticks.u.tolist() == [1.0, 0.0]  # the frames still carry it


# --------------------------------------------------------------------------- clocks


def exchange(offset: float, there: float, back: float, queueing: float = 0.0, rounds: int = 20, seed: int = 0):
    """Agents 1 and 2, 2's clock `offset` s ahead of 1's; frames take `there` s from 1 to 2 and
    `back` s from 2 to 1, plus up to `queueing` s at random. Each sends a time.sync a second,
    and 1 a radio frame in between."""
    rng = np.random.default_rng(seed)
    q = lambda: rng.uniform(0, queueing)
    a, b = PeerClocks(1, bound=0.010), PeerClocks(2, bound=0.010)
    t = 100.0  # agent 1's clock
    for _ in range(rounds):
        b.heard(1, t, t + there + q() + offset)  # 1 -> 2: a radio frame
        msg = b.sync_frame()
        t2 = t + 0.3 + offset  # 2 -> 1: its time.sync, stamped on its clock
        arrival = t + 0.3 + back + q()
        a.synced(2, msg, t2, arrival)
        a.heard(2, t2, arrival)
        b.synced(1, a.sync_frame(), t + 0.6, t + 0.6 + there + q() + offset)  # 1 -> 2: ours
        t += 1.0
    return a, b


def test_the_peers_clock_offset_is_estimated_to_within_half_the_round_trip():
    """NTP's four timestamps: with equal delays both ways the offset is exact; unequal, off by
    half their difference; with queueing, within half the round trip of the sample with the
    smallest one, which is the one used."""
    a, b = exchange(offset=0.015, there=0.004, back=0.004)
    assert a.offset(2) == pytest.approx(0.015, abs=1e-9) and b.offset(1) == pytest.approx(-0.015, abs=1e-9)
    a, b = exchange(offset=0.015, there=0.002, back=0.006)
    assert a.offset(2) == pytest.approx(0.015 - 0.002, abs=1e-9)  # (there - back) / 2, invisible to NTP
    a, b = exchange(offset=0.015, there=0.002, back=0.006, queueing=0.02)
    for clocks, peer, truth in ((a, 2, 0.015), (b, 1, -0.015)):
        rt, off = clocks.best(peer)
        assert abs(off - truth) <= rt / 2 and rt < 0.008 + 0.02  # the least queued of 20
    assert a.stats()["clock_offset_ms"][2]["offset_ms"] == pytest.approx(a.offset(2) * 1e3)
    a, b = exchange(offset=0.030, there=0.002, back=0.006, queueing=0.02)
    assert a.exceeded[2] > 0 and a.stats()["clock_exceeded"] == a.exceeded[2]  # 30 ms: beyond the 10 ms bound
    a, b = exchange(offset=0.003, there=0.002, back=0.002, queueing=0.02)
    assert abs(a.offset(2) - 0.003) < 0.01 and a.exceeded[2] == 0


def test_a_time_sync_without_our_stamp_says_nothing():
    a = PeerClocks(1)
    a.synced(2, TimeSync([]), 5.0, 5.1)
    assert a.samples == {} and a.stats()["clock_offset_ms"] == {}
    a.synced(2, TimeSync([]), None, 5.1)
    assert a.dropped["unstamped"] == 1
