"""Attacks of issue 26, each from its own process with only what that attacker has (run by
test_trust.py). An outsider knows the wire spec and the swarm's name and hears every key;
a member also holds one key directory.

It prints what it sent as JSON, {"sent": {"<key kind>/<expected reason>": n}, ...}, so the test
can check that every frame was refused for the reason the attacker meant.

usage: python attacker.py ATTACK ENDPOINT SWARM FIRST_TICK LAST_TICK [ARGS...]

    launcher   outsider: kill and restart events, clock-shaped frames on events, `done`-like
               and captured frames on clock, all unsealed or replayed (finding 1)
    flood      outsider: one captured delivery to agent 2 replayed as fast as it can (finding 4)
    trailer-flood [FRAMES SIZE RATE]
               outsider: 60 KB frames ending in a captured trailer, 10,000 a second, on agent 2's
               radio and sensor keys (finding 5)
    sensors    outsider: agent 1's sealed sensor frames replayed to agent 4 (finding 2)
    stats      outsider: the agents' captured sealed stats answers, and junk, to every stats query (finding 3)
    stop KEYS  member (agent 2's own keys only): one stop clock claiming to be netsim's (finding 9)
    lockout KEYS
               member (agent 2's own keys only): captured frames of netsim's sealed again claiming
               to be netsim's, and agent 2's own with counters far ahead (findings 8, 10)
    forge KEYS member (agent 2's own keys only): frames claiming to be agent 3's on its radio key,
               netsim's on agent 1's sensor key, and deliveries to agent 1 (finding 10)
"""

import json
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import zenoh

from swarmloc import wire
from swarmloc.wire.messages import Clock, Done, Event


class Attacker:
    """A Zenoh client on the swarm's router that hears every key and remembers the last frame of each."""

    def __init__(self, endpoint: str, swarm: str):
        self.keys = wire.Keys(swarm)
        deadline = time.monotonic() + 120
        while True:  # netsim may not be listening yet
            try:
                self.session = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("client", connect=[endpoint])))
                break
            except zenoh.ZError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.1)
        self.captured: dict[str, bytes] = {}
        self.attachments: dict[str, bytes] = {}
        self.tick = -1
        self.stopped = False  # netsim's stop clock seen: the run is over
        self.lock = threading.Lock()
        self.sent: Counter[str] = Counter()
        self.pubs: dict[str, zenoh.Publisher] = {}
        self.flood_pubs: dict[str, zenoh.Publisher] = {}
        self.sub = self.session.declare_subscriber(f"{self.keys.prefix}/**", self._capture,
                                                   allowed_origin=zenoh.Locality.REMOTE)

    def _capture(self, s) -> None:
        key, data = str(s.key_expr), s.payload.to_bytes()
        with self.lock:
            self.captured[key] = data
            if s.attachment is not None:
                self.attachments[key] = s.attachment.to_bytes()
        if key == self.keys.clock:
            try:
                c = wire.decode(data).body
                self.tick = max(self.tick, c.k)
                self.stopped |= c.mode == "stop"
            except wire.WireError:
                pass

    def put(self, key: str, data: bytes, label: str, attachment: bytes | None = None, flood: bool = False) -> None:
        """`flood`: never wait for a slow receiver (Zenoh drops instead), as a flooder would."""
        pubs = self.flood_pubs if flood else self.pubs
        pub = pubs.get(key) or pubs.setdefault(key, self.session.declare_publisher(
            key, **wire.publisher_options(zenoh, lossy=flood)))
        pub.put(data, attachment=attachment)
        self.sent[label] += 1

    def wait_tick(self, k: int, timeout: float = 120) -> bool:
        deadline = time.monotonic() + timeout
        while self.tick < k and time.monotonic() < deadline:
            time.sleep(0.005)
        return self.tick >= k

    def snapshot(self) -> dict[str, bytes]:
        with self.lock:
            return dict(self.captured)

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def launcher(at: Attacker, first: int, last: int) -> dict:
    """Finding 1: the launcher obeyed unsealed kill and restart events and crashed on frames of
    the wrong type. Each round: an unsealed kill and restart of agent 2, a clock on events, a
    `done` and a stop clock on clock (unsealed), and netsim's own last clock and event frames
    replayed on their keys and on each other's."""
    k = at.keys
    rounds = 0
    at.wait_tick(first)
    while at.tick < last:
        snap = at.snapshot()
        at.put(k.events, wire.encode(Event("kill", 2, 0.0), 0, 10**9), "events/auth-unauthenticated")
        at.put(k.events, wire.encode(Event("restart", 2, 0.0), 0, 10**9), "events/auth-unauthenticated")
        at.put(k.events, wire.encode(Clock(10**6, 0.0, "lockstep", 0.1), 0, 10**9), "events/wrong-type")
        at.put(k.events, b"\xc1", "events/malformed")
        at.put(k.clock, wire.encode(Done(10**6, 0, 0), 0, 10**9), "clock/wrong-type")
        at.put(k.clock, wire.encode(Clock(at.tick, 0.0, "stop", 0.1), 0, 10**9), "clock/auth-unauthenticated")
        at.put(k.clock, wire.encode(Clock(at.tick, 0.0, "stop", 0.1), 2, 10**9), "clock/src-mismatch")
        if k.clock in snap:
            at.put(k.clock, snap[k.clock], "clock/auth-replayed")  # or too-old: netsim seals many frames a tick
            at.put(k.events, snap[k.clock], "events/wrong-type")  # refused before its counter counts as seen
        rounds += 1
        time.sleep(0.01)
    return {"rounds": rounds}


MEMBER = 2  # the member whose keys (agent-2.secret and members.json, nothing else) the attacker holds


def member_ring(keys: str):
    """Agent 2's own keys: what a captured or faulty agent 2 holds (never the hub's)."""
    from swarmloc.wire.auth import Keyring

    ring = Keyring.load(Path(keys), f"agent-{MEMBER}")
    assert ring.master is None and ring.mac_key("agent-1") is None and ring.signer("netsim") is None
    return ring


def reseal(ring, sealed: bytes, key: str, to: int, counter: int | None = None, claim: int | None = None) -> bytes:
    """A captured sealed frame sealed again with the member's own keys for `to` on `key` (with
    `counter` if given), its trailer then claiming sender `claim`: the best a member can do to
    speak as another (per-member identity makes the tag or signature the member's, not the
    claimed sender's)."""
    from swarmloc.wire.auth import HEADER, Sealer, trailer_size

    sealer = Sealer(ring, MEMBER)
    if counter is not None:
        sealer.counter = counter - 1
    data = bytearray(sealer.seal(sealed[:-trailer_size(sealed)], key, to))
    if claim is not None:
        at = len(data) - trailer_size(bytes(data))
        data[at:at + 4] = claim.to_bytes(4, "little")
    assert HEADER.unpack_from(data, len(data) - trailer_size(bytes(data)))[2] == (counter or sealer.counter)
    return bytes(data)


def lockout(at: Attacker, first: int, last: int, keys: str) -> dict:
    """Finding 8, one member's key: a frame sealed as netsim with a counter far ahead (on the
    clock and each agent's sensor key), and one sealed as agent 2 (on its radio key), used to
    lock their sender out for good. Each round sends both, once far ahead of every clock. With
    agent 2's own keys only, the ones claiming netsim carry agent 2's signature (finding 10)."""
    from swarmloc.wire.auth import BROADCAST

    ring = member_ring(keys)
    k = at.keys
    rounds = 0
    at.wait_tick(first)
    far = (time.time_ns() // 1000) + 10**12  # eleven days ahead
    while at.tick < last:
        snap = at.snapshot()
        if k.clock in snap and k.radio_tx(2) in snap and k.sensors(1) in snap:
            at.put(k.clock, reseal(ring, snap[k.clock], k.clock, BROADCAST, far + rounds, 0), "clock/auth-bad-signature")
            at.put(k.sensors(1), reseal(ring, snap[k.sensors(1)], k.sensors(1), 1, far + rounds, 0),
                   "1/auth-bad-signature")
            at.put(k.radio_tx(2), reseal(ring, snap[k.radio_tx(2)], k.radio_tx(2), 0, far + rounds),
                   "tx/auth-from-the-future")
            rounds += 1
        time.sleep(0.05)
    return {"rounds": rounds}


def replay_flood(at: Attacker, first: int, last: int, frames: str = "20000") -> dict:
    """Finding 4, outsider: one captured delivery of netsim's to agent 2 (its tag is netsim's)
    replayed as fast as this process can publish, to overflow agent 2's inbox and make it lose a
    genuine delivery, after which it used to refuse every later one. FRAMES copies in all (the
    issue's 10,000 a second for two seconds)."""
    k = at.keys
    at.wait_tick(first)
    key = k.radio_rx(2)
    while key not in at.attachments and at.tick < last:
        time.sleep(0.01)
    with at.lock:
        data, att = at.captured[key], at.attachments[key]
    t0, n = time.monotonic(), 0
    while n < int(frames) and at.tick < last:
        for _ in range(1000):
            at.put(key, data, "2/rx-out-of-sequence", att)
        n += 1000
    rate = n / (time.monotonic() - t0)
    time.sleep(1.0)  # what is still queued in this session goes out before it closes
    return {"frames": n, "rate": rate}


def stop(at: Attacker, first: int, last: int, keys: str) -> dict:
    """Finding 9, one member's key: one `stop` on the clock claiming to be netsim's, at tick FIRST.
    Agent 2's own keys cannot sign as netsim: its signature under a trailer that says netsim."""
    from swarmloc.wire.auth import BROADCAST

    ring = member_ring(keys)
    at.wait_tick(first)
    stop_frame = wire.encode(Clock(at.tick, 0.0, "stop", 0.5), 0, 10**9)
    at.put(at.keys.clock, reseal(ring, stop_frame + bytes(83 - 2) + b"E2", at.keys.clock, BROADCAST, claim=0),
           "clock/auth-bad-signature")
    return {"at_tick": at.tick}


def forge(at: Attacker, first: int, last: int, keys: str) -> dict:
    """Finding 10, one member's key: agent 2 speaks as others. Each round: agent 3's last radio
    frame sealed again with agent 2's MAC key under a trailer claiming agent 3 (to netsim, on
    radio/tx/3), netsim's last sensor frame for agent 1 claiming netsim (signed by agent 2), a
    delivery to agent 1 under the next numbers tagged with agent 2's own key (the lock-out of
    the issue: a number far ahead), and agent 2's own radio frame replayed on agent 3's key."""
    from swarmloc.wire.auth import TAG_BYTES

    ring = member_ring(keys)
    k = at.keys
    rounds = 0
    at.wait_tick(first)
    import hmac

    from swarmloc.wire import auth
    while at.tick < last:
        snap = at.snapshot()
        if k.radio_tx(3) in snap and k.sensors(1) in snap and k.radio_rx(1) in at.attachments and k.radio_tx(2) in snap:
            at.put(k.radio_tx(3), reseal(ring, snap[k.radio_tx(3)], k.radio_tx(3), 0, claim=3), "tx/auth-bad-tag")
            at.put(k.sensors(1), reseal(ring, snap[k.sensors(1)], k.sensors(1), 1, claim=0), "1/auth-bad-signature")
            with at.lock:
                att = at.attachments[k.radio_rx(1)]
            data = snap[k.radio_tx(2)]
            for ahead in (1, 32_000):
                head = wire.encode_delivery(wire.decode_delivery(att[:-TAG_BYTES])[0] + ahead, None)
                tag = hmac.digest(ring.mac, auth._delivery_msg(ring, 1, head, data), "sha256")[:TAG_BYTES]
                at.put(k.radio_rx(1), data, "1/auth-bad-delivery", head + tag)
            at.put(k.radio_tx(3), snap[k.radio_tx(2)], "tx/auth-bad-tag")  # its own frame on another's key
            rounds += 1
        time.sleep(0.05)
    return {"rounds": rounds}


def stats(at: Attacker, first: int, last: int) -> dict:
    """Finding 3, outsider: answer netsim's end-of-run stats query (and anyone's) with the agents'
    own sealed answers, captured from a query of our own, and with junk; until the run is over."""
    k = at.keys
    at.wait_tick(first)
    captured = {}
    for r in at.session.get(k.stats("*"), timeout=3.0):  # short: the queryable must be up before the run ends
        if r.ok is not None:
            captured[str(r.ok.key_expr)] = r.ok.payload.to_bytes()
    answered = Counter()

    def answer(q):
        for key, data in captured.items():
            q.reply(key, data)
        q.reply(k.stats(1), b"\xc1")
        answered["queries"] += 1

    queryable = at.session.declare_queryable(k.stats("*"), answer)
    while not at.stopped:
        time.sleep(0.05)
    queryable.undeclare()
    n = answered["queries"]
    at.sent.update({"stats/stale-nonce": n * len(captured), "stats/auth-unauthenticated": n})
    return {"captured": len(captured), "queries": n}


def sensors(at: Attacker, first: int, last: int) -> dict:
    """Finding 2, outsider: every sensor frame netsim seals for agent 1, replayed at once to agent 4
    (it used to pass agent 4's checks and sometimes arrive before its own)."""
    k = at.keys
    at.wait_tick(first)
    sent_last = None
    while at.tick < last:
        with at.lock:
            data = at.captured.get(k.sensors(1))
        if data is not None and data != sent_last:
            at.put(k.sensors(4), data, "4/misaddressed")
            sent_last = data
        time.sleep(0.001)
    return {"rounds": at.sent["4/misaddressed"]}


def trailer_flood(at: Attacker, first: int, last: int, frames: str = "50000", size: str = "60000",
                  rate: str = "10000") -> dict:
    """Finding 5, outsider: FRAMES frames of SIZE bytes, each ending in a trailer captured from
    netsim (its sender, a known key id, a tag of another frame), at RATE a second, alternately on
    agent 2's radio key (under a delivery number far ahead, so the cheap copy check passes it)
    and its sensor key. Each used to cost a full MAC in agent 2's one loop and to push genuine
    frames out of its inbox."""
    from swarmloc.wire.auth import TRAILER

    k = at.keys
    at.wait_tick(first)
    rx, sensors = k.radio_rx(2), k.sensors(2)
    while (rx not in at.attachments or sensors not in at.captured) and at.tick < last:
        time.sleep(0.01)
    with at.lock:
        trailer, att = at.captured[sensors][-TRAILER.size:], at.attachments[rx]
    n_rx = wire.decode_delivery(att[:16])[0] + 10**6
    body = bytes(int(size) - TRAILER.size)
    ahead = wire.encode_delivery(n_rx, None) + bytes(16)
    t0, n = time.monotonic(), 0
    while n < int(frames) and at.tick < last:
        due = min(int(frames), int((time.monotonic() - t0) * float(rate)))
        while n < due:
            if n % 2:
                at.put(sensors, body + trailer, "2/sensors/auth-bad-tag", flood=True)
            else:
                at.put(rx, body + trailer, "2/rx/auth-bad-delivery", ahead, flood=True)
            n += 1
        time.sleep(0.001)
    rate_sent = n / (time.monotonic() - t0)
    time.sleep(1.0)  # what is still queued in this session goes out before it closes
    return {"frames": n, "rate": rate_sent}


def oversize(at: Attacker, first: int, last: int, frames: str = "200", size: str = "60000") -> dict:
    """Issue 26, cheap refusals first, outsider: FRAMES frames of SIZE bytes (within the hard
    ceiling), each ending in a trailer captured from netsim, alternately on the clock key (every
    agent and the launcher hear it: a clock frame is at most a few hundred bytes) and on agent
    2's done key (netsim hears it), delivered reliably, about 200 a second."""
    from swarmloc.wire.auth import SIG_TRAILER

    k = at.keys
    at.wait_tick(first)
    while k.clock not in at.captured and at.tick < last:
        time.sleep(0.01)
    with at.lock:
        trailer = at.captured[k.clock][-SIG_TRAILER.size:]
    body = bytes(int(size) - len(trailer))
    n = 0
    while n < int(frames) and at.tick < last:
        if n % 2:
            at.put(k.done(2), body + trailer, "done/oversize")
        else:
            at.put(k.clock, body + trailer, "clock/oversize")
        n += 1
        time.sleep(0.005)
    time.sleep(1.0)  # what is still queued in this session goes out before it closes
    return {"frames": n}


def revoked(at: Attacker, first: int, last: int, keys: str, frames: str = "100") -> dict:
    """Revocation while the run goes: agent 2, revoked, still holds its own keys (KEYS, a copy
    taken before) and seals fresh frames with them, alternately on its radio key and its `done`
    key, from tick FIRST, about 200 a second."""
    from swarmloc.wire.auth import Sealer

    ring = member_ring(keys)
    sealer, k, n = Sealer(ring, MEMBER), at.keys, 0
    at.wait_tick(first)
    while n < int(frames) and at.tick < last:
        key, label = (k.radio_tx(MEMBER), "tx") if n % 2 else (k.done(MEMBER), "done")
        at.put(key, sealer.seal(wire.encode(Done(at.tick, 0, 0), MEMBER, 10**6 + n), key, 0), f"{label}/auth-revoked")
        n += 1
        time.sleep(0.005)
    time.sleep(1.0)
    return {"frames": n}


ATTACKS = {"revoked": revoked, "oversize": oversize, "sensors": sensors, "stats": stats, "stop": stop, "launcher": launcher, "lockout": lockout, "flood": replay_flood,
           "trailer-flood": trailer_flood, "forge": forge}


def member_lies(at: Attacker, first: int, last: int, keys: str, lie: str, size: str = "0", limit: str = "1000000",
                liar: str = "2") -> dict:
    """Finding 7, one member's key: agent LIAR's chain frames, each rewritten with plausible-looking
    but wrong numbers the moment it is sent, and handed to its receiver as netsim would, sealed
    as LIAR, under the receiver's next delivery number (so either the lie or the genuine frame
    reaches the receiver, never both). LIE:

        yn      every commit with Y = nu = 1e11 (the issue: every agent 1e12 m off)
        gains   every commit with its gains x SIZE (the issue: x100, 56 km, covariances indefinite)
        range   every start with its range SIZE m longer (the issue: 1 km, estimates 1,171 m off)
        scale   every start with its range SIZE m longer and its noise inflated so that the
                lie passes every check: what one member can do unrefused (benchmarks/member_damage.py)

    At most LIMIT frames, from tick FIRST to LAST."""
    import msgspec
    import numpy as np

    from swarmloc.wire.auth import TAG_BYTES, Keyring, Sealer, delivery_tag, trailer_size
    from swarmloc.wire.messages import DclCommit, DclStart

    # Agent LIAR's lies as netsim routes them: sealed as LIAR to netsim, handed over under netsim's
    # delivery tag. With per-member identity only netsim can tag a delivery (under the receiver's
    # key), so this attacker stands in for a lying agent whose frames netsim routes: it needs the
    # hub's file for the tag, which a real liar never has (docs/security.md).
    ring = Keyring.load(Path(keys))
    src, k, size = int(liar), at.keys, float(size)
    sealer = Sealer(ring, src)

    def forged(body):
        if lie in ("yn", "gains") and isinstance(body, DclCommit) and body.seq and body.gains:
            if lie == "yn":
                return msgspec.structs.replace(body, Y=np.full_like(body.Y, 1e11), nu=np.full_like(body.nu, 1e11))
            return msgspec.structs.replace(body, gains={j: g * size for j, g in body.gains.items()})
        if lie in ("range", "scale") and isinstance(body, DclStart) and body.key[1] == 0:
            z, R = body.z.copy(), body.R.copy()
            z[0] += size
            if lie == "scale":  # the lie within 3 sigma of the noise it claims: NIS about 9
                R[0, 0] = max(R[0, 0], (size / 3.0) ** 2)
            return msgspec.structs.replace(body, z=z, R=R)
        return None

    def on_tx(s):
        if at.tick < first or at.tick > last or sum(at.sent.values()) >= int(limit):
            return
        data = s.payload.to_bytes()
        try:
            env = wire.decode(data[:-trailer_size(data)])
        except wire.WireError:
            return
        body = forged(env.body) if env.dst is not None and env.dst != src else None
        if body is None:
            return
        with at.lock:
            att = at.attachments.get(k.radio_rx(env.dst))
        n = 0 if att is None else wire.decode_delivery(att[:-TAG_BYTES])[0]
        frame = sealer.seal(wire.encode(body, src, env.seq, env.dst), k.radio_tx(src), 0)
        attachment = wire.encode_delivery(n + 1, None)
        attachment += delivery_tag(ring, env.dst, attachment, frame)
        at.put(k.radio_rx(env.dst), frame, f"{env.dst}/{type(body).__name__}", attachment)

    for r in range(1, 17):  # declared up front, not in the subscriber's callback
        at.pubs[k.radio_rx(r)] = at.session.declare_publisher(k.radio_rx(r), **wire.publisher_options(zenoh))
    sub = at.session.declare_subscriber(k.radio_tx(src), on_tx, allowed_origin=zenoh.Locality.REMOTE)
    at.wait_tick(first)
    while at.tick < last and not at.stopped:
        time.sleep(0.05)
    sub.undeclare()
    return {"lie": lie, "size": size, "frames": sum(at.sent.values())}


ATTACKS["member"] = member_lies


if __name__ == "__main__":
    name, endpoint, swarm, first, last, *rest = sys.argv[1:]
    attacker = Attacker(endpoint, swarm)
    try:
        report = ATTACKS[name](attacker, int(first), int(last), *rest)
    finally:
        attacker.close()
    print(json.dumps({**report, "sent": attacker.sent}))

