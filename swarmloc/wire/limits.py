"""Bounds on what a driver (the agent daemon, netsim) takes in (docs/security.md#limits): a
flood is dropped and counted, never buffered without bound, and one sender cannot take all of
a loop's time. Sans I/O, for both drivers."""

from __future__ import annotations

import queue
import threading
from collections import Counter, OrderedDict
from collections.abc import Callable

from swarmloc.wire import auth
from swarmloc.wire.schema import MAX_WIRE_BYTES

INBOX_FRAMES = 8192
INBOX_BYTES = 32 << 20
"""What an inbox holds at most: frames, and their bytes (frames are at most wire.MAX_WIRE_BYTES,
so the byte bound is the one a flood of large frames meets first)."""
RATE = 5000.0
BURST = 5000.0
"""Frames a second one sender may have taken, and how many at once: ten times what the
busiest honest sender (netsim, to one agent, in a fast lockstep run) sends."""
MAX_SENDERS = 4096  # token buckets kept; the least recently heard sender is forgotten first
SENDER_SHARE = 0.5
"""The part of an inbox's frames and bytes one authenticated sender may hold: a member flooding
with its own key cannot push netsim's frames, or another member's, out of a receiver's inbox."""


class Inbox:
    """What Zenoh's callback threads hand a driver's one loop: a FIFO bounded in frames and in
    bytes. A frame that does not fit is dropped at once and counted (`dropped`, `dropped_bytes`).
    The items travel in a SimpleQueue (C, and what the loop's wake-up latency in lockstep
    needs); only the bookkeeping takes a lock."""

    def __init__(self, max_frames: int = INBOX_FRAMES, max_bytes: int = INBOX_BYTES, share: float = SENDER_SHARE):
        self.max_frames, self.max_bytes = max_frames, max_bytes
        self.share_frames, self.share_bytes = int(max_frames * share), int(max_bytes * share)
        self._items: queue.SimpleQueue = queue.SimpleQueue()
        self._lock = threading.Lock()
        self.frames = 0
        self.bytes = 0
        self._held: dict[int, list[int]] = {}  # authenticated sender -> [frames, bytes] waiting
        self.dropped = 0
        self.dropped_bytes = 0
        self.dropped_share = 0  # of `dropped`: a sender over its share while there was room
        self.peak_bytes = 0
        # Called after every item queued: an agent host's one loop learns which of its agents
        # has something (agents/host.py); a driver that blocks on get() needs none.
        self.wake: Callable[[], object] | None = None

    def put(self, item, size: int = 0, force: bool = False, sender: int | None = None) -> bool:
        """Queue `item` (`size` bytes of payload); False if it was dropped. `force`: a control
        item of the driver's own (stop), never dropped. `sender`: who sealed it, when the
        driver verified that already; such a sender holds at most its share of the inbox."""
        with self._lock:
            held = self._held.get(sender) if sender is not None else None
            over_share = held is not None and (held[0] >= self.share_frames or held[1] + size > self.share_bytes)
            if not force and (over_share or self.frames >= self.max_frames or self.bytes + size > self.max_bytes):
                self.dropped += 1
                self.dropped_bytes += size
                self.dropped_share += over_share
                return False
            if sender is not None:
                held = self._held.setdefault(sender, [0, 0])
                held[0] += 1
                held[1] += size
            self.frames += 1
            self.bytes += size
            self.peak_bytes = max(self.peak_bytes, self.bytes)
        self._items.put((item, size, sender))
        if self.wake is not None:
            self.wake()
        return True

    def get(self, timeout: float | None = None):
        """The oldest item; queue.Empty after `timeout` seconds without one (0: at once)."""
        if timeout is None:
            item, size, sender = self._items.get()
        elif timeout <= 0:
            item, size, sender = self._items.get_nowait()
        else:
            item, size, sender = self._items.get(timeout=timeout)
        with self._lock:
            self.frames -= 1
            self.bytes -= size
            if sender is not None:
                held = self._held[sender]
                held[0] -= 1
                held[1] -= size
                if held[0] == 0:
                    del self._held[sender]
        return item

    def empty(self) -> bool:
        return self._items.empty()

    def stats(self) -> dict:
        return {"dropped": self.dropped, "dropped_bytes": self.dropped_bytes, "dropped_share": self.dropped_share,
                "peak_bytes": self.peak_bytes}


class RateLimit:
    """A token bucket per sender: `rate` frames a second, `burst` at once."""

    def __init__(self, rate: float = RATE, burst: float = BURST, max_senders: int = MAX_SENDERS):
        self.rate, self.burst, self.max_senders = rate, burst, max_senders
        self._buckets: OrderedDict[int, list[float]] = OrderedDict()  # sender -> [tokens, when]

    def allow(self, sender: int, now: float) -> bool:
        b = self._buckets.get(sender)
        if b is None:
            if len(self._buckets) >= self.max_senders:
                self._buckets.popitem(last=False)
            b = self._buckets[sender] = [self.burst, now]
        else:
            self._buckets.move_to_end(sender)
            b[0] = min(self.burst, b[0] + (now - b[1]) * self.rate)
            b[1] = now
        if b[0] < 1.0:
            return False
        b[0] -= 1.0
        return True


class Door:
    """What a driver's Zenoh callbacks do with a frame before it takes a place in the inbox: the
    refusals that cost least, cheapest first, so a flood of frames nobody sealed costs a MAC at
    most and never pushes a genuine frame out (issue 26, finding 5). In order: the size limit of
    the key it came on (before the payload is copied out of Zenoh's buffer), then the seal's
    tag (`auth.Opener.verify`: receiver, key, MAC or signature; stateless), then the sender's share of the inbox. What is left to
    the loop: the counter window (`auth.Opener.admit`), the rate limit, decoding.

    Refusals are counted by (kind, reason) in `refused`; the reasons are those the loop would
    give (`oversize`, `auth-unauthenticated`, `auth-bad-tag`, `auth-unknown-key`)."""

    def __init__(self, inbox: Inbox, opener: auth.Opener | None = None):
        self.inbox, self.opener = inbox, opener
        self.refused: Counter[tuple[str, str]] = Counter()
        self._lock = threading.Lock()

    def refuse(self, kind: str, reason: str) -> None:
        with self._lock:
            self.refused[(kind, reason)] += 1

    def admit(self, kind: str, payload, make_item, rule=None, limit: int = MAX_WIRE_BYTES, key: str = "",
              verify=None) -> bool:
        """Queue make_item(data) for a payload (Zenoh ZBytes, or bytes) of at most `limit` bytes
        whose seal for this receiver on key expression `key` is right; False, counted,
        otherwise. `rule()`: the driver's own cheap check for this key (a reason to refuse, or
        None), after the size and before the MAC. `verify(data)`: the seal's check instead of
        the opener's (an agent's deliveries: netsim's tag), the sender or AuthError."""
        if len(payload) > limit:
            self.refuse(kind, "oversize")
            return False
        if rule is not None and (why := rule()) is not None:
            self.refuse(kind, why)
            return False
        data = payload if isinstance(payload, bytes) else payload.to_bytes()
        sender = None
        if verify is not None or self.opener is not None:
            try:
                sender = verify(data) if verify is not None else self.opener.verify(data, key)
            except auth.AuthError as exc:
                self.refuse(kind, f"auth-{exc.reason}")
                return False
        return self.inbox.put(make_item(data), len(data), sender=sender)

    def snapshot(self) -> Counter[tuple[str, str]]:
        """Refusals by (kind, reason), copied while the callbacks wait."""
        with self._lock:
            return Counter(self.refused)

    def counts(self) -> Counter[str]:
        """Refusals by reason, every kind together."""
        out: Counter[str] = Counter()
        for (_, reason), n in self.snapshot().items():
            out[reason] += n
        return out
