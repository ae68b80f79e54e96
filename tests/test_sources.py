"""Sensor sources and outputs of `swarmloc agent --config` (agents/sources.py): a flight
controller in and out (tests/fake_fc.py over UDP), a missing one, a recording replayed, and
garbage on a zenoh source key. Real agent processes, real Zenoh sessions on 127.0.0.1."""

import os
import signal
import subprocess
import sys
import threading
import time
import uuid

import numpy as np
import pytest
import yaml
import zenoh

from agents.mavlink import mavlink
from conftest import free_port
from fake_fc import FakeFlightController
from netsim.sim import Simulation
from swarmloc import wire
from swarmloc.messages import EstimateMsg, Reply
from swarmloc.runner import InProcessRunner, make_nodes
from swarmloc.scenario import load as load_scenario
from test_mavlink import udp_port


class Agent:
    """`swarmloc agent --config` in a subprocess, its stderr collected line by line."""

    def __init__(self, tmp_path, **fields):
        self.swarm = "s" + uuid.uuid4().hex[:8]
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        data = {"version": 1, "id": 1, "swarm": self.swarm, "estimator": {"name": "il"},
                "model": "planar-speed-heading", "prior": {"position": [0.0, 0.0]},
                "zenoh": {"mode": "peer", "listen": [self.endpoint]}, **fields}
        path = tmp_path / f"agent-{self.swarm}.yaml"
        path.write_text(yaml.safe_dump(data))
        self.keys = wire.Keys(self.swarm)
        self.lines: list[str] = []
        self.proc = subprocess.Popen([sys.executable, "-m", "agents", "agent", "--config", str(path), "-v"],
                                     stderr=subprocess.PIPE, text=True, cwd=tmp_path)
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
    from swarmloc.messages import OdometryMsg, Sensors

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
