"""The wire: key expressions, the MessagePack envelope and validated decoding.

Everything that crosses a process boundary is encoded and decoded here, so netsim, the agent
daemon and any other implementation agree by construction. docs/wire.md is the spec; this
package is its executable form. No Zenoh import: keys are plain strings, sessions live in the
processes.

The room: this module (the codec: envelope, encode/decode, key expressions, Zenoh settings),
schema.py (field specs and the message registry), messages.py (every message type), auth.py
(frame seals), limits.py (bounded inboxes and per-sender rate limits for the drivers).
"""

from __future__ import annotations

import json
import math
import struct
from typing import Any, ClassVar

import msgspec

# messages registers every type in REGISTRY, which decoding looks frame types up in.
from swarmloc.wire import messages as _messages  # noqa: F401
from swarmloc.wire.schema import (
    ENCODER,
    MAX_FRAME_BYTES,
    MAX_ID,
    MAX_WIRE_BYTES,
    REGISTRY,
    SCHEMA_VERSION,
    SEAL_TRAILERS,
    Array,
    FrameTooLarge,
    Message,
    WireError,
    _arrays,
    _text,
    decode_body,
    frame_decoder,
    max_bytes,
    message,
    parses,
)

# The front door: the codec below, plus the schema's names a caller needs to read or build frames.
__all__ = ["SCHEMA_VERSION", "MAX_FRAME_BYTES", "MAX_WIRE_BYTES", "MAX_ID", "ZENOH_MAX_MESSAGE_BYTES", "REGISTRY",
           "WireError", "FrameTooLarge", "Array", "Message", "message", "max_bytes", "decode_body", "Envelope",
           "encode", "decode", "Keys", "zenoh_config", "key_limit", "bounded", "publisher_options", "encode_send_time",
           "decode_send_time", "encode_delivery", "decode_delivery"]


class Envelope(msgspec.Struct, frozen=True, gc=False):
    """What every payload on the wire is: who sent which message, in which order, to whom."""

    type: str
    src: int
    seq: int
    body: Any
    dst: int | None = None  # radio frames only: None means broadcast

    KEYS: ClassVar[frozenset] = frozenset({"v", "type", "src", "seq", "dst", "body"})


class _Out(msgspec.Struct, gc=False):
    """The envelope as the encoder writes it: these six keys, in this order. Not tracked by the
    garbage collector (cheaper to make, once a frame): it lives for one call."""

    v: int
    type: str
    src: int
    seq: int
    dst: Any
    body: Any


class _In(msgspec.Struct, forbid_unknown_fields=True):
    """The envelope as the decoder reads it: only `body` is required to call it one; the header
    fields are checked below in the spec's order (docs/wire.md, section 4), and the body is left
    as MessagePack bytes until the type is known, since the type name lives in the envelope and
    not in the body (no msgspec tagged union can key on it)."""

    body: msgspec.Raw
    v: Any = None
    type: Any = None
    src: Any = None
    seq: Any = None
    dst: Any = None


_ENVELOPE = msgspec.msgpack.Decoder(_In)


_FRAMES = frame_decoder(Envelope)  # every type is registered (messages, above): decode's fast path
# ... and by `expect`: a frame of a type not expected is refused at its tag, its body unread.
_FRAMES_FOR: dict[tuple, msgspec.msgpack.Decoder] = {}


def _frames_for(expect):
    if type(expect) is not tuple or len(_FRAMES_FOR) >= 64:  # not a tuple or too many kinds: all types
        return _FRAMES
    d = _FRAMES_FOR[expect] = frame_decoder(Envelope, expect) or _FRAMES
    return d


def encode(msg, src: int, seq: int, dst: int | None = None) -> bytes:
    # int() only for what is no int already (a numpy integer, a bool): a call costs as much as
    # a tenth of a small frame's encoding.
    return ENCODER.encode(_Out(SCHEMA_VERSION, msg.TYPE, src if src.__class__ is int else int(src),
                               seq if seq.__class__ is int else int(seq), dst, msg))


def _int(v, path: str, lo: int, hi: int) -> int:
    if type(v) is not int:  # also rejects bool, an int subclass
        raise WireError(f"{path}: expected int, got {type(v).__name__}")
    if v < lo or v > hi:
        raise WireError(f"{path}: {v} out of range [{lo}, {hi}]")
    return v


def _envelope(data: bytes):
    try:
        return _ENVELOPE.decode(data)
    except msgspec.ValidationError:
        parses(data)
        raise WireError("not an envelope") from None
    except Exception as exc:  # msgspec.DecodeError, or a parser limit (nesting) of any kind
        raise WireError(f"not MessagePack: {_text(exc)}") from None


def _header(env: _In, size: int, expect):
    """The frame's type, once the header is checked in the spec's order (docs/wire.md, section 4)."""
    if type(env.v) is not int or env.v != SCHEMA_VERSION:
        raise WireError(f"schema version {env.v!r} not supported")
    cls = REGISTRY.get(env.type) if isinstance(env.type, str) else None
    if cls is None:
        raise WireError(f"unknown message type {env.type!r}")
    if size > cls.MAX_BYTES:
        raise FrameTooLarge(f"frame of {size} bytes exceeds {cls.MAX_BYTES} ({cls.TYPE})")
    if expect is not None and cls not in expect:
        raise WireError(f"message type {cls.TYPE!r} not expected here")
    _int(env.src, "src", 0, MAX_ID)
    _int(env.seq, "seq", 0, 2**63 - 1)
    if env.dst is not None:
        _int(env.dst, "dst", 0, MAX_ID)
    return cls


def decode(data: bytes, expect: tuple[type, ...] | None = None, body: bool = True) -> Envelope:
    """Validate and decode a frame; raises WireError naming the problem.

    body=False checks the envelope only and leaves the body as its MessagePack bytes (a
    msgspec.Raw, for `decode_body`): for a router (netsim) that needs src, dst and seq but
    leaves the content to the receiver."""
    if data.__class__ is not bytes:
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise WireError("payload is not bytes")
        if len(data) > MAX_WIRE_BYTES:
            raise FrameTooLarge(f"frame of {len(data)} bytes exceeds {MAX_WIRE_BYTES}")
        data = bytes(data)
    elif len(data) > MAX_WIRE_BYTES:
        raise FrameTooLarge(f"frame of {len(data)} bytes exceeds {MAX_WIRE_BYTES}")
    if body:
        try:
            f = (_FRAMES if expect is None else _FRAMES_FOR.get(expect) or _frames_for(expect)).decode(data)
        except Exception:
            pass  # refused, or a sealed frame: the checks below, in the spec's order, say why
        else:
            cls = f.CLS
            if len(data) <= cls.MAX_BYTES and (expect is None or cls in expect):
                env = f.OPEN(f)
                if env is None:
                    _arrays(f.body, cls.PLAN, "body")  # the spec's checks of the arrays, which name a refusal
                    env = Envelope(cls.TYPE, f.src, f.seq, f.body, f.dst)
                return env
    size = len(data)  # the frame's, without a seal's trailer
    try:
        env = _ENVELOPE.decode(data)
    except msgspec.ValidationError:  # a DecodeError too: first
        parses(data)  # the spec's order: MessagePack as a whole first, then an envelope
        raise WireError("not an envelope") from None
    except msgspec.DecodeError as exc:
        # A sealed frame (swarmloc/wire/auth.py) read by someone without the key, or not checking
        # it (a monitor): the envelope before its trailer. Receivers that must believe a
        # frame open it first, which checks the trailer.
        trailer = SEAL_TRAILERS.get(data[-2:], 0)
        if "trailing characters" not in str(exc) or not trailer or size <= trailer:
            raise WireError(f"not MessagePack: {_text(exc)}") from None
        size -= trailer
        env = _envelope(data[:size])
    except Exception as exc:  # a parser limit (nesting) of any kind
        raise WireError(f"not MessagePack: {type(exc).__name__}") from None
    src, seq, dst, t = env.src, env.seq, env.dst, env.type
    cls = REGISTRY.get(t) if type(t) is str else None
    if (cls is None or env.v != SCHEMA_VERSION or type(env.v) is not int or size > cls.MAX_BYTES
            or (expect is not None and cls not in expect) or type(src) is not int or not 0 <= src <= MAX_ID
            or type(seq) is not int or not 0 <= seq < 2**63
            or (dst is not None and (type(dst) is not int or not 0 <= dst <= MAX_ID))):
        parses(data[:size])  # the spec's order: a frame that is no MessagePack is refused as such first
        _header(env, size, expect)  # raises, naming the first thing wrong
    if not body:
        # The body is MessagePack as a whole even for a router: parsing it (no typed check)
        # refuses what a skip over it does not (a str that is no UTF-8, an impossible key).
        parses(env.body)
        return Envelope(cls.TYPE, src, seq, env.body, dst)
    try:
        msg = cls.DECODER.decode(env.body)
    except Exception:
        msg = decode_body(cls, env.body)  # raises, with the reason
    if cls.PLAN:
        _arrays(msg, cls.PLAN, "body")
    return Envelope(cls.TYPE, src, seq, msg, dst)


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


# Every session's ingress filter (Zenoh's low_pass_filter) drops a message larger than this
# before any subscriber sees it, and a router does not forward it: a hostile publisher cannot
# make an agent take megabytes (issue 26, finding 6: Zenoh 1.10 delivered 8 MB messages in
# spite of transport.link.rx.max_message_size). Frames between MAX_WIRE_BYTES and this still
# reach the callbacks, which count them as oversize without copying them.
ZENOH_MAX_MESSAGE_BYTES = 4 * MAX_WIRE_BYTES


def zenoh_config(mode: str, listen: list[str] = (), connect: list[str] = (), gossip: bool | None = None) -> str:
    """JSON5 for zenoh.Config.from_json5: no multicast scouting, bounded message size (an
    ingress filter on every session, below).

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
        "low_pass_filter": [{"flows": ["ingress"], "messages": ["put", "query", "reply"], "key_exprs": ["**"],
                             "size_limit": ZENOH_MAX_MESSAGE_BYTES}],
    }
    return json.dumps(cfg)


def key_limit(*types) -> int:
    """The most bytes a frame on a key that carries only message types `types` (classes, or
    type names) can take, sealed: the largest of their frame limits and a seal's longest
    trailer, at most the hard ceiling. A driver refuses a longer payload on that key by its
    length, before it costs a MAC (docs/security.md#limits)."""
    return min(MAX_WIRE_BYTES, max(map(max_bytes, types)) + max(SEAL_TRAILERS.values()))


def bounded(payload, limit: int = MAX_WIRE_BYTES) -> bytes | None:
    """A subscriber's payload (Zenoh ZBytes) as bytes, or None when it exceeds `limit` (the
    hard ceiling MAX_WIRE_BYTES, or the key's own, `key_limit`): an oversized frame is never
    copied out of Zenoh's buffer, let alone queued. (A frame within the limit but above its
    own type's is refused by `decode`.)"""
    return payload.to_bytes() if len(payload) <= limit else None


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
