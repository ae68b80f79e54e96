"""The wire's schema: every message type a msgspec Struct whose annotations are the spec.

A message type is a `Message` registered with @message("name") (swarmloc/wire/messages.py holds
them all). Its field annotations carry the bounds docs/wire.md states, as msgspec constraints
(`Annotated[int, Meta(ge=0, le=MAX_ID)]`), so msgspec's compiled decoder checks types, required
fields, unknown fields, ranges and lengths. Arrays (`Annotated[np.ndarray, Array(...)]`) travel
as {dtype, shape, data} maps, decoded by msgspec into a small typed struct (dtype, shape and each
dimension's range checked there) and turned into numpy afterwards, every array of a frame in one
vectorised pass (`_arrays`). Decoding never trusts a peer; every failure raises WireError with
the field path, which the receiver counts and logs before dropping the frame. Those checks, in
the spec's order, decide every refusal; a frame that passes them all is decoded by a faster
road to the same value (see "the fast path" below).

What msgspec cannot express is done here, each with its reason: a field with a default is
optional to msgspec's decoder, while on the wire every field is required (the defaults are
taken out of the struct and applied by the constructor, `_MessageMeta`); an array's element
count, squareness, data length, finiteness and bound are properties of the decoded value
(`_arrays`); a free-form field's depth and the absence of binary data (`_plain`); the message's
type name lives in the envelope, not in the body, so it is no msgspec tag (swarmloc.wire.decode
reads the envelope first).
"""

from __future__ import annotations

import math
import re
import sys
import typing
from typing import Annotated, Any, Literal, Union

import msgspec
import numpy as np
from msgspec import Meta
from msgspec.structs import force_setattr

SCHEMA_VERSION = 4  # 2: UAS sensor fields, clock speed, estimate NIS, fusion-centre payloads; 3: targets, turn rate, CSL-CTL payloads; 4: range-bearing to agents and landmarks, 4-part chain keys, core-coordinate transitions (phi) in UKF-DCL chains
MAX_FRAME_BYTES = 64 * 1024  # a message type's frame limit unless it declares its own (@message max_bytes)
# The hard ceiling: the largest frame limit any type may declare. Checked on the raw payload
# before parsing (and by `bounded`), because a frame's type is known only once it is parsed.
MAX_WIRE_BYTES = 64 * 1024
MAX_ARRAY_ELEMENTS = 4096  # an array's default limit on each dimension and on its element count
MAX_COLLECTION = 1024
MAX_ID = 2**31 - 1  # agent ids fit a signed 32-bit integer
SEAL_TRAILERS = {b"S2": 35, b"E2": 83}  # swarmloc.wire.auth's trailers by their last two bytes: MAC, signature
MAX_MAGNITUDE = 1e12
"""Largest absolute value of any float on the wire (scalar or array element), unless its field
says less: far beyond any position (m), time (s) or variance the estimators meet, and far
enough below float64's 1.8e308 that squaring and summing such values never overflows."""


class WireError(ValueError):
    """A frame that does not decode to a valid message; the reason names the field."""


class FrameTooLarge(WireError):
    """A frame above the hard ceiling (MAX_WIRE_BYTES) or above its type's own frame limit."""


# --------------------------------------------------------------------------- field types

class Named(str):
    """Annotation metadata: the name docs/wire.md gives a field type (msgspec ignores it)."""


Id = Annotated[int, Meta(ge=0, le=MAX_ID), Named("Id")]
Tick = Annotated[int, Meta(ge=0, le=2**40), Named("Tick")]
Float = Annotated[float, Meta(ge=-MAX_MAGNITUDE, le=MAX_MAGNITUDE)]
"""A float: finite (NaN and +-inf fail the bounds) and at most MAX_MAGNITUDE in absolute value;
a plain `float` annotation is one that may be non-finite. An int on the wire is taken as a float."""


def Int(lo: int | None = None, hi: int | None = None):  # noqa: N802 (reads as a type)
    return Annotated[int, Meta(ge=lo, le=hi)]


def FloatIn(lo: float = -MAX_MAGNITUDE, hi: float = MAX_MAGNITUDE):  # noqa: N802
    return Annotated[float, Meta(ge=lo, le=hi)]


def Str(max_len: int = 64):  # noqa: N802
    return Annotated[str, Meta(max_length=max_len)]


def ListOf(item, max_len: int = MAX_COLLECTION, length: int | None = None):  # noqa: N802
    return Annotated[list[item], Meta(min_length=length, max_length=max_len if length is None else length)]


def MapOf(key, value, max_len: int = MAX_COLLECTION):  # noqa: N802
    return Annotated[dict[key, value], Meta(max_length=max_len)]


class Array:
    """Float array field (`Annotated[np.ndarray, Array(...)]`) as {dtype, shape, data}: `ndim`
    fixed; `dtype` "<f8" (float64, the default) or "<f4" (float32), the only one accepted for
    the field; each dimension within its `dims` range (default 0..MAX_ARRAY_ELEMENTS each) and
    at most `max_elements` elements (default MAX_ARRAY_ELEMENTS); every value finite and at most
    `bound` (default MAX_MAGNITUDE) in absolute value.

    Constructing a message converts the value to the field's dtype: a float64 value in a "<f4"
    field is rounded to the nearest float32 (IEEE round to nearest, ties to even; numpy's
    astype), and one beyond the float32 range becomes +-inf, which the receiver refuses as
    non-finite (as for NaN in a "<f8" field, the encoder does not check). Decoding gives a
    writable numpy array of the field's dtype (float32 stays float32)."""

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
        self.bound, self.itemsize = bound, self.DTYPES[dtype]
        self.np_dtype, self.fmt = np.dtype(dtype), {"<f8": "d", "<f4": "f"}[dtype]  # numpy's, and memoryview's
        # What msgspec checks: the map's keys, the dtype string, the number of dimensions and
        # each one's range, data as bin. The rest is a property of the values (_arrays).
        shape = tuple[tuple(Annotated[int, Meta(ge=lo, le=hi)] for lo, hi in dims)] if ndim else tuple[()]
        self.wire = msgspec.defstruct(f"Array{ndim}", [("dtype", Literal[dtype]), ("shape", shape), ("data", bytes)],
                                      forbid_unknown_fields=True, frozen=True, gc=False)
        self.wire.SPEC = self

    def encode(self, v) -> dict:
        """The field's value as the wire's map (what a message's encoding writes for it)."""
        with np.errstate(over="ignore"):  # float64 beyond the float32 range: +-inf, documented above
            a = np.ascontiguousarray(v, dtype=self.dtype)
        return {"dtype": self.dtype, "shape": list(a.shape), "data": a.tobytes()}

    def describe(self) -> str:
        text = "array square" if self.square else f"array {self.ndim}-D"
        if self.bound != MAX_MAGNITUDE:
            text += f", values in [-{_num(self.bound)}, {_num(self.bound)}]"
        return text + (f', `"{self.dtype}"`' if self.dtype != "<f8" or any(d != (0, MAX_ARRAY_ELEMENTS)
                                                                         for d in self.dims) else "")


class _Plain:
    """Marks a free-form field (`Annotated[Any, PLAIN]`: control requests and replies)."""


PLAIN = _Plain()


# --------------------------------------------------------------------------- messages

_NO = object()  # no value given (constructor) / no default (field)
_FIELD = type(msgspec.field())
_UNION = (Union, type(int | None))


def _wire_type(t):
    """A field annotation as msgspec decodes it: each Array field becomes its wire struct."""
    origin, args = typing.get_origin(t), typing.get_args(t)
    if origin is Annotated:
        spec = next((m for m in t.__metadata__ if isinstance(m, Array)), None)
        if spec is not None:
            return spec.wire
        return Annotated[(_wire_type(args[0]), *t.__metadata__)]
    if origin in _UNION:
        return Union[tuple(_wire_type(a) for a in args)]
    if origin is list:
        return list[_wire_type(args[0])]
    if origin is dict:
        return dict[args[0], _wire_type(args[1])]
    if t is np.ndarray:
        raise TypeError("an array field needs an Array spec: Annotated[np.ndarray, Array(...)]")
    return t


def _coercer(t):
    """What the constructor applies to a field's value so that it encodes as its type: numpy
    and Python ints into a float field become floats, numpy ints ints, arrays the field's dtype."""
    origin = typing.get_origin(t)
    if origin is Annotated:
        spec = next((m for m in t.__metadata__ if isinstance(m, Array)), None)
        if spec is not None:
            def array(v, ndarray=np.ndarray, np_dtype=spec.np_dtype, dtype=spec.dtype):
                # what a sender passes, most often: an array of the field's dtype, C order
                if v.__class__ is ndarray and v.dtype is np_dtype and v.flags.c_contiguous:
                    return v
                return None if v is None else _as_array(v, dtype)
            array.takes_none = True
            return array
        return _coercer(typing.get_args(t)[0])
    if origin in _UNION:
        inner = [a for a in typing.get_args(t) if a is not type(None)]
        conv = _coercer(inner[0]) if len(inner) == 1 else None
        if conv is None or getattr(conv, "takes_none", False):  # an array's: one call, not two
            return conv
        return lambda v: None if v is None else conv(v)
    if t is float:
        return lambda v: v if v.__class__ is float else float(v)
    if t is int:
        return lambda v: v if v.__class__ is int else int(v)
    return None


_NP_DTYPES = {"<f8": np.dtype("<f8"), "<f4": np.dtype("<f4")}


def _as_array(v, dtype):
    if type(v) is np.ndarray and v.dtype == _NP_DTYPES[dtype] and v.flags.c_contiguous:
        return v
    with np.errstate(over="ignore"):  # float64 beyond the float32 range: +-inf (Array's docstring)
        return np.ascontiguousarray(v, dtype=dtype)


class _MessageMeta(msgspec.StructMeta):
    """Keeps a message's defaults out of msgspec (to its decoder a field with a default may be
    missing from a frame; on the wire none may) and applies them, and each field's coercion,
    when the message is constructed."""

    def __new__(mcls, name, bases, ns, **kw):
        hints = ns.get("__annotations__", {})
        defaults = {}
        for f in list(hints):
            if f in ns:
                v = ns.pop(f)
                defaults[f] = (v.default_factory, True) if isinstance(v, _FIELD) else (v, False)
        ns["__annotations__"] = {f: (_wire_type(t) if not isinstance(t, str) else t) for f, t in hints.items()}
        cls = super().__new__(mcls, name, bases, ns, **kw)
        cls._hints = {**getattr(cls, "_hints", {}), **hints}
        cls._defaults = {**getattr(cls, "_defaults", {}), **defaults}
        names = cls.__struct_fields__
        cls._index = {f: i for i, f in enumerate(names)}
        cls._coerce = [(i, c) for i, f in enumerate(names) if (c := _coercer(cls._hints[f])) is not None]
        return cls

    def __call__(cls, *args, **kw):
        if kw or len(args) != len(cls.__struct_fields__):
            vals = cls._fill(args, kw)
        else:  # every field given in order, what senders do: no defaults to apply
            vals = list(args)
        for i, c in cls._coerce:
            vals[i] = c(vals[i])
        return _struct_call(cls, *vals)

    def _fill(cls, args, kw) -> list:
        names = cls.__struct_fields__
        if len(args) > len(names):
            raise TypeError(f"{cls.__name__} takes {len(names)} fields, {len(args)} given")
        vals = [*args, *(_NO,) * (len(names) - len(args))]
        for f, v in kw.items():
            i = cls._index.get(f)
            if i is None or vals[i] is not _NO:
                raise TypeError(f"{cls.__name__}: {'unexpected' if i is None else 'repeated'} field {f!r}")
            vals[i] = v
        for i, v in enumerate(vals):
            if v is _NO:
                d = cls._defaults.get(names[i])
                if d is None:
                    raise TypeError(f"{cls.__name__}: missing field {names[i]!r}")
                vals[i] = d[0]() if d[1] else d[0]
        return vals


_struct_call = msgspec.StructMeta.__call__  # what super().__call__ is above, without making a super()


class Message(msgspec.Struct, metaclass=_MessageMeta, frozen=True, forbid_unknown_fields=True, gc=False):
    """Base of every message type. TYPE and MAX_BYTES are set by @message. Not tracked by the
    garbage collector (cheaper to create by the thousand): a message never refers to itself."""


REGISTRY: dict[str, type] = {}


def message(name: str, max_bytes: int | None = None):
    """Register a Message subclass as wire message type `name`. `max_bytes`: the type's frame
    limit (whole encoded frame, envelope included), at most the hard ceiling MAX_WIRE_BYTES; by
    default the most its schema lets a frame take (frame_bound), at most MAX_FRAME_BYTES."""
    if max_bytes is not None and not 0 < max_bytes <= MAX_WIRE_BYTES:
        raise TypeError(f"message type {name!r}: max_bytes {max_bytes} not in 1..{MAX_WIRE_BYTES}")

    def wrap(cls):
        if name in REGISTRY:
            raise TypeError(f"message type {name!r} registered twice")
        if not (isinstance(cls, type) and issubclass(cls, Message)):
            raise TypeError(f"message type {name!r}: {cls!r} is not a wire Message")
        if max_bytes is None:
            # The most the type's schema lets a frame take (strings, lists and arrays at their
            # bounds): a driver refuses a larger frame on the type's key before it costs a MAC
            # (limits.Door), and a limit is never looser than the schema.
            bound = frame_bound(name, cls)
            limit = MAX_FRAME_BYTES if bound is None else min(MAX_FRAME_BYTES, bound)
        else:
            limit = max_bytes
        cls.TYPE, cls.MAX_BYTES = name, limit
        cls.DECODER, cls.PLAN = _decoder(cls), _plan(cls)
        REGISTRY[name] = cls
        return cls

    return wrap


def encoded_bound(t) -> int | None:
    """The most bytes a value of field annotation `t` can take in MessagePack, or None when its
    schema bounds nothing (a free-form field, a string or list with no limit). Every header is
    taken at its widest (5 bytes), a string at 4 bytes a character (UTF-8)."""
    origin, args = typing.get_origin(t), typing.get_args(t)
    if origin is Annotated:
        spec = next((m for m in t.__metadata__ if isinstance(m, Array)), None)
        if spec is not None:  # {dtype, shape, data}: the keys and small values, the bin
            elements = min(spec.max_elements, math.prod(hi for _, hi in spec.dims))
            return 64 + 9 * spec.ndim + 5 + elements * spec.itemsize
        if any(m is PLAIN for m in t.__metadata__):
            return None
        meta = next((m for m in t.__metadata__ if isinstance(m, Meta)), Meta())
        base, inner = args[0], typing.get_origin(args[0])
        if base is str:
            return None if meta.max_length is None else 5 + 4 * meta.max_length
        if inner is list:
            item = encoded_bound(typing.get_args(base)[0])
            return None if item is None or meta.max_length is None else 5 + meta.max_length * item
        if inner is dict:
            k, v = (encoded_bound(a) for a in typing.get_args(base))
            return None if k is None or v is None or meta.max_length is None else 5 + meta.max_length * (k + v)
        return encoded_bound(base)
    if origin in _UNION:
        parts = [encoded_bound(a) for a in args]
        return None if None in parts else max(parts)
    if isinstance(t, type) and issubclass(t, Message):
        parts = [encoded_bound(h) for h in (t._hints[f] for f in t.__struct_fields__)]
        if None in parts:
            return None
        return 5 + sum(5 + len(f.encode()) + b for f, b in zip(t.__struct_fields__, parts))
    if t is type(None) or t is bool:
        return 1
    if t is int or t is float:
        return 9
    return None  # str, list or dict with no limit, Any


def frame_bound(name: str, cls) -> int | None:
    """The most bytes a whole frame of message type `name` (class `cls`) can take: the envelope
    (swarmloc.wire.encode's six keys, every number at its widest) around the largest body."""
    body = encoded_bound(cls)
    return None if body is None else 5 + sum(5 + len(k) for k in ("v", "type", "src", "seq", "dst", "body")) + \
        4 * 9 + 5 + len(name.encode()) + body


def max_bytes(msg) -> int:
    """The frame limit of a message's type (a message, its class, or a type name)."""
    if isinstance(msg, str):
        return REGISTRY[msg].MAX_BYTES
    return msg.MAX_BYTES


# --------------------------------------------------------------------------- encoding


_DTYPE_NAMES = {np.dtype("<f8"): "<f8", np.dtype("<f4"): "<f4"}
_F8, _F4 = np.dtype("<f8"), np.dtype("<f4")


class _ArrayOut(msgspec.Struct, gc=False):
    """An array as the encoder writes it: {dtype, shape, data} in this order."""

    dtype: str
    shape: tuple
    data: Any


def _enc_hook(v, ndarray=np.ndarray, f8=_F8, f4=_F4, out=_ArrayOut):
    """Arrays and numpy scalars, which msgspec does not encode itself. The constructor gives a
    message's arrays their field's dtype, C order; a decoded one is a C-order view already.
    (Called for every array of every frame: the defaults are locals, cheaper than globals.)"""
    if v.__class__ is ndarray:
        # The data a copy in C order, whatever the array's: for the small arrays of most frames
        # cheaper than a view of its buffer (v.data), and never a view msgspec cannot read. The
        # dtype by identity first: hashing one (the dict) costs more than the rest of this.
        t = v.dtype
        if t is f8:
            return out("<f8", v.shape, v.tobytes())
        if t is f4:
            return out("<f4", v.shape, v.tobytes())
        name = _DTYPE_NAMES.get(t)
        if name is None:  # not through the constructor (msgspec.structs.replace): as Array.encode would
            v, name = np.ascontiguousarray(v, "<f8"), "<f8"
        return out(name, v.shape, v.tobytes())
    if isinstance(v, np.ndarray):
        return _enc_hook(np.asarray(v))
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.floating):
        return float(v)
    if isinstance(v, np.bool_):
        return bool(v)
    raise TypeError(f"{type(v).__name__} cannot go on the wire")


ENCODER = msgspec.msgpack.Encoder(enc_hook=_enc_hook)


# --------------------------------------------------------------------------- decoding

_ARRAY, _BLOCKS, _NESTED, _LIST, _PLAIN = range(5)
_PLANS: dict[type, list] = {}
_DECODERS: dict[type, msgspec.msgpack.Decoder] = {}
_ANY = msgspec.msgpack.Decoder()


def _plan(cls) -> list:
    """Where a message type's arrays, nested messages with arrays and free-form fields are: what
    the pass after msgspec's decode visits (nothing, for most types)."""
    if cls in _PLANS:
        return _PLANS[cls]
    plan = []
    for f in cls.__struct_fields__:
        kind = _kind(cls._hints[f])
        if kind is not None:
            plan.append((f, *kind))
    _PLANS[cls] = plan
    return plan


def _kind(t):
    origin, args = typing.get_origin(t), typing.get_args(t)
    if origin is Annotated:
        spec = next((m for m in t.__metadata__ if isinstance(m, Array)), None)
        if spec is not None:
            return _ARRAY, spec
        if any(m is PLAIN for m in t.__metadata__):
            return _PLAIN, None
        return _kind(args[0])
    if origin in _UNION:
        kinds = [k for a in args if a is not type(None) and (k := _kind(a)) is not None]
        return kinds[0] if kinds else None
    if origin is list:
        inner = _kind(args[0])
        return None if inner is None else (_LIST, inner[1]) if inner[0] == _NESTED else None
    if origin is dict:
        inner = _kind(args[1])
        return None if inner is None else (_BLOCKS, inner[1]) if inner[0] == _ARRAY else None
    if isinstance(t, type) and issubclass(t, Message):
        return (_NESTED, t) if _plan(t) else None
    return None


def _decoder(cls) -> msgspec.msgpack.Decoder:
    d = _DECODERS.get(cls)
    if d is None:
        d = _DECODERS[cls] = msgspec.msgpack.Decoder(cls)
    return d


_ARRAY_PART = re.compile(r"^(.+)\.(dtype|shape|data)((?:\[\d+\])?)$")
_AT = re.compile(r"^(.*?)(?: - at `(?:key` in `)?\$(.*?)`)?$")


_BOUND = re.compile(r"^Expected `(int|float)` (>=|<=) (\S+)$")
_STEP = re.compile(r"\.(\w+)|\[(\d+)\]")
_FIELD_ERROR = re.compile(r"^Object (missing required|contains unknown) field `(.*)`$")


def _reason(exc: Exception, path: str, body=None) -> str:
    """msgspec's error as one line naming the field: `<path>: <what>`, in the words the spec
    uses (docs/wire.md, section 4): a value out of its bounds is named with the value, which
    msgspec's message leaves out, read again from the body (`body`; only for a refusal)."""
    text = _text(exc)
    m = _AT.match(text)
    what, where = m.group(1), m.group(2) or ""
    bound = _BOUND.match(what)
    if bound and "`key` in `" not in text and (v := _value_at(body, where)) is not _NO:
        kind, op, limit = bound.groups()
        what = "not finite" if kind == "float" and not math.isfinite(v) else \
            f"{v} {'below' if op == '>=' else 'above'} {limit}"
    elif field := _FIELD_ERROR.match(what):  # the name as msgspec quotes it, spaces and all
        what = f"{'missing' if field.group(1) == 'missing required' else 'unknown'} field '{field.group(2)}'"
    else:
        what = what.replace("`", "")
        what = what[:1].lower() + what[1:]
    if "`key` in `" in text:
        where += " (a key)"
    part = _ARRAY_PART.match(where)
    if part:  # inside an array's map: name the array, in the spec's words
        where, what = part.group(1), (f"dtype {what.split(' ', 3)[3]} not allowed" if part.group(2) == "dtype" and
                                      what.startswith("invalid enum value") else f"bad {part.group(2)}{part.group(3)}: {what}")
    return f"{path}{where}: {what}"


def _value_at(body, where: str):
    """The value at msgspec's path (`.field`, `[index]`) in a body's MessagePack, or _NO."""
    if body is None or not where or not _STEP.sub("", where) == "":
        return _NO  # no body, or a path through a map's values (`[...]`): their keys are not named
    try:
        v = _ANY.decode(body)
        for name, index in _STEP.findall(where):
            v = v[name] if name else v[int(index)]
    except Exception:
        return _NO
    return v if isinstance(v, (int, float)) and not isinstance(v, bool) else _NO


def _text(exc: Exception) -> str:
    """An error's message on one line: a peer's key or string in it (an unknown field's name)
    may hold any character, so control characters are escaped, not cut at."""
    text = str(exc) or type(exc).__name__
    return text if text.isprintable() else "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def parses(data) -> None:
    """Refuses data that is not exactly one MessagePack value (whatever its shape)."""
    try:
        _ANY.decode(data)
    except Exception as exc:  # msgspec.DecodeError, or a parser limit (nesting) of any kind
        raise WireError(f"not MessagePack: {_text(exc)}") from None


def decode_body(cls, body, path: str = "body"):
    """The message of type `cls` from its body's MessagePack bytes (msgspec.Raw, as
    swarmloc.wire.decode(..., body=False) leaves it, or bytes)."""
    try:
        msg = _decoder(cls).decode(body)
    except msgspec.ValidationError as exc:
        parses(body)  # the spec's order: a body that is no MessagePack is refused as such first
        raise WireError(_reason(exc, path, body)) from None
    except Exception as exc:  # msgspec.DecodeError, or a body that is no MessagePack at all
        raise WireError(f"not MessagePack: {_text(exc)}") from None
    plan = _plan(cls)
    if plan:
        _arrays(msg, plan, path)
    return msg


def _collect(msg, plan, found: list) -> None:
    """The arrays under a decoded message, as (owner, field or key, its wire struct, spec);
    free-form fields are checked on the way."""
    for f, kind, sub in plan:
        v = getattr(msg, f)
        if v is None:
            continue
        if kind == _ARRAY:
            found.append((msg, f, v, sub))
        elif kind == _BLOCKS:
            for k, a in v.items():
                found.append((v, k, a, sub))
        elif kind == _NESTED:
            _collect(v, _PLANS[sub], found)
        elif kind == _LIST:
            p = _PLANS[sub]
            for x in v:
                _collect(x, p, found)
        else:
            _plain(v, f"body.{f}")


def _where(msg, plan, path: str, target) -> str | None:
    """The field path of the array whose wire struct is `target` (for a refusal's reason)."""
    for f, kind, sub in plan:
        v = getattr(msg, f)
        if v is None:
            continue
        if kind == _ARRAY and v is target:
            return f"{path}.{f}"
        if kind == _BLOCKS:
            for k, a in v.items():
                if a is target:
                    return f"{path}.{f}[{k!r}]"
        elif kind == _NESTED:
            if (got := _where(v, _PLANS[sub], f"{path}.{f}", target)) is not None:
                return got
        elif kind == _LIST:
            for i, x in enumerate(v):
                if (got := _where(x, _PLANS[sub], f"{path}.{f}[{i}]", target)) is not None:
                    return got
    return None


def _arrays(msg, plan, path: str) -> None:
    """Every array of one frame from its wire struct to numpy, all of one dtype at once: one
    copy of their data, one check of finiteness and bounds over all of it (the smallest of
    their bounds: NaN and inf fail it), then each array, its element count, shape and data
    length checked, a writable view of its part of the copy. Anything unusual (a refusal, or
    values beyond the smallest bound) goes to the exact check, array by array."""
    found: list = []
    _collect(msg, plan, found)
    if not found:
        return
    dtype, bound = found[0][3].dtype, MAX_MAGNITUDE
    for it in found:
        spec = it[3]
        if spec.dtype != dtype:  # float32 and float64 arrays in one frame (nbp.belief): one pass each
            _exact(found, msg, plan, path)
            for dt in {it[3].dtype for it in found}:
                _views([it for it in found if it[3].dtype == dt], msg, plan, path, dt)
            return
        if spec.bound < bound:
            bound = spec.bound
    _views(found, msg, plan, path, dtype, bound)


# Up to this many values, math.hypot checks them faster than two numpy reductions; it reads them
# through a memoryview in the machine's byte order, which must then be the wire's.
_FAST_CHECK = 64 if sys.byteorder == "little" else 0


def _views(items, msg, plan, path, dtype, bound=None) -> None:
    spec0 = items[0][3]
    data = b"".join([it[2].data for it in items])
    if bound is not None and data:
        # All values within the smallest bound: hypot (>= every |value|; NaN and inf fail it)
        # for a few values, one min and max over them otherwise. Anything else (a bad data
        # length included) goes to the exact check, which refuses or finds them within their own.
        try:
            if len(data) <= _FAST_CHECK * spec0.itemsize:
                ok = math.hypot(*memoryview(data).cast(spec0.fmt)) <= bound
            else:
                buf = np.frombuffer(data, spec0.np_dtype)
                ok = -bound <= buf.min() and buf.max() <= bound
        except (TypeError, ValueError):  # not a whole number of values
            ok = False
        if not ok:
            _exact(items, msg, plan, path)
    ba = bytearray(data)  # the one copy: the arrays are writable views of it
    o = 0
    for owner, key, w, spec in items:
        shape, nbytes = w.shape, len(w.data)
        n = shape[0] if len(shape) == 1 else shape[0] * shape[1] if len(shape) == 2 else math.prod(shape)
        if nbytes != n * spec.itemsize or n > spec.max_elements or (spec.square and shape[0] != shape[1]):
            _exact(items, msg, plan, path)  # refuses, naming the array
            raise WireError(f"{_where(msg, plan, path, w)}: malformed array")  # not reached
        a = np.ndarray(shape, spec.np_dtype, ba, o)
        o += nbytes
        if type(owner) is dict:
            owner[key] = a
        else:
            force_setattr(owner, key, a)


def _exact(items, msg, plan, path) -> None:
    """Each array's own checks in the spec's order (docs/wire.md, section 3), refusing the first
    that fails with a reason that names it: the slow path, for frames refused."""
    for owner, key, w, spec in items:
        n = math.prod(w.shape)
        where = lambda: _where(msg, plan, path, w)  # noqa: E731 (found only for a refusal)
        if n > spec.max_elements:
            raise WireError(f"{where()}: {n} elements exceed {spec.max_elements}")
        if spec.square and len(set(w.shape)) != 1:
            raise WireError(f"{where()}: shape {list(w.shape)} not square")
        if len(w.data) != spec.itemsize * n:
            raise WireError(f"{where()}: data length does not match shape {list(w.shape)}")
    for owner, key, w, spec in items:
        a = np.frombuffer(w.data, spec.dtype)
        if a.size:
            m = np.abs(a).max()
            if not np.isfinite(m):
                raise WireError(f"{_where(msg, plan, path, w)}: non-finite values")
            if m > spec.bound:
                raise WireError(f"{_where(msg, plan, path, w)}: a value beyond +-{spec.bound:g}")


def _plain(v, path) -> None:
    """A free-form field: msgspec decodes it as any MessagePack; the limits on its depth and
    sizes and the ban on binary data and extensions are ours (msgspec has no such constraint
    for an untyped value)."""

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


# --------------------------------------------------------------------------- the fast path
# A frame that passes every check is decoded by msgspec in one pass, envelope and body (the
# envelope's `type` a tag), and its arrays made by a pass written out for its type: the checks
# above, one by one in the spec's order, cost more than the decode itself. Whatever this path
# does not take, it hands to them untouched; they decide (and name) every refusal.

Seq = Annotated[int, Meta(ge=0, le=2**63 - 1)]


_FRAME_STRUCTS: dict[type, type] = {}


def frame_decoder(envelope, types=None) -> msgspec.msgpack.Decoder | None:
    """Whole frames of the types registered so far (of those in `types`, if given: a frame of
    another type is refused at its tag, before its body is read), for swarmloc.wire.decode. A
    frame's struct has its message type (CLS) and OPEN, which makes it an `envelope` (see
    `_opener`). The decoder refuses all that the spec's checks refuse before the arrays, and
    more (a repeated key is checked at each occurrence), not in the spec's order and without the
    reason: its refusal only sends the frame to those checks. None when no type is left."""
    structs = []
    for name, cls in REGISTRY.items():
        if types is not None and cls not in types:
            continue
        if cls not in _FRAME_STRUCTS:
            _FRAME_STRUCTS[cls] = msgspec.defstruct(
                f"Frame_{name}", [("v", Literal[SCHEMA_VERSION]), ("src", Id), ("seq", Seq), ("body", cls),
                                  ("dst", Union[Id, None], None)],
                tag_field="type", tag=name, forbid_unknown_fields=True, gc=False,
                namespace={"CLS": cls, "OPEN": staticmethod(_opener(cls, envelope))})
        structs.append(_FRAME_STRUCTS[cls])
    # Always a union: msgspec requires a tag only to choose among structs, and decodes a frame
    # without `type` as the one struct it is given.
    return msgspec.msgpack.Decoder(Union[(*structs, _NoFrame)]) if structs else None


class _NoType:
    MAX_BYTES = -1  # what decode's fast path takes no frame for


_NoFrame = msgspec.defstruct("NoFrame", [], tag_field="type", tag="\0", forbid_unknown_fields=True,
                             namespace={"CLS": _NoType})


def _optional(t) -> bool:
    origin, args = typing.get_origin(t), typing.get_args(t)
    if origin is Annotated:
        return _optional(args[0])
    return origin in _UNION and type(None) in args


def _ordinary_tops(dtype: np.dtype, bound: float) -> bytes:
    """A translation table of the last byte of a `dtype` value on the wire (little-endian: its
    sign and the exponent's top bits) to a letter when every value with that last byte is at
    most `bound` in absolute value, whatever its other bytes (all finite values but the
    largest), and to a digit otherwise (NaN, inf, values near or beyond the bound)."""
    shift = 8 * (dtype.itemsize - 1)
    top = np.array([(b & 0x7F) << shift | ((1 << shift) - 1) for b in range(256)], f"<u{dtype.itemsize}")
    with np.errstate(invalid="ignore"):
        return b"".join(b"a" if ok else b"0" for ok in np.abs(top.view(dtype)) <= bound)


def _opener(cls, envelope):
    """A decoded frame of type `cls` to an `envelope`, its arrays made numpy by code written for
    the type (a loop over the plan costs a few times the arrays' own numpy work), or None,
    leaving the message untouched, for anything `_arrays` must look at (a refusal, a value
    near or beyond the smallest bound). Written out for a type whose arrays are its own fields
    or maps of them, none optional, all of one dtype (every radio frame of UKF-DCL, RDL, EKF-CI
    and CTL); any other type's arrays go through `_arrays`."""
    plan = _plan(cls)
    if not plan:
        def open(f, envelope=envelope, name=cls.TYPE):
            return envelope(name, f.src, f.seq, f.body, f.dst)
        return open
    if (any(k not in (_ARRAY, _BLOCKS) or _optional(cls._hints[f]) for f, k, _ in plan)
            or len({s.dtype for _, _, s in plan}) > 1):
        def open(f, envelope=envelope, name=cls.TYPE, plan=plan):
            _arrays(f.body, plan, "body")
            return envelope(name, f.src, f.seq, f.body, f.dst)
        return open
    env = {"Envelope": envelope, "TYPE": cls.TYPE}
    # compiled once a type, at import: a few milliseconds for all of them
    text = "\n    ".join(_written_out(cls, plan, "return Envelope(TYPE, f.src, f.seq, m, f.dst)", env))
    exec(text.replace("def open(f):", "def open(f, " + ", ".join(f"{k}={k}" for k in env) + "):"), env)  # noqa: S102
    env["open"].__doc__ = text  # what it does, for a reader
    return env["open"]


def _written_out(cls, plan, done: str, env: dict) -> list[str]:
    """The lines of `_opener`'s function for `cls`; the names they use are put in `env`."""
    specs = [s for _, _, s in plan]
    size, fmt, bound = specs[0].itemsize, specs[0].fmt, min(s.bound for s in specs)

    def checks(s: str, d: str, n: str, spec) -> str:
        """`return None` unless the array of shape `s` and data `d` is ordinary."""
        dims = [f"{s}[{j}]" for j in range(spec.ndim)]
        cond = [f"len({d}) != {n} * {size}"]
        if math.prod(hi for _, hi in spec.dims) > spec.max_elements:  # else msgspec's dims imply it
            cond.insert(0, f"{n} > {spec.max_elements}")
        if spec.square:
            cond += [f"{a} != {b}" for a, b in zip(dims, dims[1:])]
        return f"{n} = {' * '.join(dims) or '1'}\n    if " + " or ".join(cond) + ": return None"

    head, tail, make = [], [], []
    firm = []  # the data of the arrays every frame has, in order
    for i, (f, kind, spec) in enumerate(plan):
        if kind == _ARRAY:
            head.append(f"w{i} = m.{f}; s{i} = w{i}.shape; d{i} = w{i}.data\n    "
                        + checks(f"s{i}", f"d{i}", f"n{i}", spec))
            firm.append(f"d{i}")
            make.append(f"force_setattr(m, {f!r}, nd(s{i}, dt, ba, o)); o += len(d{i})")
    for i, (f, kind, spec) in enumerate(plan):
        if kind == _BLOCKS:
            tail.append(f"b{i} = m.{f}\n    for w in b{i}.values():\n        s = w.shape; d = w.data\n        "
                        + checks("s", "d", "n", spec).replace("\n", "\n    ") + "\n        data.append(d)")
            make.append(f"for k, w in b{i}.items(): b{i}[k] = nd(w.shape, dt, ba, o); o += len(w.data)")
    env.update(nd=np.ndarray, dt=specs[0].np_dtype, hypot=math.hypot, frombuffer=np.frombuffer,
               force_setattr=force_setattr, tops=_ordinary_tops(specs[0].np_dtype, bound))
    # Every value at once: first by its last byte on the wire, letters all when every value is
    # far enough within the bound (two calls in C for any number of values); else as _views
    # does it: hypot (>= every |value|; NaN and inf fail it) for a few values, one min and max
    # for more.
    return ["def open(f):", "m = f.body", *head, f"data = [{', '.join(firm)}]", *tail,
            "ba = bytearray().join(data)",
            f"if not ba[{size - 1}::{size}].translate(tops).isalpha():",
            f"    if len(ba) <= {_FAST_CHECK * size}:",
            f"        if not hypot(*memoryview(ba).cast({fmt!r})) <= {bound!r}: return None",
            "    else:",
            "        a = frombuffer(ba, dt)",
            f"        if not (-{bound!r} <= a.min() and a.max() <= {bound!r}): return None",
            "o = 0", *make, done]


# --------------------------------------------------------------------------- the spec's tables


def _num(x) -> str:
    if x < 0:
        return "-" + _num(-x)
    if isinstance(x, int) and x > 1024 and (x & (x - 1)) == 0:
        return f"2^{x.bit_length() - 1}"
    if isinstance(x, int) and x > 1024 and ((x + 1) & x) == 0:
        return f"2^{x.bit_length()}-1"
    if isinstance(x, float) and x == int(x):
        x = int(x)
        return f"1e{len(str(abs(x))) - 1}" if abs(x) >= 10**4 and str(abs(x)).rstrip("0") == "1" else str(x)
    return str(x)


def describe(t) -> str:
    """A field annotation as docs/wire.md's section 5 writes its type (tests/test_wire_docs.py)."""
    origin, args = typing.get_origin(t), typing.get_args(t)
    if origin is Annotated:
        spec = next((m for m in t.__metadata__ if isinstance(m, Array)), None)
        if spec is not None:
            return spec.describe()
        if any(m is PLAIN for m in t.__metadata__):
            return "Plain"
        name = next((m for m in t.__metadata__ if isinstance(m, Named)), None)
        if name is not None:
            return str(name)
        meta = next((m for m in t.__metadata__ if isinstance(m, Meta)), Meta())
        base = args[0]
        if base is float:
            if (meta.ge, meta.le) == (-MAX_MAGNITUDE, MAX_MAGNITUDE):
                return "float"
            if meta.le == MAX_MAGNITUDE:
                return f"float >= {_num(meta.ge)}"
            return f"float in [{_num(meta.ge)}, {_num(meta.le)}]"
        if base is int:
            return f"int >= {_num(meta.ge)}" if meta.le is None else f"int in [{_num(meta.ge)}, {_num(meta.le)}]"
        if base is str:
            return f"str <= {meta.max_length}"
        inner = typing.get_origin(base)
        if inner is list:
            item = typing.get_args(base)[0]
            text = f"list of {describe(item)}"
            if meta.min_length is not None and meta.min_length == meta.max_length:
                return "[" + ", ".join([describe(item)] * meta.max_length) + "]"
            return text + (f", <= {meta.max_length}" if meta.max_length != MAX_COLLECTION else "")
        if inner is dict:
            k, v = typing.get_args(base)
            return f"map {describe(k)} -> {describe(v)}" + (f", <= {meta.max_length}" if meta.max_length != MAX_COLLECTION
                                                             else "")
        return describe(base)
    if origin in _UNION:
        inner = [a for a in args if a is not type(None)]
        return f"{describe(inner[0])}, or nil"
    if isinstance(t, type) and issubclass(t, Message):
        return f"nested `{t.TYPE}`"
    if t is bool:
        return "bool"
    if t is float:
        return "float, may be non-finite"
    raise TypeError(f"no description for {t!r}")


def fields(cls) -> list[tuple[str, Any]]:
    """A message type's fields and their annotations, in wire order."""
    return [(f, cls._hints[f]) for f in cls.__struct_fields__]


# A chain key: (measurer, kind, target, index within the tick), swarmloc.node.keyed_measurements;
# chains run in this order.
ChainKey = Annotated[ListOf(Id, length=4), Named("ChainKey")]
# How many state-changing commits of each measurer a UKF-DCL node has applied (a version
# vector, zero entries left out). Two nodes with equal versions hold equal copies of every
# cross-covariance between them.
Version = Annotated[MapOf(Id, Int(1, 2**40)), Named("Version")]
