"""Frame authentication (swarmloc/wire/auth.py): key files, seal and open, replay windows, and the
agent daemon's and netsim's use of them at their I/O boundary (sans I/O: no Zenoh session)."""

import os
import stat
import time

import numpy as np
import pytest

from agents.daemon import AgentConfig, AgentDaemon
from swarmloc import wire
from swarmloc.wire import auth
from swarmloc.wire.auth import AuthError, Keyring, Opener, Sealer
from swarmloc.wire.messages import Beacon, Clock, OdometryMsg, Sensors


def test_a_key_file_is_its_owners_only(tmp_path):
    ring = Keyring.generate("field")
    path = tmp_path / "swarm.key"
    ring.save(path)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    back = Keyring.load(path)
    assert back == ring and len(back.keys[1]) == 32
    os.chmod(path, 0o644)
    with pytest.raises(ValueError, match="accessible by others.*chmod 600"):
        Keyring.load(path)
    os.chmod(path, 0o600)
    path.write_text('{"version": 1, "swarm": "field", "current": 2, "keys": {"1": "AAAA"}}')
    with pytest.raises(ValueError, match="not a swarmloc key file"):
        Keyring.load(path)


def test_seal_and_open():
    ring = Keyring.generate("field")
    sealer, opener = Sealer(ring, 3), Opener(ring)
    frame = wire.encode(Clock(5, 2.5, "lockstep", 0.5), 3, 1)
    sealed = sealer.seal(frame)
    assert len(sealed) == len(frame) + auth.TRAILER.size
    assert opener.open(sealed) == (frame, 3)
    with pytest.raises(AuthError) as e:
        opener.open(sealed)  # the same frame again
    assert e.value.reason == "replayed"
    tampered = bytearray(sealer.seal(frame))
    tampered[3] ^= 1
    with pytest.raises(AuthError) as e:
        opener.open(bytes(tampered))
    assert e.value.reason == "bad-tag"
    with pytest.raises(AuthError) as e:
        opener.open(frame)
    assert e.value.reason == "unauthenticated"
    other = Keyring.generate("field")  # same swarm name, another key
    with pytest.raises(AuthError) as e:
        opener.open(Sealer(other, 3).seal(frame))
    assert e.value.reason == "bad-tag"
    renamed = Keyring("elsewhere", dict(ring.keys), ring.current)  # the key, another swarm
    with pytest.raises(AuthError) as e:
        opener.open(Sealer(renamed, 3).seal(frame))
    assert e.value.reason == "bad-tag"


def test_the_window_takes_reordering_and_refuses_what_is_too_old():
    ring = Keyring.generate("s")
    sealer, opener = Sealer(ring, 1), Opener(ring)
    frames = [sealer.seal(b"x%d" % i) for i in range(2000)]
    opener.open(frames[5])
    opener.open(frames[2])  # older, not seen: accepted
    opener.open(frames[-1])
    opener.open(frames[0])  # far below the highest by count: still fresh by the clock
    opener.open(frames[-2])
    with pytest.raises(AuthError) as e:
        opener.open(frames[-2])
    assert e.value.reason == "replayed"


def test_one_frame_with_a_counter_far_ahead_locks_nobody_out():
    """Issue 26, finding 8: freshness by the receiver's clock, not by the highest counter seen."""
    ring = Keyring.generate("s")
    sealer, opener = Sealer(ring, 1), Opener(ring)
    opener.open(sealer.seal(b"a"))
    with pytest.raises(AuthError) as e:
        opener.open(at_counter(ring, 1, b"forged", time.time_ns() // 1000 + 10**12))
    assert e.value.reason == "from-the-future"
    ahead = at_counter(ring, 1, b"ahead", time.time_ns() // 1000 + auth.MAX_AHEAD_US // 2)
    opener.open(ahead)  # within the span: taken, and it moves nothing
    opener.open(sealer.seal(b"b"))  # the sender's next frame still opens
    with pytest.raises(AuthError) as e:
        opener.open(at_counter(ring, 1, b"late", time.time_ns() // 1000 - auth.MAX_AGE_US - 10**6))
    assert e.value.reason == "too-old"


def at_counter(ring, sender: int, frame: bytes, counter: int) -> bytes:
    """A frame sealed with exactly this counter (what a key holder can make)."""
    header = auth.TRAILER.pack(sender, counter, ring.current, b"", b"")[:13]
    return frame + header + auth._tag(ring.keys[ring.current], ring.swarm.encode(), frame, header) + auth.MAGIC


def test_a_restarted_sender_goes_on_above_what_it_sent():
    ring = Keyring.generate("s")
    opener = Opener(ring)
    first = Sealer(ring, 4)
    for _ in range(100):
        opener.open(first.seal(b"f"))
    again = Sealer(ring, 4)  # the agent restarted: its counter starts from the clock again
    opener.open(again.seal(b"g"))


def test_rotation_drops_the_old_key():
    ring = Keyring.generate("s")
    old = Sealer(Keyring("s", dict(ring.keys), ring.current), 2).seal(b"f")
    kid = ring.rotate()
    assert kid == 2 and list(ring.keys) == [2]
    with pytest.raises(AuthError) as e:
        Opener(ring).open(old)
    assert e.value.reason == "unknown-key"


def test_delivery_tags_bind_receiver_number_and_frame():
    ring = Keyring.generate("s")
    att = wire.encode_delivery(7, 1.5)
    tag = auth.delivery_tag(ring, 3, att, b"frame")
    assert auth.check_delivery(ring, 3, att + tag, b"frame") == att
    for receiver, attachment, data in [(4, att, b"frame"), (3, wire.encode_delivery(8, 1.5), b"frame"),
                                       (3, att, b"other")]:
        with pytest.raises(AuthError):
            auth.check_delivery(ring, receiver, attachment + tag, data)


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


def arrive(d: AgentDaemon, kind: str, data: bytes, attachment=None) -> None:
    """A frame the way Zenoh's callback hands it over: through the daemon's door (size, seal),
    then, if it got in, out of the inbox to the loop."""
    if d.door.admit(kind, data, lambda x: (kind, x, attachment)):
        d._handle(*d.inbox.get(0))


def test_the_daemon_takes_only_sealed_frames():
    """A sealed sensor frame is stepped on; the same frame unsealed, sealed with another key,
    sealed by another sender than its src, or replayed, is refused and counted, and changes
    nothing."""
    ring = Keyring.generate("default")
    d, _ = daemon(ring)
    netsim = Sealer(ring, 0)
    d._handle("sensors", netsim.seal(wire.encode(sensors(0), 0, 1)), None)
    assert d.node.k == 0
    frame1 = netsim.seal(wire.encode(sensors(1), 0, 2))
    before = d.node.estimate()
    arrive(d, "sensors", wire.encode(sensors(1), 0, 2))
    arrive(d, "sensors", Sealer(Keyring.generate("default"), 0).seal(wire.encode(sensors(1), 0, 2)))
    arrive(d, "sensors", Sealer(ring, 7).seal(wire.encode(sensors(1), 0, 2)))
    assert d.node.k == 0
    np.testing.assert_array_equal(d.node.estimate().mean, before.mean)
    arrive(d, "sensors", frame1)
    arrive(d, "sensors", frame1)
    assert d.node.k == 1
    # No seal and a wrong key are refused at the door, before the inbox; the rest in the loop.
    assert dict(d.door.counts()) == {"auth-unauthenticated": 1, "auth-bad-tag": 1}
    assert dict(d.rejected) == {"auth-src-mismatch": 1, "auth-replayed": 1}
    assert d.stats()["rejected"] == {"auth-unauthenticated": 1, "auth-bad-tag": 1, "auth-src-mismatch": 1,
                                     "auth-replayed": 1}


def test_a_stats_answer_counts_only_from_its_agent_to_its_query():
    """Issue 26, finding 3: the nonce, the agent's key and its seal, all checked."""
    from swarmloc.wire.messages import Reply

    ring = Keyring.generate("s")
    keys, opener = wire.Keys("s"), Opener(ring)
    nonce = auth.query_nonce()
    assert auth.nonce_of(nonce.encode()) == nonce and auth.nonce_of(b"junk") == ""

    def answer(sender, src, n):
        return Sealer(ring, sender).seal(wire.encode(Reply(True, "", {"k": 5, **({"nonce": n} if n else {})}), src, 0))

    assert auth.open_stats_reply(opener, keys.stats(2), answer(2, 2, nonce), nonce) == (2, {"k": 5})
    for key, data, reason in [(keys.stats(2), answer(2, 2, auth.query_nonce()), "stale-nonce"),
                              (keys.stats(2), answer(2, 2, ""), "stale-nonce"),
                              (keys.stats(3), answer(2, 2, nonce), "wrong-sender"),
                              (keys.stats(2), answer(2, 3, nonce), "src-mismatch"),
                              (keys.stats(2), b"\xc1", "unauthenticated"),
                              ("swarmloc/s/elsewhere", answer(2, 2, nonce), "unknown-agent")]:
        with pytest.raises(AuthError) as e:
            auth.open_stats_reply(opener, key, data, nonce)
        assert e.value.reason == reason


def test_a_sensor_frame_sealed_for_another_agent_is_misaddressed():
    """Issue 26, finding 2: netsim addresses each sensor frame under its seal."""
    ring = Keyring.generate("default")
    d, _ = daemon(ring, direct=False)
    netsim = Sealer(ring, 0)
    d._handle("sensors", netsim.seal(wire.encode(sensors(0), 0, 1, 4)), None)  # agent 4's
    assert d.node.k == -1 and dict(d.rejected) == {"misaddressed": 1}
    d._handle("sensors", netsim.seal(wire.encode(sensors(0), 0, 2, 1)), None)
    assert d.node.k == 0


def test_a_stale_sensor_frame_is_no_tick():
    """Issue 26: an agent's `ticks` counted the stale frames its node dropped."""
    ring = Keyring.generate("default")
    d, _ = daemon(ring)
    netsim = Sealer(ring, 0)
    for seq, k in enumerate((0, 1, 1, 0, 2), 1):  # ticks 1 and 0 again: fresh frames, stale ticks
        d._handle("sensors", netsim.seal(wire.encode(sensors(k), 0, seq)), None)
    assert d.node.k == 2 and d.ticks == 3


def test_a_forged_delivery_number_is_refused_under_netsim():
    """Under netsim the delivery number is netsim's, tagged for this receiver and this frame:
    an authentic frame handed over by someone else under the next number is refused, and the
    number stays netsim's to give."""
    ring = Keyring.generate("default")
    d, _ = daemon(ring, direct=False)
    beacon = Sealer(ring, 2).seal(wire.encode(Beacon(0, np.zeros(2), np.eye(2), {}), 2, 1))
    att = wire.encode_delivery(1, None)
    d._handle("rx", beacon, Attachment(att))  # no tag
    d._handle("rx", beacon, Attachment(att + b"\0" * auth.TAG_BYTES))  # a made-up tag
    assert d.consumed == 0
    d._handle("rx", beacon, Attachment(att + auth.delivery_tag(ring, 1, att, beacon)))
    assert d.consumed == 1
    assert dict(d.rejected) == {"auth-unauthenticated": 1, "auth-bad-delivery": 1}


def test_netsim_routes_only_frames_sealed_by_the_agent_whose_key_they_are_on():
    """The dcl.log forgery of the security issue, at netsim's door: a frame on radio/tx/2 that
    says src 2 but is unsealed, sealed with another key, or sealed by agent 3, is refused and
    counted; agent 2's own sealed frame is taken once."""
    from netsim.server import NetsimServer, ServerConfig
    from swarmloc.experiment.scenario import load
    from swarmloc.wire.messages import DclLog

    ring = Keyring.generate("default")
    server = NetsimServer(load("wang2019"), ServerConfig(keyring=ring))
    key = server.keys.radio_tx(2)
    frame = wire.encode(DclLog(3, []), 2, 1, 1)

    def arrive(payload):  # through netsim's door, then its loop
        if server.door.admit("tx", payload, lambda x: x):
            return server._from_agent("tx", key, server.q.get(0))

    for payload in (frame, Sealer(Keyring.generate("default"), 2).seal(frame), Sealer(ring, 3).seal(frame)):
        assert arrive(payload) is None
    sealed = Sealer(ring, 2).seal(frame)
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
        ring = Keyring.load(keys)
        opener = Opener(ring)
        operator = zenoh.open(zenoh.Config.from_json5(json.dumps(tls.zenoh_tls(
            wire.zenoh_config("client", connect=[f"tcp/127.0.0.1:{port}"]), keys, "operator"))))
        got = []
        operator.declare_subscriber("swarmloc/sec/agent/*/estimate",
                                    lambda s: got.append(wire.decode(opener.open(s.payload.to_bytes())[0]).body))
        time.sleep(max(0.0, epoch + 10.0 / 4 + 1.5 - time.time()))
        stats = {}
        for r in operator.get("swarmloc/sec/agent/*/stats", timeout=3.0):
            if r.ok is not None:
                env = wire.decode(opener.open(r.ok.payload.to_bytes())[0], expect=(Reply,))
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
