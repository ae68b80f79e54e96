"""Frame authentication (docs/security.md): every frame on a swarm's keys is sealed by its
sender with that sender's OWN key (per-member identity, issue 26 finding 10), bound to its
sender, its receiver and the key expression it is published on, and verified before its body is
decoded.

Sans I/O: `Sealer.seal` turns a wire-encoded frame into an authenticated one, `Opener.open`
gives the frame back or raises AuthError naming why not. The drivers (the agent daemon, netsim,
the launcher, the control client) call them at their I/O boundary; estimators never see them.

Two suites, chosen by the link (measured: benchmarks/bench_auth.py, docs/benchmarks.md):

- **MAC** (magic `S2`): HMAC-SHA256 under the key of the one member at the far end of a link
  to or from netsim. Member m's key K_m is known to m and to netsim only (netsim derives every
  member's from the hub's master secret), so a frame agent i sends to netsim, and one netsim
  sends to agent j, can be sealed by nobody else. 3 us to seal or open, as before.
- **Signature** (magic `E2`): Ed25519 under the sender's own private key, checked against its
  public key in the swarm's directory: netsim's broadcasts (clock, events, links), an agent's
  stats answers, and every frame of a swarm without netsim (direct mode). About 10 times a MAC
  to make and 20 times to check: never on a frame netsim routes.

Layout: the frame, then a trailer, little-endian:

    sender   u32   who sealed it (an agent's id, 0 for netsim, operator() for the CLI)
    receiver u32   who it is for (0 netsim, an agent or operator id, BROADCAST = 0xFFFFFFFF)
    counter  u64   the sender's counter, strictly increasing over its frames
    epoch    u8    the key generation of the member whose key seals it (1..255)
    tag      16 B  (S2) HMAC-SHA256(K, msg)[:16]    or   64 B (E2) Ed25519 signature of msg
    magic    2 B   b"S2" or b"E2"

    msg = DOMAIN + swarm + 0x00 + key expression + 0x00 + frame + the 17 header bytes above

35 bytes (S2) or 83 bytes (E2). The frame's type is inside the frame, so under the tag too.

The counter is the sender's UNIX time in microseconds (one more than its last when it sends
faster than that), so a restarted sender goes on above everything it sent before. Freshness is
by the receiver's clock: a counter more than MAX_AHEAD_US ahead of it or MAX_AGE_US behind it is
refused, and within that span a receiver remembers, per (sender, receiver), every counter it
accepted: a counter seen before is a replay. Nothing a frame carries moves that span, so no
frame, however far ahead its counter, can make a sender's later frames look old (issue 26,
finding 8).
"""

from __future__ import annotations

import base64
import hashlib
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

HEADER = struct.Struct("<IIQB")  # sender, receiver, counter, epoch: 17 bytes
TRAILER = struct.Struct("<IIQB16s2s")  # the MAC suite's trailer: 35 bytes
SIG_TRAILER = struct.Struct("<IIQB64s2s")  # the signature suite's: 83 bytes
MAGIC = b"S2"
SIG_MAGIC = b"E2"
TRAILERS = {MAGIC: TRAILER.size, SIG_MAGIC: SIG_TRAILER.size}  # magic -> trailer size
DOMAIN = b"swarmloc/frame/2/"
TAG_BYTES = 16
SIG_BYTES = 64
KEY_BYTES = 32
BROADCAST = 0xFFFFFFFF
"""The receiver of a frame for everyone on its key (netsim's clock, events, links; a direct
broadcast)."""
NETSIM = 0
MAX_AGE_US = 60_000_000
"""A frame sealed longer ago than this (by the receiver's clock) is refused as too old: wider than
any queue a frame waits in on a loaded machine and than the clock offset of NTP-synchronised
hosts, so that lateness is never mistaken for a replay."""
MAX_AHEAD_US = 60_000_000
"""A counter further ahead of the receiver's clock than this is refused (from-the-future)."""
MAX_SEEN = 1 << 20
"""Counters one receiver remembers per (sender, receiver) at most (a sender's MAX_AGE_US of
frames); the oldest go first. A key holder flooding beyond it can at worst replay its own old
frames."""
MAX_SENDERS = 4096
"""(sender, receiver) windows a receiver keeps; the least recently heard is forgotten first (its
frames within MAX_AGE_US could then be replayed once: a memory bound, not a hole outsiders can
open, since only a key holder makes new senders)."""
OPERATOR = 2**31
"""Sender ids from here up are operators' (the CLI, monitors): one per process, operator() = this
+ its pid, so that two of them at once never share a counter (agents' ids are below 2**31). They
all speak as the member `operator`."""
KEY_FILE = "swarm.key"  # the hub's file (the master secret): the admin's directory and netsim only
DIRECTORY_FILE = "members.json"  # every member's public key and key generation, and who is revoked
SECRET_SUFFIX = ".secret"  # <member>.secret: that member's own MAC key and signing key
KEYRING_VERSION = 2


class AuthError(ValueError):
    """A frame that is not authentic: `reason` is the counter's name (`auth-<reason>`)."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


def member_of(sid: int) -> str:
    """The member whose key speaks for sender id `sid`: `netsim` (0), `operator` (2**31 and up),
    else `agent-<sid>` (an agent, or a sensor driver with an id of its own)."""
    if sid == NETSIM:
        return "netsim"
    return "operator" if sid >= OPERATOR else f"agent-{sid}"


_IPAD = bytes(x ^ 0x36 for x in range(256))
_OPAD = bytes(x ^ 0x5C for x in range(256))
_PADS: dict[bytes, tuple] = {}  # key -> SHA-256 states after its inner and outer pad (RFC 2104)


def mac(key: bytes, msg: bytes) -> bytes:
    """HMAC-SHA256 of `msg` under `key`, the same 32 bytes as `hmac.digest(key, msg, "sha256")`.

    Not that function because it releases the GIL around every call, however small the
    message: in an agent host (then 32 agents on a thread each, and Zenoh's callback threads) getting
    it back waited behind the other threads, 5 to 16 ms of wall time a MAC on average in a
    lockstep swarm256 run, on every frame sealed or checked (docs/benchmarks.md, "The GIL and the MAC"). A hash
    object's copy, and its update under 2 KiB, keep the GIL; the two pads are hashed once per
    key, which also halves the CPU of a MAC (about 1.2 against 2.3 us here)."""
    pads = _PADS.get(key)
    if pads is None:
        k = (hashlib.sha256(key).digest() if len(key) > 64 else key).ljust(64, b"\0")
        if len(_PADS) >= 4096:  # members x generations of one swarm are far fewer: a bound only
            _PADS.clear()
        pads = _PADS[key] = (hashlib.sha256(k.translate(_IPAD)), hashlib.sha256(k.translate(_OPAD)))
    inner = pads[0].copy()
    inner.update(msg)
    outer = pads[1].copy()
    outer.update(inner.digest())
    return outer.digest()


def _derive(master: bytes, swarm: str, what: bytes, member: str, epoch: int) -> bytes:
    return mac(master, b"swarmloc/member/2/" + what + b"/" + swarm.encode() + b"\0" + member.encode() + b"\0"
               + bytes([epoch]))


def _b64(b: bytes) -> str:
    return base64.b64encode(b).decode()


def _unb64(s: str) -> bytes:
    return base64.b64decode(s, validate=True)


def _write_private(path: Path, text: str, mode: int = 0o600) -> None:
    """Written whole (a temporary file renamed over it), readable by its owner only."""
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.chmod(tmp, mode)
    os.replace(tmp, path)


def _read_private(path: Path) -> str:
    try:
        mode = path.stat().st_mode
        text = path.read_text()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read the key file: {exc.strerror or exc}") from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise ValueError(f"{path}: key file is accessible by others (mode {stat.S_IMODE(mode):04o}); chmod 600 {path}")
    return text


@dataclass
class Keyring:
    """One process's view of the swarm's keys (docs/security.md#the-key-directory).

    Every ring holds the directory: each member's key generation (`members`, name -> epoch 1..255)
    and Ed25519 public key, and who is revoked. The hub's ring (KEY_FILE; the admin and netsim)
    holds the master secret every member's keys derive from; a member's ring (`<member>.secret`)
    holds only that member's own MAC key and signing key."""

    swarm: str
    members: dict[str, int]
    publics: dict[str, bytes]
    revoked: set[str] = field(default_factory=set)
    master: bytes | None = None  # the hub's
    member: str | None = None  # whose ring this is; None: the hub's
    mac: bytes | None = None  # the member's own MAC key
    seed: bytes | None = None  # the member's own Ed25519 private key (32 raw bytes)
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    # ------------------------------------------------------------ making and changing

    @classmethod
    def generate(cls, swarm: str, agents=()) -> Keyring:
        """A new hub: a fresh master secret, and the members netsim, operator and agent-<id> for
        every id in `agents` (more can be added)."""
        ring = cls(swarm, {}, {}, set(), secrets.token_bytes(KEY_BYTES))
        for name in ("netsim", "operator", *(f"agent-{int(a)}" for a in agents)):
            ring.add(name)
        return ring

    def _hub(self) -> None:
        if self.master is None:
            raise ValueError("only the hub's key file (swarm.key) can do this")

    def add(self, name: str) -> int:
        """A member in the directory (hub only): a revoked one comes back under a new key
        generation (its old keys open nothing); returns its epoch."""
        self._hub()
        epoch = self.members.get(name, 0)
        if epoch == 0 or name in self.revoked:
            epoch = epoch % 255 + 1
        self.revoked.discard(name)
        self.members[name] = epoch
        self.publics[name] = self._signing(name, epoch).public_key().public_bytes_raw()
        self._cache.clear()
        return epoch

    def revoke(self, name: str) -> None:
        """Every frame sealed with the member's keys refused from now on, by whoever holds this
        directory; nobody else's keys change."""
        self.revoked.add(name)
        self._cache.clear()

    def rotate(self) -> None:
        """A new master secret (hub only): every member's keys change (the hub's file was lost)."""
        self._hub()
        self.master = secrets.token_bytes(KEY_BYTES)
        for name in list(self.members):
            if name not in self.revoked:
                self.members[name] = self.members[name] % 255 + 1
                self.publics[name] = self._signing(name, self.members[name]).public_key().public_bytes_raw()
        self._cache.clear()

    def for_member(self, name: str) -> Keyring:
        """Member `name`'s own ring (hub only): the directory and its two keys, nobody else's."""
        self._hub()
        if name not in self.members or name in self.revoked:
            raise ValueError(f"{name} is not a member of swarm {self.swarm!r}" + (" (revoked)" if name in self.revoked else ""))
        epoch = self.members[name]
        return Keyring(self.swarm, dict(self.members), dict(self.publics), set(self.revoked), None, name,
                       _derive(self.master, self.swarm, b"mac", name, epoch), _derive(self.master, self.swarm, b"sign", name, epoch))

    # ------------------------------------------------------------ keys

    def _signing(self, name: str, epoch: int):
        from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

        return Ed25519PrivateKey.from_private_bytes(_derive(self.master, self.swarm, b"sign", name, epoch))

    def mac_key(self, name: str) -> bytes | None:
        """Member `name`'s MAC key if this ring holds it (its own, or the hub's: any member's)."""
        if name == self.member:
            return self.mac
        if self.master is None or name not in self.members:
            return None
        got = self._cache.get(("mac", name))
        if got is None:
            got = self._cache[("mac", name)] = _derive(self.master, self.swarm, b"mac", name, self.members[name])
        return got

    def signer(self, name: str):
        """Member `name`'s Ed25519 private key if this ring holds it, else None."""
        got = self._cache.get(("signer", name))
        if got is None:
            if name == self.member and self.seed is not None:
                from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

                got = Ed25519PrivateKey.from_private_bytes(self.seed)
            elif self.master is not None and name in self.members:
                got = self._signing(name, self.members[name])
            else:
                return None
            self._cache[("signer", name)] = got
        return got

    def public(self, name: str):
        """Member `name`'s Ed25519 public key, None for a stranger."""
        got = self._cache.get(("public", name))
        if got is None:
            raw = self.publics.get(name)
            if raw is None:
                return None
            from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

            got = self._cache[("public", name)] = Ed25519PublicKey.from_public_bytes(raw)
        return got

    def fingerprint(self, name: str) -> str:
        import hashlib

        return hashlib.sha256(self.publics[name]).hexdigest()[:16]

    # ------------------------------------------------------------ files

    def directory_json(self) -> str:
        return json.dumps({"version": KEYRING_VERSION, "swarm": self.swarm, "revoked": sorted(self.revoked),
                           "members": {n: {"epoch": e, "public": _b64(self.publics[n])}
                                       for n, e in sorted(self.members.items())}}, indent=1)

    def to_json(self) -> str:
        if self.master is not None:
            return json.dumps({"version": KEYRING_VERSION, "kind": "hub", "swarm": self.swarm,
                               "master": _b64(self.master), "revoked": sorted(self.revoked),
                               "members": dict(sorted(self.members.items()))}, indent=1)
        return json.dumps({"version": KEYRING_VERSION, "kind": "member", "swarm": self.swarm, "member": self.member,
                           "epoch": self.members[self.member], "mac": _b64(self.mac), "sign": _b64(self.seed)}, indent=1)

    @classmethod
    def from_json(cls, text: str, source: str = "key file", directory: str | None = None) -> Keyring:
        """A hub's file, or a member's file with the directory's text beside it."""
        try:
            d = json.loads(text)
            if d.get("version") != KEYRING_VERSION:
                raise ValueError(f"version {d.get('version')!r}, this swarmloc reads {KEYRING_VERSION}")
            if d["kind"] == "hub":
                ring = cls(str(d["swarm"]), {}, {}, set(), _unb64(d["master"]))
                for name, epoch in d["members"].items():
                    if not 1 <= int(epoch) <= 255:
                        raise ValueError(f"epoch {epoch} of {name}")
                    ring.members[str(name)] = int(epoch)
                    ring.publics[str(name)] = ring._signing(str(name), int(epoch)).public_key().public_bytes_raw()
                ring.revoked = set(map(str, d["revoked"]))
                if len(ring.master) != KEY_BYTES:
                    raise ValueError("master of the wrong length")
                return ring
            if d["kind"] != "member" or directory is None:
                raise ValueError(f"kind {d['kind']!r}")
            dd = json.loads(directory)
            if dd.get("version") != KEYRING_VERSION or dd["swarm"] != d["swarm"]:
                raise ValueError(f"{DIRECTORY_FILE} is not this swarm's directory")
            members = {str(n): int(m["epoch"]) for n, m in dd["members"].items()}
            publics = {str(n): _unb64(m["public"]) for n, m in dd["members"].items()}
            ring = cls(str(d["swarm"]), members, publics, set(map(str, dd["revoked"])), None, str(d["member"]),
                       _unb64(d["mac"]), _unb64(d["sign"]))
            if len(ring.mac) != KEY_BYTES or len(ring.seed) != KEY_BYTES or any(len(p) != 32 for p in publics.values()):
                raise ValueError("keys of the wrong length")
            if members.get(ring.member) != int(d["epoch"]):
                raise ValueError(f"{ring.member}'s keys are not the directory's (generation {d['epoch']}, the directory "
                                 f"has {members.get(ring.member)}): `swarmloc keys add` issued new ones")
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise ValueError(f"{source}: not a swarmloc key file ({exc})") from None
        return ring

    def save(self, path: Path) -> None:
        """This ring's file (the hub's or a member's), readable by its owner only."""
        _write_private(Path(path), self.to_json())

    def save_directory(self, directory: Path, members=None) -> None:
        """The key directory's files (hub only): KEY_FILE, DIRECTORY_FILE and a `<member>.secret`
        for each of `members` (every member not revoked if None); a revoked member's is deleted."""
        self._hub()
        directory = Path(directory)
        self.save(directory / KEY_FILE)
        _write_private(directory / DIRECTORY_FILE, self.directory_json(), 0o600)
        for name in (self.members if members is None else members):
            if name not in self.revoked:
                self.for_member(name).save(directory / f"{name}{SECRET_SUFFIX}")
        for name in self.revoked:
            (directory / f"{name}{SECRET_SUFFIX}").unlink(missing_ok=True)

    @classmethod
    def load(cls, path: Path, member: str | None = None) -> Keyring:
        """A key directory's ring: the hub's (KEY_FILE) without `member`, member `member`'s own
        (`<member>.secret` and DIRECTORY_FILE) with it; `path` may also name the file itself.
        ValueError if a file is unreadable, malformed, or readable by anyone but its owner (as
        ssh refuses such a private key)."""
        path = Path(path)
        if path.is_dir():
            path = path / (KEY_FILE if member is None else f"{member}{SECRET_SUFFIX}")
        text = _read_private(path)
        directory = None
        if path.name != KEY_FILE:
            dpath = path.with_name(DIRECTORY_FILE)
            try:
                directory = dpath.read_text()
            except OSError:
                directory = None
        ring = cls.from_json(text, str(path), directory)
        if member is not None and ring.member not in (None, member):
            raise ValueError(f"{path}: the keys of {ring.member}, not of {member}")
        if member is not None and ring.member is None:
            return ring.for_member(member)
        return ring


def operator() -> int:
    """This process's sender id as an operator (control requests)."""
    return OPERATOR + os.getpid() % OPERATOR


def _msg(swarm: bytes, key: bytes, frame: bytes, header: bytes) -> bytes:
    return DOMAIN + swarm + b"\0" + key + b"\0" + frame + header


def _link(sender: int, receiver: int) -> str | None:
    """The member whose MAC key seals a frame from `sender` to `receiver`: a link to or from
    netsim has one; any other link (a broadcast, agent to agent) none."""
    if sender == NETSIM and receiver not in (NETSIM, BROADCAST):
        return member_of(receiver)
    if receiver == NETSIM and sender != NETSIM:
        return member_of(sender)
    return None


class Sealer:
    """One sender's side: seals its frames with its own keys and its counter."""

    def __init__(self, keyring: Keyring, sender: int):
        self.keyring, self.sender = keyring, int(sender)
        self.name = member_of(self.sender)
        self._swarm = keyring.swarm.encode()
        self.counter = time.time_ns() // 1000

    def seal(self, frame: bytes, key: str, to: int = BROADCAST) -> bytes:
        """`frame` sealed for receiver `to` on key expression `key`: with the link's MAC key
        when it is a link to or from netsim and this ring holds that key, with this sender's
        signature otherwise. ValueError if this ring holds neither."""
        self.counter = max(self.counter + 1, time.time_ns() // 1000)
        ring = self.keyring
        link = _link(self.sender, to)
        link_key = ring.mac_key(link) if link is not None else None
        if link_key is not None:
            header = HEADER.pack(self.sender, to, self.counter, ring.members.get(link, 0))
            tag = mac(link_key, _msg(self._swarm, key.encode(), frame, header))[:TAG_BYTES]
            return frame + header + tag + MAGIC
        signer = ring.signer(self.name)
        if signer is None:
            raise ValueError(f"this key file cannot seal as {self.name}")
        header = HEADER.pack(self.sender, to, self.counter, ring.members.get(self.name, 0))
        return frame + header + signer.sign(_msg(self._swarm, key.encode(), frame, header)) + SIG_MAGIC


def trailer_size(data: bytes) -> int:
    """The size of a sealed frame's trailer (by its magic), AuthError if it has none."""
    size = TRAILERS.get(bytes(data[-2:]))
    if size is None or len(data) < size:
        raise AuthError("unauthenticated", "no trailer")
    return size


def unwrap(data: bytes) -> tuple[bytes, int, int, int]:
    """(frame, sender, receiver, counter) of a sealed frame, NOT verified: for a frame whose
    authenticity something else vouches for (netsim's delivery tag)."""
    size = trailer_size(data)
    sender, receiver, counter, _ = HEADER.unpack_from(data, len(data) - size)
    return data[:-size], sender, receiver, counter


class _Window:
    """The counters of one (sender, receiver) accepted within the last MAX_AGE_US, oldest first."""

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
    """One receiver's side: the receiver, the sender's key and the tag or signature, then the
    counter against its (sender, receiver) window. `me`: this receiver's id (an agent's, 0 for
    netsim, operator() for a control client); None takes only frames for everyone (the
    launcher)."""

    keyring: Keyring
    me: int | None = None
    windows: OrderedDict = field(default_factory=OrderedDict)  # (sender, receiver) -> _Window, least recent first

    def __post_init__(self):
        self._swarm = self.keyring.swarm.encode()

    def verify(self, data: bytes, key: str) -> int:
        """The sealer of a frame sealed for this receiver on `key` whose tag or signature is
        right, AuthError otherwise: no counter, no state, so a driver's Zenoh callback threads
        can call it at once, before a frame takes a place in the inbox (docs/security.md#limits).
        Cheapest first: the trailer, the receiver, revocation and the key, then the MAC or the
        signature."""
        size = trailer_size(data)
        end = len(data) - size
        header = data[end:end + HEADER.size]
        sender, receiver, _, epoch = HEADER.unpack(header)
        if receiver != BROADCAST and receiver != self.me:
            raise AuthError("misaddressed", f"sealed for {receiver}")
        ring = self.keyring
        name = member_of(sender)
        if name in ring.revoked:
            raise AuthError("revoked", name)
        body = data[end + HEADER.size:-2]
        if size == TRAILER.size:
            link = _link(sender, receiver)
            if link is None or link in ring.revoked:
                raise AuthError("bad-tag", f"no MAC key between {sender} and {receiver}")
            link_key = ring.mac_key(link)
            if link_key is None or ring.members.get(link) != epoch:
                raise AuthError("unknown-key", f"{link}, generation {epoch}")
            if not hmac.compare_digest(body, mac(link_key, _msg(self._swarm, key.encode(), data[:end], header))[:TAG_BYTES]):
                raise AuthError("bad-tag", f"sender {sender}")
            return sender
        public = ring.public(name)
        if public is None or ring.members.get(name) != epoch:
            raise AuthError("unknown-key", f"{name}, generation {epoch}")
        from cryptography.exceptions import InvalidSignature

        try:
            public.verify(body, _msg(self._swarm, key.encode(), data[:end], header))
        except InvalidSignature:
            raise AuthError("bad-signature", f"sender {sender}") from None
        return sender

    def open(self, data: bytes, key: str, sender: int | None = None) -> tuple[bytes, int]:
        """(frame, sender) of an authentic frame sealed for this receiver on `key`, not seen
        before; AuthError otherwise. With `sender`, a frame sealed by anyone else is refused
        before its counter counts as seen."""
        self.verify(data, key)
        return self.admit(data, sender)

    def admit(self, data: bytes, sender: int | None = None) -> tuple[bytes, int]:
        """`open` for a frame `verify` passed already (in a Zenoh callback): the sender and the
        counter against its (sender, receiver) window, from the one loop that owns the windows."""
        frame, sealer, receiver, counter = unwrap(data)
        if sender is not None and sealer != sender:
            raise AuthError("wrong-sender", f"sealed by {sealer}, expected {sender}")
        wk = (sealer, receiver)
        window = self.windows.get(wk)
        if window is None:
            if len(self.windows) >= MAX_SENDERS:
                self.windows.popitem(last=False)
            window = self.windows[wk] = _Window()
        else:
            self.windows.move_to_end(wk)
        why = window.admit(counter, time.time_ns() // 1000)
        if why is not None:
            raise AuthError(why, f"sender {sealer} counter {counter}")
        return frame, sealer


class Revocations:
    """Revocations made while a process runs (`swarmloc keys revoke`): the file that lists them
    (the hub's KEY_FILE, or a member's DIRECTORY_FILE) looked at again at most every `period`
    seconds, and a member newly listed revoked in `ring` from then on, so its keys open nothing
    more. Only revocations: a member added or given new keys needs its receivers restarted."""

    def __init__(self, ring: Keyring, path: Path, period: float = 1.0):
        path = Path(path)
        if path.is_dir():
            path = path / (KEY_FILE if ring.member is None else DIRECTORY_FILE)
        elif path.name != KEY_FILE:
            path = path.with_name(DIRECTORY_FILE)
        self.ring, self.path, self.period = ring, path, period
        self._next, self._seen = 0.0, self._stamp()

    def _stamp(self):
        try:
            st = self.path.stat()
        except OSError:
            return None
        return st.st_mtime_ns, st.st_size

    def poll(self, now: float) -> list[str]:
        """Members revoked since the last look (revoked in the ring now), [] if none or too soon.
        A file caught half-written, or unreadable, is looked at again next time."""
        if now < self._next:
            return []
        self._next = now + self.period
        stamp = self._stamp()
        if stamp is None or stamp == self._seen:
            return []
        try:
            listed = set(map(str, json.loads(self.path.read_text())["revoked"]))
        except (OSError, ValueError, KeyError, TypeError):
            return []
        self._seen = stamp
        new = sorted(listed - self.ring.revoked)
        for name in new:
            self.ring.revoke(name)
        return new


DELIVERY_DOMAIN = b"swarmloc/delivery/2/"


def _delivery_msg(ring: Keyring, receiver: int, attachment: bytes, data: bytes) -> bytes:
    return DELIVERY_DOMAIN + ring.swarm.encode() + b"\0" + struct.pack("<I", receiver) + attachment + data


def delivery_tag(keyring: Keyring, receiver: int, attachment: bytes, data: bytes) -> bytes:
    """netsim's tag on one delivery, under the RECEIVER's own MAC key (which only it and netsim
    hold): its attachment (the receiver's delivery number and the send time,
    wire.encode_delivery) bound to the receiver and to the frame's bytes with their seal, so
    nobody else, no other member either, can hand an agent a frame under a delivery number
    (issue 26: with the swarm's one key, a member could forge one 32,768 ahead)."""
    key = keyring.mac_key(member_of(receiver))
    if key is None:
        raise ValueError(f"this key file holds no key of agent {receiver}")
    return mac(key, _delivery_msg(keyring, receiver, attachment, data))[:TAG_BYTES]


def check_delivery(keyring: Keyring, receiver: int, attachment: bytes, data: bytes) -> bytes:
    """The delivery attachment without its tag, if the tag is netsim's; AuthError otherwise."""
    if len(attachment) <= TAG_BYTES:
        raise AuthError("unauthenticated", "delivery without a tag")
    head, tag = attachment[:-TAG_BYTES], attachment[-TAG_BYTES:]
    key = keyring.mac_key(member_of(receiver))
    if key is None or not hmac.compare_digest(
            tag, mac(key, _delivery_msg(keyring, receiver, head, data))[:TAG_BYTES]):
        raise AuthError("bad-delivery", f"to {receiver}")
    return head


NONCE_CHARS = 32  # a query's nonce: 16 random bytes, in hex


def query_nonce() -> str:
    """The nonce a stats or control query carries: only an answer holding it, under its sender's
    seal, answers this query (issue 26, finding 3: captured answers were taken)."""
    return secrets.token_hex(NONCE_CHARS // 2)


def nonce_of(payload) -> str:
    """The nonce a query carried (its payload, Zenoh ZBytes or bytes), '' if none fits."""
    raw = payload.to_bytes() if hasattr(payload, "to_bytes") else bytes(payload or b"")
    text = raw[:NONCE_CHARS].decode("ascii", "replace")
    return text if len(raw) == NONCE_CHARS and all(c in "0123456789abcdef" for c in text) else ""


def _open_reply(opener: Opener | None, key: str, payload: bytes, sender: int, nonce: str | None):
    """A Reply on `key` sealed by `sender`, its envelope's src `sender`, holding `nonce` (None:
    not checked): (the reply, its data without the nonce). AuthError otherwise."""
    from swarmloc import wire
    from swarmloc.wire.messages import Reply

    if opener is not None:
        payload, _ = opener.open(payload, key, sender)
    try:
        env = wire.decode(payload, expect=(Reply,))
    except wire.WireError as exc:
        raise AuthError("malformed", str(exc)) from None
    if env.src != sender:
        raise AuthError("src-mismatch", f"src {env.src} on {key}")
    data = env.body.data if isinstance(env.body.data, dict) else {}
    if nonce is not None and data.get("nonce") != nonce:
        raise AuthError("stale-nonce", f"the answer of {sender} to another request")
    return env.body, {k: v for k, v in data.items() if k != "nonce"}


def open_stats_reply(opener: Opener | None, key: str, payload: bytes, nonce: str) -> tuple[int, dict]:
    """(agent id, stats) of an agent's answer to the stats query that carried `nonce`: on that
    agent's key, signed by it, its envelope's src, holding the nonce. AuthError otherwise, with
    the reason (a ValueError)."""
    from swarmloc import wire

    try:
        aid = wire.Keys.agent_of(key)
    except ValueError:
        raise AuthError("unknown-agent", key) from None
    return aid, _open_reply(opener, key, payload, aid, nonce)[1]


def open_control_reply(opener: Opener | None, key: str, payload: bytes, nonce: str):
    """netsim's Reply to the control request that carried `nonce`: sealed by netsim for this
    operator (the opener's `me`) on `key`, fresh, holding the nonce (issue 26: a captured reply
    was accepted within 60 s). AuthError otherwise. Its data comes back without the nonce; an
    unsealed swarm's answer (no opener) is not held to the nonce."""
    from msgspec.structs import replace

    reply, data = _open_reply(opener, key, payload, NETSIM, nonce if opener is not None else None)
    return replace(reply, data=data)
