"""Frame authentication (swarmloc/wire/auth.py): key files, per-member identity, seal and open,
replay windows per (sender, receiver), and the agent daemon's and netsim's use of them at their
I/O boundary (sans I/O: no Zenoh session)."""

import os
import stat
import time

import numpy as np
import pytest

from agents.daemon import MAX_DELIVERY_GAP, AgentConfig, AgentDaemon
from swarmloc import wire
from swarmloc.wire import auth
from swarmloc.wire.auth import BROADCAST, AuthError, Keyring, Opener, Sealer
from swarmloc.wire.messages import Beacon, Clock, OdometryMsg, Sensors

K = wire.Keys("default")


def reason(fn, *args) -> str:
    with pytest.raises(AuthError) as e:
        fn(*args)
    return e.value.reason


def test_a_key_directory_holds_each_members_own_keys_readable_by_its_owner_only(tmp_path):
    hub = Keyring.generate("field", [1, 2])
    hub.save_directory(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["agent-1.secret", "agent-2.secret", "members.json",
                                                          "netsim.secret", "operator.secret", "swarm.key"]
    for p in tmp_path.iterdir():
        assert stat.S_IMODE(p.stat().st_mode) == 0o600
    back = Keyring.load(tmp_path)
    assert back.master == hub.master and back.members == hub.members and back.publics == hub.publics
    one = Keyring.load(tmp_path, "agent-1")
    assert one.master is None and one.mac == hub.mac_key("agent-1") and one.mac_key("agent-2") is None
    assert one.signer("agent-2") is None and one.signer("netsim") is None and one.public("netsim") is not None
    path = tmp_path / "agent-1.secret"
    os.chmod(path, 0o644)
    with pytest.raises(ValueError, match="accessible by others.*chmod 600"):
        Keyring.load(tmp_path, "agent-1")
    os.chmod(path, 0o600)
    with pytest.raises(ValueError, match="the keys of agent-1, not of agent-2"):
        Keyring.load(path, "agent-2")
    (tmp_path / "swarm.key").write_text('{"version": 1, "swarm": "field", "current": 2, "keys": {"1": "AAAA"}}')
    with pytest.raises(ValueError, match="not a swarmloc key file"):
        Keyring.load(tmp_path)


def test_seal_and_open():
    hub = Keyring.generate("field", [3])
    a3 = hub.for_member("agent-3")
    opener = Opener(hub, 0)  # netsim
    frame = wire.encode(Clock(5, 2.5, "lockstep", 0.5), 3, 1)
    sealed = Sealer(a3, 3).seal(frame, K.radio_tx(3), 0)
    assert len(sealed) == len(frame) + auth.TRAILER.size == len(frame) + 35 and sealed[-2:] == b"S2"
    assert opener.open(sealed, K.radio_tx(3)) == (frame, 3)
    assert reason(opener.open, sealed, K.radio_tx(3)) == "replayed"
    tampered = bytearray(Sealer(a3, 3).seal(frame, K.radio_tx(3), 0))
    tampered[3] ^= 1
    assert reason(opener.open, bytes(tampered), K.radio_tx(3)) == "bad-tag"
    assert reason(opener.open, frame, K.radio_tx(3)) == "unauthenticated"
    other = Keyring.generate("field", [3]).for_member("agent-3")  # same swarm name, another hub
    assert reason(opener.open, Sealer(other, 3).seal(frame, K.radio_tx(3), 0), K.radio_tx(3)) == "bad-tag"
    # Bound to its key expression: the same sealed frame on another key is refused.
    assert reason(opener.open, Sealer(a3, 3).seal(frame, K.radio_tx(3), 0), K.done(3)) == "bad-tag"
    # Netsim's broadcasts are signed (E2), for everyone, and open with the directory alone.
    clock = Sealer(hub, 0).seal(frame, K.clock)
    assert len(clock) == len(frame) + auth.SIG_TRAILER.size == len(frame) + 83 and clock[-2:] == b"E2"
    assert Opener(a3, 3).open(clock, K.clock) == (frame, 0)
    assert Opener(hub).open(clock, K.clock) == (frame, 0)  # the launcher: frames for everyone only
    assert reason(Opener(a3, 3).open, clock, K.events) == "bad-signature"
    assert wire.decode(clock).type == wire.decode(sealed).type == "clock"  # a monitor skips either trailer


def test_no_member_can_speak_as_another_or_as_netsim():
    """Finding 10: agent 2 holds its own keys only. Sealing as netsim or as agent 3 is
    impossible with them; a trailer claiming either, with agent 2's tag or signature, is refused."""
    hub = Keyring.generate("s", [1, 2, 3])
    a1, a2 = hub.for_member("agent-1"), hub.for_member("agent-2")
    frame = wire.encode(Clock(0, 0.0, "stop", 0.5), 0, 9)
    for sender, to in ((0, BROADCAST), (0, 1), (3, 0), (3, BROADCAST)):
        with pytest.raises(ValueError, match="cannot seal as"):
            Sealer(a2, sender).seal(frame, K.clock, to)
    mine = Sealer(a2, 2)

    def forged(sender, to, key):  # agent 2's own seal, its header rewritten to claim `sender`
        data = bytearray(mine.seal(frame, key, to))
        size = auth.trailer_size(bytes(data))
        data[len(data) - size:len(data) - size + 4] = sender.to_bytes(4, "little")
        return bytes(data)

    assert reason(Opener(a1, 1).open, forged(0, BROADCAST, K.clock), K.clock) == "bad-signature"  # a stop as netsim
    assert reason(Opener(a1, 1).open, forged(0, 1, K.sensors(1)), K.sensors(1)) == "bad-signature"
    assert reason(Opener(hub, 0).open, forged(3, 0, K.radio_tx(3)), K.radio_tx(3)) == "bad-tag"  # as agent 3 to netsim
    assert reason(Opener(hub).open, forged(0, BROADCAST, K.events), K.events) == "bad-signature"  # the launcher
    # Nor can it hand agent 1 a delivery: the tag is under agent 1's key, which it does not hold.
    with pytest.raises(ValueError, match="no key of agent 1"):
        auth.delivery_tag(a2, 1, wire.encode_delivery(5, None), frame)


def test_a_revoked_member_is_refused_and_nobody_else_is_rekeyed(tmp_path):
    hub = Keyring.generate("s", [1, 2, 3])
    hub.save_directory(tmp_path)
    a1_before = Keyring.load(tmp_path, "agent-1")
    frame = wire.encode(Clock(0, 0.0, "lockstep", 0.5), 2, 1)
    from_2 = Sealer(Keyring.load(tmp_path, "agent-2"), 2).seal(frame, K.radio_tx(2), 0)
    hub.revoke("agent-2")
    hub.save_directory(tmp_path, [])
    assert not (tmp_path / "agent-2.secret").exists()
    assert reason(Opener(Keyring.load(tmp_path), 0).open, from_2, K.radio_tx(2)) == "revoked"
    a1 = Keyring.load(tmp_path, "agent-1")  # its file unchanged; the new directory beside it
    assert a1.mac == a1_before.mac and a1.seed == a1_before.seed and "agent-2" in a1.revoked
    netsim = Opener(Keyring.load(tmp_path), 0)
    assert netsim.open(Sealer(a1_before, 1).seal(frame, K.radio_tx(1), 0), K.radio_tx(1))[1] == 1
    signed = Sealer(hub.for_member("agent-3"), 3).seal(frame, K.stats(3))
    assert Opener(a1, 1).open(signed, K.stats(3))[1] == 3
    # Back under a new key generation: its old keys still open nothing.
    assert hub.add("agent-2") == 2
    assert reason(Opener(hub, 0).open, from_2, K.radio_tx(2)) == "unknown-key"
    assert Opener(hub, 0).open(Sealer(hub.for_member("agent-2"), 2).seal(frame, K.radio_tx(2), 0), K.radio_tx(2))[1] == 2


def test_a_running_process_takes_a_revocation_from_its_key_file(tmp_path):
    """auth.Revocations: netsim's ring (and a member's, from members.json) takes a revocation
    written while it runs, at the next look once its period has passed; nothing before."""
    from swarmloc.wire.auth import Revocations

    hub = Keyring.generate("s", [1, 2])
    hub.save_directory(tmp_path)
    frame = wire.encode(Clock(0, 0.0, "lockstep", 0.5), 2, 1)
    from_2 = Sealer(Keyring.load(tmp_path, "agent-2"), 2)
    running, member = Keyring.load(tmp_path), Keyring.load(tmp_path, "agent-1")
    watches = [Revocations(running, tmp_path, period=1.0), Revocations(member, tmp_path / "agent-1.secret", period=1.0)]
    opener = Opener(running, 0)
    assert [w.poll(0.0) for w in watches] == [[], []]
    assert opener.open(from_2.seal(frame, K.radio_tx(2), 0), K.radio_tx(2))[1] == 2
    admin = Keyring.load(tmp_path)  # `swarmloc keys revoke DIR 2`
    admin.revoke("agent-2")
    admin.save_directory(tmp_path, [])
    assert [w.poll(0.5) for w in watches] == [[], []]  # too soon
    assert "agent-2" not in running.revoked
    assert [w.poll(1.0) for w in watches] == [["agent-2"], ["agent-2"]]
    assert "agent-2" in running.revoked and "agent-2" in member.revoked
    assert reason(opener.open, from_2.seal(frame, K.radio_tx(2), 0), K.radio_tx(2)) == "revoked"
    assert [w.poll(5.0) for w in watches] == [[], []]  # once
    (tmp_path / "swarm.key").write_text("{half written")
    assert watches[0].poll(10.0) == [] and "agent-2" in running.revoked


def test_a_frame_counts_only_at_its_receiver_and_windows_are_per_sender_and_receiver():
    """Issue 26, finding 2: the receiver is under the seal. A frame netsim sealed for agent 1 is
    refused by agent 4 before any MAC; netsim's frames to two receivers are two windows."""
    hub = Keyring.generate("s", [1, 4])
    frame = wire.encode(Clock(0, 0.0, "lockstep", 0.5), 0, 1)
    netsim = Sealer(hub, 0)
    for_1 = netsim.seal(frame, K.sensors(1), 1)
    assert reason(Opener(hub.for_member("agent-4"), 4).verify, for_1, K.sensors(1)) == "misaddressed"
    assert reason(Opener(hub.for_member("agent-4"), 4).verify, for_1, K.sensors(4)) == "misaddressed"
    opener = Opener(hub, 1)
    opener.open(for_1, K.sensors(1))
    opener.open(netsim.seal(frame, K.clock), K.clock)
    assert set(opener.windows) == {(0, 1), (0, BROADCAST)}


def test_the_window_takes_reordering_and_refuses_what_is_too_old():
    hub = Keyring.generate("s", [1])
    sealer, opener = Sealer(hub.for_member("agent-1"), 1), Opener(hub, 0)
    frames = [sealer.seal(b"x%d" % i, "k", 0) for i in range(2000)]
    order = list(range(2000))
    order[100], order[1900] = order[1900], order[100]  # far out of order: both still open
    for i in order:
        opener.open(frames[i], "k")
    for i in (0, 1000, 1999):
        assert reason(opener.open, frames[i], "k") == "replayed"
    old = _resealed(hub, 1, b"y", time.time_ns() // 1000 - auth.MAX_AGE_US - 10**6, "k", 0)
    assert reason(opener.open, old, "k") == "too-old"


def _resealed(hub, sender, frame, counter, key, to):
    """A frame sealed with a counter the sender's clock would never give (the clock is ahead)."""
    import hmac as _hmac

    link = auth._link(sender, to)
    header = auth.HEADER.pack(sender, to, counter, hub.members[link])
    tag = _hmac.digest(hub.mac_key(link), auth._msg(hub.swarm.encode(), key.encode(), frame, header), "sha256")[:16]
    return frame + header + tag + auth.MAGIC


def test_one_frame_with_a_counter_far_ahead_locks_nobody_out():
    """Finding 8: a frame with a counter far ahead is refused and its sender's next frame opens."""
    hub = Keyring.generate("s", [1])
    sealer, opener = Sealer(hub.for_member("agent-1"), 1), Opener(hub, 0)
    opener.open(sealer.seal(b"a", "k", 0), "k")
    far = time.time_ns() // 1000 + 10**12
    assert reason(opener.open, _resealed(hub, 1, b"x", far, "k", 0), "k") == "from-the-future"
    opener.open(sealer.seal(b"b", "k", 0), "k")


def test_a_restarted_sender_goes_on_above_what_it_sent():
    hub = Keyring.generate("s", [4])
    opener = Opener(hub, 0)
    first = Sealer(hub.for_member("agent-4"), 4)
    for _ in range(100):
        opener.open(first.seal(b"f", "k", 0), "k")
    again = Sealer(hub.for_member("agent-4"), 4)  # the agent restarted: its counter starts from the clock again
    opener.open(again.seal(b"g", "k", 0), "k")


def test_rotation_replaces_every_members_keys():
    hub = Keyring.generate("s", [2])
    old = Sealer(hub.for_member("agent-2"), 2).seal(b"f", "k", 0)
    hub.rotate()
    assert reason(Opener(hub, 0).open, old, "k") == "unknown-key"


def test_delivery_tags_bind_receiver_number_and_frame_under_the_receivers_key():
    hub = Keyring.generate("s", [3, 4])
    a3 = hub.for_member("agent-3")
    att = wire.encode_delivery(7, 1.5)
    tag = auth.delivery_tag(hub, 3, att, b"frame")
    assert auth.check_delivery(a3, 3, att + tag, b"frame") == att
    for receiver, attachment, data in [(4, att, b"frame"), (3, wire.encode_delivery(8, 1.5), b"frame"),
                                       (3, att, b"other")]:
        with pytest.raises(AuthError):
            auth.check_delivery(hub, receiver, attachment + tag, data)
    with pytest.raises(AuthError):  # agent 4 holds no key to check agent 3's deliveries
        auth.check_delivery(hub.for_member("agent-4"), 3, att + tag, b"frame")


def test_the_mac_is_hmac_sha256_for_every_key_and_frame_size():
    # auth.mac keeps the GIL (hmac.digest releases it on every call); the wire needs the same
    # bytes, for keys and messages around SHA-256's block and the size where hashlib lets go.
    import hmac

    rng = np.random.default_rng(3)
    for key_len in (0, 1, 32, 63, 64, 65, 200):
        key = rng.bytes(key_len)
        for size in (0, 1, 55, 64, 500, 2047, 2048, 40_000):
            msg = rng.bytes(size)
            assert auth.mac(key, msg) == hmac.digest(key, msg, "sha256"), (key_len, size)
            assert auth.mac(key, msg) == hmac.digest(key, msg, "sha256")  # its cached pads, again


# ---------------------------------------------------------------------------- the daemon


class Attachment:
    def __init__(self, data: bytes):
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


def daemon(ring, direct=True):
    from swarmloc.experiment.runner import make_nodes
    from swarmloc.experiment.scenario import load

    sc = load("wang2019")
    node = make_nodes("ukf-dcl", sc, [1])[1]
    return AgentDaemon(node, AgentConfig(direct=direct, publish_swarm=False, keyring=ring)), sc


def sensors(k):
    return Sensors(k, 0.5 * k, OdometryMsg(0.5 if k else 0.0, 1.0, 0.0, 0.5, 0.01), [])


def arrive(d: AgentDaemon, kind: str, data: bytes, attachment=None, key=None) -> None:
    """A frame the way Zenoh's callback hands it over: through the daemon's door (size, seal),
    then, if it got in, out of the inbox to the loop."""
    key = key or {"sensors": K.sensors(1), "clock": K.clock}[kind]
    if d.door.admit(kind, data, lambda x: (kind, x, attachment), key=key):
        d._handle(*d.inbox.get(0))


def test_the_daemon_takes_only_sealed_frames():
    """A sealed sensor frame is stepped on; the same frame unsealed, sealed with another hub's
    keys, sealed by another sender than its src, or replayed, is refused and counted, and changes
    nothing."""
    hub = Keyring.generate("default", [1, 7])
    d, _ = daemon(hub.for_member("agent-1"))
    netsim = Sealer(hub, 0)
    arrive(d, "sensors", netsim.seal(wire.encode(sensors(0), 0, 1), K.sensors(1), 1))
    assert d.node.k == 0
    frame1 = netsim.seal(wire.encode(sensors(1), 0, 2), K.sensors(1), 1)
    before = d.node.estimate()
    arrive(d, "sensors", wire.encode(sensors(1), 0, 2))
    arrive(d, "sensors", Sealer(Keyring.generate("default", [1]), 0).seal(wire.encode(sensors(1), 0, 2), K.sensors(1), 1))
    arrive(d, "sensors", Sealer(hub.for_member("agent-7"), 7).seal(wire.encode(sensors(1), 0, 2), K.sensors(1), 1))
    assert d.node.k == 0
    np.testing.assert_array_equal(d.node.estimate().mean, before.mean)
    arrive(d, "sensors", frame1)
    arrive(d, "sensors", frame1)
    assert d.node.k == 1
    # No seal and a wrong key are refused at the door, before the inbox; the rest in the loop.
    assert dict(d.door.counts()) == {"auth-unauthenticated": 1, "auth-bad-tag": 1}
    assert dict(d.rejected) == {"auth-src-mismatch": 1, "auth-replayed": 1}


def test_a_stats_answer_counts_only_from_its_agent_to_its_query():
    """Issue 26, finding 3: the nonce, the agent's key and its signature, all checked."""
    from swarmloc.wire.messages import Reply

    hub = Keyring.generate("s", [2, 3])
    keys, opener = wire.Keys("s"), Opener(hub.for_member("operator"), auth.operator())
    nonce = auth.query_nonce()
    assert auth.nonce_of(nonce.encode()) == nonce and auth.nonce_of(b"junk") == ""

    def answer(sender, src, n, key=None):
        return Sealer(hub.for_member(f"agent-{sender}"), sender).seal(
            wire.encode(Reply(True, "", {"k": 5, **({"nonce": n} if n else {})}), src, 0), key or keys.stats(sender))

    assert auth.open_stats_reply(opener, keys.stats(2), answer(2, 2, nonce), nonce) == (2, {"k": 5})
    for key, data, why in [(keys.stats(2), answer(2, 2, auth.query_nonce()), "stale-nonce"),
                           (keys.stats(2), answer(2, 2, ""), "stale-nonce"),
                           (keys.stats(3), answer(2, 2, nonce), "bad-signature"),
                           (keys.stats(3), answer(2, 2, nonce, keys.stats(3)), "wrong-sender"),
                           (keys.stats(2), answer(2, 3, nonce), "src-mismatch"),
                           (keys.stats(2), b"\xc1", "unauthenticated"),
                           ("swarmloc/s/elsewhere", answer(2, 2, nonce), "unknown-agent")]:
        assert reason(auth.open_stats_reply, opener, key, data, nonce) == why


def test_a_control_answer_counts_only_for_its_operator_and_its_request():
    """Issue 26: a control client takes netsim's answer sealed for it, fresh, to its nonce."""
    from swarmloc.wire.messages import Reply

    hub = Keyring.generate("s")
    me = auth.operator()
    opener = Opener(hub.for_member("operator"), me)
    key, nonce = wire.Keys("s").control, auth.query_nonce()
    netsim = Sealer(hub, 0)

    def answer(n, to=me, k=key):
        return netsim.seal(wire.encode(Reply(True, "", {"x": 1, "nonce": n}), 0, 0), k, to)

    good = answer(nonce)
    assert auth.open_control_reply(opener, key, good, nonce).data == {"x": 1}
    assert reason(auth.open_control_reply, opener, key, good, nonce) == "replayed"  # captured, replayed
    assert reason(auth.open_control_reply, opener, key, answer(auth.query_nonce()), nonce) == "stale-nonce"
    assert reason(auth.open_control_reply, opener, key, answer(nonce, me + 1), nonce) == "misaddressed"
    assert reason(auth.open_control_reply, opener, key, answer(nonce, k="x"), nonce) == "bad-tag"


def test_a_sensor_frame_sealed_for_another_agent_is_misaddressed():
    """Issue 26, finding 2: netsim addresses each sensor frame under its seal (and its envelope)."""
    hub = Keyring.generate("default", [1, 4])
    d, _ = daemon(hub.for_member("agent-1"), direct=False)
    netsim = Sealer(hub, 0)
    arrive(d, "sensors", netsim.seal(wire.encode(sensors(0), 0, 1, 4), K.sensors(4), 4))  # agent 4's
    assert d.node.k == -1 and dict(d.door.counts()) == {"auth-misaddressed": 1}
    d._handle("sensors", netsim.seal(wire.encode(sensors(0), 0, 1, 4), K.sensors(1), 1), None)  # sealed for 1, says 4
    assert d.node.k == -1 and dict(d.rejected) == {"misaddressed": 1}
    arrive(d, "sensors", netsim.seal(wire.encode(sensors(0), 0, 2, 1), K.sensors(1), 1))
    assert d.node.k == 0


def test_a_stale_sensor_frame_is_no_tick():
    """Issue 26: an agent's `ticks` counted the stale frames its node dropped."""
    hub = Keyring.generate("default", [1])
    d, _ = daemon(hub.for_member("agent-1"))
    netsim = Sealer(hub, 0)
    for seq, k in enumerate((0, 1, 1, 0, 2), 1):  # ticks 1 and 0 again: fresh frames, stale ticks
        d._handle("sensors", netsim.seal(wire.encode(sensors(k), 0, seq), K.sensors(1), 1), None)
    assert d.node.k == 2 and d.ticks == 3


def beacon_from(hub, src=2, seq=1):
    return Sealer(hub.for_member(f"agent-{src}"), src).seal(
        wire.encode(Beacon(0, np.zeros(2), np.eye(2), {}), src, seq), K.radio_tx(src), 0)


def deliver(d, hub, n, data, to=1):
    """netsim's delivery number n of `data` to agent `to`, through the daemon's door and loop."""
    att = wire.encode_delivery(n, None)
    att += auth.delivery_tag(hub, to, att, data)
    before = d.consumed
    d.door.admit("rx", data, lambda x: ("rx", x, Attachment(att)),
                 verify=lambda x: auth.check_delivery(d.cfg.keyring, 1, att, x) and auth.unwrap(x)[1])
    if not d.inbox.empty():
        d._handle(*d.inbox.get(0))
    return d.consumed != before


def test_a_forged_delivery_number_is_refused_under_netsim():
    """Under netsim the delivery number is netsim's, tagged under this receiver's own key: an
    authentic frame handed over by anyone else, a member included, under any number is refused,
    and the number stays netsim's to give (issue 26: with one swarm key a member could forge
    one MAX_DELIVERY_GAP ahead and lock the agent out of every genuine delivery)."""
    hub = Keyring.generate("default", [1, 2])
    d, _ = daemon(hub.for_member("agent-1"), direct=False)
    beacon = beacon_from(hub)
    att = wire.encode_delivery(1, None)
    d._handle("rx", beacon, Attachment(att))  # no tag
    d._handle("rx", beacon, Attachment(att + b"\0" * auth.TAG_BYTES))  # a made-up tag
    member = hub.for_member("agent-2")  # a member's own key: its tag is not netsim's for agent 1
    import hmac as _hmac
    ahead = wire.encode_delivery(MAX_DELIVERY_GAP, None)
    fake = _hmac.digest(member.mac, auth._delivery_msg(member, 1, ahead, beacon), "sha256")[:16]
    d._handle("rx", beacon, Attachment(ahead + fake))
    assert d.consumed == 0
    assert deliver(d, hub, 1, beacon) and d.consumed == 1
    assert dict(d.rejected) == {"auth-unauthenticated": 1, "auth-bad-delivery": 2}


def test_a_lost_delivery_is_a_gap_stepped_over_and_one_too_far_is_refused():
    """Issue 26, finding 4: deliveries lost on the way (an inbox overflowed) are stepped over and
    counted (`deliveries_lost`), never a reason to refuse the later ones; a number further ahead
    than MAX_DELIVERY_GAP is refused (`rx-too-far`) and moves nothing; copies of consumed ones
    are refused (`rx-out-of-sequence`)."""
    hub = Keyring.generate("default", [1, 2])
    d, _ = daemon(hub.for_member("agent-1"), direct=False)
    assert deliver(d, hub, 1, beacon_from(hub, 2, 1))
    assert deliver(d, hub, 5, beacon_from(hub, 2, 2))  # 2, 3, 4 lost
    assert d.consumed == 5 and d.deliveries_lost == 3
    assert not deliver(d, hub, 5 + MAX_DELIVERY_GAP + 1, beacon_from(hub, 2, 3))  # netsim's own tag, too far
    assert d.consumed == 5
    assert not deliver(d, hub, 4, beacon_from(hub, 2, 4))  # a late one, consumed already
    assert deliver(d, hub, 5 + MAX_DELIVERY_GAP, beacon_from(hub, 2, 5))  # the farthest step taken
    assert deliver(d, hub, 6 + MAX_DELIVERY_GAP, beacon_from(hub, 2, 6))  # and the next one after it
    assert d.deliveries_lost == 3 + MAX_DELIVERY_GAP - 1
    assert d.rejected["rx-too-far"] == 1
    assert d.rejected["rx-out-of-sequence"] == 1
    assert d.stats()["deliveries_lost"] == d.deliveries_lost


def test_netsim_routes_only_frames_sealed_by_the_agent_whose_key_they_are_on():
    """The dcl.log forgery of the security issue, at netsim's door: a frame on radio/tx/2 that
    says src 2 but is unsealed, sealed with another hub's keys, or sealed by agent 3 (its own
    keys), is refused and counted; agent 2's own sealed frame is taken once."""
    from netsim.server import NetsimServer, ServerConfig
    from swarmloc.experiment.scenario import load
    from swarmloc.wire.messages import DclLog

    hub = Keyring.generate("default", [1, 2, 3, 4])
    server = NetsimServer(load("wang2019"), ServerConfig(keyring=hub))
    key = server.keys.radio_tx(2)
    frame = wire.encode(DclLog(3, []), 2, 1, 1)

    def arrive(payload):  # through netsim's door, then its loop
        if server.door.admit("tx", payload, lambda x: x, key=key):
            return server._from_agent("tx", key, server.q.get(0))

    a3 = Sealer(hub.for_member("agent-3"), 3)
    for payload in (frame, Sealer(Keyring.generate("default", [2]).for_member("agent-2"), 2).seal(frame, key, 0),
                    a3.seal(frame, key, 0)):
        assert arrive(payload) is None
    sealed = Sealer(hub.for_member("agent-2"), 2).seal(frame, key, 0)
    aid, env = arrive(sealed)
    assert (aid, env.src, env.type) == (2, 2, "dcl.log")
    assert arrive(sealed) is None
    assert server._rejected()["tx"] == {"auth-unauthenticated": 1, "auth-bad-tag": 1, "auth-wrong-sender": 1,
                                        "auth-replayed": 1}


# ---------------------------------------------------------------------------- processes


@pytest.mark.slow
def test_secured_agents_through_a_tls_router(tmp_path):
    """`swarmloc keys` makes the swarm's keys; two UKF-DCL agents from configuration files
    (security.keys, security.tls) are clients of `swarmloc router --keys --agents 1,2 --direct`
    and replay a recording on the swarm clock: they cooperate (chains commit) with every frame
    sealed and nothing refused; a session without a certificate cannot connect; the operator's
    certificate reads their sealed estimates and stats."""
    import json
    import signal
    import subprocess
    import sys
    import time

    import yaml
    import zenoh
    from conftest import free_port

    from agents import tls
    from netsim.sim import Simulation
    from swarmloc.experiment.runner import InProcessRunner, make_nodes
    from swarmloc.experiment.scenario import load
    from swarmloc.wire.messages import EstimateMsg, Reply

    def swarmloc(*args):
        p = subprocess.run([sys.executable, "-m", "agents", *args], capture_output=True, text=True, timeout=60)
        assert p.returncode == 0, p.stderr
        return p.stdout

    keys = tmp_path / "keys"
    swarmloc("keys", "new", str(keys), "--swarm", "sec")
    for member in ("1", "2", "router", "operator"):
        swarmloc("keys", "add", str(keys), member, "--host", "127.0.0.1")
    sc = load("wang2019").with_overrides(**{"clock.duration": 10.0, "sensors.range.probability": 1.0})
    record = InProcessRunner(Simulation(sc), make_nodes("ukf-dcl", sc)).run()
    np.savez(tmp_path / "sensors.npz", **record.sensor_arrays())
    port = free_port()
    router = subprocess.Popen([sys.executable, "-m", "agents", "router", "--listen", f"tcp/127.0.0.1:{port}", "--keys",
                               str(keys), "--agents", "1,2", "--direct"], stderr=subprocess.PIPE, text=True)
    procs = {}
    def config(a, epoch):
        cfg = {"version": 1, "id": a, "swarm": "sec", "estimator": {"name": "ukf-dcl"},
               "model": "planar-speed-heading", "prior": {"position": sc.prior(a)[0].tolist(), "std": 0.1},
               "zenoh": {"mode": "client", "connect": [f"tcp/127.0.0.1:{port}"]},
               "sensors": [{"kind": "file", "path": "sensors.npz", "speed": 4.0}],
               "clock": {"epoch": epoch}, "security": {"keys": "keys", "tls": True}}
        (tmp_path / f"a{a}.yaml").write_text(yaml.safe_dump(cfg))

    try:
        assert "mutual TLS" in router.stderr.readline()
        # Tick 0 is on the swarm clock: late enough that both agents are up by then however busy
        # the machine (a late agent skips the overdue ticks, which this test is not about). So
        # first time what an agent's start costs here now: checking its configuration.
        config(1, time.time())
        began = time.monotonic()
        swarmloc("agent", "--config", str(tmp_path / "a1.yaml"), "--check-config")
        epoch = time.time() + max(6.0, 4 * (time.monotonic() - began))
        for a in (1, 2):
            config(a, epoch)
            procs[a] = subprocess.Popen([sys.executable, "-m", "agents", "agent", "--config", str(tmp_path / f"a{a}.yaml")],
                                        stderr=subprocess.PIPE, text=True)
        with pytest.raises(zenoh.ZError):  # no certificate: not even a session
            zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("client", connect=[f"tls/127.0.0.1:{port}"])))
        ring = Keyring.load(keys, "operator")
        opener = Opener(ring)  # for everyone: estimates and stats are signed without netsim
        operator = zenoh.open(zenoh.Config.from_json5(json.dumps(tls.zenoh_tls(
            wire.zenoh_config("client", connect=[f"tcp/127.0.0.1:{port}"]), keys, "operator"))))
        got = []
        operator.declare_subscriber("swarmloc/sec/agent/*/estimate",
                                    lambda s: got.append(wire.decode(opener.open(s.payload.to_bytes(), str(s.key_expr))[0]).body))
        time.sleep(max(0.0, epoch + 10.0 / 4 + 1.5 - time.time()))
        stats = {}
        for r in operator.get("swarmloc/sec/agent/*/stats", timeout=3.0):
            if r.ok is not None:
                env = wire.decode(opener.open(r.ok.payload.to_bytes(), str(r.ok.key_expr))[0], expect=(Reply,))
                stats[env.src] = env.body.data
        operator.close()
    finally:
        for p in [*procs.values(), router]:
            p.send_signal(signal.SIGTERM)
        logs = {a: p.communicate(timeout=10)[1] for a, p in procs.items()}
        router.communicate(timeout=10)
    assert set(stats) == {1, 2}, (stats, logs)
    for a, s in stats.items():
        assert s["ticks"] == sc.clock.steps + 1 and s["chains_committed"] > 0, (s, logs)
        assert not any(r.startswith("auth") for r in s["rejected"]), s["rejected"]
        assert s["peers"] == [3 - a]
    assert {e.k for e in got if isinstance(e, EstimateMsg)} >= set(range(1, sc.clock.steps + 1))
