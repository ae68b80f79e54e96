"""The environment as pure code: world, radio and faults, with no transport.

The netsim process wraps this in Zenoh; the in-process runner (swarmloc.experiment.runner) drives it
directly. Both therefore see the same trajectories, sensor noise and link decisions.

Two ways to move frames, one per clock mode:
- exchange(round): lockstep. Every frame the swarm sent since the last round is offered at
  the same modelled instant, in (sender, seq) order, and resolved to the end. The content of
  a round depends only on what the agents computed, never on wall-clock arrival order, so a
  lockstep run is deterministic for a seed, whatever the radio model.
- offer(frame, t) / advance(t): real time. Frames enter the medium when they arrive and
  come out after their modelled airtime, queueing and latency.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import Counter

import numpy as np
from pydantic import TypeAdapter, ValidationError

from netsim.channel import DROP_REASONS, ChannelConfig, Jammer, Outcomes, RadioMedium, TxFrame, UnitDisk
from netsim.faults import BLOCK_REASONS, FaultState
from netsim.world import World, streams
from swarmloc.errors import readable
from swarmloc.experiment.faults import FaultError, _Fault
from swarmloc.experiment.scenario import Scenario, ScenarioError
from swarmloc.node import RadioRx as Rx
from swarmloc.node import RadioTx as Tx
from swarmloc.wire.messages import LinkNack

log = logging.getLogger(__name__)


def _pos3(p) -> np.ndarray:
    """A 2D (planar) or 3D position as 3D: planar robots and jammers sit at height 0."""
    p = np.asarray(p, float)
    return np.pad(p, (0, 3 - p.size))


CHANNEL = TypeAdapter(ChannelConfig)


def channel_of(scenario: Scenario):
    try:
        return CHANNEL.validate_python(scenario.radio)
    except ValidationError as exc:
        lines = [f"  radio.{'.'.join(str(p) for p in e['loc'][1:])}: {readable(e)}" for e in exc.errors()]
        raise ScenarioError(f"{scenario.name}: invalid radio\n" + "\n".join(lines)) from None


# Every reason a reception can fail, as small integers: the channel's codes (netsim.channel)
# first, then the overlay's. "" (code 0) is a delivery.
REASONS: tuple[str, ...] = ("", *DROP_REASONS, "down", "radio-off", "fault", "partition", "loss", "unknown")
_CODE = {r: k for k, r in enumerate(REASONS)}
_FROM_BLOCK = np.array([0 if r is None else _CODE[r] for r in BLOCK_REASONS], np.int8)


def _direct_rx_ok() -> bool:
    fields = tuple(f.name for f in dataclasses.fields(Rx))
    return (fields == ("receiver", "t", "data", "nack", "src", "seq", "unicast") and not hasattr(Rx, "__slots__")
            and not hasattr(Rx, "__post_init__"))


# A frozen dataclass's __init__ sets each field through object.__setattr__; filling the
# instance dict at once gives the same object (equal, hashable, same repr) for a third of
# the cost, which matters at one delivery per frame and receiver. Only while RadioRx is the
# plain frozen dataclass this assumes; otherwise its constructor.
_DIRECT_RX = _direct_rx_ok()


def _make_rx(receivers: list[int], times: list[float], frames: list[tuple[bytes, int, int, bool]],
             frame_of: list[int]) -> list[Rx]:
    """Deliveries: receivers[i] gets frames[frame_of[i]] (data, src, seq, unicast) at times[i]."""
    if not _DIRECT_RX:
        return [Rx(r, t, *_with_nack(frames[f])) for r, t, f in zip(receivers, times, frame_of)]
    new, put = object.__new__, object.__setattr__
    out = []
    for r, t, f in zip(receivers, times, frame_of):
        data, src, seq, unicast = frames[f]
        rx = new(Rx)
        put(rx, "__dict__", {"receiver": r, "t": t, "data": data, "nack": None, "src": src, "seq": seq,
                             "unicast": unicast})
        out.append(rx)
    return out


class Deliveries:
    """A batch of deliveries in order, without a RadioRx each: receiver i gets
    ``frames[frame_of[i]]`` (data, src, seq, unicast) at ``times[i]``. Iterating makes the
    RadioRx objects (what :meth:`Simulation.exchange` returns); :meth:`raw` gives their fields
    as tuples, which is what netsim's server needs to put a frame on, for a tenth of the cost
    at hundreds of receivers."""

    __slots__ = ("receivers", "times", "frames", "frame_of")

    def __init__(self, receivers: list[int], times: list[float], frames: list[tuple[bytes, int, int, bool]],
                 frame_of: list[int]):
        self.receivers, self.times, self.frames, self.frame_of = receivers, times, frames, frame_of

    def __len__(self) -> int:
        return len(self.receivers)

    def __iter__(self):
        return iter(_make_rx(self.receivers, self.times, self.frames, self.frame_of))

    def raw(self):
        """(receiver, t, data, src, seq, unicast) per delivery, in order."""
        frames = self.frames
        for r, t, f in zip(self.receivers, self.times, self.frame_of):
            yield (r, t, *frames[f])


def _with_nack(frame: tuple[bytes, int, int, bool]) -> tuple:
    data, src, seq, unicast = frame
    return data, None, src, seq, unicast


class RadioLog:
    """Every reception attempt, stored as arrays per batch of receptions.

    Iterates as (k, src, receiver, size, reason) tuples, reason "" if delivered.
    """

    def __init__(self) -> None:
        self._parts: list[tuple[np.ndarray, ...]] = []
        self._n = 0

    def add(self, k: int, src: np.ndarray, receiver: np.ndarray, size: np.ndarray, code: np.ndarray) -> None:
        if len(src):
            self._parts.append((np.full(len(src), k, np.int64), src, receiver, size, code))
            self._n += len(src)

    def __len__(self) -> int:
        return self._n

    def __iter__(self):
        for k, src, receiver, size, code in self._parts:
            yield from zip(k.tolist(), src.tolist(), receiver.tolist(), size.tolist(),
                           [REASONS[c] for c in code.tolist()])

    def arrays(self) -> dict[str, np.ndarray]:
        cols = [np.concatenate(c) for c in zip(*self._parts)] or [np.zeros(0, np.int64)] * 4 + [np.zeros(0, np.int8)]
        k, src, receiver, size, code = cols
        return {"k": k.astype(np.int64), "src": src.astype(np.int64), "receiver": receiver.astype(np.int64),
                "size": size.astype(np.int64), "delivered": code == 0,
                "reason": np.array(REASONS, dtype="U16")[code.astype(np.intp)]}


def world_of(scenario: Scenario, seed: int | None = None):
    """The scenario's world: simulated, or a recording replayed (world.source)."""
    if scenario.world.source == "mrclam":
        from netsim.world.recorded import ReplayWorld

        return ReplayWorld(scenario, seed)
    if scenario.world.source == "mcap":
        from netsim.world.recorded import McapWorld

        return McapWorld(scenario, seed)
    return World(scenario, seed)


# A batch of outcomes of one frame with at most this many receptions is counted and delivered
# in plain Python (_resolve_one): numpy's fixed cost per call is most of the work for a few.
_SCALAR_MAX = 8


class Simulation:
    def __init__(self, scenario: Scenario, seed: int | None = None, scalar: bool = True):
        """``scalar=False`` routes every round through the vectorised path alone (the reference
        the scalar path is tested against: tests/test_scalar_path.py)."""
        self.scalar = scalar
        self.sc = scenario
        self.world = world_of(scenario, seed)
        rng = streams(scenario.seed if seed is None else seed)
        self.ids = scenario.agent_ids
        self.steps = self.world.steps
        self.channel = channel_of(scenario)
        self.medium = RadioMedium(self.channel, rng["radio"])
        self.medium.scalar = scalar
        self.loss_seed = int(rng["loss"].integers(2**62))
        self.faults = FaultState(self.ids)
        self.down: set[int] = set()  # agents whose process is not running (netsim's view)
        self.medium.set_positions(self.world.pos)  # a link table is available before tick 0
        self.timeline = sorted(scenario.faults, key=lambda f: f.at)
        self.k, self.t = -1, 0.0
        self.vt = 0.0  # modelled time of the next lockstep round
        self._uid = 0
        self._inflight: dict[int, list] = {}  # uid -> [frame, outcomes still to come]
        # Per ordered pair of agents (rows: sender, columns: receiver, in self.ids order).
        n = len(self.ids)
        self._id_array = np.array(self.ids, np.int64)  # ascending (Scenario.agent_ids)
        self._attempts = np.zeros((n, n), np.int64)  # frames src -> receiver, whatever their fate
        self._delivered = np.zeros((n, n), np.int64)
        self._dropped = np.zeros((n, n, len(REASONS)), np.int64)
        self._unknown: Counter[tuple[int, int, str]] = Counter()  # frames from or to ids outside the swarm
        self._last_heard = np.full((n, n), np.nan)
        self._last_sinr = np.full((n, n), np.nan)  # SINR of the last frame src -> receiver
        self._jam_cache: tuple[tuple, np.ndarray] | None = None
        self._clean_cache: tuple[tuple, bool] | None = None
        self._off: tuple[int, list[bool]] | None = None
        self._index = {a: i for i, a in enumerate(self.ids)}
        self.radio_log = RadioLog()
        self.link_log: list[tuple[np.ndarray, ...]] = []  # per tick: (k, t, a, b, snr_db, up, delivered, dropped)

    @property
    def fault_log(self) -> list[dict]:
        return self.faults.log

    # Per-pair counters as {(src, receiver): value}, built on demand from the arrays.
    @property
    def delivered(self) -> Counter[tuple[int, int]]:
        return self._pair_counter(self._delivered)

    @property
    def attempts(self) -> Counter[tuple[int, int]]:
        return self._pair_counter(self._attempts)

    @property
    def dropped(self) -> Counter[tuple[int, int, str]]:
        out: Counter[tuple[int, int, str]] = Counter()
        for i, j, c in zip(*(v.tolist() for v in np.nonzero(self._dropped))):
            out[(self.ids[i], self.ids[j], REASONS[c])] = int(self._dropped[i, j, c])
        return out + self._unknown

    @property
    def last_heard(self) -> dict[tuple[int, int], float]:
        return self._pair_dict(self._last_heard)

    @property
    def last_sinr(self) -> dict[tuple[int, int], float]:
        return self._pair_dict(self._last_sinr)

    def _pair_counter(self, a: np.ndarray) -> Counter[tuple[int, int]]:
        i, j = np.nonzero(a)
        return Counter({(self.ids[x], self.ids[y]): v for x, y, v in zip(i.tolist(), j.tolist(), a[i, j].tolist())})

    def _pair_dict(self, a: np.ndarray) -> dict[tuple[int, int], float]:
        i, j = np.nonzero(~np.isnan(a))
        return {(self.ids[x], self.ids[y]): v for x, y, v in zip(i.tolist(), j.tolist(), a[i, j].tolist())}

    # ---------------------------------------------------------------- clock

    def tick(self, live_faults: list[_Fault] = ()):
        """Advance one tick; faults due by now (timeline, expiring --for, live) apply to its frames."""
        # Faults first, so a GNSS outage or a kill due at t already shapes tick t's frames.
        self.k, self.t = self.world.k + 1, (self.world.k + 1) * self.world.dt
        while self.timeline and self.timeline[0].at <= self.t + 1e-9:
            self.apply(self.timeline.pop(0), "scenario")
        for f in self.faults.due(self.t):
            self.apply(f, "duration")
        for f in live_faults:
            self.apply(f, "live")
        frames = self.world.step(self.faults.gnss_ok, lambda a, b: self.faults.blocked(a, b) is None)
        self.medium.set_positions(self.world.pos)
        self.medium.set_jammers([Jammer(tuple(pos), f.power_dbm, self.t, float("inf"), f.band_hz)
                                 for f, pos in self.faults.jammers(self.t)])
        self.vt = max(self.t, self.medium.now)
        self._record_links()
        return self.k, self.t, frames

    def command(self, aid: int, u) -> str | None:
        """An agent's actuator command for its vehicle, in force from the next tick: None when
        applied, else why not ("command-off": a fault keeps the stream from the vehicle;
        "malformed", "not-a-vehicle"). Counted in `commands`."""
        fleet = getattr(self.world, "vehicles", None)
        if fleet is None:
            return "not-a-vehicle"
        if not self.faults.command_ok(aid):
            fleet.commands["command-off"] += 1
            return "command-off"
        return fleet.command(aid, u)

    @property
    def commands(self) -> dict:
        """Closed loop: the commands received (`applied`, or refused by reason; an agent may send
        several in a tick, the last one counts) and per vehicle the ticks it flew on an older
        command (`held_ticks`); {} when the agents command nothing."""
        fleet = getattr(self.world, "vehicles", None)
        if fleet is None or fleet.autopilot:
            return {}
        return {"received": dict(sorted(fleet.commands.items())), "held_ticks": {str(a): n for a, n in fleet.held.items()}}

    def targets(self) -> dict[int, np.ndarray]:
        """True target positions now ({} without targets)."""
        return self.world.targets()

    def truth(self) -> dict[int, np.ndarray]:
        """Every agent's true state in its model's layout (docs/run-format.md)."""
        return self.world.states()

    def apply(self, f: _Fault, source: str) -> None:
        try:
            self.faults.apply(f, self.t, self.k, source)
        except FaultError as exc:
            log.error("fault not applied: %s", exc)
            raise
        log.info("t=%.1f %s fault: %s", self.t, source, f.model_dump(exclude_none=True))

    # ---------------------------------------------------------------- radio

    def exchange(self, frames: list[Tx]) -> list[Rx]:
        """Lockstep: one round of frames, offered together, resolved completely."""
        out = self.exchange_batch(frames)
        return out if isinstance(out, list) else list(out)

    def exchange_batch(self, frames: list[Tx]) -> list[Rx] | Deliveries:
        """:meth:`exchange`, the deliveries of a round without NACKs as :class:`Deliveries`."""
        early: list[Rx] = []
        offered: list[Outcomes] = []
        for tx in sorted(frames, key=lambda f: (f.src, f.seq)):
            nacks, drops = self._offer(tx, self.vt)
            early += nacks
            if drops is not None:
                offered.append(drops)
        out = self._resolve(Outcomes.concat([*offered, self.medium.run_to_idle()]), in_round_order=True,
                            batch=not early)
        if early:
            out = sorted(early + out, key=lambda r: (r.t, r.receiver, r.nack is not None))
        if out:
            self.vt = max(self.vt, out.times[-1] if isinstance(out, Deliveries) else out[-1].t)  # sorted by time
        return out

    def offer(self, tx: Tx, t: float) -> list[Rx]:
        nacks, drops = self._offer(tx, t)
        return nacks + self._resolve(drops) if drops is not None else nacks

    def _offer(self, tx: Tx, t: float) -> tuple[list[Rx], Outcomes | None]:
        """NACKs decided before the medium (unknown ids, radio off), and the medium's immediate drops."""
        if tx.src not in self.world.pos or (tx.dst is not None and (tx.dst not in self.world.pos or tx.dst == tx.src)):
            self._unknown[(tx.src, tx.dst if tx.dst is not None else -1, "unknown")] += 1
            return (self._nack(tx, t, "unknown") if tx.dst is not None else []), None
        i = self._index[tx.src]
        if self._radio_off()[i]:
            # A radio that is off does not even transmit (and so interferes with nobody).
            receivers = np.array([self._index[tx.dst]] if tx.dst is not None else
                                 [j for j in range(len(self.ids)) if j != i], np.int64)
            k = len(receivers)
            code = np.full(k, _CODE["radio-off"], np.int8)
            off = Outcomes(np.zeros(k, np.int64), np.full(k, tx.src, np.int64), self._id_array[receivers],
                           np.full(k, t), code, np.full(k, np.nan))
            self._count(off, np.full(k, i), receivers, code, np.full(k, len(tx.data), np.int64))
            return (self._nack(tx, t, "radio-off") if tx.dst is not None else []), None
        self._uid += 1
        self._inflight[self._uid] = [tx, 1 if tx.dst is not None else len(self.ids) - 1]
        return [], self.medium.offer_arrays(TxFrame(self._uid, tx.src, tx.dst, len(tx.data)), t)

    def advance(self, t: float) -> list[Rx]:
        return self._resolve(self.medium.advance_arrays(t))

    def _radio_off(self) -> list[bool]:
        """Per agent (self.ids order), whether its radio is off."""
        if self._off is None or self._off[0] != self.faults.version:
            codes = self.faults.blocked_matrix().diagonal()
            self._off = (self.faults.version, (codes == BLOCK_REASONS.index("radio-off")).tolist())
        return self._off[1]

    def next_event_time(self) -> float | None:
        return self.medium.next_event_time()

    def _agent(self, ids: np.ndarray) -> np.ndarray:
        return np.searchsorted(self._id_array, ids)

    def _frames_of(self, uid: np.ndarray) -> tuple[list[Tx], np.ndarray]:
        """The frames behind these outcomes, and each outcome's index among them."""
        lo = int(uid.min())
        span = int(uid.max()) - lo + 1
        if span <= 4 * len(uid) + 64:  # uids are consecutive in a round: count them, no sort
            counts = np.bincount(uid - lo, minlength=span)
            present = np.flatnonzero(counts)
            index = np.zeros(span, np.int64)
            index[present] = np.arange(present.size)
            uids, frame_of, counts = present + lo, index[uid - lo], counts[present]
        else:
            uids, frame_of, counts = np.unique(uid, return_inverse=True, return_counts=True)
        txs: list[Tx] = []
        for u, c in zip(uids.tolist(), counts.tolist()):
            entry = self._inflight[u]
            txs.append(entry[0])
            entry[1] -= c
            if entry[1] <= 0:
                del self._inflight[u]
        return txs, frame_of.reshape(-1)

    def _resolve(self, out: Outcomes, in_round_order: bool = False, batch: bool = False) -> list[Rx] | Deliveries:
        """Overlay down agents and faults on the channel's outcomes, count them, and make the
        deliveries and NACKs: in outcome order, or sorted as a lockstep round returns them."""
        if not len(out):
            return []
        if self.scalar and len(out) <= _SCALAR_MAX:
            uids = out.uid.tolist()
            if uids.count(uids[0]) == len(uids):
                rx = self._resolve_one(out, uids[0], in_round_order)
                if rx is not None:
                    return rx
        txs, frame_of = self._frames_of(out.uid)
        s, r = self._agent(out.src), self._agent(out.receiver)
        code = out.reason.copy()
        ok = np.flatnonzero(code == 0)
        if ok.size:
            code[ok] = self._overlay(txs, frame_of[ok], s[ok], r[ok])
        sizes = np.array([len(tx.data) for tx in txs], np.int64)
        self._count(out, s, r, code, sizes[frame_of])
        return self._deliveries(out, code, txs, frame_of, in_round_order, batch)

    def _resolve_one(self, out: Outcomes, uid: int, in_round_order: bool) -> list[Rx] | None:
        """_resolve of a few outcomes of one frame, element by element: the same counts, log
        and deliveries in the same order. None (nothing done): a receiver outside the swarm,
        left to the general path."""
        index = self._index
        receivers = out.receiver.tolist()
        rows = [index.get(x, -1) for x in receivers]
        entry = self._inflight[uid]
        tx = entry[0]
        i = index.get(tx.src, -1)
        if i < 0 or -1 in rows:
            return None
        k = len(receivers)
        entry[1] -= k
        if entry[1] <= 0:
            del self._inflight[uid]
        codes = out.reason.tolist()
        if 0 in codes and not self._clean():
            code = out.reason.copy()
            ok = np.flatnonzero(code == 0)
            code[ok] = self._overlay([tx], np.zeros(ok.size, np.int64), np.full(ok.size, i), np.array(rows)[ok])
            codes = code.tolist()
        times, sinrs = out.t.tolist(), out.sinr_db.tolist()
        attempts, delivered, dropped = self._attempts, self._delivered, self._dropped
        heard, sinr = self._last_heard, self._last_sinr
        for j, c, t, q in zip(rows, codes, times, sinrs):
            attempts[i, j] += 1
            if c == 0:
                delivered[i, j] += 1
                heard[i, j] = t
            else:
                dropped[i, j, c] += 1
            if math.isfinite(q):
                sinr[i, j] = q
        self.radio_log.add(self.k, out.src, out.receiver, np.full(k, len(tx.data), np.int64), np.array(codes, np.int8))
        unicast = tx.dst is not None
        got = [m for m, c in enumerate(codes) if c == 0]
        if in_round_order:
            got.sort(key=lambda m: (times[m], receivers[m]))
        rx = _make_rx([receivers[m] for m in got], [times[m] for m in got], [(tx.data, tx.src, tx.seq, unicast)],
                      [0] * len(got))
        nacked = [m for m, c in enumerate(codes) if c != 0] if unicast else []
        if not nacked:
            return rx
        nacks = [Rx(tx.src, times[m], nack=LinkNack(tx.seq, tx.dst, REASONS[codes[m]][:32])) for m in nacked]
        if in_round_order:
            return sorted(rx + nacks, key=lambda x: (x.t, x.receiver, x.nack is not None))
        both = sorted(zip(got + nacked, rx + nacks), key=lambda p: p[0])
        return [x for _, x in both]

    def _clean(self) -> bool:
        """No fault, down agent or jammer can change what the channel delivered this tick."""
        if self.down:
            return False
        key = (self.faults.version, self.k)
        if self._clean_cache is None or self._clean_cache[0] != key:
            blocked, loss = self._fault_tables()
            self._clean_cache = (key, blocked is None and loss is None and not self._jammed_mask().any())
        return self._clean_cache[1]

    def _overlay(self, txs: list[Tx], frame: np.ndarray, s: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Why a frame the channel delivered is lost all the same (0: it is not)."""
        blocked, loss = self._fault_tables()
        code = np.zeros(len(r), np.int8) if blocked is None else _FROM_BLOCK[blocked[s, r]]
        if self.down:
            code[np.isin(self._id_array, list(self.down))[r]] = _CODE["down"]
        jammed = self._jammed_mask()
        if jammed.any():
            code[(code == 0) & jammed[r]] = _CODE["jammed"]
        if loss is not None:
            p = loss[s, r]
            lossy = np.flatnonzero((code == 0) & (p > 0))
            if lossy.size:
                u = self._uniform(txs, frame[lossy], r[lossy])
                code[lossy[u < p[lossy]]] = _CODE["loss"]
        return code

    def _fault_tables(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The faults' blocked codes and extra loss per pair, None where no pair has any."""
        blocked, loss = self.faults.blocked_matrix(), self.faults.loss_matrix()
        return (blocked if blocked.any() else None), (loss if loss.any() else None)

    def _uniform(self, txs: list[Tx], frame: np.ndarray, receiver: np.ndarray) -> np.ndarray:
        # Keyed by the frame, not drawn in arrival order: the same frame meets the same fate
        # whichever order frames reach netsim, so lockstep stays deterministic without rounds.
        u = np.empty(len(frame))
        for f in np.unique(frame).tolist():
            tx = txs[f]
            at = frame == f
            u[at] = np.random.default_rng([self.loss_seed, self.k, tx.src, tx.seq]).random(len(self.ids))[receiver[at]]
        return u

    def _jammed_mask(self) -> np.ndarray:
        """Receivers a jammer silences: unit disk has no notion of power, so a jammer there
        silences receivers within its radius."""
        key = (self.faults.version, self.k)
        if self._jam_cache is None or self._jam_cache[0] != key:
            jammed = np.zeros(len(self.ids), bool)
            if isinstance(self.channel, UnitDisk):
                where = np.array([_pos3(self.world.pos[a]) for a in self.ids]).reshape(-1, 3)
                for f, pos in self.faults.jammers(self.t):
                    jammed |= np.linalg.norm(where - _pos3(pos), axis=1) <= f.radius_m
            self._jam_cache = (key, jammed)
        return self._jam_cache[1]

    def _count(self, out: Outcomes, s: np.ndarray, r: np.ndarray, code: np.ndarray, size: np.ndarray) -> None:
        n = len(self.ids)
        pair = s * n + r
        tries = np.bincount(pair, minlength=n * n)
        self._attempts += tries.reshape(n, n)
        repeated = bool(tries.max() > 1)
        ok = code == 0
        self._delivered += np.bincount(pair[ok], minlength=n * n).reshape(n, n)
        if not ok.all():
            np.add.at(self._dropped, (s[~ok], r[~ok], code[~ok]), 1)
        judged = np.isfinite(out.sinr_db)
        self._keep_last(self._last_sinr, pair[judged], out.sinr_db[judged], repeated)
        self._keep_last(self._last_heard, pair[ok], out.t[ok], repeated)
        self.radio_log.add(self.k, out.src, out.receiver, size, code)

    @staticmethod
    def _keep_last(a: np.ndarray, pair: np.ndarray, v: np.ndarray, repeated: bool) -> None:
        # The last value per pair in outcome order: numpy leaves repeated fancy assignment unordered.
        if repeated:
            _, first_from_end = np.unique(pair[::-1], return_index=True)
            last = len(pair) - 1 - first_from_end
            pair, v = pair[last], v[last]
        a.flat[pair] = v

    def _deliveries(self, out: Outcomes, code: np.ndarray, txs: list[Tx], frame_of: np.ndarray,
                    in_round_order: bool, batch: bool = False) -> list[Rx] | Deliveries:
        got = np.flatnonzero(code == 0)
        nacked = np.flatnonzero(code != 0)
        if nacked.size:
            unicast = np.array([tx.dst is not None for tx in txs])
            nacked = nacked[unicast[frame_of[nacked]]]
        if in_round_order:  # by (t, receiver, NACK last), ties in outcome order
            got = got[np.lexsort((out.receiver[got], out.t[got]))]
        frames = [(tx.data, tx.src, tx.seq, tx.dst is not None) for tx in txs]
        if batch and not nacked.size:
            return Deliveries(out.receiver[got].tolist(), out.t[got].tolist(), frames, frame_of[got].tolist())
        rx = _make_rx(out.receiver[got].tolist(), out.t[got].tolist(), frames, frame_of[got].tolist())
        if not nacked.size:
            return rx
        nacks = [Rx(src, t, nack=LinkNack(txs[f].seq, txs[f].dst, REASONS[c][:32]))
                 for src, t, f, c in zip(out.src[nacked].tolist(), out.t[nacked].tolist(),
                                         frame_of[nacked].tolist(), code[nacked].tolist())]
        # Merge: by (t, receiver, NACK last) in a round, else in outcome order.
        if in_round_order:
            return sorted(rx + nacks, key=lambda x: (x.t, x.receiver, x.nack is not None))
        at = np.concatenate([got, nacked])
        both = rx + nacks
        return [both[i] for i in np.argsort(at, kind="stable").tolist()]

    @staticmethod
    def _nack(tx: Tx, t: float, reason: str) -> list[Rx]:
        return [Rx(tx.src, t, nack=LinkNack(tx.seq, tx.dst, reason[:32]))]

    # ---------------------------------------------------------------- link table

    def link_state(self, a: int, b: int) -> tuple[bool, float, str]:
        """(up, distance, reason if down) for a -> b: physics and faults, no random draw."""
        info = self.medium.link(a, b)
        blocked = ("down" if self.down & {a, b} else None) or self.faults.blocked(a, b) \
            or ("jammed" if self._jammed_mask()[self._index[b]] else None)
        if blocked:
            return False, info.distance_m, blocked
        return info.up, info.distance_m, "" if info.up else "distance"

    def _directed_links(self) -> tuple[np.ndarray, ...]:
        """link_state for every ordered pair: (up, distance, reason code), and the channel's SNR and PDR."""
        ids, dist, _, snr, pdr, up = self.medium.link_arrays()
        at = np.searchsorted(ids, self._id_array)
        pick = np.ix_(at, at)
        dist, snr, pdr, up = dist[pick], snr[pick], pdr[pick], up[pick]
        down = np.isin(self._id_array, list(self.down))
        blocked = np.where(down[:, None] | down[None, :], _CODE["down"], _FROM_BLOCK[self.faults.blocked_matrix()])
        blocked[(blocked == 0) & self._jammed_mask()[None, :]] = _CODE["jammed"]
        reason = np.where(blocked != 0, blocked, np.where(up, 0, _CODE["distance"]))
        return reason == 0, dist, reason, snr, pdr

    def _pair_arrays(self) -> dict[str, np.ndarray]:
        """The link table's columns, one entry per unordered pair a < b."""
        up, dist, reason, snr, pdr = self._directed_links()
        a, b = np.triu_indices(len(self.ids), 1)
        dlv = self._delivered[a, b] + self._delivered[b, a]
        total = self._attempts[a, b] + self._attempts[b, a]
        with np.errstate(invalid="ignore"):
            return {"a": self._id_array[a], "b": self._id_array[b], "up": up[a, b] & up[b, a],
                    "distance": dist[a, b], "reason": np.where(reason[a, b] != 0, reason[a, b], reason[b, a]),
                    "snr_db": snr[a, b], "sinr_db": np.fmin(self._last_sinr[a, b], self._last_sinr[b, a]),
                    "pdr_model": pdr[a, b], "delivered": dlv, "dropped": total - dlv, "total": total,
                    "last_heard": np.fmax(self._last_heard[a, b], self._last_heard[b, a])}

    def link_table(self, in_reach: bool = False) -> list[dict]:
        """One row per unordered pair a < b. `in_reach`: only the pairs that are links, i.e. not
        down for distance alone (a pair out of radio range in a direction and not otherwise
        cut): what netsim publishes and draws. In `swarm256` (256 agents over 640 m) 3,074 of
        the 32,640 pairs, which the wire's Links frame (at most 4,096 rows) could not carry."""
        c = self._pair_arrays()
        if in_reach:
            keep = c["reason"] != _CODE["distance"]
            c = {f: v[keep] for f, v in c.items()}
        none_if_nan = lambda v: None if v != v else v  # noqa: E731
        return [{"a": a, "b": b, "up": up, "distance": d, "reason": REASONS[why], "snr_db": snr,
                 "sinr_db": none_if_nan(sinr), "pdr_model": pdr, "delivered": dlv, "dropped": drp,
                 "delivery_ratio": dlv / total if total else None, "last_heard": none_if_nan(heard)}
                for a, b, up, d, why, snr, sinr, pdr, dlv, drp, total, heard in zip(
                    *(c[f].tolist() for f in ("a", "b", "up", "distance", "reason", "snr_db", "sinr_db", "pdr_model",
                                              "delivered", "dropped", "total", "last_heard")))]

    def _record_links(self) -> None:
        c = self._pair_arrays()
        self.link_log.append((np.full(len(c["a"]), self.k, np.int64), np.full(len(c["a"]), self.t), c["a"], c["b"],
                              c["snr_db"], c["up"], c["delivered"], c["dropped"]))

    def radio_arrays(self) -> dict[str, np.ndarray]:
        """Every reception attempt, the link table per tick and every fault (radio.npz)."""
        faults = self.faults.log
        links = [np.concatenate(c) for c in zip(*self.link_log)] if self.link_log else \
            [np.zeros(0, t) for t in (np.int64, float, np.int64, np.int64, float, bool, np.int64, np.int64)]
        names = ("link_k", "link_t", "link_a", "link_b", "link_snr_db", "link_up", "link_delivered", "link_dropped")
        types = (np.int64, float, np.int64, np.int64, float, bool, np.int64, np.int64)
        return {
            **self.radio_log.arrays(),
            **{name: np.asarray(col, dtype) for name, col, dtype in zip(names, links, types)},
            "fault_t": np.array([f["t"] for f in faults], float),
            "fault_k": np.array([f["k"] for f in faults], np.int64),
            "fault_action": np.array([f["action"] for f in faults], dtype="U16"),
            "fault_source": np.array([f["source"] for f in faults], dtype="U16"),
        }

    def radio_summary(self) -> dict:
        reasons: Counter[str] = Counter()
        totals = self._dropped.sum(axis=(0, 1))
        for c in np.flatnonzero(totals).tolist():
            reasons[REASONS[c]] = int(totals[c])
        for (_, _, why), n in self._unknown.items():
            reasons[why] += n
        return {"delivered": int(self._delivered.sum()), "dropped": dict(reasons)}
