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
    assert box.stats() == {"dropped": 2, "dropped_bytes": 40, "dropped_share": 0, "peak_bytes": 90} and box.bytes == 0
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


def test_one_authenticated_sender_holds_at_most_its_share():
    """Issue 26, finding 5: a member flooding with its own key fills half the inbox at most, so
    netsim's frames (sender 0) still find room."""
    box = Inbox(max_frames=8, max_bytes=1000, share=0.5)
    assert all(box.put(f"m{i}", 10, sender=2) for i in range(4))
    assert not box.put("m4", 10, sender=2)  # over its share of frames
    assert box.put("n0", 10, sender=0) and box.put("n1", 400, sender=0)
    assert not box.put("n2", 100, sender=0)  # over its share of bytes (510 > 500)
    assert box.stats()["dropped"] == 2 and box.stats()["dropped_share"] == 2
    assert box.get(0) == "m0" and box.put("m5", 10, sender=2)  # a place freed is its again


def test_the_door_refuses_what_is_oversized_or_not_sealed_before_the_inbox():
    from swarmloc.wire import auth
    from swarmloc.wire.limits import Door

    ring = auth.Keyring.generate("s", [3])
    box = Inbox()
    door = Door(box, auth.Opener(ring, 0))  # netsim's
    sealed = auth.Sealer(ring.for_member("agent-3"), 3).seal(b"x" * 100, "k", 0)
    forged = b"y" * 60_000 + sealed[-auth.TRAILER.size:]  # a real trailer on other bytes
    assert door.admit("rx", sealed, lambda d: d, key="k")
    assert not door.admit("rx", forged, lambda d: d, key="k")
    assert not door.admit("rx", b"z" * 100, lambda d: d, key="k")
    assert not door.admit("rx", b"z" * 70_000, lambda d: d, key="k")
    assert door.counts() == {"auth-bad-tag": 1, "auth-unauthenticated": 1, "oversize": 1}
    assert box.frames == 1 and box.get(0) == sealed
    # What the door passed, the loop admits once: its counter is then seen.
    opener = door.opener
    assert opener.admit(sealed) == (b"x" * 100, 3)
    with pytest.raises(auth.AuthError, match="replayed"):
        opener.admit(sealed)


def test_a_key_that_carries_one_small_type_refuses_a_longer_payload_before_its_mac(monkeypatch):
    """Issue 26, "cheap refusals first": on the clock key a payload longer than the widest
    sealed clock frame is refused by its length (`oversize`); the seal is never checked."""
    from swarmloc import wire
    from swarmloc.wire import auth
    from swarmloc.wire.limits import Door
    from swarmloc.wire.messages import Clock

    ring = auth.Keyring.generate("s", [3])
    opener = auth.Opener(ring.for_member("agent-3"), 3)
    checked = []
    real = opener.verify
    monkeypatch.setattr(opener, "verify", lambda data, key: checked.append(len(data)) or real(data, key))
    door, limit = Door(Inbox(), opener), wire.key_limit(Clock)
    assert limit < 400
    key = wire.Keys("s").clock
    for size in (limit + 1, 60_000):
        forged = b"y" * (size - auth.TRAILER.size) + b"\0" * (auth.TRAILER.size - 2) + b"E2"
        assert not door.admit("clock", forged, lambda d: d, limit=limit, key=key)
    assert door.counts() == {"oversize": 2} and checked == []
    at_limit = b"y" * (limit - auth.TRAILER.size) + b"\0" * (auth.TRAILER.size - 2) + b"S2"
    assert not door.admit("clock", at_limit, lambda d: d, limit=limit, key=key)  # its size passes: the seal is checked
    assert checked == [limit]
