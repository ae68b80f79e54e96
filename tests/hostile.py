"""A hostile publisher outside the swarm (run as its own process by test_hostile.py).

It knows only the wire spec, not the run's key: it listens to everything on the swarm's keys
and, while the clock runs between two ticks, publishes bad frames on every key an agent or
netsim listens to: malformed, oversized, forged (a `dcl.log` carrying a commit at agent 1's
version, as the security issue's attack; estimates; a delivery with the next number), and
copies of real, sealed frames it captured. It prints what it sent, per key kind and the reason
it is expected to be refused for, as JSON, so the test can check that every frame was counted.

usage: python hostile.py ENDPOINT SWARM AGENT_IDS FIRST_TICK LAST_TICK
"""

import json
import sys
import threading
import time
from collections import Counter

import numpy as np
import zenoh

from swarmloc import wire
from swarmloc.wire.messages import DclCommit, DclLog, Done, EstimateMsg

OVERSIZE = b"\x00" * (wire.MAX_FRAME_BYTES + 4096)  # over our limit, under Zenoh's: reaches the callbacks


def forged_commit(a: int, b: int) -> DclCommit:
    """A commit of a range chain a-b whose gain moves a's estimate by 10 m east."""
    return DclCommit(k=0, epoch=0, key=[a, 0, b, 0], seq=1, version={a: 1, b: 1}, L=np.eye(1), Y=np.ones((2, 1)),
                     Pz=np.eye(1), nu=np.array([1.0]), parent={}, gains={a: np.array([[10.0], [0.0]])},
                     participants=[a, b], removed=[], finished=True, pending=[])


def main(endpoint, swarm, ids, first, last):
    ids = [int(a) for a in ids.split(",")]
    keys = wire.Keys(swarm)
    deadline = time.monotonic() + 120
    while True:  # netsim may not be listening yet
        try:
            session = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("client", connect=[endpoint])))
            break
        except zenoh.ZError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)
    captured: dict[str, tuple[bytes, bytes | None]] = {}
    tick = [-1]
    lock = threading.Lock()

    def capture(s):
        key = str(s.key_expr)
        data = s.payload.to_bytes()
        with lock:
            captured[key] = (data, s.attachment.to_bytes() if s.attachment is not None else None)
        if key == keys.clock:
            tick[0] = max(tick[0], wire.decode(data).body.k)

    sub = session.declare_subscriber(f"{keys.prefix}/**", capture, allowed_origin=zenoh.Locality.REMOTE)
    pubs: dict[str, zenoh.Publisher] = {}
    sent: Counter[str] = Counter()

    def put(key, data, reason, attachment=None):
        pub = pubs.get(key) or pubs.setdefault(key, session.declare_publisher(key, **wire.publisher_options(zenoh)))
        pub.put(data, attachment=attachment)
        sent[reason] += 1

    while tick[0] < first and time.monotonic() < deadline:
        time.sleep(0.01)
    # A stranger's token on an agent's key (Zenoh reports only a key's first token and its
    # last going, so netsim sees nothing of it), and one on a key that names no agent.
    extra = session.liveliness().declare_token(keys.alive(ids[1]))
    stranger = session.liveliness().declare_token(keys.alive(99))
    sent["alive/unknown-agent"] += 1
    rounds = 0
    while tick[0] < last and time.monotonic() < deadline:
        with lock:
            snap = dict(captured)
        for a in ids:
            b = ids[(ids.index(a) + 1) % len(ids)]
            put(keys.radio_tx(a), b"\xc1", "tx/auth-unauthenticated")
            put(keys.radio_tx(a), OVERSIZE, "tx/oversize")
            put(keys.radio_tx(99), b"\xc1", "tx/unknown-agent")
            if keys.radio_tx(b) in snap:  # b's frame on a's key: the key expression is under b's tag
                put(keys.radio_tx(a), snap[keys.radio_tx(b)][0], "tx/auth-bad-tag")
            if keys.radio_tx(a) in snap:
                put(keys.radio_tx(a), snap[keys.radio_tx(a)][0], "tx/auth-replayed")
            # The forged commit: a log from b to a holding a commit that moves a by 10 m.
            forged = wire.encode(DclLog(max(tick[0], 0), [forged_commit(a, b)]), b, 10**6, a)
            put(keys.radio_tx(b), forged, "tx/auth-unauthenticated")
            put(keys.done(a), b"\xc1", "done/auth-unauthenticated")
            put(keys.done(a), wire.encode(Done(10**6, 0, 0), b, 10**9), "done/auth-unauthenticated")
            if keys.done(a) in snap:
                put(keys.done(a), snap[keys.done(a)][0], "done/auth-replayed")
            put(keys.estimate(a), wire.encode(EstimateMsg(3, "ukf-dcl", np.full(2, 120.0), np.eye(2)), b, 10**9),
                "estimate/auth-unauthenticated")
            put(keys.estimate(a), OVERSIZE, "estimate/oversize")
            if keys.estimate(a) in snap:
                put(keys.estimate(a), snap[keys.estimate(a)][0], "estimate/auth-replayed")
            # What agents hear: their radio key, their sensor key and the clock.
            put(keys.radio_rx(a), b"\xc1", f"{a}/rx-unnumbered")
            put(keys.radio_rx(a), OVERSIZE, f"{a}/oversize", wire.encode_delivery(1))
            if keys.radio_rx(a) in snap:
                data, att = snap[keys.radio_rx(a)]
                put(keys.radio_rx(a), data, f"{a}/rx-out-of-sequence", att)  # netsim's tag, an old number
                # Straight to a, under a delivery number (netsim's tag it cannot make).
                put(keys.radio_rx(a), forged, f"{a}/auth-unauthenticated", wire.encode_delivery(1))
            put(keys.sensors(a), b"\xc1", f"{a}/auth-unauthenticated")
            put(keys.sensors(a), OVERSIZE, f"{a}/oversize")
            if keys.sensors(a) in snap:
                put(keys.sensors(a), snap[keys.sensors(a)][0], f"{a}/auth-replayed")
        put(keys.clock, b"\xc1", "clock/auth-unauthenticated")
        if keys.clock in snap:
            put(keys.clock, snap[keys.clock][0], "clock/auth-replayed")
        rounds += 1
        time.sleep(0.01)
    extra.undeclare()
    stranger.undeclare()
    sent["alive/unknown-agent"] += 1
    sub.undeclare()
    session.close()
    print(json.dumps({"rounds": rounds, "sent": sent}))


if __name__ == "__main__":
    main(*sys.argv[1:4], int(sys.argv[4]), int(sys.argv[5]))
