"""Clock offsets between the swarm's hosts, estimated continuously (docs/deploy.md#clock-offsets).

In direct mode every radio frame carries its sender's UNIX send time (the attachment,
docs/wire.md). Every `period` seconds each agent's daemon also broadcasts a `time.sync` frame
echoing, for each peer it has heard, that peer's send stamp of its latest frame and when it
arrived here. A peer that finds its own stamp echoed holds NTP's four timestamps: t1 its send,
t2 our arrival, t3 our send of the echo, t4 its arrival of the echo. Then

    offset (theirs minus ours, seen from the peer) = ((t2 - t1) + (t3 - t4)) / 2
    round trip                                      = (t4 - t1) - (t3 - t2)

and, when the two directions take equally long, the offset is exact; whatever asymmetry there
is (queueing in one direction, our loop picking a frame up late) biases it by at most half the
round trip. So the estimate is the offset of the sample with the smallest round trip among the
last `window` ones (NTP's clock filter), re-chosen at every sample, so a drifting clock is
followed. An estimate beyond `bound` (10 ms by default) by more than its own uncertainty (half
its round trip) is counted and logged: the swarm clock (`clock.epoch`) assumes the hosts agree
to a small part of a tick, and this daemon does not correct a clock, it says which one is off
(docs/deploy.md: fixing it with chrony).
"""

from __future__ import annotations

import logging
import math
from collections import Counter, deque

from swarmloc.wire.messages import TimeEcho, TimeSync

log = logging.getLogger("swarmloc.agent")

PERIOD = 1.0
"""s between two time.sync frames of one agent."""

WINDOW = 16
"""Samples per peer the offset is chosen from (16 s at PERIOD): enough that one of them
crossed both ways without queueing, few enough to follow a clock being stepped."""

MAX_ROUND_TRIP = 5.0
"""s: a sample whose round trip is longer (an echo of a stamp from before a long outage) says
nothing useful and is dropped."""


class PeerClocks:
    """One agent's view of its peers' clocks. `heard` for every radio frame with a send stamp,
    `sync_frame` when `due`, `synced` for a peer's time.sync; `stats` for the agent's stats."""

    def __init__(self, aid: int, bound: float = 0.010, period: float = PERIOD, window: int = WINDOW):
        self.aid, self.bound, self.period = aid, float(bound), float(period)
        self.last: dict[int, tuple[float, float]] = {}  # peer: (its send stamp, our arrival) of its latest frame
        self.samples: dict[int, deque] = {}  # peer: (round trip, offset)
        self.exceeded: Counter[int] = Counter()  # peer: estimates above the bound
        self.dropped: Counter[str] = Counter()
        self._over: set[int] = set()  # peers whose offset is above the bound now (for the log)
        self._next = -math.inf

    def heard(self, peer: int, sent: float | None, arrival: float) -> None:
        if sent is not None and math.isfinite(sent):
            self.last[peer] = (sent, arrival)

    def due(self, now: float) -> bool:
        """Whether a time.sync frame is due (now: monotonic); at most one per period. It goes
        out with no echoes too: its own stamp is what a peer that hears nothing else from us
        (an estimator without radio traffic) echoes back."""
        if now < self._next:
            return False
        self._next = now + self.period
        return True

    def sync_frame(self) -> TimeSync:
        return TimeSync([TimeEcho(p, s, r) for p, (s, r) in sorted(self.last.items())][:64])

    def synced(self, peer: int, msg: TimeSync, sent: float | None, arrival: float) -> None:
        """A peer's time.sync, sent (t3, its clock) and taken at `arrival` (t4, ours)."""
        if sent is None or not math.isfinite(sent):
            self.dropped["unstamped"] += 1
            return
        mine = [e for e in msg.echoes if e.peer == self.aid]
        if not mine:
            return  # it has not heard us yet
        t1, t2, t3, t4 = mine[0].sent, mine[0].received, sent, arrival
        round_trip = (t4 - t1) - (t3 - t2)
        if not (0.0 <= round_trip <= MAX_ROUND_TRIP):
            self.dropped["round-trip"] += 1
            return
        offset = ((t2 - t1) + (t3 - t4)) / 2.0  # the peer's clock minus ours
        self.samples.setdefault(peer, deque(maxlen=WINDOW)).append((round_trip, offset))
        rt, est = self.best(peer)
        # Beyond the bound only if its whole uncertainty (half the round trip) is: one slow
        # sample (a session just opened, a loaded host) is not a clock that is off.
        if abs(est) - rt / 2 > self.bound:
            self.exceeded[peer] += 1
            n = self.exceeded[peer]
            if peer not in self._over or n % 100 == 0:
                log.warning("agent %s: peer %s's clock is %+.1f ms from ours (round trip %.1f ms), beyond the %.0f ms "
                            "bound (%d times): fix the hosts' clocks (docs/deploy.md#clock-offsets)", self.aid, peer,
                            est * 1e3, rt * 1e3, self.bound * 1e3, n)
            self._over.add(peer)
        elif peer in self._over:
            self._over.discard(peer)
            log.warning("agent %s: peer %s's clock is back within %.0f ms of ours (%+.1f ms)", self.aid, peer,
                        self.bound * 1e3, est * 1e3)

    def best(self, peer: int) -> tuple[float, float]:
        return min(self.samples[peer])

    def offset(self, peer: int) -> float:
        """The peer's clock minus ours (s), from the sample with the smallest round trip."""
        return self.best(peer)[1]

    def stats(self) -> dict:
        peers = {}
        for p, d in sorted(self.samples.items()):
            if d:
                rt, off = self.best(p)
                peers[p] = {"offset_ms": off * 1e3, "round_trip_ms": rt * 1e3, "samples": len(d),
                            "exceeded": self.exceeded[p]}
        return {"clock_offset_ms": peers, "clock_bound_ms": self.bound * 1e3,
                "clock_exceeded": sum(self.exceeded.values()),
                **({"clock_dropped": dict(self.dropped)} if self.dropped else {})}
