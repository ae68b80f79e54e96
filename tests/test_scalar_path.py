"""The scalar path for a frame alone on the air, against the vectorised path it stands in for.

RadioMedium judges a frame that nothing can overlap without its event loop (RadioMedium._alone),
and Simulation counts and delivers a few outcomes of one frame element by element
(Simulation._resolve_one). Both must be invisible: the same outcomes, the same deliveries, the
same counters and radio log, and the random stream left in the same state, since every later
draw depends on it. Here every case is played twice, scalar path on and off, and compared
exactly (not approximately): PER draws, jitter and shadowing all on.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from netsim.channel import Jammer, LogDistance, RadioMedium, TxFrame, UnitDisk
from netsim.sim import Simulation
from swarmloc.experiment import scenario as SC
from swarmloc.node import RadioTx

MODELS = {
    "log-distance": LogDistance(),
    "log-distance, retries, no carrier sense": LogDistance(unicast_retries=3, carrier_sense=False),
    "unit-disk": UnitDisk(range_m=250.0, latency_s=0.002, jitter_s=0.001),
}


def _arrays(out) -> tuple:
    return tuple(np.asarray(getattr(out, f)).tolist() for f in ("uid", "src", "receiver", "t", "reason")) + (
        np.nan_to_num(out.sinr_db, nan=-999.0).tolist(),)


def _state(medium: RadioMedium) -> tuple:
    return (medium._rng.bit_generator.state, medium._spare.tolist(), medium._first_stage.tolist(), medium.now,
            medium._stage.tolist(), medium._try_at.tolist(), medium.next_event_time())


def _play(model, steps, scalar: bool) -> tuple[list, tuple, int]:
    medium = RadioMedium(model, np.random.default_rng(5))
    medium.scalar = scalar
    got, alone = [], 0
    original = medium._alone

    def counting(*a):
        nonlocal alone
        done = original(*a)
        alone += done
        return done

    medium._alone = counting
    for step in steps:
        kind = step[0]
        if kind == "pos":
            medium.set_positions(step[1])
        elif kind == "jam":
            medium.set_jammers(step[1])
        elif kind == "offer":
            drops = medium.offer_arrays(step[1], step[2])
            got.append(("drops", _arrays(drops) if drops is not None else None))
        elif kind == "advance":
            got.append(("advance", _arrays(medium.advance_arrays(step[1]))))
        else:
            got.append(("idle", _arrays(medium.run_to_idle())))
        got.append(_state(medium))
    return got, _state(medium), alone


def _steps(seed: int, n: int = 9) -> list[tuple]:
    """Rounds of one frame (broadcasts, unicasts near and far, to a node that is not there),
    staggered real-time offers that sometimes overlap, a sender with frames queued, a jammer
    over part of the time, a node that leaves the world and comes back, and moves."""
    rng = np.random.default_rng(seed)
    pos = {i: rng.uniform(0, 500, 2) for i in range(n)}
    steps: list[tuple] = [("pos", pos)]
    uid = itertools.count(1)
    t = 0.0
    for burst in range(40):
        kind = rng.integers(0, 6)
        src = int(rng.integers(0, n))
        dst = None if rng.random() < 0.5 else int(rng.choice([d for d in range(n + 1) if d != src]))
        size = int(rng.integers(0, 200))
        if kind <= 1:  # a lockstep round of one frame
            steps += [("offer", TxFrame(next(uid), src, dst, size), t), ("idle",)]
        elif kind == 2:  # real time: offered, advanced past its end (alone) or into its airtime (not)
            steps += [("offer", TxFrame(next(uid), src, dst, size), t), ("advance", t + float(rng.uniform(0, 3e-3)))]
        elif kind == 3:  # two senders at once, or one sender with a frame queued behind
            other = src if rng.random() < 0.5 else (src + 1) % n
            steps += [("offer", TxFrame(next(uid), src, dst, size), t),
                      ("offer", TxFrame(next(uid), other, None, size), t + float(rng.uniform(0, 1e-3))),
                      ("advance", t + 0.01)]
        elif kind == 4:
            steps.append(("jam", [Jammer(tuple(rng.uniform(0, 500, 2)), 10.0, t, t + float(rng.uniform(0, 0.02)))]
                          if rng.random() < 0.5 else []))
            steps += [("offer", TxFrame(next(uid), src, dst, size), t + 0.001), ("advance", t + 0.02)]
        else:  # the world changes: a move, a node gone, a node back
            moved = {i: p + rng.normal(0, 20, 2) for i, p in pos.items()}
            if rng.random() < 0.4:
                moved.pop(int(rng.integers(0, n)))
            steps.append(("pos", moved))
        t += 0.05
    steps.append(("idle",))
    return steps


@pytest.mark.parametrize("model", list(MODELS))
@pytest.mark.parametrize("seed", range(6))
def test_medium_scalar_path_equals_vectorised(model: str, seed: int) -> None:
    steps = _steps(seed)
    fast, fast_state, alone = _play(MODELS[model], steps, scalar=True)
    slow, slow_state, never = _play(MODELS[model], steps, scalar=False)
    assert never == 0 and alone >= 10  # the script takes the scalar path, and not always
    assert fast == slow
    assert fast_state == slow_state


def test_medium_scalar_path_draws_and_loses() -> None:
    """Where frames are lost and retried, the scalar path draws as the vectorised one does."""
    model = LogDistance(unicast_retries=1, shadowing_sigma_db=0.0)
    steps: list[tuple] = [("pos", {0: (0.0, 0.0), 1: (470.0, 0.0), 2: (120.0, 0.0)})]
    for k in range(200):
        steps += [("offer", TxFrame(k + 1, k % 3, 1 if k % 3 != 1 else 0, 100), 0.1 * k), ("idle",)]
    fast, fast_state, alone = _play(model, steps, scalar=True)
    slow, slow_state, _ = _play(model, steps, scalar=False)
    assert fast == slow and fast_state == slow_state
    reasons = {r for entry in fast if entry[0] == "idle" for r in entry[1][4]}
    assert {0, 2} <= reasons and alone > 200  # deliveries and "sinr" losses, retries taken alone too


def _rounds(sim: Simulation, seed: int, realtime: bool) -> list:
    rng = np.random.default_rng(seed)
    seq = dict.fromkeys(sim.ids, 0)
    out = []
    for _ in range(10):
        sim.tick()
        for _ in range(8):
            frames = []
            for _ in range(1 if rng.random() < 0.7 else int(rng.integers(2, 5))):
                src = int(rng.choice(sim.ids))
                seq[src] += 1
                dst = None if rng.random() < 0.5 else int(rng.choice([a for a in sim.ids if a != src] + [99]))
                frames.append(RadioTx(src, dst, seq[src], bytes(int(rng.integers(0, 120)))))
            if realtime:
                t = sim.t + float(rng.uniform(0, 0.4))
                for tx in frames:
                    out.append(sim.offer(tx, t))
                out.append(sim.advance(t + float(rng.uniform(0, 0.01))))
            else:
                out.append(sim.exchange(frames))
        if realtime:
            out.append(sim.advance(sim.t + 0.5))
    return out


FAULTS = [{"at": 1.0, "action": "loss", "probability": 0.3}, {"at": 2.0, "action": "partition", "groups": [[1, 2], [3]]},
          {"at": 3.0, "action": "heal"}, {"at": 3.5, "action": "radio-off", "node": 4, "duration": 1.0}]


@pytest.mark.parametrize("radio", [{"model": "log-distance"}, {"model": "log-distance", "queue_size": 1},
                                   {"model": "unit-disk", "range_m": 300.0, "jitter_s": 0.001},
                                   {"model": "unit-disk", "range_m": 300.0}])  # no jitter: ties in time
@pytest.mark.parametrize("realtime", [False, True])
@pytest.mark.parametrize("faults", [[], FAULTS])
def test_simulation_scalar_path_equals_vectorised(radio: dict, realtime: bool, faults: list) -> None:
    taken = []

    def run(scalar: bool) -> tuple[list, Simulation]:
        sim = Simulation(SC.load("random7").with_overrides(radio=radio, faults=faults), scalar=scalar)
        if faults:
            sim.down.add(5)  # an agent whose process is gone: its frames drop as "down"
        original = sim._resolve_one
        sim._resolve_one = lambda *a: taken.append(scalar) or original(*a)
        return _rounds(sim, 3, realtime), sim

    (fast, a), (slow, b) = run(True), run(False)
    assert fast == slow and sum(map(len, fast)) > 100
    assert taken.count(True) >= 10 and False not in taken
    ra, rb = a.radio_arrays(), b.radio_arrays()
    assert all(np.array_equal(ra[key], rb[key], equal_nan=ra[key].dtype.kind == "f") for key in ra)
    assert a.radio_summary() == b.radio_summary() and a.dropped == b.dropped
    assert a.last_heard == b.last_heard and a.last_sinr == b.last_sinr
    assert a.medium._rng.bit_generator.state == b.medium._rng.bit_generator.state
    assert repr(a.link_table()) == repr(b.link_table())  # repr: exact, and NaN equals NaN
