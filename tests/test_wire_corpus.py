"""The codec against a recorded corpus (tests/data/record_wire.py, recorded with the schema
layer the codec had before msgspec): every frame of in-process runs of each estimator family
decodes to the values recorded and encodes again to the same bytes, and every hostile input
gets the verdict recorded: accepted with the same value, or refused as the same error class."""

import gc
import gzip
import re
import sys
from collections import Counter
from pathlib import Path

import msgpack
import pytest

from swarmloc import wire

DATA = Path(__file__).with_name("data")
sys.path.insert(0, str(DATA))
from record_wire import canon, verdict  # noqa: E402


@pytest.fixture(scope="module")
def corpus():
    gc.disable()  # a million small containers: the collector would run through them again and again
    try:
        data = msgpack.unpackb(gzip.decompress((DATA / "wire_corpus.msgpack.gz").read_bytes()), strict_map_key=False)
        gc.freeze()  # and later, through the same ones
        return data
    finally:
        gc.enable()


# Types registered after the codec moved to msgspec: no hand-written decoder ever read them, so
# there is nothing to hold them to here; tests/test_fuzz.py's samples and hostile inputs cover them.
SINCE_MSGSPEC = {"rdl.meas", "rdl.req", "rdl.commit"}


def test_corpus_covers_every_type_and_family(corpus):
    types = Counter(cn[1] for _, _, _, cn in corpus["frames"])
    assert not set(types) & SINCE_MSGSPEC
    assert set(types) | SINCE_MSGSPEC == set(wire.REGISTRY)  # nested-only types through tests/test_fuzz.py's samples
    radio = Counter(case for case, key, _, _ in corpus["frames"] if key == "radio")
    assert radio["ukf-dcl/wang2019"] > 6000 and all(radio[c] > 0 for c in radio if c != "samples")


# The fast tier takes every 20th entry; the full tier (make test-all) every one.
STRIDES = [20, pytest.param(1, marks=pytest.mark.slow)]


@pytest.mark.parametrize("stride", STRIDES)
def test_recorded_frames_decode_to_the_recorded_values_and_encode_to_the_same_bytes(corpus, stride):
    for case, key, data, recorded in corpus["frames"][::stride]:
        env = wire.decode(data)
        assert canon(env) == recorded, (case, key)
        assert wire.encode(env.body, env.src, env.seq, env.dst) == data, (case, key)
        head = wire.decode(data, body=False)
        assert (head.type, head.src, head.seq, head.dst) == (env.type, env.src, env.seq, env.dst)


@pytest.mark.parametrize("stride", STRIDES)
def test_hostile_inputs_get_the_recorded_verdict(corpus, stride):
    """Accepted or refused alike, as the same error class, with or without the body; a reason
    that names the same thing. Where the old decoder checked a body's missing fields before
    its values and a frame has both faults, msgspec (one pass over the map) names the wrong
    value first: there the reason need only name a body field."""
    renamed = limited = 0
    for data, with_body, envelope_only in corpus["refusals"][::stride]:
        got = verdict(data)
        assert got[0] == with_body[0], (data[:80], with_body, got)
        if got[0] == "ok":
            assert got == with_body
        elif got[1] == "FrameTooLarge" and with_body[1] == "WireError":
            # Refused before its body since a type's frame limit became the most its schema lets
            # a frame take (issue 26): only a frame longer than that limit, by its size.
            size, limit, name = re.fullmatch(r"frame of (\d+) bytes exceeds (\d+) \((.+)\)", got[2]).groups()
            assert int(size) == len(data) > int(limit) == wire.max_bytes(name) < wire.MAX_FRAME_BYTES
            assert head_verdict(data)[:2] == ["err", "FrameTooLarge"]
            limited += 1
            continue
        else:
            assert got[1] == with_body[1], (data[:80], with_body, got)  # WireError or FrameTooLarge
            assert "\n" not in got[2]
            old, new = what(with_body[2]), what(got[2])
            if old != new:
                assert re.search(r"^body: missing fields|^body\.[^ ]*: unknown fields", with_body[2]) and \
                    new.startswith("body"), (with_body[2], got[2])
                renamed += 1
        got = head_verdict(data)
        assert got == (envelope_only[:2] if envelope_only[0] == "err" else ["ok", envelope_only[1][1:5]]), \
            (data[:80], envelope_only, got)
    assert renamed <= len(corpus["refusals"][::stride]) // 50
    print(f"{limited} of {len(corpus['refusals'][::stride])} refused by their type's frame limit")


def what(reason: str) -> str:
    """What a reason names: its kind for frame-level refusals, else the field path (a
    dictionary's key as [], an array's dtype, shape or data as the array)."""
    for kind in ("not MessagePack", "not an envelope", "schema version", "unknown message type", "frame of",
                 "message type", "payload is not bytes"):
        if reason.startswith(kind):
            return kind
    path = reason.split(": ")[0].replace(" (a key)", "").replace(".key", "")
    return re.sub(r"\[[^\]]*\]", "[]", re.sub(r"\.(shape|dtype|data)(\[\d+\])?$", "", path))


def head_verdict(data):
    """The envelope-only decode's verdict: its header, or its error's class (the body is left
    as MessagePack bytes, so it has no value to compare)."""
    try:
        env = wire.decode(data, body=False)
    except wire.WireError as exc:
        return ["err", type(exc).__name__]
    return ["ok", [env.type, env.src, env.seq, env.dst]]
