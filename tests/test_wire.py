"""Wire codec: round trips of every message type, and rejection of bad frames with a reason."""

import math

import msgpack
import numpy as np
import pytest

from swarmloc import wire
from swarmloc.wire.messages import (
    Beacon,
    DclCommit,
    DclLog,
    DclToken,
    Done,
    EstimateMsg,
    NbpBelief,
    OdometryMsg,
    RangeMsg,
    Sensors,
)


def token(**over):
    fields = dict(k=3, epoch=0, key=[1, 0, 2, 0], status=0, L=np.eye(4), Y=np.ones((4, 1)), Pz=np.eye(1), nu=np.zeros(1),
                  order=[1, 2], parent={2: 1}, gains={1: np.zeros((2, 1))}, versions={1: {1: 4, 2: 3}, 2: {1: 4, 2: 3}},
                  orphans=[], pending=[[1, 0, 2, 0]])
    fields.update(over)
    return DclToken(**fields)


def test_round_trip_preserves_floats_bit_for_bit():
    rng = np.random.default_rng(0)
    msg = token(L=rng.normal(size=(4, 4)), gains={1: rng.normal(size=(2, 1)), 7: rng.normal(size=(2, 1))})
    env = wire.decode(wire.encode(msg, src=1, seq=9, dst=2))
    assert (env.type, env.src, env.seq, env.dst) == ("dcl.token", 1, 9, 2)
    assert np.array_equal(env.body.L, msg.L)
    assert env.body.gains.keys() == {1, 7}
    assert np.array_equal(env.body.gains[7], msg.gains[7])


def test_nested_messages_round_trip():
    s = Sensors(4, 2.0, OdometryMsg(0.5, 1.1, 0.2, 0.5, 0.01), [RangeMsg(3, 41.5, 1.0)])
    assert wire.decode(wire.encode(s, 0, 1)).body == s


def test_commit_log_round_trips_with_versions():
    t = token()
    commit = DclCommit(3, 0, [1, 0, 2, 0], 5, {1: 4, 2: 3}, t.L, t.Y, t.Pz, t.nu, {2: 1}, t.gains, [1], [], True, [])
    body = wire.decode(wire.encode(DclLog(9, [commit, commit]), 2, 1, 1)).body
    assert len(body.commits) == 2 and body.commits[1].version == {1: 4, 2: 3} and body.commits[0].seq == 5
    assert np.array_equal(body.commits[0].gains[1], t.gains[1])


def _envelope(body, type_="beacon"):
    return msgpack.packb({"v": wire.SCHEMA_VERSION, "type": type_, "src": 1, "seq": 1, "dst": None, "body": body}, use_bin_type=True)


def _arr(a):
    return wire.Array(1).encode(np.asarray(a, float))


_COV = wire.Array(2).encode(np.eye(2))


@pytest.mark.parametrize(
    "data, reason",
    [
        (b"\x00\xff\x13garbage", "not MessagePack"),
        (msgpack.packb([1, 2, 3]), "not an envelope"),
        (msgpack.packb({"v": 1, "type": "beacon", "src": 1, "seq": 1, "body": {}}), "schema version"),
        (_envelope({"cov": _COV, "k": 1, "version": {}, "position": _arr([0, 0])}, "no.such.type"), "unknown message type"),
        (_envelope({"cov": _COV, "k": "one", "version": {}, "position": _arr([0, 0])}), "body.k: expected int"),
        (_envelope({"cov": _COV, "k": True, "version": {}, "position": _arr([0, 0])}), "body.k: expected int"),
        (_envelope({"cov": _COV, "k": 1, "version": {}, "position": _arr([0, math.nan])}), "body.position: non-finite"),
        (_envelope({"cov": _COV, "k": 1, "version": {}, "position": _arr([0, math.inf])}), "body.position: non-finite"),
        (_envelope({"cov": _COV, "k": 1, "version": {}, "position": wire.Array(2).encode(np.eye(2))}), "body.position: bad shape"),
        (_envelope({"cov": _COV, "k": 1, "version": {}, "position": {"dtype": "<i8", "shape": [2], "data": b"\0" * 16}}), "dtype"),
        (_envelope({"cov": _COV, "k": 1, "version": {}, "position": {"dtype": "<f8", "shape": [3], "data": b"\0" * 16}}), "data length"),
        (_envelope({"cov": _COV, "k": 1, "version": {}}), "body: missing field 'position'"),
        (_envelope({"cov": _COV, "k": 1, "version": {3: 0}, "position": _arr([0, 0])}), r"body.version\[...\]: expected int >= 1"),
        (_envelope({"cov": _COV, "k": 1, "version": {-3: 1}, "position": _arr([0, 0])}), r"body.version \(a key\): expected int >= 0"),
        (_envelope({"cov": _COV, "k": 1, "version": {}, "position": _arr([0, 0]), "extra": 1}), "body: unknown field 'extra'"),
        (_envelope({"cov": _COV, "k": 1, "version": {}, "position": _arr([0, 2e12])}), r"body.position: a value beyond \+-1e\+12"),
        (_envelope({"cov": wire.Array(2).encode(np.ones((2, 3))), "k": 1, "version": {}, "position": _arr([0, 0])}),
         r"body.cov: shape \[2, 3\] not square"),
        (b"\x91" * (wire.MAX_FRAME_BYTES + 1), "exceeds"),
        (_envelope({"cov": _COV, "k": 1, "version": {}, "position": {"dtype": "<f8", "shape": [2**63], "data": b""}}),
         r"body.position: bad shape\[0\]: 9223372036854775808 above 4096"),
    ],
)
def test_bad_frames_are_rejected_with_reason(data, reason):
    with pytest.raises(wire.WireError, match=reason):
        wire.decode(data)


def test_oversized_array_rejected_even_inside_frame_limit():
    big = {"dtype": "<f8", "shape": [5000], "data": b"\0" * 8 * 5000}
    with pytest.raises(wire.WireError, match=r"body.position: bad shape\[0\]: 5000 above 4096"):
        wire.decode(_envelope({"cov": _COV, "k": 1, "version": {}, "position": big}))


def test_a_peers_field_name_is_named_on_one_line():
    """An unknown key is the peer's string: any character, spaces and line breaks included
    (the fuzz corpus found a `da\\ra` key inside an array's map)."""
    good = {"cov": _COV, "k": 1, "version": {}, "position": _arr([0, 0])}
    for body, reason in [({**good, "a b": 1}, "body: unknown field 'a b'"),
                         ({**good, "x\ny": 1}, "body: unknown field 'x\\ny'"),
                         ({**good, "position": {"dtype": "<f8", "shape": [2], "da\ra": b"\0" * 16}},
                          "body.position: unknown field 'da\\ra'")]:
        with pytest.raises(wire.WireError) as err:
            wire.decode(_envelope(body))
        assert str(err.value) == reason


def test_unexpected_type_rejected_where_not_expected():
    data = wire.encode(Done(1, 0, 0), 1, 1)
    with pytest.raises(wire.WireError, match="not expected"):
        wire.decode(data, expect=(EstimateMsg,))


def test_random_bytes_never_raise_anything_but_wire_error():
    rng = np.random.default_rng(5)
    good = wire.encode(token(), 1, 1, 2)
    for i in range(2000):
        if i % 2:
            data = rng.bytes(int(rng.integers(0, 200)))
        else:  # corrupt a valid frame in a few places
            b = bytearray(good)
            for j in rng.integers(0, len(b), size=3):
                b[j] = int(rng.integers(0, 256))
            data = bytes(b)
        try:
            wire.decode(data)
        except wire.WireError:
            pass


def test_keys():
    k = wire.Keys("lab")
    assert k.radio_rx(3) == "swarmloc/lab/radio/rx/3"
    assert wire.Keys.agent_of("swarmloc/lab/agent/12/done") == 12
    with pytest.raises(ValueError):
        wire.Keys("a/b")


def test_beacon_registered_once():
    assert wire.REGISTRY["beacon"] is Beacon
    with pytest.raises(TypeError, match="registered twice"):
        wire.message("beacon")(type("Dup", (wire.Message,), {}))


# --------------------------------------------------------------------------- float32 arrays, per-type limits, dNBP


def belief(M=3, d=2, rng=None, **over):
    rng = np.random.default_rng(1) if rng is None else rng
    fields = dict(k=7, it=2, normal=True, samples=rng.normal(size=(M, d)).astype(np.float32),
                  weights=np.full(M, 1.0 / M, np.float32), bandwidth=np.eye(d) * 0.25)
    fields.update(over)
    return NbpBelief(**fields)


def _belief_body(**over):
    body = msgpack.unpackb(wire.encode(belief(), 1, 1), strict_map_key=False)["body"]
    body.update(over)
    return body


def test_f4_round_trip_bit_for_bit():
    rng = np.random.default_rng(2)
    samples = (rng.normal(size=(50, 3)) * 1e3).astype(np.float32)
    samples[0, 0] = np.float32(1e-45)  # a subnormal is finite
    msg = belief(samples=samples, weights=rng.random(50).astype(np.float32), bandwidth=np.eye(3))
    body = wire.decode(wire.encode(msg, 4, 1)).body
    assert body.samples.dtype == np.float32 and body.weights.dtype == np.float32 and body.bandwidth.dtype == np.float64
    assert body.samples.tobytes() == samples.tobytes() and body.weights.tobytes() == msg.weights.tobytes()
    assert body.samples.flags.writeable  # a copy, as for "<f8"
    raw = msgpack.unpackb(wire.encode(msg, 4, 1))["body"]["samples"]
    assert raw["dtype"] == "<f4" and raw["shape"] == [50, 3] and len(raw["data"]) == 4 * 150


def test_f8_values_in_an_f4_field_are_rounded_to_nearest_float32():
    x = np.array([[0.1, 1 / 3], [2.0**-30, -7.123456789]])
    body = wire.decode(wire.encode(belief(M=2, samples=x, weights=np.array([0.5, 0.5])), 1, 1)).body
    assert body.samples.tobytes() == x.astype(np.float32).tobytes()


@pytest.mark.parametrize("field, arr", [
    ("samples", wire.Array(2).encode(np.zeros((3, 2)))),  # "<f8" where "<f4" is declared
    ("weights", wire.Array(1).encode(np.ones(3))),
    ("bandwidth", wire.Array(2, dtype="<f4").encode(np.eye(2))),  # "<f4" where "<f8" is declared
])
def test_dtype_mismatch_refused(field, arr):
    with pytest.raises(wire.WireError, match=f"body.{field}: dtype '<f[48]' not allowed"):
        wire.decode(_envelope(_belief_body(**{field: arr}), "nbp.belief"))


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_f4_refused(bad):
    w = np.full(3, 1 / 3, np.float32)
    w[1] = bad
    with pytest.raises(wire.WireError, match="body.weights: non-finite"):
        wire.decode(wire.encode(belief(weights=w), 1, 1))
    with pytest.raises(wire.WireError, match="body.samples: non-finite"):  # float64 overflow becomes inf in float32
        wire.decode(wire.encode(belief(samples=np.array([[1e39, 0.0], [0, 0], [0, 0]])), 1, 1))


def test_f4_data_length_is_four_bytes_per_value():
    arr = {"dtype": "<f4", "shape": [3], "data": b"\0" * 24}  # 3 float64s' worth
    with pytest.raises(wire.WireError, match="body.weights: data length"):
        wire.decode(_envelope(_belief_body(weights=arr), "nbp.belief"))


def test_belief_of_1000_3d_samples_fits_its_limit_and_decodes():
    msg = belief(M=1000, d=3, k=2**40, it=255, weights=np.random.default_rng(3).random(1000))
    data = wire.encode(msg, wire.MAX_ID, 2**63 - 1, wire.MAX_ID)  # largest header values
    assert wire.max_bytes(msg) == wire.max_bytes(NbpBelief) == wire.max_bytes("nbp.belief") == 20480
    assert len(data) == 16265 <= wire.max_bytes(msg)
    body = wire.decode(data).body
    assert body.samples.shape == (1000, 3) and np.array_equal(body.samples, msg.samples)
    assert body.weights.tobytes() == msg.weights.astype(np.float32).tobytes()


def test_belief_shape_limits():
    for field, shape in [("samples", (1001, 3)), ("weights", (1001,)), ("samples", (3, 4)), ("samples", (0, 2)),
                         ("bandwidth", (4, 4)), ("bandwidth", (0, 0))]:
        arr = wire.Array(len(shape), dtype="<f8" if field == "bandwidth" else "<f4").encode(np.zeros(shape))
        with pytest.raises(wire.WireError, match=f"body.{field}: bad shape"):
            wire.decode(_envelope(_belief_body(**{field: arr}), "nbp.belief"))
    data = wire.encode(belief(M=1001, d=3), 1, 1)  # the encoder does not check; 20 KiB would fit it
    assert len(data) < wire.max_bytes(NbpBelief)
    with pytest.raises(wire.WireError, match=r"body.samples: bad shape\[0\]: 1001 above 1000"):
        wire.decode(data)


def test_type_frame_limit_checked_after_type_before_body():
    limit = wire.max_bytes(NbpBelief)
    pad = {"dtype": "<f4", "shape": [1], "data": b"\0" * 4}
    body = _belief_body(weights=pad, samples={"dtype": "<f4", "shape": [1, 1], "data": b"\0" * (limit + 1)})
    data = _envelope(body, "nbp.belief")
    assert limit < len(data) <= wire.MAX_WIRE_BYTES
    with pytest.raises(wire.FrameTooLarge, match=f"frame of {len(data)} bytes exceeds {limit} \\(nbp.belief\\)"):
        wire.decode(data)
    with pytest.raises(wire.FrameTooLarge):  # also for a router that leaves the body alone
        wire.decode(data, body=False)


def _widest(t):
    """The value of annotation t that encodes longest: every string, list and array at its
    bound (a string of 4-byte characters), every number at its widest valid value."""
    import typing

    from msgspec import Meta

    from swarmloc.wire import schema

    origin, args = typing.get_origin(t), typing.get_args(t)
    if origin is typing.Annotated:
        spec = next((m for m in t.__metadata__ if isinstance(m, wire.Array)), None)
        if spec is not None:
            shape, room = [], spec.max_elements
            for lo, hi in spec.dims:
                n = max(lo, min(hi, room)) if not spec.square or not shape else shape[0]
                shape.append(n)
                room //= max(n, 1)
            return np.full(shape, 1.0e-300)  # finite, inside every bound, all 8 (or 4) bytes used
        meta = next((m for m in t.__metadata__ if isinstance(m, Meta)), Meta())
        base, inner = args[0], typing.get_origin(args[0])
        if base is str:
            return "\U0001F600" * meta.max_length
        if base is int:
            return meta.le if meta.le is not None else 2**63 - 1
        if base is float:
            return float(meta.le if meta.le is not None and meta.le < schema.MAX_MAGNITUDE else 1.0e12)
        if inner is list:
            return [_widest(typing.get_args(base)[0]) for _ in range(meta.max_length)]
        if inner is dict:
            k, v = typing.get_args(base)
            top = _widest(k)
            return {top - i: _widest(v) for i in range(meta.max_length)}
        return _widest(base)
    if origin in (typing.Union, type(int | None)):
        return _widest(next(a for a in args if a is not type(None)))
    if isinstance(t, type) and issubclass(t, wire.Message):
        return t(**{f: _widest(h) for f, h in schema.fields(t)})
    return {bool: True, int: 2**63 - 1, float: 1.0e12}[t]


def test_a_types_frame_limit_is_the_most_its_schema_lets_a_frame_take():
    """Issue 26: a type's limit is its schema's bound (so a driver may refuse a longer frame on
    the type's key before its MAC): the widest valid frame of each type fits it and decodes."""
    from swarmloc.wire import schema

    assert wire.MAX_WIRE_BYTES == wire.MAX_FRAME_BYTES == 65536 and wire.ZENOH_MAX_MESSAGE_BYTES == 4 * 65536
    own = 0
    for name, cls in wire.REGISTRY.items():
        bound = schema.frame_bound(name, cls)
        if name == "nbp.belief":  # declares its own, above what its schema allows
            assert bound <= cls.MAX_BYTES == 20480
        else:
            assert cls.MAX_BYTES == (65536 if bound is None else min(65536, bound)), name
        if cls.MAX_BYTES < 65536:
            own += 1
            msg = _widest(cls)
            data = wire.encode(msg, wire.MAX_ID, 2**63 - 1, wire.MAX_ID)
            assert len(data) <= cls.MAX_BYTES, (name, len(data), cls.MAX_BYTES)
            wire.decode(data)
    assert own >= 15  # clock, done, event, time.echo, radio.nack, link ...: a few hundred bytes each
    assert wire.max_bytes("clock") < 300 and wire.max_bytes("done") < 300 and wire.max_bytes("event") < 300
    assert wire.key_limit("clock") == wire.max_bytes("clock") + 83  # an E2 trailer's room
    assert wire.key_limit("sensors", "clock") == wire.MAX_WIRE_BYTES


def test_other_types_keep_the_64_kib_limit():
    assert max(cls.MAX_BYTES for cls in wire.REGISTRY.values()) <= wire.MAX_WIRE_BYTES
    # a beacon of 60000 bytes (the array limit passed for once) is still a valid frame ...
    big = wire.Array(1, max_elements=10**6, dims=((0, 10**6),)).encode(np.zeros(7480))
    ok = _envelope({"cov": _COV, "k": 1, "version": {}, "position": big})
    assert 59000 < len(ok) <= 65536
    with pytest.raises(wire.WireError, match="body.position: bad shape"):  # ... refused only by its array limit
        wire.decode(ok)
    big = wire.Array(1, max_elements=10**6, dims=((0, 10**6),)).encode(np.zeros(8200))
    over = _envelope({"cov": _COV, "k": 1, "version": {}, "position": big})
    with pytest.raises(wire.FrameTooLarge, match=f"frame of {len(over)} bytes exceeds 65536$"):
        wire.decode(over)
    with pytest.raises(TypeError, match="max_bytes"):
        wire.message("too.big", max_bytes=wire.MAX_WIRE_BYTES + 1)
