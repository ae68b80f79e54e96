"""Sensor sources and outputs of `swarmloc agent --config` (agents/companion/sources.py): a flight
controller in and out (tests/fake_fc.py over UDP), a missing one, a recording replayed, and
garbage on a zenoh source key. Real agent processes, real Zenoh sessions on 127.0.0.1."""

import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
import uuid
import warnings

import numpy as np
import pytest
import yaml
import zenoh
from conftest import free_port
from fake_fc import FakeFlightController
from test_mavlink import udp_port

from agents.companion.mavlink import mavlink
from netsim.sim import Simulation
from swarmloc import wire
from swarmloc.experiment.runner import InProcessRunner, make_nodes
from swarmloc.experiment.scenario import load as load_scenario
from swarmloc.wire.messages import EstimateMsg, Reply

SKEWED = """
import runpy, sys, time
_time = time.time
time.time = lambda: _time() + {skew}
sys.argv[0] = "agents"
runpy.run_module("agents", run_name="__main__", alter_sys=True)
"""


class Agent:
    """`swarmloc agent --config` in a subprocess, its stderr collected line by line."""

    def __init__(self, tmp_path, *, clock_skew: float = 0.0, **fields):
        """`clock_skew` (s): this process's UNIX clock reads that much ahead of the host's, as a
        companion whose clock is off does (time.time, which the daemon stamps and ticks with)."""
        self.swarm = "s" + uuid.uuid4().hex[:8]
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        data = {"version": 1, "id": 1, "swarm": self.swarm, "estimator": {"name": "il"},
                "model": "planar-speed-heading", "prior": {"position": [0.0, 0.0]},
                "zenoh": {"mode": "peer", "listen": [self.endpoint]}, **fields}
        path = tmp_path / f"agent-{self.swarm}.yaml"
        path.write_text(yaml.safe_dump(data))
        self.keys = wire.Keys(self.swarm)
        self.lines: list[str] = []
        python = [sys.executable, "-c", SKEWED.format(skew=clock_skew)] if clock_skew else [sys.executable, "-m", "agents"]
        self.proc = subprocess.Popen([*python, "agent", "--config", str(path), "-v"], stderr=subprocess.PIPE, text=True,
                                     cwd=tmp_path)
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self):
        for line in self.proc.stderr:
            self.lines.append(line)

    def wait_for(self, text: str, timeout: float = 20.0) -> str:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            hit = [line for line in self.lines if text in line]
            if hit:
                return hit[0]
            assert self.proc.poll() is None, f"agent exited {self.proc.returncode}:\n{''.join(self.lines)}"
            time.sleep(0.02)
        raise AssertionError(f"no {text!r} in:\n{''.join(self.lines)}")

    def session(self) -> zenoh.Session:
        return zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("peer", [], [self.endpoint])))

    def stop(self) -> int:
        self.proc.send_signal(signal.SIGTERM)
        return self.proc.wait(10)


@pytest.fixture
def agents():
    started = []
    yield lambda *a, **kw: started.append(Agent(*a, **kw)) or started[-1]
    for a in started:
        if a.proc.poll() is None:
            a.proc.kill()
            a.proc.wait()


def estimates(session, key) -> list:
    got = []
    session.declare_subscriber(key, lambda s: got.append(wire.decode(s.payload.to_bytes(), expect=(EstimateMsg,)).body))
    return got


def wait_until(predicate, timeout: float):
    end = time.monotonic() + timeout
    while time.monotonic() < end and not predicate():
        time.sleep(0.02)


@pytest.mark.slow
@pytest.mark.parametrize("swarm, message", [(True, "odometry"), (False, "vision_position_estimate")])
def test_flight_controller_round_trip(tmp_path, agents, swarm, message):
    port = udp_port()
    # The fake FC flies a 20 m circle about its origin counter-clockwise at 5 m/s from (20, 0),
    # nose north: the prior is where it starts, and dead reckoning from its velocity and yaw
    # must follow the circle.
    agent = agents(tmp_path, prior={"position": [20.0, 0.0], "std": 0.05},
                   sensors=[{"kind": "mavlink", "url": f"udpin:127.0.0.1:{port}", "tick": 0.1}],
                   outputs={"swarm": swarm, "mavlink": {"rate_hz": 5, "message": message}})
    agent.wait_for("INFO agent 1 up")
    with agent.session() as session:
        on_swarm = estimates(session, agent.keys.estimate(1))
        with FakeFlightController(port) as sim:
            time.sleep(2.5)
        assert agent.stop() in (0, 143)
        time.sleep(0.1)
    kind = "ODOMETRY" if message == "odometry" else "VISION_POSITION_ESTIMATE"
    sent = [m for m in sim.received if m.get_type() == kind]
    assert all((m.get_srcSystem(), m.get_srcComponent()) == (1, mavlink.MAV_COMP_ID_ONBOARD_COMPUTER) for m in sent)
    assert 9 <= len(sent) <= 14, len(sent)  # 5 Hz over ~2.4 s of estimates
    stamps = [(m.time_usec if kind == "ODOMETRY" else m.usec) * 1e-6 for m in sent]
    # On the 0.1 s tick grid, about every other tick: the limiter keeps a wall-clock schedule, so
    # a late estimate may go one tick later and the next one a tick sooner.
    gaps = np.round(np.diff(stamps) / 0.1)
    assert set(gaps.tolist()) <= {1.0, 2.0, 3.0} and abs(gaps.mean() - 2.0) <= 0.3, gaps
    variances = []
    for m, t in zip(sent, stamps):
        cov = m.pose_covariance if kind == "ODOMETRY" else m.covariance
        truth = sim.truth(t)["position"]
        north_east = np.array([m.x, m.y])
        assert np.linalg.norm(north_east - truth[[1, 0]]) < 0.1, (t, north_east, truth)
        assert m.z == pytest.approx(-10.0, abs=0.1)  # the FC's own height, handed back
        assert cov[0] > 0 and cov[6] > 0 and cov[11] == pytest.approx(1e4)
        variances.append(cov[0] + cov[6])
    assert np.all(np.diff(variances) > 0)  # dead reckoning: ever less sure
    if kind == "ODOMETRY":
        assert all(m.frame_id == mavlink.MAV_FRAME_LOCAL_NED for m in sent)
    if swarm:
        assert len(on_swarm) >= 20 and [e.k for e in on_swarm] == list(range(on_swarm[0].k, on_swarm[-1].k + 1))
        last = on_swarm[-1]
        assert last.algorithm == "il" and last.cov[0, 0] > 0.05**2
    else:
        assert on_swarm == []


@pytest.mark.slow
def test_flight_controller_ticks_on_the_swarm_clock(tmp_path, agents):
    """Two agents, each with its own FC booted at a different time, number their ticks from
    the swarm clock's epoch (100 s ago): an estimate of tick k comes out just after
    epoch + k * tick on the system clock, on both, and a fresh agent starts at its first tick
    from its prior, not inflated for the thousand ticks before it."""
    epoch, tick = time.time() - 100.0, 0.1
    ports = [udp_port(), udp_port()]
    started = [agents(tmp_path, id=aid, prior={"position": [20.0, 0.0], "std": 0.05}, clock={"epoch": epoch},
                      sensors=[{"kind": "mavlink", "url": f"udpin:127.0.0.1:{port}", "tick": tick}])
               for aid, port in zip((1, 2), ports)]
    for a in started:
        a.wait_for("INFO agent")
    sessions = [a.session() for a in started]
    got = [[], []]
    subs = [s.declare_subscriber(a.keys.estimate(aid), lambda x, g=g: g.append(
        (time.time(), wire.decode(x.payload.to_bytes(), expect=(EstimateMsg,)).body)))
        for s, a, aid, g in zip(sessions, started, (1, 2), got)]
    with FakeFlightController(ports[0]):
        time.sleep(1.3)  # the second FC boots 1.3 s after the first: its clock reads 1.3 s less
        with FakeFlightController(ports[1]):
            time.sleep(2.0)
    for a in started:
        assert a.stop() in (0, 143)
    for s in sessions:
        s.close()
    for aid, estimates_ in zip((1, 2), got):
        assert len(estimates_) >= 15, (aid, len(estimates_))
        first = estimates_[0][1]
        assert first.k >= 1000 and first.cov[0, 0] == pytest.approx(0.05**2)
        # The start tick goes out on its first sample; each later one after it ends, when a
        # sample of the next tick completes it (20 ms at 50 Hz), then the step.
        late = np.array([at - (epoch + e.k * tick) for at, e in estimates_[1:]])
        assert 0.0 < np.median(late) < 0.1 and late.min() > -0.01 and late.max() < 0.3, (aid, late)
@pytest.mark.slow
def test_missing_flight_controller(tmp_path, agents):
    url = f"udpin:127.0.0.1:{udp_port()}"
    agent = agents(tmp_path, sensors=[{"kind": "mavlink", "url": url}], outputs={"mavlink": {}})
    agent.wait_for("INFO agent 1 up")
    line = agent.wait_for("no heartbeat", timeout=6)
    assert f"WARNING no heartbeat from the flight controller at {url} for 3 s" in line
    time.sleep(0.3)
    assert agent.proc.poll() is None
    start = time.monotonic()
    assert agent.stop() in (0, 143)
    assert time.monotonic() - start < 2.0
    assert sum("no heartbeat" in line for line in agent.lines) == 1 and "Traceback" not in "".join(agent.lines)


def test_a_flight_controller_that_cannot_be_opened_is_retried(tmp_path, agents):
    """A serial device that is not plugged in: one warning, the agent keeps running (its radio
    and stats work) and tries again every 2 s; SIGTERM still ends it within 2 s."""
    device = str(tmp_path / "ttyACM9")
    agent = agents(tmp_path, sensors=[{"kind": "mavlink", "url": device}], outputs={"mavlink": {}})
    line = agent.wait_for("cannot open the flight controller")
    assert f"cannot open the flight controller at {device}" in line and "retrying every 2 s" in line
    with agent.session() as session:
        stats = {}

        def poll():
            replies = list(session.get(agent.keys.stats(1), timeout=2.0))
            stats.update(wire.decode(replies[0].ok.payload.to_bytes()).body.data if replies else {})
            return stats.get("sources", {}).get(f"mavlink {device}", {}).get("open_failures", 0) >= 2

        wait_until(poll, 8)
        assert stats["sources"][f"mavlink {device}"]["link"] == "unopened", stats
    start = time.monotonic()
    assert agent.stop() in (0, 143)
    assert time.monotonic() - start < 2.0
    assert sum("cannot open" in line for line in agent.lines) == 1 and "Traceback" not in "".join(agent.lines)


def test_a_recording_replays_as_the_in_process_run(tmp_path, agents):
    sc = load_scenario("wang2019")
    sc = sc.model_copy(update={"clock": sc.clock.model_copy(update={"duration": 40.0})})
    record = InProcessRunner(Simulation(sc), make_nodes("il", sc)).run()
    np.savez(tmp_path / "sensors.npz", **record.sensor_arrays())
    aid = record.ids[1]
    prior = sc.prior(aid)[0]
    # The test listens and the agent connects: the subscription is in place before the first
    # frame, so no estimate goes out unheard.
    here = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("peer", [here], []))) as session:
        got = estimates(session, f"swarmloc/*/agent/{aid}/estimate")
        agent = agents(tmp_path, id=aid, prior={"position": prior.tolist(), "std": sc.estimation.initial_std},
                       zenoh={"mode": "peer", "connect": [here]},
                       sensors=[{"kind": "file", "path": "sensors.npz", "speed": "as_fast_as_possible"}])
        agent.wait_for("replayed", timeout=30)
        wait_until(lambda: got and got[-1].k == record.k[-1], 5)
        time.sleep(0.2)
        assert agent.proc.poll() is None  # the recording is over, the agent is not
    assert agent.stop() in (0, 143)
    want = record.est["il"]
    assert [e.k for e in got] == record.k
    for e in got:
        ref = want[e.k][aid]
        np.testing.assert_array_equal(e.mean, ref.mean)
        np.testing.assert_array_equal(e.cov, ref.cov)
    assert sum("replayed" in line for line in agent.lines) == 1


def test_garbage_on_a_zenoh_source_is_counted_and_dropped(tmp_path, agents):
    key = f"drivers/{uuid.uuid4().hex[:6]}/frames"
    agent = agents(tmp_path, sensors=[{"kind": "zenoh", "key": key}])
    agent.wait_for("INFO agent 1 up")
    assert key in agent.wait_for("waiting for sensor frames on")
    from swarmloc.wire.messages import OdometryMsg, Sensors

    with agent.session() as session:
        pub = session.declare_publisher(key, **wire.publisher_options(zenoh))
        time.sleep(0.3)  # the agent's subscription reaches this session
        good = lambda k: wire.encode(Sensors(k, 0.1 * k, OdometryMsg(0.1, 1.0, 0.0, 0.1, 0.01), []), 1, k)
        for data in [good(0), b"\x00garbage", wire.encode(Reply(True, "", {}), 1, 0), good(1), os.urandom(64), good(2)]:
            pub.put(data)
        stats = {}

        def poll():
            replies = list(session.get(agent.keys.stats(1), timeout=2.0))
            stats.update(wire.decode(replies[0].ok.payload.to_bytes()).body.data if replies else {})
            return stats.get("ticks") == 3

        wait_until(poll, 5)
        assert stats["ticks"] == 3 and stats["rejected"]["malformed"] == 3, stats
        assert agent.proc.poll() is None
    assert agent.stop() in (0, 143)


def recorder():
    """A dead-reckoning node that keeps every frame it is handed (the daemon's merging, sans I/O)."""
    from swarmloc.estimators.il import IndependentNode

    class Recorder(IndependentNode):
        def step(self, frame):
            self.frames.append(frame)
            return super().step(frame)

    node = Recorder(1, np.zeros(2), np.eye(2))
    node.frames = []
    return node


def test_measurements_join_the_next_frame():
    """Partial frames from a measurements source: their ranges (up to the wire's 64), the first
    fix and pseudoranges join the next whole frame; their motion data and tick are not used,
    and whatever does not fit is counted."""
    from agents.daemon import AgentConfig, AgentDaemon
    from swarmloc.wire.messages import GnssMsg, ImuMsg, OdometryMsg, RangeMsg, Sensors

    node = recorder()
    daemon = AgentDaemon(node, AgentConfig(direct=True, measurement_keys=("drivers/uwb",), publish_swarm=False))
    odo = OdometryMsg(0.1, 1.0, 0.0, 0.1, 0.01)
    part = lambda k, ranges, gnss=None, **kw: wire.encode(Sensors(k, 9.9, None, ranges, gnss, **kw), 7, k)
    r = lambda target: RangeMsg(target, 10.0 + target, 0.1)
    daemon._handle("measurements", part(50, [r(2), r(3)]), None)
    daemon._handle("measurements", part(3, [r(4)], GnssMsg(np.array([1.0, 2.0]), 0.5)), None)
    daemon._handle("measurements", part(4, [r(5)] * 63, GnssMsg(np.array([9.0, 9.0]), 0.5),
                                        imu=ImuMsg(0.01, np.zeros((1, 6)))), None)
    daemon._handle("measurements", b"\x00garbage", None)
    daemon._step(Sensors(0, 0.0, odo, [r(9)]), None, None)
    daemon._step(Sensors(1, 0.1, odo, []), None, None)
    first, second = node.frames
    assert [m.target for m in first.ranges] == [9, 2, 3, 4] + [5] * 60
    assert (first.k, first.t, first.odometry) == (0, 0.0, odo)  # the whole frame's own
    np.testing.assert_array_equal(first.gnss.position, [1.0, 2.0])
    assert second.ranges == [] and second.gnss is None  # merged once
    assert daemon.merged == {"ranges": 63, "ranges-dropped-full": 3, "gnss": 1, "gnss-dropped-taken": 1,
                             "imu-ignored": 1}
    assert daemon.rejected["malformed"] == 1


def test_a_measurements_source_feeds_a_running_agent(tmp_path, agents):
    """A driver publishing ranges on its own key while a recording gives the frames: the agent
    steps on every frame and counts the ranges merged into them."""
    sc = load_scenario("wang2019")
    sc = sc.model_copy(update={"clock": sc.clock.model_copy(update={"duration": 10.0})})
    record = InProcessRunner(Simulation(sc), make_nodes("il", sc)).run()
    np.savez(tmp_path / "sensors.npz", **record.sensor_arrays())
    key = f"drivers/{uuid.uuid4().hex[:6]}/uwb"
    agent = agents(tmp_path, sensors=[{"kind": "file", "path": "sensors.npz", "speed": 4.0},
                                      {"kind": "zenoh", "key": key, "role": "measurements"}])
    agent.wait_for("join the next sensor frame")
    from swarmloc.wire.messages import RangeMsg, Sensors

    with agent.session() as session:
        pub = session.declare_publisher(key, **wire.publisher_options(zenoh))
        stats = {}

        def poll():
            pub.put(wire.encode(Sensors(0, 0.0, None, [RangeMsg(2, 5.0, 0.1)]), 1, 0))
            replies = list(session.get(agent.keys.stats(1), timeout=2.0))
            stats.update(wire.decode(replies[0].ok.payload.to_bytes()).body.data if replies else {})
            return stats.get("merged", {}).get("ranges", 0) >= 5

        wait_until(poll, 10)
        assert stats["merged"]["ranges"] >= 5 and stats["ticks"] > 0, stats
        assert stats["rejected"] == {}, stats
    assert agent.stop() in (0, 143)


def test_a_recording_on_the_swarm_clock_skips_what_is_overdue(tmp_path):
    """An agent that starts (or restarts) 3.2 s after the swarm clock's epoch plays the frame
    that is due now, not the 3 s it missed: the frames more than a tick overdue are skipped
    and counted, and the next comes on the common schedule."""
    from agents.companion.sources import FilePlayer

    sc = load_scenario("wang2019")
    sc = sc.model_copy(update={"clock": sc.clock.model_copy(update={"duration": 10.0})})
    record = InProcessRunner(Simulation(sc), make_nodes("il", sc)).run()
    np.savez(tmp_path / "sensors.npz", **record.sensor_arrays())
    player = FilePlayer(tmp_path / "sensors.npz", 1, 1.0, epoch=time.time() - 3.2)
    now = time.monotonic()
    assert [f.k for f in player.ready(now)] == [6]  # t = 3.0 s is due; 0 .. 2.5 s are past
    assert player.skipped == 6 and player.stats() == {"frames": 7, "of": 21, "skipped": 6}
    assert player.wait(now) == pytest.approx(0.3, abs=0.02)


def test_a_cameras_sightings_join_a_vehicles_next_frame():
    """Relative positions to other vehicles from a camera driver join the FC's vehicle frame:
    the latest sighting of each vehicle (a backlog costs no backlog of fusions), the driver's
    command, attitude and dt unused; a frame without vehicle readings takes none."""
    from agents.daemon import AgentConfig, AgentDaemon
    from swarmloc.wire.messages import OdometryMsg, RelPosMsg, Sensors, VehicleMsg

    node = recorder()
    daemon = AgentDaemon(node, AgentConfig(direct=True, measurement_keys=("drivers/camera",), publish_swarm=False))
    sight = lambda n, *targets: wire.encode(Sensors(0, 0.0, None, [], vehicle=VehicleMsg(
        0.0, np.array([9.0, 9.0]), np.array([9.0]), 9.0, [RelPosMsg(t, np.full(3, float(n)), 0.05) for t in targets])), 7, n)
    for n, targets in enumerate([(2,), (5, 2), (2,)]):
        daemon._handle("measurements", sight(n, *targets), None)
    own = VehicleMsg(0.05, np.array([0.1, 0.0]), np.array([0.3]), 0.01, [RelPosMsg(4, np.zeros(3), 0.05)])
    merged = daemon._merge(Sensors(8, 0.4, None, [], vehicle=own))
    seen = {r.target: r.z[0] for r in merged.vehicle.seen}
    assert seen == {4: 0.0, 2: 2.0, 5: 1.0}  # vehicle 2's latest is the third sighting
    assert (merged.vehicle.dt, merged.vehicle.u.tolist(), merged.vehicle.attitude_std) == (0.05, [0.1, 0.0], 0.01)
    assert daemon.merged == {"seen": 4, "seen-superseded": 2}
    daemon._handle("measurements", sight(3, 2), None)
    plain = daemon._merge(Sensors(9, 0.45, OdometryMsg(0.05, 1.0, 0.0, 0.1, 0.01), []))
    assert plain.vehicle is None and daemon.merged["vehicle-ignored"] == 1


def _fc_output_run(tmp_path, agents) -> list[tuple[float, float]]:
    """One run of the test below: every assertion but the dead reckoning's accuracy; returns
    (FC time s from the first stamp, position error m) of every ODOMETRY the FC got."""
    from fake_fc import SimulatedAutopilot

    tmp_path.mkdir(parents=True, exist_ok=True)
    port = udp_port()
    agent = agents(tmp_path, prior={"position": [0.0, 0.0], "std": 0.05},
                   sensors=[{"kind": "mavlink", "url": f"udpin:127.0.0.1:{port}", "tick": 0.1}],
                   outputs={"swarm": False, "mavlink": {"rate_hz": 30}, "log": "est.jsonl"})
    agent.wait_for("INFO agent 1 up")
    with SimulatedAutopilot(port, "rover", drive=(1.0, 0.1)) as sim:
        time.sleep(4.0)
    assert agent.stop() in (0, 143)
    sent = [m for m in sim.received if m.get_type() == "ODOMETRY"]
    stamps = np.array([m.time_usec for m in sent]) * 1e-6
    ticks = np.array([json.loads(line)["t"] for line in (tmp_path / "est.jsonl").read_text().splitlines()])
    assert len(sent) > 20 and np.all(np.diff(stamps) > 0)
    between = [not np.any(np.abs(ticks - t) < 1e-6) for t in stamps]
    assert np.mean(between) > 0.5, (stamps, ticks)
    assert {m.reset_counter for m in sent} == {0}
    counts = sim.ev.counts
    assert "gated" not in counts and counts.get("fused", 0) > 0.8 * len(sent), counts
    truth = np.array(sim.truth_log, float)
    errors = []
    for m, t in zip(sent, stamps):
        east, north = np.interp(t, truth[:, 0], truth[:, 1]), np.interp(t, truth[:, 0], truth[:, 2])
        errors.append((float(t - stamps[0]), math.hypot(m.y - east, m.x - north)))
    return errors


@pytest.mark.slow
def test_the_flight_controller_gets_the_estimate_between_ticks_and_fuses_it(tmp_path, agents):
    """A 10 Hz swarm tick, a 30 Hz output, and a simulated PX4 whose pilot drives a circle: the
    ODOMETRY it gets is the estimate moved on with its own samples between ticks (most stamps
    are FC sample times between ticks, each later than the one before), its reset counter
    unchanged (nothing jumps), and PX4's EKF2 would fuse it (never gated). Rate and jitter are
    measured by benchmarks/fc_output.py, not asserted here.

    Dead reckoning on the FC's own velocity is centimetres in 4 s (every sample within 0.3 m;
    0.09-0.10 m at most in 6 runs alone and beside two busy cores). Once, late in a full
    `make test-all`, one sample was 0.35 m off at 2.7 s (about a third of a second behind the
    truth at 1 m/s), cause not found (docs/deploy.md, "Known issues"): a run with such a sample
    is reported as a warning and run again once; a second one fails."""
    errors = _fc_output_run(tmp_path / "first", agents)
    worst = max(errors, key=lambda e: e[1])
    if worst[1] >= 0.3:
        warnings.warn(f"FC output: a sample {worst[1]:.3f} m off at {worst[0]:.2f} s; running again", stacklevel=1)
        errors = _fc_output_run(tmp_path / "again", agents)
        worst = max(errors, key=lambda e: e[1])
    assert worst[1] < 0.3, worst
