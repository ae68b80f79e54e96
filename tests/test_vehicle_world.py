"""netsim's vehicles (netsim/world/vehicles.py): truth under the command in force, body-frame
relative positions along the graph within proximity, GPS on its schedule, commands and their
faults, and the scenario schema's checks."""

import math

import numpy as np
import pytest

from netsim.sim import Simulation
from swarmloc.experiment import scenario
from swarmloc.experiment.faults import CommandOff, CommandOn, Cut
from swarmloc.experiment.scenario import ScenarioError
from swarmloc.models.vehicles import MODELS, CircleReference, relpos


def _short(name, seconds=4.0, **over):
    return scenario.load(name).with_overrides(**{"clock.duration": seconds, **over})


def _run(sim):
    frames = []
    for _ in range(sim.steps + 1):
        frames.append(sim.tick()[2])
    return frames


def test_autopilots_follow_their_circles():
    sc = _short("oliveros3", 20.0)
    sim = Simulation(sc)
    _run(sim)
    for spec in sc.world.agents:
        if spec.model == "ground-station":
            continue
        m = spec.motion
        ref = CircleReference(tuple(m.center), m.radius, m.period, m.phase, m.yaw)
        err = np.linalg.norm(sim.truth()[spec.id][:3] - ref.derivatives(20.0, 0)[0])
        assert err < 0.05, (spec.id, err)


def test_same_seed_same_world_bit_for_bit():
    a, b = (_run(Simulation(_short("oliveros3", 2.0))) for _ in range(2))
    for fa, fb in zip(a, b):
        for aid in fa:
            va, vb = fa[aid].vehicle, fb[aid].vehicle
            if va is None:
                continue
            assert va.u.tobytes() == vb.u.tobytes() and va.attitude.tobytes() == vb.attitude.tobytes()
            assert [r.z.tobytes() for r in va.seen] == [r.z.tobytes() for r in vb.seen]


@pytest.mark.slow
def test_relative_positions_in_body_frame_along_graph_within_proximity():
    sc = _short("oliveros3", 40.0)
    sim = Simulation(sc)
    cfg = sc.sensors.vehicle
    graph = {tuple(e) for e in cfg.graph}
    seen_any = {e: False for e in graph}
    for _ in range(sim.steps + 1):
        _, _, frames = sim.tick()
        truth = sim.truth()
        for b, f in frames.items():
            if f.vehicle is None:
                continue
            mb = MODELS[sc.agent(b).model]
            for r in f.vehicle.seen:
                assert (b, r.target) in graph
                seen_any[(b, r.target)] = True
                mt = MODELS[sc.agent(r.target).model]
                d = np.linalg.norm(truth[r.target][:3] - truth[b][:3])
                assert d <= cfg.range_of(mb.name, mt.name)
                z = relpos(mb, truth[b], mt, truth[r.target])
                assert np.all(np.abs(r.z - z) < 6 * cfg.relpos_noise)
            # A pair in range along the graph is measured.
            for e in graph:
                if e[0] == b:
                    mt = MODELS[sc.agent(e[1]).model]
                    d = np.linalg.norm(truth[e[1]][:3] - truth[b][:3])
                    assert (d <= cfg.range_of(mb.name, mt.name)) == any(r.target == e[1] for r in f.vehicle.seen)
    assert all(seen_any.values()), seen_any


def test_gps_schedule():
    case3 = scenario.load("oliveros-caravan-3").sensors.vehicle.gps_schedule
    assert [case3.active(t) for t in (0, 39.9, 40, 79.9, 80, 119.9, 120, 159.9)] == [0, 0, 1, 1, 0, 0, 1, 1]
    assert scenario.load("oliveros-caravan-2").sensors.vehicle.gps_schedule.active(0.0)
    # The same schedule, shortened, in the frames: only vehicle 4 has GPS, and only when on.
    sc = _short("oliveros-caravan-3", 2.2, **{"sensors.vehicle.gps_schedule": {"start": 0.5, "on_for": 0.5,
                                                                              "off_for": 0.5}})
    sim = Simulation(sc)
    for _ in range(sim.steps + 1):
        k, t, frames = sim.tick()
        assert (frames[4].gnss is not None) == (0.5 <= t < 1.0 or 1.5 <= t < 2.0), t
        assert all(frames[a].gnss is None for a in frames if a != 4)


def test_a_cut_removes_the_edge_and_restore_brings_it_back():
    sim = Simulation(_short("oliveros-caravan-1", 1.0))
    sim.tick()
    assert [r.target for r in sim.tick()[2][1].vehicle.seen] == [2, 5]
    sim.apply(Cut(link=(1, 2)), "live")
    assert [r.target for r in sim.tick()[2][1].vehicle.seen] == [5]
    sim.apply(Cut(link=(1, 5), direction="forward"), "live")
    assert sim.tick()[2][1].vehicle.seen == []


def test_commands_apply_from_the_next_tick_and_a_lost_stream_keeps_the_last():
    sc = _short("oliveros3", 1.0, **{"world.control": "agents"})
    sim = Simulation(sc)
    sim.tick()
    hover = MODELS["quadrotor"].hover_input()
    assert np.array_equal(sim.tick()[2][1].vehicle.u, hover)  # nothing sent yet: hover
    u = hover + np.array([0.5, 0.0, 0.0, 0.0])
    assert sim.command(1, u) is None
    assert np.array_equal(sim.tick()[2][1].vehicle.u, u)
    sim.apply(CommandOff(node=1), "live")
    assert sim.command(1, hover) == "command-off"
    assert np.array_equal(sim.tick()[2][1].vehicle.u, u)  # the last command stays in force
    assert sim.command(1, np.array([1.0, math.nan, 0.0, 0.0])) == "command-off"
    sim.apply(CommandOn(node=1), "live")
    assert sim.command(1, np.array([1.0, math.nan, 0.0, 0.0])) == "malformed"
    assert sim.command(1, np.zeros(2)) == "malformed"  # a ground robot's size
    assert sim.command(3, np.zeros(2)) is None
    assert sim.command(10, np.zeros(2)) == "not-a-vehicle"
    assert sim.commands["received"] == {"applied": 2, "command-off": 2, "malformed": 2, "not-a-vehicle": 1}
    assert np.array_equal(sim.tick()[2][1].vehicle.u, u)
    # Ticks flown on an older command: none came before ticks 1 and 3, vehicle 1's before tick 2,
    # vehicle 3's before tick 4.
    assert sim.commands["held_ticks"] == {"1": 3, "2": 4, "3": 3}


def test_without_commands_a_quadrotor_hovers_where_it_is():
    sc = _short("oliveros3", 2.0, **{"world.control": "agents"})
    sim = Simulation(sc)
    _run(sim)
    start = np.array(sc.agent(1).start)
    assert np.linalg.norm(sim.truth()[1][:3] - start) < 0.5  # actuator noise only


@pytest.mark.parametrize("override, match", [
    ({"sensors.vehicle.graph": [[1, 10]]}, "two different vehicles"),
    ({"sensors.vehicle.graph": [[1, 1]]}, "two different vehicles"),
    ({"sensors.vehicle.gps": [10]}, "not vehicles"),
    ({"clock.dt": 0.1}, "clock.dt"),
    ({"sensors.vehicle.proximity": {"quadrotor/boat": 2.0}}, "proximity key"),
    ({"sensors.vehicle.proximity": {"quadrotor/quadrotor": -1.0}}, "must be > 0"),
    ({"world.agents": [{"id": 1, "model": "quadrotor", "start": [0, 0, 1], "motion": {"kind": "circle"}}]},
     "does not fit model"),
    ({"world.agents": [{"id": 1, "model": "quadrotor", "start": [0, 0]}]}, "3 finite numbers"),
])
def test_scenario_errors_name_the_field(override, match):
    with pytest.raises((ScenarioError, ValueError), match=match):
        scenario.load("oliveros3").with_overrides(**override)


def test_control_by_agents_needs_vehicles():
    with pytest.raises((ScenarioError, ValueError), match="needs quadrotor or ground-robot"):
        scenario.load("wang2019").with_overrides(**{"world.control": "agents"})


def test_netsim_takes_an_agents_commands_and_counts_what_it_refuses():
    """netsim's door for `agent/<id>/command` (no Zenoh needed): a command counts by its number
    even when its body is malformed (lockstep must not wait for it; the vehicle keeps its last
    command); repeats, strangers and agents not joined are refused and counted."""
    import msgpack

    from netsim.server import NetsimServer, ServerConfig
    from swarmloc import wire
    from swarmloc.wire.messages import Command, Done

    sc = _short("oliveros3", 1.0, **{"world.control": "agents"})
    server = NetsimServer(sc, ServerConfig())
    key = server.keys.command(1)
    good = wire.encode(Command(0, MODELS["quadrotor"].hover_input() + 1.0), 1, 1)
    server._on_command(key, good)
    assert server.rejected["command"] == {"not-joined": 1} and server.commands[1] == 0
    server.alive.update(sc.agent_ids)
    server._on_command(key, good)
    server._on_command(key, good)  # the same number again
    tree = msgpack.unpackb(wire.encode(Command(0, np.zeros(4)), 1, 2), raw=False)
    tree["body"]["u"] = "thrust"
    server._on_command(key, msgpack.packb(tree, use_bin_type=True))
    server._on_command(server.keys.command(99), good)
    server._on_command(key, wire.encode(Command(0, np.zeros(4)), 2, 3))  # on 1's key, from 2
    assert server.commands[1] == 2
    assert dict(server.rejected["command"]) == {"not-joined": 1, "stale": 1, "unknown-agent": 1, "src-mismatch": 1}
    assert server.sim.commands["received"] == {"applied": 1, "malformed": 1}
    # Lockstep's quiet condition: a `done` that says 3 commands waits for the third.
    server.done[1] = Done(0, 0, 0, 3)
    assert not server._quiet_agent(1, 0)
    server._on_command(key, wire.encode(Command(0, np.zeros(4)), 1, 3))
    assert server._quiet_agent(1, 0)
