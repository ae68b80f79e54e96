"""Node timers (swarmloc.node.Timer): modelled time in lockstep, wall time in real time."""

import threading
import time
from dataclasses import replace

import numpy as np
import pytest
import zenoh
from conftest import free_port

from agents.daemon import AgentConfig, AgentDaemon
from agents.host import Host, Hosted
from netsim.sim import Simulation
from swarmloc import wire
from swarmloc.experiment import scenario as S
from swarmloc.experiment.runner import InProcessRunner
from swarmloc.node import Node, Timer, Timers
from swarmloc.wire.messages import Clock, Sensors


class Alarm(Node):
    """Sets a timer of `delay` at tick 3 and one of 0 s inside its callback; records firings."""

    algorithm = "alarm"

    def __init__(self, aid, delay):
        super().__init__(aid, np.zeros(2), np.eye(2))
        self.delay, self.fired = delay, []

    def step(self, sensors):
        self.k = sensors.k
        return [Timer(self.delay, "late"), Timer(1.0, "replaced")] if sensors.k == 3 else (
            [Timer(0.25, "replaced")] if sensors.k == 4 else [])

    def on_timer(self, tag, t):
        self.fired.append((tag, self.k, round(t, 9)))
        return [Timer(0.0, "again")] if tag == "late" else []


def test_timers_fire_earliest_first_and_a_tag_set_again_replaces_its_timer():
    timers = Timers()
    assert timers.split([Timer(2.0, "b"), "send", Timer(1.0, "a")], now=10.0) == ["send"]
    timers.split([Timer(5.0, "b")], now=10.0)  # replaces b's 12.0 with 15.0
    assert timers.pop_due(11.0) == ["a"] and timers.pop_due(14.9) == [] and timers.next_due() == 15.0
    assert timers.pop_due(15.0) == ["b"] and timers.next_due() is None


def test_lockstep_timers_fire_at_the_first_tick_at_or_after_their_time():
    sc = S.load("wang2019").with_overrides(**{"clock.duration": 6.0})  # dt 0.5
    nodes = {a: Alarm(a, 1.2) for a in sc.agent_ids}
    InProcessRunner(Simulation(sc), nodes).run()
    # Set at tick 3 (t = 1.5): due at 2.7, fired before tick 6's frame (t = 3.0), while the node
    # is still at tick 5. "replaced" was set again at tick 4 (t = 2.0 + 0.25): fires at tick 5.
    # "again", set inside the callback at t = 3.0 with delay 0, fires at the next tick.
    assert nodes[1].fired == [("replaced", 4, 2.5), ("late", 5, 3.0), ("again", 6, 3.5)]
    assert all(n.fired == nodes[1].fired for n in nodes.values())  # deterministic


class _Built:
    """A Hosted's spec: the node itself."""

    def __init__(self, node):
        self.node = node

    def build(self):
        return self.node


@pytest.mark.parametrize("driver", ["own loop", "host"])
def test_real_time_timers_fire_in_wall_time_without_any_input(driver):
    """An agent daemon (real Zenoh session, no netsim) in real time: the timer set on a sensor
    frame fires by itself, after its delay of modelled time at the clock's speed; the same for
    an agent of a host, whose one loop serves a hostmate that sets no timer."""
    port = free_port()
    node, mate = Alarm(1, 0.4), Alarm(2, 0.4)
    cfg = AgentConfig(swarm="timers", mode="peer", listen=(f"tcp/127.0.0.1:{port}",), connect=(), exit_on_stop=False)
    if driver == "host":
        host = Host([Hosted(1, _Built(node), cfg), Hosted(2, _Built(mate), replace(cfg, listen=()))],
                    report=lambda line, why: None)
        host.start(1)
        host.start(2)
        daemon = host.agents[1].daemon
    else:
        daemon = AgentDaemon(node, cfg)
        daemon.open()
        loop = threading.Thread(target=daemon.run, daemon=True)
        loop.start()
    conf = zenoh.Config.from_json5(wire.zenoh_config("peer", (), (f"tcp/127.0.0.1:{port}",)))
    session = zenoh.open(conf)
    try:
        keys = wire.Keys("timers")
        clock, sensors = session.declare_publisher(keys.clock), session.declare_publisher(keys.sensors(1))
        deadline = time.monotonic() + 20.0
        seq = 0
        while daemon.clock_k != 3 and time.monotonic() < deadline:  # until the peers have found each other
            seq += 1
            clock.put(wire.encode(Clock(3, 1.5, "realtime", 0.5, 2.0), 0, seq))
            time.sleep(0.05)
        assert daemon.clock_k == 3, "the daemon never heard the clock"
        sensors.put(wire.encode(Sensors(3, 1.5, None, []), 0, seq + 1))
        started = time.monotonic()
        deadline = started + 10.0
        while len(node.fired) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        waited = time.monotonic() - started
    finally:
        if driver == "host":
            host.stop()
        else:
            daemon.stop()
            loop.join(5)
            daemon.close()
        session.close()
    assert [f[0] for f in node.fired][:2] == ["late", "again"]  # "replaced" may follow before the loop stops
    assert waited >= 0.4 / 2.0  # 0.4 s of modelled time at speed 2
    assert node.fired[0][2] >= 1.5 + 0.4  # the node is told the modelled time it fired at
    assert mate.fired == []
