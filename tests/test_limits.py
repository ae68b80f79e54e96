"""Bounds on what the drivers take in (swarmloc/wire/limits.py): the inbox and the rate limit."""

import queue
import threading
import time

import pytest

from swarmloc.wire.limits import Inbox, RateLimit


def test_the_inbox_drops_what_does_not_fit_and_counts_it():
    box = Inbox(max_frames=3, max_bytes=100)
    assert box.put("a", 40) and box.put("b", 40)
    assert not box.put("c", 40)  # 120 bytes: over
    assert box.put("d", 10) and not box.put("e", 0)  # 3 frames: full
    assert box.put("stop", 0, force=True)  # the driver's own never is
    assert [box.get(0) for _ in range(4)] == ["a", "b", "d", "stop"]
    assert box.stats() == {"dropped": 2, "dropped_bytes": 40, "peak_bytes": 90} and box.bytes == 0
    with pytest.raises(queue.Empty):
        box.get(timeout=0.01)


def test_the_inbox_wakes_its_reader():
    box = Inbox()
    threading.Timer(0.05, lambda: box.put("x", 1)).start()
    t0 = time.monotonic()
    assert box.get(timeout=2.0) == "x" and time.monotonic() - t0 < 1.0


def test_a_sender_over_its_rate_is_refused_and_the_others_are_not():
    limit = RateLimit(rate=100.0, burst=10.0, max_senders=2)
    assert all(limit.allow(1, 0.0) for _ in range(10))
    assert not limit.allow(1, 0.0)  # the burst is spent
    assert limit.allow(2, 0.0)  # another sender's own bucket
    assert limit.allow(1, 0.011) and not limit.allow(1, 0.011)  # 0.011 s at 100/s: one more
    limit.allow(3, 0.02)  # a third sender: the least recently heard (2) is forgotten
    assert set(limit._buckets) == {1, 3}
