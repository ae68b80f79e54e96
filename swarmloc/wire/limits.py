"""Bounds on what a driver (the agent daemon, netsim) takes in (docs/security.md#limits): a
flood is dropped and counted, never buffered without bound, and one sender cannot take all of
a loop's time. Sans I/O, for both drivers."""

from __future__ import annotations

import queue
import threading
from collections import OrderedDict

INBOX_FRAMES = 8192
INBOX_BYTES = 32 << 20
"""What an inbox holds at most: frames, and their bytes (frames are at most wire.MAX_WIRE_BYTES,
so the byte bound is the one a flood of large frames meets first)."""
RATE = 5000.0
BURST = 5000.0
"""Frames a second one sender may have taken, and how many at once: ten times what the
busiest honest sender (netsim, to one agent, in a fast lockstep run) sends."""
MAX_SENDERS = 4096  # token buckets kept; the least recently heard sender is forgotten first


class Inbox:
    """What Zenoh's callback threads hand a driver's one loop: a FIFO bounded in frames and in
    bytes. A frame that does not fit is dropped at once and counted (`dropped`, `dropped_bytes`).
    The items travel in a SimpleQueue (C, and what the loop's wake-up latency in lockstep
    needs); only the bookkeeping takes a lock."""

    def __init__(self, max_frames: int = INBOX_FRAMES, max_bytes: int = INBOX_BYTES):
        self.max_frames, self.max_bytes = max_frames, max_bytes
        self._items: queue.SimpleQueue = queue.SimpleQueue()
        self._lock = threading.Lock()
        self.frames = 0
        self.bytes = 0
        self.dropped = 0
        self.dropped_bytes = 0
        self.peak_bytes = 0

    def put(self, item, size: int = 0, force: bool = False) -> bool:
        """Queue `item` (`size` bytes of payload); False if it was dropped. `force`: a control
        item of the driver's own (stop), never dropped."""
        with self._lock:
            if not force and (self.frames >= self.max_frames or self.bytes + size > self.max_bytes):
                self.dropped += 1
                self.dropped_bytes += size
                return False
            self.frames += 1
            self.bytes += size
            self.peak_bytes = max(self.peak_bytes, self.bytes)
        self._items.put((item, size))
        return True

    def get(self, timeout: float | None = None):
        """The oldest item; queue.Empty after `timeout` seconds without one (0: at once)."""
        if timeout is None:
            item, size = self._items.get()
        elif timeout <= 0:
            item, size = self._items.get_nowait()
        else:
            item, size = self._items.get(timeout=timeout)
        with self._lock:
            self.frames -= 1
            self.bytes -= size
        return item

    def empty(self) -> bool:
        return self._items.empty()

    def stats(self) -> dict:
        return {"dropped": self.dropped, "dropped_bytes": self.dropped_bytes, "peak_bytes": self.peak_bytes}


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
