"""Wire codec: round trips of every message type, and rejection of bad frames with a reason."""

import math

import msgpack
import numpy as np
import pytest

from swarmloc import wire
from swarmloc.messages import Beacon, DclCommit, DclLog, DclToken, Done, EstimateMsg, OdometryMsg, RangeMsg, Sensors


def token(**over):
    fields = dict(k=3, epoch=0, key=[1, 2, 0], status=0, L=np.eye(4), Y=np.ones((4, 1)), Pz=np.eye(1), nu=np.zeros(1),
                  order=[1, 2], parent={2: 1}, gains={1: np.zeros((2, 1))}, versions={1: {1: 4, 2: 3}, 2: {1: 4, 2: 3}},
                  orphans=[], pending=[[1, 2, 0]])
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
    commit = DclCommit(3, 0, [1, 2, 0], 5, {1: 4, 2: 3}, t.L, t.Y, t.Pz, t.nu, {2: 1}, t.gains, [1], [], True, [])
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
        (_envelope({"cov": _COV, "k": 1, "version": {}}), "missing fields"),
        (_envelope({"cov": _COV, "k": 1, "version": {3: 0}, "position": _arr([0, 0])}), r"body.version\[3\]: 0 out of range"),
        (_envelope({"cov": _COV, "k": 1, "version": {}, "position": _arr([0, 0]), "extra": 1}), "unknown fields"),
        (b"\x91" * (wire.MAX_FRAME_BYTES + 1), "exceeds"),
        (_envelope({"cov": _COV, "k": 1, "version": {}, "position": {"dtype": "<f8", "shape": [2**63], "data": b""}}), "bad shape"),
    ],
)
def test_bad_frames_are_rejected_with_reason(data, reason):
    with pytest.raises(wire.WireError, match=reason):
        wire.decode(data)


def test_oversized_array_rejected_even_inside_frame_limit():
    big = {"dtype": "<f8", "shape": [5000], "data": b"\0" * 8 * 5000}
    with pytest.raises(wire.WireError, match="bad shape|exceed"):
        wire.decode(_envelope({"cov": _COV, "k": 1, "version": {}, "position": big}))


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
        wire.message("beacon")(type("Dup", (), {"__annotations__": {}}))
