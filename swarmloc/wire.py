"""The wire: key expressions, the MessagePack envelope and validated decoding.

Everything that crosses a process boundary is encoded and decoded here, so netsim, the agent
daemon and any other implementation agree by construction. docs/wire.md is the spec; this
module is its executable form. No Zenoh import: keys are plain strings, sessions live in the
processes.

A message type is a frozen dataclass registered with @message("name"); each field is
annotated with a Spec that both encodes and validates it. Decoding never trusts a peer:
types, shapes, finiteness and sizes are checked, and every failure raises WireError with the
field path, which the receiver counts and logs before dropping the frame.
"""

from __future__ import annotations

import dataclasses
import json
import math
import struct
import typing
from dataclasses import dataclass
from typing import Any, ClassVar

import msgpack
import numpy as np

SCHEMA_VERSION = 4  # 2: UAS sensor fields, clock speed, estimate NIS, fusion-centre payloads; 3: targets, turn rate, CSL-CTL payloads; 4: range-bearing to agents and landmarks, 4-part chain keys, core-coordinate transitions (phi) in UKF-DCL chains
MAX_FRAME_BYTES = 64 * 1024  # a message type's frame limit unless it declares its own (@message max_bytes)
# The hard ceiling: the largest frame limit any type may declare. Checked on the raw payload
# before parsing (and by `bounded`), because a frame's type is known only once it is parsed.
MAX_WIRE_BYTES = 64 * 1024
MAX_ARRAY_ELEMENTS = 4096  # an array's default limit on each dimension and on its element count
MAX_COLLECTION = 1024
MAX_ID = 2**31 - 1  # agent ids fit a signed 32-bit integer
SEAL_TRAILER, SEAL_MAGIC = 31, b"S1"  # swarmloc.auth's trailer: its size and last two bytes
MAX_MAGNITUDE = 1e12
"""Largest absolute value of any float on the wire (scalar or array element), unless its field
says less: far beyond any position (m), time (s) or variance the estimators meet, and far
enough below float64's 1.8e308 that squaring and summing such values never overflows."""


class WireError(ValueError):
    """A frame that does not decode to a valid message; the reason names the field."""


class FrameTooLarge(WireError):
    """A frame above the hard ceiling (MAX_WIRE_BYTES) or above its type's own frame limit."""


# --------------------------------------------------------------------------- field specs


class Spec:
    def encode(self, v: Any) -> Any:
        return v

    def decode(self, v: Any, path: str) -> Any:
        raise NotImplementedError


class Int(Spec):
    def __init__(self, lo: int | None = None, hi: int | None = None):
        self.lo, self.hi = lo, hi

    def encode(self, v):
        return int(v)

    def decode(self, v, path):
        if type(v) is not int:  # also rejects bool, an int subclass
            raise WireError(f"{path}: expected int, got {type(v).__name__}")
        if (self.lo is not None and v < self.lo) or (self.hi is not None and v > self.hi):
            raise WireError(f"{path}: {v} out of range [{self.lo}, {self.hi}]")
        return v


class Float(Spec):
    """A float; finite ones within [lo, hi] and at most MAX_MAGNITUDE in absolute value."""

    def __init__(self, finite: bool = True, lo: float | None = None, hi: float | None = None):
        self.finite, self.lo = finite, lo
        self.hi = MAX_MAGNITUDE if hi is None and finite else hi
        if finite and self.lo is None:
            self.lo = -MAX_MAGNITUDE

    def encode(self, v):
        return float(v)

    def decode(self, v, path):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise WireError(f"{path}: expected float, got {type(v).__name__}")
        v = float(v)
        if self.finite and not math.isfinite(v):
            raise WireError(f"{path}: not finite")
        if self.lo is not None and v < self.lo:
            raise WireError(f"{path}: {v} below {self.lo}")
        if self.hi is not None and v > self.hi:
            raise WireError(f"{path}: {v} above {self.hi}")
        return v


class Bool(Spec):
    def decode(self, v, path):
        if not isinstance(v, bool):
            raise WireError(f"{path}: expected bool, got {type(v).__name__}")
        return v


class Str(Spec):
    def __init__(self, max_len: int = 64):
        self.max_len = max_len

    def decode(self, v, path):
        if not isinstance(v, str):
            raise WireError(f"{path}: expected str, got {type(v).__name__}")
        if len(v) > self.max_len:
            raise WireError(f"{path}: string longer than {self.max_len}")
        return v


class Array(Spec):
    """Float array as {dtype, shape, data}: `ndim` fixed; `dtype` "<f8" (float64, the default) or
    "<f4" (float32), the only one accepted for the field; each dimension within its `dims` range
    (default 0..MAX_ARRAY_ELEMENTS each) and at most `max_elements` elements (default
    MAX_ARRAY_ELEMENTS); every value finite and at most `bound` (default MAX_MAGNITUDE) in
    absolute value.

    Encoding converts to the field's dtype: a float64 value in a "<f4" field is rounded to the
    nearest float32 (IEEE round to nearest, ties to even; numpy's astype), and one beyond the
    float32 range becomes +-inf, which the receiver refuses as non-finite (as for NaN in a "<f8"
    field, the encoder does not check). Decoding gives a writable numpy copy of the field's
    dtype (float32 stays float32)."""

    DTYPES = {"<f8": 8, "<f4": 4}

    def __init__(self, ndim: int, square: bool = False, dtype: str = "<f8",
                 dims: tuple[tuple[int, int], ...] | None = None, max_elements: int = MAX_ARRAY_ELEMENTS,
                 bound: float = MAX_MAGNITUDE):
        if dtype not in self.DTYPES:
            raise TypeError(f"array dtype {dtype!r} not supported (only {sorted(self.DTYPES)})")
        dims = tuple((0, MAX_ARRAY_ELEMENTS) for _ in range(ndim)) if dims is None else tuple(map(tuple, dims))
        if len(dims) != ndim or not all(0 <= lo <= hi for lo, hi in dims):
            raise TypeError(f"array dims {dims!r} must give ndim = {ndim} ranges lo <= hi")
        self.ndim, self.square, self.dtype, self.dims, self.max_elements = ndim, square, dtype, dims, max_elements
        self.bound = bound

    def encode(self, v):
        with np.errstate(over="ignore"):  # float64 beyond the float32 range: +-inf, documented above
            a = np.ascontiguousarray(v, dtype=self.dtype)
        return {"dtype": self.dtype, "shape": list(a.shape), "data": a.tobytes()}

    def decode(self, v, path):
        if not isinstance(v, dict) or set(v) != {"dtype", "shape", "data"}:
            raise WireError(f"{path}: expected array map with dtype, shape, data")
        if v["dtype"] != self.dtype:
            raise WireError(f"{path}: dtype {v['dtype']!r} not allowed (only {self.dtype!r})")
        shape = v["shape"]
        if not isinstance(shape, list) or len(shape) != self.ndim or not all(
            isinstance(s, int) and not isinstance(s, bool) and lo <= s <= hi for s, (lo, hi) in zip(shape, self.dims)
        ):
            want = ", ".join(f"{lo}..{hi}" for lo, hi in self.dims)
            raise WireError(f"{path}: bad shape {shape!r} (want {self.ndim} dims of {want})")
        if self.square and len(set(shape)) != 1:
            raise WireError(f"{path}: shape {shape} not square")
        count = math.prod(shape)
        if count > self.max_elements:
            raise WireError(f"{path}: {count} elements exceed {self.max_elements}")
        data = v["data"]
        if not isinstance(data, bytes) or len(data) != self.DTYPES[self.dtype] * count:
            raise WireError(f"{path}: data length does not match shape {shape}")
        a = np.frombuffer(data, dtype=self.dtype).reshape(shape).copy()
        if a.size:
            m = np.abs(a).max()  # one pass for both checks: NaN propagates into the max
            if not np.isfinite(m):
                raise WireError(f"{path}: non-finite values")
            if m > self.bound:
                raise WireError(f"{path}: a value beyond +-{self.bound:g}")
        return a


class ListOf(Spec):
    def __init__(self, item: Spec, max_len: int = MAX_COLLECTION, length: int | None = None):
        self.item, self.max_len, self.length = item, max_len, length

    def encode(self, v):
        return [self.item.encode(x) for x in v]

    def decode(self, v, path):
        if not isinstance(v, list):
            raise WireError(f"{path}: expected list, got {type(v).__name__}")
        if len(v) > self.max_len or (self.length is not None and len(v) != self.length):
            raise WireError(f"{path}: bad length {len(v)}")
        return [self.item.decode(x, f"{path}[{i}]") for i, x in enumerate(v)]


class MapOf(Spec):
    def __init__(self, key: Spec, value: Spec, max_len: int = MAX_COLLECTION):
        self.key, self.value, self.max_len = key, value, max_len

    def encode(self, v):
        return {self.key.encode(k): self.value.encode(x) for k, x in v.items()}

    def decode(self, v, path):
        if not isinstance(v, dict):
            raise WireError(f"{path}: expected map, got {type(v).__name__}")
        if len(v) > self.max_len:
            raise WireError(f"{path}: {len(v)} entries exceed {self.max_len}")
        return {self.key.decode(k, f"{path}.key"): self.value.decode(x, f"{path}[{k!r}]") for k, x in v.items()}


class Optional(Spec):
    def __init__(self, inner: Spec):
        self.inner = inner

    def encode(self, v):
        return None if v is None else self.inner.encode(v)

    def decode(self, v, path):
        return None if v is None else self.inner.decode(v, path)


class Nested(Spec):
    def __init__(self, cls: type):
        self.cls = cls

    def encode(self, v):
        return encode_body(v)

    def decode(self, v, path):
        return decode_body(self.cls, v, path)


class Plain(Spec):
    """Free-form msgpack data (control requests and replies): bounded size, no arrays."""

    def decode(self, v, path):
        def walk(x, depth):
            if depth > 6:
                raise WireError(f"{path}: nested too deep")
            if isinstance(x, dict):
                if len(x) > MAX_COLLECTION:
                    raise WireError(f"{path}: map too large")
                for k, y in x.items():
                    walk(k, depth + 1)
                    walk(y, depth + 1)
            elif isinstance(x, list):
                if len(x) > MAX_COLLECTION:
                    raise WireError(f"{path}: list too large")
                for y in x:
                    walk(y, depth + 1)
            elif not (x is None or isinstance(x, (bool, int, float, str))):
                raise WireError(f"{path}: {type(x).__name__} not allowed")

        walk(v, 0)
        return v


# --------------------------------------------------------------------------- registry

REGISTRY: dict[str, type] = {}


def message(name: str, max_bytes: int = MAX_FRAME_BYTES):
    """Register a dataclass as wire message type `name`; its Annotated specs define the body.
    `max_bytes`: the type's frame limit (whole encoded frame, envelope included), at most the
    hard ceiling MAX_WIRE_BYTES."""
    if not 0 < max_bytes <= MAX_WIRE_BYTES:
        raise TypeError(f"message type {name!r}: max_bytes {max_bytes} not in 1..{MAX_WIRE_BYTES}")

    def wrap(cls):
        cls = dataclass(frozen=True)(cls)
        hints = typing.get_type_hints(cls, include_extras=True)
        specs = {}
        for f in dataclasses.fields(cls):
            meta = getattr(hints[f.name], "__metadata__", ())
            spec = next((m for m in meta if isinstance(m, Spec)), None)
            if spec is None:
                raise TypeError(f"{cls.__name__}.{f.name} has no wire Spec")
            specs[f.name] = spec
        cls.TYPE = name
        cls.MAX_BYTES = max_bytes
        cls._specs = specs
        if name in REGISTRY:
            raise TypeError(f"message type {name!r} registered twice")
        REGISTRY[name] = cls
        return cls

    return wrap


def max_bytes(msg) -> int:
    """The frame limit of a message's type (a message, its class, or a type name)."""
    if isinstance(msg, str):
        return REGISTRY[msg].MAX_BYTES
    return msg.MAX_BYTES


def encode_body(msg) -> dict:
    return {name: spec.encode(getattr(msg, name)) for name, spec in msg._specs.items()}


def decode_body(cls, body, path="body"):
    if not isinstance(body, dict):
        raise WireError(f"{path}: expected map")
    specs = cls._specs
    extra = set(body) - set(specs)
    if extra:
        raise WireError(f"{path}: unknown fields {sorted(map(str, extra))}")
    missing = set(specs) - set(body)
    if missing:
        raise WireError(f"{path}: missing fields {sorted(missing)}")
    return cls(**{name: spec.decode(body[name], f"{path}.{name}") for name, spec in specs.items()})


@dataclass(frozen=True)
class Envelope:
    """What every payload on the wire is: who sent which message, in which order, to whom."""

    type: str
    src: int
    seq: int
    body: Any
    dst: int | None = None  # radio frames only: None means broadcast

    KEYS: ClassVar[frozenset] = frozenset({"v", "type", "src", "seq", "dst", "body"})


_SRC, _SEQ, _DST = Int(0, MAX_ID), Int(0, 2**63 - 1), Optional(Int(0, MAX_ID))  # every frame's header fields


def encode(msg, src: int, seq: int, dst: int | None = None) -> bytes:
    env = {"v": SCHEMA_VERSION, "type": msg.TYPE, "src": int(src), "seq": int(seq), "dst": dst, "body": encode_body(msg)}
    return msgpack.packb(env, use_bin_type=True)


def decode(data: bytes, expect: tuple[type, ...] | None = None, body: bool = True) -> Envelope:
    """Validate and decode a frame; raises WireError naming the problem.

    body=False checks the envelope only and leaves the body as raw msgpack data: for a
    router (netsim) that needs src, dst and seq but leaves the content to the receiver."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise WireError("payload is not bytes")
    if len(data) > MAX_WIRE_BYTES:
        raise FrameTooLarge(f"frame of {len(data)} bytes exceeds {MAX_WIRE_BYTES}")
    data = data if type(data) is bytes else bytes(data)
    size = len(data)  # the frame's, without a seal's trailer
    try:
        env = msgpack.unpackb(data, raw=False, strict_map_key=False, max_bin_len=MAX_WIRE_BYTES)
    except msgpack.ExtraData as exc:
        # A sealed frame (swarmloc/auth.py) read by someone without the key, or not checking
        # it (a monitor): the envelope before its trailer. Receivers that must believe a
        # frame open it first, which checks the trailer.
        if len(exc.extra) != SEAL_TRAILER or exc.extra[-2:] != SEAL_MAGIC:
            raise WireError("not MessagePack: ExtraData") from None
        env, size = exc.unpacked, len(data) - SEAL_TRAILER
    except Exception as exc:  # msgpack raises several unrelated exception types
        raise WireError(f"not MessagePack: {exc.__class__.__name__}") from None
    if not isinstance(env, dict) or not Envelope.KEYS.issuperset(env) or "body" not in env:
        raise WireError("not an envelope")
    if type(env.get("v")) is not int or env["v"] != SCHEMA_VERSION:
        raise WireError(f"schema version {env.get('v')!r} not supported")
    cls = REGISTRY.get(env.get("type")) if isinstance(env.get("type"), str) else None
    if cls is None:
        raise WireError(f"unknown message type {env.get('type')!r}")
    if size > cls.MAX_BYTES:
        raise FrameTooLarge(f"frame of {size} bytes exceeds {cls.MAX_BYTES} ({cls.TYPE})")
    if expect is not None and cls not in expect:
        raise WireError(f"message type {cls.TYPE!r} not expected here")
    src = _SRC.decode(env.get("src"), "src")
    seq = _SEQ.decode(env.get("seq"), "seq")
    dst = _DST.decode(env.get("dst"), "dst")
    return Envelope(cls.TYPE, src, seq, decode_body(cls, env["body"]) if body else env["body"], dst)


# --------------------------------------------------------------------------- key expressions


class Keys:
    """Key expressions of one swarm (docs/wire.md, "Keys")."""

    def __init__(self, swarm: str):
        if not swarm or any(c in swarm for c in "/*$#?"):
            raise ValueError(f"bad swarm name {swarm!r}")
        self.prefix = f"swarmloc/{swarm}"

    clock = property(lambda self: f"{self.prefix}/clock")
    control = property(lambda self: f"{self.prefix}/netsim/control")
    links = property(lambda self: f"{self.prefix}/netsim/links")
    events = property(lambda self: f"{self.prefix}/netsim/events")

    def sensors(self, aid: int | str) -> str:
        return f"{self.prefix}/agent/{aid}/sensors"

    def estimate(self, aid: int | str) -> str:
        return f"{self.prefix}/agent/{aid}/estimate"

    def done(self, aid: int | str) -> str:
        return f"{self.prefix}/agent/{aid}/done"

    def stats(self, aid: int | str) -> str:
        return f"{self.prefix}/agent/{aid}/stats"

    def command(self, aid: int | str) -> str:
        return f"{self.prefix}/agent/{aid}/command"

    def alive(self, aid: int | str) -> str:
        return f"{self.prefix}/agent/{aid}/alive"

    def radio_tx(self, aid: int | str) -> str:
        return f"{self.prefix}/radio/tx/{aid}"

    def radio_rx(self, aid: int | str) -> str:
        return f"{self.prefix}/radio/rx/{aid}"

    def truth(self, aid: int | str) -> str:
        return f"{self.prefix}/truth/{aid}"

    @staticmethod
    def agent_of(key: str) -> int:
        """The agent id in .../agent/<id>/... or .../radio/{tx,rx}/<id>."""
        parts = str(key).split("/")
        for i, p in enumerate(parts[:-1]):
            if p in ("agent", "tx", "rx", "truth"):
                return int(parts[i + 1])
        raise ValueError(f"no agent id in {key!r}")


# Zenoh refuses to reassemble a message larger than this for a client or peer session, so a
# hostile publisher cannot make an agent buffer megabytes; frames between MAX_WIRE_BYTES and
# this still reach the subscriber callbacks, which count them as oversize without copying them.
ZENOH_MAX_MESSAGE_BYTES = 4 * MAX_WIRE_BYTES


def zenoh_config(mode: str, listen: list[str] = (), connect: list[str] = (), gossip: bool | None = None) -> str:
    """JSON5 for zenoh.Config.from_json5: no multicast scouting, bounded message size.

    Scouting is off so a test's sessions never find a stranger's on the same machine. Gossip
    (a peer learns the others from those it connects to, and dials them) is on for peers
    unless `gossip` says otherwise.
    """
    cfg = {
        "mode": mode,
        "listen": {"endpoints": list(listen)},
        "connect": {"endpoints": list(connect)},
        "scouting": {"multicast": {"enabled": False},
                     "gossip": {"enabled": mode == "peer" if gossip is None else gossip}},
        "transport": {"link": {"rx": {"max_message_size": ZENOH_MAX_MESSAGE_BYTES}}},
    }
    return json.dumps(cfg)


def bounded(payload) -> bytes | None:
    """A subscriber's payload (Zenoh ZBytes) as bytes, or None when it exceeds the hard ceiling
    MAX_WIRE_BYTES: an oversized frame is never copied out of Zenoh's buffer, let alone queued.
    (A frame within the ceiling but above its own type's limit is refused by `decode`.)"""
    return payload.to_bytes() if len(payload) <= MAX_WIRE_BYTES else None


def publisher_options(zenoh, lossy: bool = False) -> dict:
    """Options of every swarmloc publisher, given the zenoh module (this module imports none).
    Reliable and blocking: with Zenoh's default (drop) a burst of small frames loses a quarter
    of them, and loss is the radio model's to decide, not the transport's. `lossy`: a physical
    radio's frames (direct mode), where loss is the network's and blocking would stall the sender."""
    cc = zenoh.CongestionControl.DROP if lossy else zenoh.CongestionControl.BLOCK
    return dict(congestion_control=cc, reliability=zenoh.Reliability.RELIABLE)


# Attachments (docs/wire.md, "Attachments"). An agent stamps each radio/tx frame with its send
# time; netsim stamps each frame it hands an agent with a per-receiver delivery number (so
# lockstep can tell "consumed what I delivered" from "consumed anything") and passes the send
# time on, so the receiver can measure the hop. Times are CLOCK_MONOTONIC seconds
# (time.perf_counter on Linux), comparable between processes of one machine only. In direct
# mode (no netsim) a radio/rx frame carries its sender's UNIX time instead, in the same format.
def encode_send_time(t: float) -> bytes:
    return struct.pack("<d", t)


def decode_send_time(b: bytes | None) -> float | None:
    return struct.unpack("<d", b)[0] if b is not None and len(b) == 8 else None


def encode_delivery(n: int, sent: float | None = None) -> bytes:
    return struct.pack("<Qd", n, math.nan if sent is None else sent)


def decode_delivery(b: bytes | None) -> tuple[int, float | None] | None:
    if b is None or len(b) != 16:
        return None
    n, sent = struct.unpack("<Qd", b)
    return n, (None if math.isnan(sent) else sent)


# Importing the wire must be enough to decode anything on it: register every message type.
from swarmloc import messages as _messages  # noqa: E402,F401
