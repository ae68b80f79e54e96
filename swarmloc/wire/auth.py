"""Frame authentication (docs/security.md): every frame on a swarm's keys carries an HMAC-SHA256
tag with the swarm's key and a per-sender counter, verified before its body is decoded.

Sans I/O: `Sealer.seal` turns a wire-encoded frame into an authenticated one, `Opener.open`
gives the frame back or raises AuthError naming why not. The drivers (the agent daemon, netsim,
the control client) call them at their I/O boundary; estimators never see them.

Layout: the frame, then a trailer of TRAILER.size = 31 bytes, little-endian:

    sender   u32   who sealed it (an agent's id, 0 for netsim, operator() for the CLI)
    counter  u64   the sender's counter, strictly increasing over its frames
    kid      u8    which of the keyring's keys
    tag      16 B  HMAC-SHA256(key, DOMAIN + swarm + 0x00 + frame + sender + counter + kid)[:16]
    magic    2 B   b"S1"

The counter is the sender's UNIX time in microseconds (one more than its last when it sends
faster than that), so a restarted sender goes on above everything it sent before. Freshness is
by the receiver's clock: a counter more than MAX_AHEAD_US ahead of it or MAX_AGE_US behind it is
refused, and within that span a receiver remembers, per sender, every counter it accepted: a
counter seen before is a replay. Nothing a frame carries moves that span, so no frame, however
far ahead its counter, can make a sender's later frames look old (issue 26, finding 8: with a
"highest counter seen" window, one sealed frame with a counter far ahead locked its sender out).
"""

from __future__ import annotations

import base64
import hmac
import json
import os
import secrets
import stat
import struct
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from pathlib import Path

TRAILER = struct.Struct("<IQB16s2s")
MAGIC = b"S1"
DOMAIN = b"swarmloc/frame/1/"
TAG_BYTES = 16
KEY_BYTES = 32
MAX_AGE_US = 60_000_000
"""A frame sealed longer ago than this (by the receiver's clock) is refused as too old: wider than
any queue a frame waits in on a loaded machine and than the clock offset of NTP-synchronised
hosts, so that lateness is never mistaken for a replay."""
MAX_AHEAD_US = 60_000_000
"""A counter further ahead of the receiver's clock than this is refused (from-the-future)."""
MAX_SEEN = 1 << 20
"""Counters one receiver remembers per sender at most (a sender's MAX_AGE_US of frames); the
oldest go first. A key holder flooding beyond it can at worst replay its own old frames."""
MAX_SENDERS = 4096
"""Senders a receiver keeps windows for; the least recently heard is forgotten first (its frames
within MAX_AGE_US could then be replayed once: a memory bound, not a hole outsiders can open,
since only a key holder makes new senders)."""
OPERATOR = 2**31
"""Sender ids from here up are operators' (the CLI, monitors): one per process, operator() = this
+ its pid, so that two of them at once never share a counter (agents' ids are below 2**31)."""
KEY_FILE = "swarm.key"  # the frame key's file in a swarm's key directory (`swarmloc keys new`)
KEYRING_VERSION = 1


class AuthError(ValueError):
    """A frame that is not authentic: `reason` is the counter's name (`auth-<reason>`)."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


@dataclass
class Keyring:
    """The swarm's keys: kid -> 32 random bytes; frames are sealed with `current`. A key
    file holds exactly this (docs/security.md#key-files)."""

    swarm: str
    keys: dict[int, bytes]
    current: int

    @classmethod
    def generate(cls, swarm: str) -> Keyring:
        return cls(swarm, {1: secrets.token_bytes(KEY_BYTES)}, 1)

    def rotate(self) -> int:
        """A new current key; every older one is dropped (a key that left with a revoked
        member must open nothing more). Returns the new kid."""
        kid = self.current % 255 + 1
        self.keys, self.current = {kid: secrets.token_bytes(KEY_BYTES)}, kid
        return kid

    def to_json(self) -> str:
        return json.dumps({"version": KEYRING_VERSION, "swarm": self.swarm, "current": self.current,
                           "keys": {str(k): base64.b64encode(v).decode() for k, v in self.keys.items()}}, indent=1)

    @classmethod
    def from_json(cls, text: str, source: str = "key file") -> Keyring:
        try:
            d = json.loads(text)
            if d.get("version") != KEYRING_VERSION:
                raise ValueError(f"version {d.get('version')!r}, this swarmloc reads {KEYRING_VERSION}")
            keys = {int(k): base64.b64decode(v, validate=True) for k, v in d["keys"].items()}
            ring = cls(str(d["swarm"]), keys, int(d["current"]))
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise ValueError(f"{source}: not a swarmloc key file ({exc})") from None
        if ring.current not in keys or any(not 1 <= k <= 255 or len(v) != KEY_BYTES for k, v in keys.items()):
            raise ValueError(f"{source}: not a swarmloc key file (bad key ids or lengths)")
        return ring

    def save(self, path: Path) -> None:
        """Written whole (a temporary file renamed over it), readable by its owner only."""
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(self.to_json())
        os.chmod(tmp, 0o600)
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: Path) -> Keyring:
        """The key file at `path` (or KEY_FILE in the key directory `path`); ValueError if it is
        unreadable, malformed, or readable by anyone but its owner (as ssh refuses such a
        private key)."""
        path = Path(path)
        if path.is_dir():
            path = path / KEY_FILE
        try:
            mode = path.stat().st_mode
            text = path.read_text()
        except OSError as exc:
            raise ValueError(f"{path}: cannot read the key file: {exc.strerror or exc}") from None
        if mode & (stat.S_IRWXG | stat.S_IRWXO):
            raise ValueError(f"{path}: key file is accessible by others (mode {stat.S_IMODE(mode):04o}); "
                             f"chmod 600 {path}")
        return cls.from_json(text, str(path))


def operator() -> int:
    """This process's sender id as an operator (control requests)."""
    return OPERATOR + os.getpid() % OPERATOR


def _tag(key: bytes, swarm: bytes, frame: bytes, header: bytes) -> bytes:
    return hmac.digest(key, DOMAIN + swarm + b"\0" + frame + header, "sha256")[:TAG_BYTES]  # one-shot, in C


class Sealer:
    """One sender's side: seals its frames with the keyring's current key and its counter."""

    def __init__(self, keyring: Keyring, sender: int):
        self.keyring, self.sender = keyring, int(sender)
        self._swarm = keyring.swarm.encode()
        self.counter = time.time_ns() // 1000

    def seal(self, frame: bytes) -> bytes:
        self.counter = max(self.counter + 1, time.time_ns() // 1000)
        kid = self.keyring.current
        header = TRAILER.pack(self.sender, self.counter, kid, b"", b"")[:13]
        return frame + header + _tag(self.keyring.keys[kid], self._swarm, frame, header) + MAGIC


class _Window:
    """The counters of one sender accepted within the last MAX_AGE_US, oldest first."""

    __slots__ = ("seen", "order")

    def __init__(self):
        self.seen: set[int] = set()
        self.order: deque[int] = deque()

    def admit(self, counter: int, now: int) -> str | None:
        """Accept `counter` at the receiver's time `now` (us) (None) or say why not."""
        if counter > now + MAX_AHEAD_US:
            return "from-the-future"
        oldest = now - MAX_AGE_US
        if counter < oldest:
            return "too-old"
        if counter in self.seen:
            return "replayed"
        order, seen = self.order, self.seen
        while order and (order[0] < oldest or len(order) >= MAX_SEEN):
            seen.discard(order.popleft())
        seen.add(counter)
        order.append(counter)
        return None


@dataclass
class Opener:
    """One receiver's side: verifies the tag, then the sender's counter against its window."""

    keyring: Keyring
    windows: OrderedDict = field(default_factory=OrderedDict)  # sender -> _Window, least recent first

    def __post_init__(self):
        self._swarm = self.keyring.swarm.encode()

    def verify(self, data: bytes) -> int:
        """The sealer of a frame whose tag is right, AuthError otherwise: the MAC alone, no
        counter, no state, so a driver's Zenoh callback threads can call it at once, before a
        frame takes a place in the inbox (docs/security.md#limits)."""
        if len(data) < TRAILER.size or data[-2:] != MAGIC:
            raise AuthError("unauthenticated", "no trailer")
        trailer = data[-TRAILER.size:]
        sealer, _, kid, tag, _ = TRAILER.unpack(trailer)
        key = self.keyring.keys.get(kid)
        if key is None:
            raise AuthError("unknown-key", f"key {kid}")
        if not hmac.compare_digest(tag, _tag(key, self._swarm, data[:-TRAILER.size], trailer[:13])):
            raise AuthError("bad-tag", f"sender {sealer}")
        return sealer

    def open(self, data: bytes, sender: int | None = None) -> tuple[bytes, int]:
        """(frame, sender) of an authentic frame not seen before; AuthError otherwise. With
        `sender`, a frame sealed by anyone else is refused before its counter counts as seen:
        a captured copy on another sender's key must not make the original a replay."""
        self.verify(data)
        return self.admit(data, sender)

    def admit(self, data: bytes, sender: int | None = None) -> tuple[bytes, int]:
        """`open` for a frame `verify` passed already (in a Zenoh callback): the sender and the
        counter against its window, from the one loop that owns the windows."""
        frame, trailer = data[:-TRAILER.size], data[-TRAILER.size:]
        sealer, counter, _, _, _ = TRAILER.unpack(trailer)
        if sender is not None and sealer != sender:
            raise AuthError("wrong-sender", f"sealed by {sealer}, expected {sender}")
        sender = sealer
        window = self.windows.get(sender)
        if window is None:
            if len(self.windows) >= MAX_SENDERS:
                self.windows.popitem(last=False)
            window = self.windows[sender] = _Window()
        else:
            self.windows.move_to_end(sender)
        why = window.admit(counter, time.time_ns() // 1000)
        if why is not None:
            raise AuthError(why, f"sender {sender} counter {counter}")
        return frame, sender


DELIVERY_DOMAIN = b"swarmloc/delivery/1/"


def delivery_tag(keyring: Keyring, receiver: int, attachment: bytes, data: bytes) -> bytes:
    """netsim's tag on one delivery: its attachment (the receiver's delivery number and the send
    time, wire.encode_delivery) bound to the receiver and to the frame's bytes, so nobody else
    can hand an agent a frame under the next delivery number."""
    msg = DELIVERY_DOMAIN + keyring.swarm.encode() + b"\0" + struct.pack("<I", receiver) + attachment + data
    return hmac.digest(keyring.keys[keyring.current], msg, "sha256")[:TAG_BYTES]


def check_delivery(keyring: Keyring, receiver: int, attachment: bytes, data: bytes) -> bytes:
    """The delivery attachment without its tag, if the tag is netsim's; AuthError otherwise."""
    if len(attachment) <= TAG_BYTES:
        raise AuthError("unauthenticated", "delivery without a tag")
    head, tag = attachment[:-TAG_BYTES], attachment[-TAG_BYTES:]
    msg = DELIVERY_DOMAIN + keyring.swarm.encode() + b"\0" + struct.pack("<I", receiver) + head + data
    for key in keyring.keys.values():
        if hmac.compare_digest(tag, hmac.digest(key, msg, "sha256")[:TAG_BYTES]):
            return head
    raise AuthError("bad-delivery", f"to {receiver}")


NONCE_CHARS = 32  # a query's nonce: 16 random bytes, in hex


def query_nonce() -> str:
    """The nonce a stats or control query carries (its payload): only an answer holding it, under
    its sender's seal, answers this query (issue 26, finding 3: captured answers were taken)."""
    return secrets.token_hex(NONCE_CHARS // 2)


def nonce_of(payload) -> str:
    """The nonce a query carried (its payload, Zenoh ZBytes or bytes), '' if none fits."""
    raw = payload.to_bytes() if hasattr(payload, "to_bytes") else bytes(payload or b"")
    text = raw[:NONCE_CHARS].decode("ascii", "replace")
    return text if len(raw) == NONCE_CHARS and all(c in "0123456789abcdef" for c in text) else ""


def open_stats_reply(opener: Opener | None, key: str, payload: bytes, nonce: str) -> tuple[int, dict]:
    """(agent id, stats) of an agent's answer to the stats query that carried `nonce`: on that
    agent's key, sealed by it, its envelope's src, holding the nonce. AuthError otherwise, with
    the reason (a ValueError)."""
    from swarmloc import wire
    from swarmloc.wire.messages import Reply

    try:
        aid = wire.Keys.agent_of(key)
    except ValueError:
        raise AuthError("unknown-agent", key) from None
    if opener is not None:
        payload, _ = opener.open(payload, aid)
    try:
        env = wire.decode(payload, expect=(Reply,))
    except wire.WireError as exc:
        raise AuthError("malformed", str(exc)) from None
    if env.src != aid:
        raise AuthError("src-mismatch", f"src {env.src} on {key}")
    data = env.body.data if isinstance(env.body.data, dict) else {}
    if data.get("nonce") != nonce:
        raise AuthError("stale-nonce", f"answer of agent {aid} to another query")
    return aid, {k: v for k, v in data.items() if k != "nonce"}
