"""The radio medium: positions, queues, overlapping transmissions and shadowing; it asks the
channel model for the physics and returns the outcome of every frame at every receiver."""

from __future__ import annotations

import math
from bisect import bisect_left
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from operator import attrgetter
from typing import Annotated, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from netsim.channel.frames import (
    CODE_DISTANCE,
    CODE_QUEUE,
    ChannelModel,
    LinkInfo,
    Outcome,
    Outcomes,
    TxFrame,
)
from netsim.channel.jammer import Jammer, pos3
from netsim.channel.log_distance import LogDistance
from netsim.channel.physics import FloatArray
from netsim.channel.unit_disk import UnitDisk

ChannelConfig = Annotated[Union[UnitDisk, LogDistance], Field(discriminator="model")]
"""Config-file union: ``{"model": "log-distance", ...}`` or ``{"model": "unit-disk", ...}``."""


# --------------------------------------------------------------------------- #
# Shadowing state
# --------------------------------------------------------------------------- #
class _ShadowField:
    """Symmetric per-pair shadowing, advanced on every position update.

    delta_d for a pair is the sum of both ends' displacements: the environment a
    link sees changes when either end moves. Because exp(-a) exp(-b) = exp(-(a+b)),
    updating every tick is equivalent to one update over the summed path, so the
    result does not depend on the tick rate.
    """

    def __init__(self, sigma_db: float, decorrelation_m: float) -> None:
        self._sigma = sigma_db
        self._dcorr = decorrelation_m
        self._index: dict[int, int] = {}
        self._pos = np.zeros((0, 3))
        self._s = np.zeros((0, 0))

    def update(self, positions: Mapping[int, FloatArray], rng: np.random.Generator) -> None:
        ids = sorted(positions)
        n = len(ids)
        pos = np.array([positions[i] for i in ids], dtype=float).reshape(n, 3)
        if self._sigma == 0.0:
            self._index = {node: k for k, node in enumerate(ids)}
            self._pos = pos
            return
        old = np.array([self._index.get(node, -1) for node in ids], dtype=int)
        kept = old >= 0
        moved = np.zeros(n)
        if kept.any():
            moved[kept] = np.linalg.norm(pos[kept] - self._pos[old[kept]], axis=1)
        iu, ju = np.triu_indices(n, 1)
        both = kept[iu] & kept[ju]
        prev = np.zeros(iu.size)
        prev[both] = self._s[old[iu[both]], old[ju[both]]]
        rho = np.where(both, np.exp(-(moved[iu] + moved[ju]) / self._dcorr), 0.0)
        z = rng.standard_normal(iu.size)
        values = rho * prev + np.sqrt(1.0 - rho * rho) * self._sigma * z
        s = np.zeros((n, n))
        s[iu, ju] = values
        s[ju, iu] = values
        self._s = s
        self._pos = pos
        self._index = {node: k for k, node in enumerate(ids)}

    def matrix(self) -> FloatArray:
        """Shadowing (dB) between every two known nodes, in ascending id order."""
        n = len(self._index)
        return np.zeros((n, n)) if self._sigma == 0.0 else self._s

    def pair(self, a: int, b: int) -> float:
        """Shadowing (dB) between ``a`` and ``b``; 0 if either is unknown."""
        if self._sigma == 0.0:
            return 0.0
        ia, ib = self._index.get(a), self._index.get(b)
        return 0.0 if ia is None or ib is None else float(self._s[ia, ib])

    def get(self, a: int, others: Sequence[int]) -> FloatArray:
        """Shadowing (dB) between ``a`` and each of ``others``; 0 for unknown nodes."""
        out = np.zeros(len(others))
        ia = self._index.get(a)
        if self._sigma == 0.0 or ia is None:
            return out
        idx = np.array([self._index.get(b, -1) for b in others], dtype=int)
        known = idx >= 0
        out[known] = self._s[ia, idx[known]]
        return out


# --------------------------------------------------------------------------- #
# Medium
# --------------------------------------------------------------------------- #
@dataclass(eq=False, slots=True)
class _Tx:
    frame: TxFrame
    start: float
    end: float
    pos: FloatArray  # sender position when the transmission started
    gen: int  # the geometry (set_positions call) it started under
    row: int  # its sender's row in that geometry

    @property
    def src(self) -> int:
        return self.frame.src


@dataclass
class _Sender:
    slot: int  # index into the medium's per-sender arrays
    queue: deque[TxFrame] = field(default_factory=deque)
    current: TxFrame | None = None


@dataclass(frozen=True)
class _Geometry:
    """Positions and what follows from them alone; fixed until the next set_positions.

    Rows and columns are the known nodes in ascending id order. ``rx_dbm[i, j]`` is the
    mean received power at j of a frame from i (shadowing included), ``hears[i, j]``
    whether j senses i's transmissions above the CCA threshold (never itself; an extra
    last column of False, so that ``hears[i, -1]`` asks about a node not in the world).
    """

    ids: NDArray[np.int64]
    index: dict[int, int]
    xyz: FloatArray
    distance: FloatArray
    shadow: FloatArray
    rx_dbm: FloatArray
    rx_mw: FloatArray
    hears: NDArray[np.bool_]


def _distances(a: FloatArray, b: FloatArray) -> FloatArray:
    diff = a[:, None, :] - b[None, :, :]
    return np.sqrt(np.add.reduce(diff * diff, axis=2))


_END_TIME = attrgetter("end")


def _owner(cls: type, name: str) -> type | None:
    """The class in ``cls``'s MRO that defines ``name`` (None: none does)."""
    return next((c for c in cls.__mro__ if name in c.__dict__), None)


class RadioMedium:
    """Discrete-event radio medium shared by all nodes.

    Usage per tick: :meth:`set_positions`, any number of :meth:`offer`, then
    :meth:`advance` to the tick time. Time never runs backwards: offers dated
    before the last ``advance`` are treated as offered at that time.

    Each sender transmits one frame at a time (FIFO; overflow is dropped as
    ``"queue"``). With carrier sense, a sender that senses another transmission
    above the CCA threshold defers until it ends plus DIFS and a random backoff;
    after each frame it performs a post-backoff. A failed unicast attempt (the
    sender is assumed to learn this instantly; ACKs use no airtime) is retried
    after a binary-exponential backoff, and only the final attempt is reported.

    :meth:`offer_arrays`, :meth:`advance_arrays` and :meth:`run_to_idle` return the
    same outcomes as :class:`Outcomes` arrays; :meth:`offer` and :meth:`advance` as
    :class:`Outcome` objects.
    """

    def __init__(self, model: ChannelModel, rng: np.random.Generator) -> None:
        self._model = model
        self._rng = rng
        self._pos: dict[int, FloatArray] = {}
        self._shadow = _ShadowField(model.shadowing_sigma_db, model.shadowing_decorrelation_m)
        self._geo = self._geometry()
        self._gen = 0
        self._links: dict[int, tuple[FloatArray, ...]] = {}
        self._jammers: tuple[Jammer, ...] = ()
        self._senders: dict[int, _Sender] = {}
        # Per sender slot: its node, the time of its next attempt (inf: none), the retries of
        # the frame in service and its row in the geometry (-1: not in the world).
        self._sender_ids: list[int] = []
        self._try_at = np.zeros(0)
        self._stage = np.zeros(0, np.int64)
        self._retrying = 0  # senders whose stage is not 0
        self._slot_row = np.zeros(0, np.int64)
        self._windows: list[tuple[float, float, int]] = []  # the model's backoff window per retry stage
        self._spare = np.zeros(0)  # uniforms drawn for backoffs and not used yet
        self._first_stage = np.zeros(0)  # stage-0 backoffs drawn and not used yet
        self._frame_bits: dict[int, int] = {}  # by payload size
        self._airtime: dict[int, float] = {}  # by payload size
        self._on_air: list[_Tx] = []  # in start order
        self._txs: list[_Tx] = []  # on air or ended recently enough to overlap one on air
        self._unjudged: list[tuple[_Tx, list[_Tx]]] = []  # ended broadcasts and what overlapped them
        self._pending: list[tuple[Outcomes, NDArray[np.int64]]] = []  # (outcomes, order reported)
        self._reported = 0
        self._now = -math.inf
        self._busy = 0  # senders with a frame in service (on air or waiting to try)
        # The scalar path for a frame alone on the air (see _alone); False: always the general one.
        self.scalar = True
        self._alone_tables: dict[tuple[int, int, int], tuple] = {}  # by (sender row, receiver row or -1, size)
        self._table_judge = _owner(type(model), "judge") is _owner(type(model), "judge_alone")
        # One table per frame size, unless the model's judge_alone says sizes do not matter to it.
        self._by_size = not (self._table_judge and getattr(model, "judge_alone_ignores_size", False))

    # --- inputs ---------------------------------------------------------------
    @property
    def model(self) -> ChannelModel:
        """The channel model this medium was built with."""
        return self._model

    @property
    def now(self) -> float:
        """Time of the last :meth:`advance` (-inf before the first)."""
        return self._now

    def set_positions(self, positions: Mapping[int, ArrayLike]) -> None:
        """Replace the set of known nodes and their 2D/3D positions (m).

        Nodes absent from ``positions`` are forgotten (frames to them drop as
        ``"distance"``); a node that reappears gets fresh shadowing.
        """
        self._pos = {int(k): pos3(v) for k, v in positions.items()}
        self._shadow.update(self._pos, self._rng)
        self._geo = self._geometry()
        self._gen += 1
        self._links = {}
        self._alone_tables = {}
        self._slot_row = np.array([self._geo.index.get(a, -1) for a in self._sender_ids], np.int64)

    def set_jammers(self, jammers: Sequence[Jammer]) -> None:
        """Replace the jammer list; each acts on frames whose airtime meets [t_start, t_end)."""
        self._jammers = tuple(jammers)

    def offer(self, frame: TxFrame, t: float) -> list[Outcome]:
        """Queue ``frame`` at its sender at time ``t``; returns the immediate ``"queue"`` drops."""
        out = self.offer_arrays(frame, t)
        return [] if out is None else out.to_list()

    def offer_arrays(self, frame: TxFrame, t: float) -> Outcomes | None:
        """:meth:`offer`, the drops (if any) as arrays."""
        t = max(t, self._now)
        sender = self._senders.get(frame.src) or self._new_sender(frame.src)
        if sender.current is None:
            sender.current = frame  # its stage is 0: _finish left it so
            self._busy += 1
            self._try_at[sender.slot] = t
            return None
        cap = self._model.queue_size
        if cap is not None and len(sender.queue) >= cap:
            return self._drops(frame, t, CODE_QUEUE)
        sender.queue.append(frame)
        return None

    # --- time -----------------------------------------------------------------
    def advance(self, t: float) -> list[Outcome]:
        """Resolve every event up to ``t``; return outcomes with ``outcome.t <= t`` in time order."""
        return self.advance_arrays(t).to_list()

    def advance_arrays(self, t: float) -> Outcomes:
        """:meth:`advance`, the outcomes as arrays."""
        self._run(t)
        self._now = max(self._now, t)
        return self._take_pending(t)

    def run_to_idle(self) -> Outcomes:
        """Resolve everything offered; the clock stops at the last event or arrival, not at infinity."""
        self._run(math.inf)
        out = self._take_pending(math.inf)
        if len(out):
            self._now = max(self._now, float(out.t[-1]))
        return out

    def next_event_time(self) -> float | None:
        """Earliest time at which :meth:`advance` could change state or return an outcome."""
        times = [min(x.end for x in self._on_air)] if self._on_air else []
        if self._try_at.size:
            times.append(float(self._try_at.min()))
        times += [float(o.t.min()) for o, _ in self._pending]
        t = min(times, default=math.inf)
        return None if t == math.inf else t

    # --- queries --------------------------------------------------------------
    def link(self, a: int, b: int, size: int | None = None) -> LinkInfo:
        """Mean interference-free quality of ``a -> b`` with the current shadowing."""
        ia, ib = self._geo.index[a], self._geo.index[b]
        d = float(self._geo.distance[ia, ib])
        size = self._model.reference_frame_bytes if size is None else size
        rx, snr, pdr, up = self._model.link_quality(d, float(self._geo.shadow[ia, ib]), size)
        return LinkInfo(a, b, d, rx, snr, pdr, up, size)

    def link_arrays(self, size: int | None = None) -> tuple[NDArray[np.int64], FloatArray, FloatArray, FloatArray,
                                                            FloatArray, NDArray[np.bool_]]:
        """:meth:`link` for every ordered pair: (ids, distance, rx dBm, SNR dB, PDR, up), matrices by id order."""
        size = self._model.reference_frame_bytes if size is None else size
        if size not in self._links:
            geo = self._geo
            self._links[size] = (geo.distance, *self._model.link_quality_arrays(geo.distance, geo.shadow, size))
        return (self._geo.ids, *self._links[size])  # type: ignore[return-value]

    def shadowing_db(self, a: int, b: int) -> float:
        """Current shadowing loss (dB) between ``a`` and ``b``; symmetric."""
        return self._shadow.pair(a, b)

    # --- geometry -------------------------------------------------------------
    def _geometry(self) -> _Geometry:
        ids = sorted(self._pos)
        n = len(ids)
        xyz = np.array([self._pos[i] for i in ids], dtype=float).reshape(n, 3)
        dist = _distances(xyz, xyz)
        shadow = self._shadow.matrix()
        rx = np.asarray(self._model.rx_power_dbm(dist, shadow), dtype=float).reshape(n, n)
        cca = self._model.cca_threshold_dbm
        hears = np.zeros((n, n + 1), dtype=bool)  # the last column answers for row -1: nobody there
        if cca is not None:
            hears[:, :n] = rx >= cca
        np.fill_diagonal(hears, False)
        return _Geometry(np.array(ids, dtype=np.int64), {a: k for k, a in enumerate(ids)}, xyz, dist, shadow, rx,
                         np.power(10.0, rx / 10.0), hears)

    def _rows(self, txs: Sequence[_Tx]) -> tuple[FloatArray, FloatArray]:
        """Distance and received power (dBm) from each transmission to every known node."""
        geo = self._geo
        rows = np.array([x.row if x.gen == self._gen else -1 for x in txs], dtype=np.int64)
        dist, dbm = geo.distance[rows], geo.rx_dbm[rows]
        for i in np.flatnonzero(rows < 0).tolist():
            # Started before the last set_positions: from where it started, with today's shadowing.
            x = txs[i]
            dist[i] = np.linalg.norm(geo.xyz - x.pos, axis=1)
            dbm[i] = self._model.rx_power_dbm(dist[i], self._shadow.get(x.src, geo.ids.tolist()))
        return dist, dbm

    # --- senders --------------------------------------------------------------
    def _new_sender(self, node: int) -> _Sender:
        sender = self._senders[node] = _Sender(len(self._sender_ids))
        self._sender_ids.append(node)
        self._try_at = np.append(self._try_at, math.inf)
        self._stage = np.append(self._stage, 0)
        self._slot_row = np.append(self._slot_row, self._geo.index.get(node, -1))
        return sender

    def _receivers(self, frame: TxFrame) -> NDArray[np.int64]:
        if frame.dst is not None:
            return np.array([frame.dst], dtype=np.int64)
        return self._geo.ids[self._geo.ids != frame.src]

    def _drops(self, frame: TxFrame, t: float, code: int) -> Outcomes:
        r = self._receivers(frame)
        k = len(r)
        return Outcomes(np.full(k, frame.uid, np.int64), np.full(k, frame.src, np.int64), r, np.full(k, t),
                        np.full(k, code, np.int8), np.full(k, np.nan))

    # --- the event loop -------------------------------------------------------
    def _run(self, limit: float) -> None:
        # Events in time order, ends before attempts at equal times. Attempts between two
        # ends that only defer are handled together (_attempts): nothing they do changes
        # what the others sense.
        while True:
            ending = min(self._on_air, key=_END_TIME) if self._on_air else None
            t_end = ending.end if ending is not None else math.inf
            first = int(np.argmin(self._try_at)) if self._try_at.size else -1  # ties in slot order
            t_try = float(self._try_at[first]) if first >= 0 else math.inf
            if ending is not None and t_end <= t_try:
                if t_end > limit:
                    break
                self._now = max(self._now, t_end)
                self._on_air.remove(ending)
                self._end(ending, t_end)
            elif t_try <= limit and t_try < math.inf:
                if ending is None and self._busy == 1 and not self._unjudged and self.scalar \
                        and self._alone(first, t_try, limit):
                    continue
                self._attempts(first, t_end, limit)
            else:
                break
        if self._unjudged:
            self._report(self._judge(self._unjudged))
            self._unjudged = []

    def _attempts(self, first: int, horizon: float, limit: float) -> None:
        """Attempts before ``horizon`` (the next end) and ``limit``, ``first`` the earliest.

        The usual case after an end: the channel is free, the earliest attempt transmits and
        every attempt during its airtime senses it and defers. Anything else is left to
        :meth:`_attempts_in_order`.
        """
        sensing = self._model.cca_threshold_dbm is not None
        if self._on_air and sensing:
            self._attempts_in_order(horizon, limit)
            return
        try_at = self._try_at
        tx = self._start(first, float(try_at[first]))
        if tx is None or not sensing:
            return
        cand = np.flatnonzero(try_at < min(horizon, tx.end, math.nextafter(limit, math.inf)))
        if not cand.size:
            return
        if self._geo.hears[tx.row, self._slot_row[cand]].all():
            try_at[cand] = tx.end + self._backoffs(cand)
        else:
            self._attempts_in_order(min(horizon, tx.end), limit)

    def _attempts_in_order(self, horizon: float, limit: float) -> None:
        """Every attempt before ``horizon`` (the next end) and ``limit``, in time order.

        A sender that senses a transmission defers past its end, hence past the next end:
        deferring never changes what anyone else senses, so the deferrals are drawn together
        at the end. Each attempt that finds the channel free starts a transmission, which
        those after it then sense, and which may bring the next end forward.
        """
        try_at = self._try_at
        cand = np.flatnonzero(try_at < min(horizon, math.nextafter(limit, math.inf)))
        if cand.size > 1:
            cand = cand[np.argsort(try_at[cand], kind="stable")]  # ties in slot order
        times = try_at[cand].tolist()
        sensing = self._model.cca_threshold_dbm is not None
        rows = self._slot_row[cand]
        busy = self._busy_until(rows) if sensing and self._on_air else None  # None: nothing sensed yet
        n, k = len(cand), 0
        deferred: list[slice] = []
        while k < n:
            i = k
            if busy is not None:
                free = np.flatnonzero(busy[k:n] == -math.inf)
                i = k + int(free[0]) if free.size else n
            if i > k:
                deferred.append(slice(k, i))
            if i == n:
                break
            tx = self._start(int(cand[i]), times[i])
            k = i + 1
            if tx is None:  # nothing went on air, but the sender may try again before horizon
                break
            if tx.end < horizon:
                horizon = tx.end
                n = max(k, bisect_left(times, horizon))
            if sensing and k < n:
                heard = self._geo.hears[tx.row, rows[k:n]]
                if busy is None:
                    busy = np.full(len(cand), -math.inf)
                busy[k:n] = np.where(heard, np.maximum(busy[k:n], tx.end), busy[k:n])
        if deferred:
            at = np.r_[tuple(deferred)] if len(deferred) > 1 else np.arange(deferred[0].start, deferred[0].stop)
            slots = cand[at]
            try_at[slots] = busy[at] + self._backoffs(slots)  # type: ignore[index]

    def _backoffs(self, slots: NDArray[np.intp]) -> FloatArray:
        """Backoffs of these senders at their retry stages, U{0..CW} slots each."""
        k = len(slots)
        stage = self._stage[slots] if self._retrying else None
        top = int(stage.max()) if stage is not None else 0
        while len(self._windows) <= top:
            self._windows.append(self._model.backoff_window(len(self._windows)))
        if top == 0:  # the usual case: drawn ahead, in blocks
            if self._first_stage.size < k:
                self._first_stage = np.concatenate([self._first_stage, self._backoff(0, self._uniforms(max(k, 1024)))])
            b, self._first_stage = self._first_stage[:k], self._first_stage[k:]
            return b
        fixed, slot, cw = (np.array(v)[stage] for v in zip(*self._windows[: top + 1]))
        return fixed + slot * np.floor(self._uniforms(k) * (cw + 1))

    def _backoff(self, stage: int, u: FloatArray) -> FloatArray:
        # Floats hold these windows exactly (far below 2^53), so the slot count is uniform on 0..CW.
        fixed, slot, cw = self._windows[stage]
        return fixed + slot * np.floor(u * (cw + 1))

    def _uniforms(self, k: int) -> FloatArray:
        # Drawn in blocks: deferrals take a few at a time, thousands of times per second.
        if self._spare.size < k:
            self._spare = np.concatenate([self._spare, self._rng.random(max(k, 1024))])
        u, self._spare = self._spare[:k], self._spare[k:]
        return u

    def _busy_until(self, rows: NDArray[np.int64]) -> FloatArray:
        """Per listener (row, -1 if gone), the latest end of what it senses now (-inf: the channel is free)."""
        geo, gen = self._geo, self._gen
        busy = np.full(len(rows), -math.inf)
        for x in self._on_air:
            heard = geo.hears[x.row, rows] if x.gen == gen else self._heard_stale(x, rows)
            busy = np.where(heard, np.maximum(busy, x.end), busy)
        return busy

    def _heard_stale(self, x: _Tx, rows: NDArray[np.int64]) -> NDArray[np.bool_]:
        geo = self._geo
        dist = np.linalg.norm(geo.xyz[rows] - x.pos, axis=1)
        listeners = geo.ids[rows]
        power = self._model.rx_power_dbm(dist, self._shadow.get(x.src, listeners.tolist()))
        cca = self._model.cca_threshold_dbm
        return (power >= cca) & (listeners != x.src) & (rows >= 0)

    def _start(self, slot: int, t: float) -> _Tx | None:
        # Deferrals need not move the clock: a deferred sender always has a later event.
        self._now = max(self._now, t)
        self._try_at[slot] = math.inf
        sender = self._senders[self._sender_ids[slot]]
        frame = sender.current
        if frame is None:
            return None
        row = int(self._slot_row[slot])
        if row < 0:
            # A sender that left the world cannot radiate; its frame reaches nobody.
            self._report(self._drops(frame, t, CODE_DISTANCE))
            self._finish(sender, t)
            return None
        airtime = self._airtime.get(frame.size)
        if airtime is None:
            airtime = self._airtime[frame.size] = self._model.airtime_s(frame.size)
        tx = _Tx(frame, t, t + airtime, self._geo.xyz[row], self._gen, row)
        self._txs.append(tx)
        self._on_air.append(tx)
        return tx

    def _end(self, tx: _Tx, t: float) -> None:
        overlapping = [x for x in self._txs if x is not tx and x.start < tx.end and x.end > tx.start]
        sender = self._senders[tx.src]
        if tx.frame.dst is None:
            # A broadcast's fate changes nothing at its sender: judge it later, with others.
            self._unjudged.append((tx, overlapping))
            self._finish(sender, t)
        else:
            self._unicast_judged(sender, self._judge([(tx, overlapping)]), t)
        self._prune()

    def _unicast_judged(self, sender: _Sender, out: Outcomes, t: float) -> None:
        slot = sender.slot
        if out.reason[0] != 0 and self._stage[slot] < self._model.unicast_retries:
            self._retrying += int(self._stage[slot] == 0)
            self._stage[slot] += 1
            self._try_at[slot] = t + self._model.backoff_s(int(self._stage[slot]), self._rng)
        else:
            self._report(out)
            self._finish(sender, t)

    # --- the scalar path ------------------------------------------------------
    def _alone(self, slot: int, t: float, limit: float) -> bool:
        """A frame alone on the air, from its start to its verdict, without the event loop.

        Only when nothing else can touch it: no other sender has a frame, this sender nothing
        queued behind it, nothing on air or waiting to be judged, no jammer over its airtime,
        and it ends by ``limit`` (so no later offer can overlap it). Then the general path
        would start it, end it and judge it with no interference, drawing what is drawn here
        in the same order (docs/radio.md, time and determinism); tests/test_scalar_path.py
        runs both on the same rounds. False: not such a frame, nothing done.
        """
        sender = self._senders[self._sender_ids[slot]]
        frame = sender.current
        row = int(self._slot_row[slot])
        if frame is None or sender.queue or row < 0:
            return False
        geo = self._geo
        dst_row = -1
        if frame.dst is not None:
            dst_row = geo.index.get(frame.dst, -1)
            if dst_row < 0:
                return False
        airtime = self._airtime.get(frame.size)
        if airtime is None:
            airtime = self._airtime[frame.size] = self._model.airtime_s(frame.size)
        end = t + airtime
        if end > limit:
            return False
        if self._jammers and self._model.models_interference and \
                any(j.t_start < end and j.t_end > t for j in self._jammers):
            return False
        # _start, then _run's clock at the end and _prune: everything older has ended by now.
        self._try_at[slot] = math.inf
        self._now = max(self._now, t, end)
        if self._txs:
            self._txs = [x for x in self._txs if x.end > self._now]
        out = self._judge_alone(frame, row, dst_row, end)
        if frame.dst is None:
            self._report(out)
            self._finish(sender, end)
        else:
            self._unicast_judged(sender, out, end)
        return True

    def _judge_alone(self, frame: TxFrame, row: int, dst_row: int, end: float) -> Outcomes:
        """_judge of one transmission nothing overlapped: the same inputs, the same draws."""
        key = (row, dst_row, frame.size if self._by_size else -1)
        table = self._alone_tables.get(key)
        if table is None:
            table = self._alone_tables[key] = self._alone_table(row, dst_row, frame.size)
        ids, d, dbm, bits, code, sinr_db, p_loss, loss_code, judged = table
        k = len(ids)
        if not self._table_judge:
            zeros = np.zeros(k)
            code, sinr_db = self._model.judge(d, dbm, zeros, zeros, np.zeros(k, bool), bits, self._rng)
        elif p_loss is not None and judged.size:
            lost = self._rng.random(judged.size) < p_loss
            if lost.any():
                code = code.copy()
                code[judged[lost]] = loss_code
        t = np.full(k, end)
        ok = code == 0
        if ok.any():
            t[ok] += self._model.delivery_delay_s(d[ok], self._rng)
        return Outcomes(np.full(k, frame.uid, np.int64), np.full(k, frame.src, np.int64), ids, t, code, sinr_db)

    def _alone_table(self, row: int, dst_row: int, size: int) -> tuple:
        geo = self._geo
        cols = np.array([dst_row]) if dst_row >= 0 else np.flatnonzero(np.arange(len(geo.ids)) != row)
        d, dbm = geo.distance[row, cols], geo.rx_dbm[row, cols]
        bits = np.full(len(cols), self._bits(size), np.int64)
        code = sinr_db = p_loss = judged = None
        loss_code = 0
        if self._table_judge:
            code, sinr_db, p_loss, loss_code = self._model.judge_alone(d, dbm, bits)
            judged = np.flatnonzero(code == 0)
            if p_loss is not None:
                p_loss = p_loss[judged]
        return geo.ids[cols], d, dbm, bits, code, sinr_db, p_loss, loss_code, judged

    def _finish(self, sender: _Sender, t: float) -> None:
        sender.current = sender.queue.popleft() if sender.queue else None
        if sender.current is None:
            self._busy -= 1
        if self._stage[sender.slot]:
            self._retrying -= 1
            self._stage[sender.slot] = 0
        if sender.current is not None:
            # Post-backoff keeps a sender with a full queue from hogging a CSMA channel.
            wait = self._model.backoff_s(0, self._rng) if self._model.cca_threshold_dbm is not None else 0.0
            self._try_at[sender.slot] = t + wait

    def _report(self, out: Outcomes) -> None:
        if len(out):
            self._pending.append((out, np.arange(self._reported, self._reported + len(out))))
            self._reported += len(out)

    def _take_pending(self, limit: float) -> Outcomes:
        if not self._pending:
            return Outcomes.empty()
        if len(self._pending) == 1:
            out = self._pending[0][0]
            t = out.t
            if len(t) == 1 or (t[1:] >= t[:-1]).all():  # in time order, so in the order below
                if t[-1] <= limit:
                    self._pending = []
                    return out
        out = Outcomes.concat([o for o, _ in self._pending])
        seq = np.concatenate([s for _, s in self._pending]) if len(self._pending) > 1 else self._pending[0][1]
        due = out.t <= limit
        self._pending = [] if due.all() else [(out.take(~due), seq[~due])]
        idx = np.flatnonzero(due)
        return out.take(idx[np.lexsort((seq[idx], out.t[idx]))])

    def _prune(self) -> None:
        # Nothing unresolved starts before the earliest on-air start, and nothing
        # new starts before now, so older transmissions can no longer interfere.
        horizon = min((x.start for x in self._on_air), default=self._now)
        horizon = min(horizon, self._now)
        self._txs = [x for x in self._txs if x.end > horizon]

    # --- judging --------------------------------------------------------------
    def _judge(self, items: Sequence[tuple[_Tx, list[_Tx]]]) -> Outcomes:
        """Outcomes of ended transmissions (each with those that overlapped it), all at once."""
        geo = self._geo
        n = len(geo.ids)
        txs = [tx for tx, _ in items]
        frames = [x.frame for x in txs]
        uid = np.array([f.uid for f in frames], dtype=np.int64)
        src = np.array([f.src for f in frames], dtype=np.int64)
        src_row = self._row_of(src)
        cols = np.arange(n)
        wanted = cols != src_row[:, None]
        unicast = np.array([f.dst is not None for f in frames], dtype=bool)
        dst, dst_row = src, np.full(len(txs), -1)
        if unicast.any():
            dst = np.array([src[i] if f.dst is None else f.dst for i, f in enumerate(frames)], dtype=np.int64)
            dst_row = np.where(unicast, self._row_of(dst), -1)
            wanted[unicast] = cols == dst_row[unicast, None]
        rx_tx, rx_row = np.nonzero(wanted)
        at = rx_tx * n + rx_row  # into the flattened (transmission, node) matrices
        dist, dbm = self._rows(txs)
        d = dist.reshape(-1)[at]
        i_tx, i_all, half_duplex = self._interference(items, n)
        if half_duplex is None:
            i_tx = i_all = np.zeros(len(at))
            half_duplex = np.zeros(len(at), bool)
        else:
            i_tx, i_all, half_duplex = (m.reshape(-1)[at] for m in (i_tx, i_all, half_duplex))
        bits = np.array([self._bits(f.size) for f in frames], dtype=np.int64)[rx_tx]
        code, sinr_db = self._model.judge(d, dbm.reshape(-1)[at], i_tx, i_all, half_duplex, bits, self._rng)
        end = np.array([x.end for x in txs])
        t = end[rx_tx]
        ok = code == 0
        if ok.any():
            t[ok] += self._model.delivery_delay_s(d[ok], self._rng)
        out = Outcomes(uid[rx_tx], src[rx_tx], geo.ids[rx_row], t, code, sinr_db)
        lost = np.flatnonzero(unicast & (dst_row < 0))  # to a node not in the world
        if lost.size:
            k = lost.size
            gone = Outcomes(uid[lost], src[lost], dst[lost], end[lost], np.full(k, CODE_DISTANCE, np.int8),
                            np.full(k, np.nan))
            out = Outcomes.concat([out, gone])
            out = out.take(np.argsort(np.concatenate([rx_tx, lost]), kind="stable"))
        return out

    def _row_of(self, ids: NDArray[np.int64]) -> NDArray[np.int64]:
        """Each node's row in the geometry, -1 for nodes not in the world."""
        # A dict look-up per id: a round has a few transmissions, and numpy's fixed cost per
        # call (searchsorted, where) was most of this for them.
        index = self._geo.index
        return np.array([index.get(i, -1) for i in ids.tolist()], dtype=np.int64)

    def _bits(self, size: int) -> int:
        bits = self._frame_bits.get(size)
        if bits is None:
            bits = self._frame_bits[size] = self._model.frame_bits(size)
        return bits

    def _interference(
        self, items: Sequence[tuple[_Tx, list[_Tx]]], n: int
    ) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]] | tuple[None, None, None]:
        """Per transmission and node: worst-case interference (transmissions only, and with
        jammers) over the airtime, in mW, and whether the node was itself transmitting;
        all None if nothing overlapped any of the transmissions."""
        T = len(items)
        others: dict[int, int] = {}
        sources: list[_Tx] = []
        pair_tx: list[int] = []
        pair_src: list[int] = []
        for i, (_, overlapping) in enumerate(items):
            for x in overlapping:
                k = others.get(id(x))
                if k is None:
                    k = others[id(x)] = len(sources)
                    sources.append(x)
                pair_tx.append(i)
                pair_src.append(k)
        start = np.array([tx.start for tx, _ in items])
        end = np.array([tx.end for tx, _ in items])
        jams = [j for j in self._jammers if np.any((j.t_start < end) & (j.t_end > start))] \
            if self._model.models_interference else []
        if not sources and not jams:
            return None, None, None  # nothing overlapped: no interference, nobody half-duplex
        half_duplex = np.zeros((T, n), dtype=bool)
        zeros = np.zeros((T, n))
        if sources:
            row = np.array([self._geo.index.get(x.src, -1) for x in sources], dtype=np.int64)[pair_src]
            half_duplex[np.asarray(pair_tx)[row >= 0], row[row >= 0]] = True
        if not self._model.models_interference:
            return zeros, zeros, half_duplex
        # Interference only rises when a source starts, so its worst piece of the airtime
        # begins at the frame's start or at one of the overlapping starts.
        k, J = len(sources), len(jams)
        s_start = np.array([x.start for x in sources] + [j.t_start for j in jams])
        s_end = np.array([x.end for x in sources] + [j.t_end for j in jams])
        overlaps = np.zeros((T, k + J), dtype=bool)
        overlaps[pair_tx, pair_src] = True
        for m, j in enumerate(jams):
            overlaps[:, k + m] = (j.t_start < end) & (j.t_end > start)
        oi, os_ = np.nonzero(overlaps)
        pt_tx = np.concatenate([np.arange(T), oi])
        pt_t = np.concatenate([start, np.maximum(s_start[os_], start[oi])])
        order = np.argsort(pt_tx, kind="stable")
        pt_tx, pt_t = pt_tx[order], pt_t[order]
        active = (overlaps[pt_tx] & (s_start <= pt_t[:, None]) & (pt_t[:, None] < s_end)
                  & (pt_t < end[pt_tx])[:, None]).astype(float)
        groups = np.searchsorted(pt_tx, np.arange(T))
        if k:
            _, dbm = self._rows(sources)
            from_tx = active[:, :k] @ np.power(10.0, dbm / 10.0)
        else:
            from_tx = np.zeros((len(pt_t), n))
        from_all = from_tx
        if J:
            jam_mw = np.array([np.power(10.0, self._model.jammer_rx_power_dbm(
                j, np.linalg.norm(self._geo.xyz - np.array(j.position), axis=1)) / 10.0) for j in jams])
            from_all = from_tx + active[:, k:] @ jam_mw
        return (np.maximum.reduceat(from_tx, groups, axis=0), np.maximum.reduceat(from_all, groups, axis=0),
                half_duplex)
