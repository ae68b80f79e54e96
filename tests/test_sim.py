"""netsim's environment as pure code: ticks, faults, rounds, link table."""

import math

import numpy as np

from netsim.sim import Simulation
from swarmloc import wire
from swarmloc.experiment import scenario as S
from swarmloc.node import RadioTx
from swarmloc.wire.messages import Beacon, LinkMsg, Links


def beacon(src, seq):
    return RadioTx(src, None, seq, wire.encode(Beacon(0, np.zeros(2), np.eye(2), {}), src, seq))


def test_link_table_before_first_tick_and_after_rounds_goes_on_the_wire():
    for radio in ({"model": "unit-disk"}, {"model": "log-distance"}):
        sim = Simulation(S.load("wang2019").with_overrides(radio=radio))
        rows = sim.link_table()  # status may be asked before tick 0
        assert len(rows) == 6
        for _ in range(3):
            sim.tick()
            sim.exchange([beacon(a, sim.k + 1) for a in sim.ids])
        assert math.isfinite(sim.vt)
        msg = Links(sim.k, [LinkMsg(**row) for row in sim.link_table()])
        back = wire.decode(wire.encode(msg, 0, 1)).body
        assert all(l.last_heard is not None and math.isfinite(l.last_heard) for l in back.links)


def test_interfering_round_is_deterministic():
    """Lockstep rounds: the same frames give the same outcomes whatever order they arrive in."""
    sc = S.load("random7").with_overrides(radio={"model": "log-distance", "carrier_sense": False})
    outcomes = []
    for order in (1, -1):
        sim = Simulation(sc)
        sim.tick()
        frames = [beacon(a, 1) for a in sim.ids][::order]
        outcomes.append([(r.receiver, r.src, r.t) for r in sim.exchange(frames)])
    assert outcomes[0] == outcomes[1]
    assert len(outcomes[0]) < 7 * 6  # simultaneous broadcasts collide


def test_fault_timeline_applies_before_frames_and_clears_after_duration():
    sc = S.load("wang2019").with_overrides(
        **{"sensors.gnss.enabled": True},
        faults=[{"at": 1.0, "action": "gnss-off", "node": 2, "duration": 1.0},
                {"at": 1.0, "action": "cut", "link": [1, 3]}])
    sim = Simulation(sc)
    seen = {}
    for _ in range(6):
        k, t, frames = sim.tick()
        seen[k] = (frames[2].gnss is None, sim.link_state(1, 3)[0])
    assert seen[1] == (False, True)
    assert seen[2] == (True, False) and seen[3] == (True, False)  # t = 1.0 and 1.5
    assert seen[4] == (False, False)  # GNSS back after 1 s; the cut has no duration
    assert [f["action"] for f in sim.fault_log] == ["gnss-off", "cut", "gnss-on"]


def test_frames_to_self_or_strangers_are_dropped_not_raised():
    sim = Simulation(S.load("wang2019"))
    sim.tick()
    for dst in (1, 99):
        out = sim.exchange([RadioTx(1, dst, 5, b"x")])
        assert [r.nack.reason for r in out] == ["unknown"] and out[0].receiver == 1
