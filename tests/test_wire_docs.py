"""docs/wire.md says what the code does: every registered type has a table (section 5) whose
rows name its fields in wire order, each with the type the schema gives it
(swarmloc.wire.schema.describe of its annotation), section 4's tables of limits give every
constant, list limit and per-type frame and array limit the schema sets, and the refusals
section 4 shows are the decoder's own words for those frames, so the spec cannot drift from
the code.

    python tests/test_wire_docs.py    # rewrites the type columns and the refusals from the code
"""

import copy
import math
import re
import sys
import typing
from pathlib import Path

import msgpack
import numpy as np

from swarmloc import wire
from swarmloc.wire import messages as M
from swarmloc.wire import schema
from swarmloc.wire.schema import describe, fields

DOC = Path(__file__).resolve().parent.parent / "docs" / "wire.md"
NAME = re.compile(r"^(?:\*\*)?`([\w.]+)`(?:\*\*)?")


def message_tables(text: str):
    """(type name, [(line index, [field names], type cell)]) for each table in section 5 whose
    header is `| field | type | ...`, named by the paragraph just above it."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("## 5."))
    end = next(i for i, line in enumerate(lines) if line.startswith("## 6."))
    i = start
    while i < end:
        if lines[i].startswith("| field | type |"):
            j = i - 1
            while j > start and not lines[j].strip():
                j -= 1
            while j > start and lines[j - 1].strip() and not lines[j - 1].startswith("|"):
                j -= 1  # the paragraph's first line
            m = NAME.match(lines[j])
            rows = []
            i += 2
            while i < end and lines[i].startswith("|"):
                cells = [c.strip() for c in lines[i].strip().strip("|").split("|")]
                rows.append((i, re.findall(r"`([^`]+)`", cells[0]), cells[1]))
                i += 1
            yield (m.group(1) if m else None), rows
        i += 1


def test_every_type_has_a_table_with_its_fields_and_types():
    documented: dict[str, str] = {}  # field -> type, for rows that refer to an earlier table
    seen = set()
    for name, rows in message_tables(DOC.read_text()):
        assert name in wire.REGISTRY, f"a field table under {name!r}, which is no message type"
        assert name not in seen, f"two tables for {name}"
        seen.add(name)
        schema = fields(wire.REGISTRY[name])
        listed = [f for _, names, _ in rows for f in names]
        assert listed == [f for f, _ in schema], f"{name}: the table lists {listed}, the schema {[f for f, _ in schema]}"
        want = dict(schema)
        for _, names, cell in rows:
            for f in names:
                text = describe(want[f])
                if cell:
                    assert cell == text, f"{name}.{f}: the table says {cell!r}, the schema {text!r}"
                else:  # "as above": the same field, documented alike for an earlier type
                    assert documented.get(f) == text, f"{name}.{f}: no type, and no earlier table gives it as {text!r}"
                documented[f] = text
    assert seen == set(wire.REGISTRY), f"types without a table: {sorted(set(wire.REGISTRY) - seen)}"


def section_4_tables(text: str) -> dict[str, list[list[str]]]:
    """Section 4's tables by their header's first cell: each a list of rows of cells."""
    body = text[text.index("\n## 4."):text.index("\n## 5.")]
    tables: dict[str, list[list[str]]] = {}
    for block in re.findall(r"((?:^\|.*\n)+)", body, re.M):
        rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in block.splitlines()]
        tables[rows[0][0]] = rows[2:]
    return tables


def _list_limit(t) -> int | None:
    """A list field's own limit on its length, if it sets one other than MAX_COLLECTION."""
    if typing.get_origin(t) is not typing.Annotated:
        return None
    base = typing.get_args(t)[0]
    if typing.get_origin(base) is typing.Annotated:
        return _list_limit(base)
    for m in t.__metadata__:
        if isinstance(m, schema.Meta) and typing.get_origin(base) is list and m.min_length != m.max_length:
            return None if m.max_length == schema.MAX_COLLECTION else m.max_length
    return None


def _array(t):
    return next((m for m in getattr(t, "__metadata__", ()) if isinstance(m, wire.Array)), None)


def _array_text(f: str, a) -> str:
    dims = ", ".join(f"{lo}..{hi}" for lo, hi in a.dims)
    return f'`{f}`: `"{a.dtype}"`, ' + ("square, " if a.square else "") + f"[{dims}], <= {a.max_elements}"


def test_the_limits_section_4_lists_are_the_schemas():
    tables = section_4_tables(DOC.read_text())
    listed = set()
    for names, value, _ in tables["constant"]:
        number = int(re.match(r"\d+", value).group())
        for name in re.findall(r"`([\w.]+)`", names):
            if "." not in name:
                assert getattr(schema, name) == number, f"{name}: the table says {number}"
                continue
            cls_name, f = name.split(".")
            t = dict(fields(getattr(M, cls_name)))[f]
            got = _array(t).max_elements if _array(t) else _list_limit(t)
            assert got == number, f"{name}: the table says {number}, the schema {got}"
            listed.add(name)
    own = {f"{cls.__name__}.{f}" for cls in wire.REGISTRY.values() for f, t in fields(cls) if _list_limit(t)}
    assert own <= listed, f"list limits the table leaves out: {sorted(own - listed)}"

    rows = {re.sub(r"`", "", name): (int(limit), arrays) for name, limit, arrays in tables["type"]}
    assert rows.pop("every other type") == (schema.MAX_FRAME_BYTES, "default")
    own = {}
    for name, cls in wire.REGISTRY.items():
        arrays = [(f, a) for f, t in fields(cls) if (a := _array(t)) is not None and
                  (a.dtype != "<f8" or a.max_elements != schema.MAX_ARRAY_ELEMENTS
                   or any(d != (0, schema.MAX_ARRAY_ELEMENTS) for d in a.dims))]
        if arrays or cls.MAX_BYTES != schema.MAX_FRAME_BYTES:
            own[name] = (cls.MAX_BYTES, "; ".join(_array_text(f, a) for f, a in arrays) or "default")
    assert rows == own, f"the per-type table says {rows}, the schema {own}"


def _frame(msg, change=None, **kw) -> bytes:
    tree = msgpack.unpackb(wire.encode(msg, 0, 36), strict_map_key=False)
    if change:
        change(tree)
    return msgpack.packb(tree, use_bin_type=True)


def _set(path, value):
    def change(tree):
        *head, last = path
        for p in head:
            tree = tree[p]
        if value is _DROP:
            del tree[last]
        else:
            tree[last] = value
    return change


_DROP = object()
_SENSORS = M.Sensors(3, 1.5, M.OdometryMsg(0.5, 0.437, 3.156, 0.5, 0.0007, 0.0146, 0.001), [M.RangeMsg(4, 116.23, 1.0)])
_CLOCK = M.Clock(0, 0.0, "lockstep", 0.5, 1.0)
_TRUTH = M.Truth(0, 0.0, np.zeros(2))
_BELIEF = M.NbpBelief(12, 1, False, np.array([[10.0, 20.5], [11.25, 19.75], [9.5, 21.0]]), np.array([0.5, 0.25, 0.25]),
                      np.eye(2) * 0.5)


def _arr(dtype, shape, n=None):
    size = 4 if dtype == "<f4" else 8
    return {"dtype": dtype, "shape": list(shape), "data": b"\0" * size * (math.prod(shape) if n is None else n)}


def _nan_weight(tree):
    tree["body"]["weights"]["data"] = np.array([0.5, math.nan, 0.5], "<f4").tobytes()


def _big_belief(tree):  # 20607 bytes: the frame limit of the type, not the ceiling
    tree["body"]["samples"] = _arr("<f4", (1, 1), 1)
    while (n := len(msgpack.packb(tree, use_bin_type=True))) != 20607:  # the bin header grows on the way
        data = tree["body"]["samples"]["data"]
        tree["body"]["samples"]["data"] = data + b"\0" * (20607 - n) if n < 20607 else data[:20607 - n]


# What section 4 shows: (what changed, the frame, the type expected on its key)
REFUSALS = [
    ("negative range", _frame(_SENSORS, _set(("body", "ranges", 0, "range"), -1.0)), None),
    ("NaN speed", _frame(_SENSORS, _set(("body", "odometry", "speed"), math.nan)), None),
    ("unknown body field", _frame(_SENSORS, _set(("body", "extra"), 1)), None),
    ("missing body field", _frame(_SENSORS, _set(("body", "t"), _DROP)), None),
    ("schema version 1", _frame(_CLOCK, _set(("v",), 1)), None),
    ("schema version true", _frame(_CLOCK, _set(("v",), True)), None),
    ("schema version 1.0", _frame(_CLOCK, _set(("v",), 1.0)), None),
    ("extra envelope key", _frame(_CLOCK, _set(("mac",), b"")), None),
    ("unknown type", _frame(_SENSORS, _set(("type",), "sensor")), None),
    ("negative src", _frame(_CLOCK, _set(("src",), -1)), None),
    ("src 2^31", _frame(_CLOCK, _set(("src",), 2**31)), None),
    ("sensors where clock expected", _frame(_SENSORS), (M.Clock,)),
    ("dtype <f4", _frame(_TRUTH, _set(("body", "state"), _arr("<f4", (2,)))), None),
    ("nbp.belief samples as <f8", _frame(_BELIEF, _set(("body", "samples"), _arr("<f8", (3, 2)))), None),
    ("nbp.belief bandwidth as <f4", _frame(_BELIEF, _set(("body", "bandwidth"), _arr("<f4", (2, 2)))), None),
    ("nbp.belief of 1001 samples", _frame(_BELIEF, _set(("body", "samples"), _arr("<f4", (1001, 3)))), None),
    ("nbp.belief samples of 4 columns", _frame(_BELIEF, _set(("body", "samples"), _arr("<f4", (3, 4)))), None),
    ("nbp.belief NaN weight", _frame(_BELIEF, _nan_weight), None),
    ("nbp.belief <f4 weights of 24 bytes", _frame(_BELIEF, _set(("body", "weights"), _arr("<f4", (3,), 6))), None),
    ("nbp.belief of 20607 bytes", _frame(_BELIEF, _big_belief), None),
    ("data too short", _frame(_TRUTH, _set(("body", "state"), _arr("<f8", (2,), 1))), None),
    ("2-D where 1-D expected", _frame(_TRUTH, _set(("body", "state"), _arr("<f8", (1, 2)))), None),
    ("4097 elements", _frame(_TRUTH, _set(("body", "state"), _arr("<f8", (4097,)))), None),
    ("5000 elements", _frame(_TRUTH, _set(("body", "state"), _arr("<f8", (5000,)))), None),
    ("clock with a 200-character mode", _frame(_CLOCK, _set(("body", "mode"), "x" * 200)), None),
    ("inf in data", _frame(_TRUTH, _set(("body", "state"), wire.Array(1).encode([0.0, math.inf]))), None),
    ("70000 bytes", b"\0" * 70000, None),
    ("not msgpack (byte 0xc1)", b"\xc1", None),
    ("one byte after the envelope", _frame(_CLOCK) + b"\0", None),
    ("a list", msgpack.packb([1, 2, 3]), None),
]
BLOCK = re.compile(r"(with one thing changed:\n\n```\n)(.*?)(\n```)", re.S)


def refusals() -> str:
    out = []
    for what, data, expect in REFUSALS:
        try:
            wire.decode(copy.copy(data), expect=expect)
        except wire.WireError as exc:
            out.append(f"{what:<38} -> {exc}")
        else:
            raise AssertionError(f"{what}: decodes")
    return "\n".join(out)


def test_the_refusals_shown_are_the_decoders():
    assert BLOCK.search(DOC.read_text()).group(2) == refusals()


def rewrite() -> None:
    lines = DOC.read_text().splitlines()
    for name, rows in message_tables("\n".join(lines)):
        if name not in wire.REGISTRY:
            continue
        want = dict(fields(wire.REGISTRY[name]))
        for i, names, cell in rows:
            texts = {describe(want[f]) for f in names if f in want}
            if cell and len(texts) == 1:
                cells = lines[i].split("|")
                cells[2] = f" {texts.pop()} "
                lines[i] = "|".join(cells)
    text = BLOCK.sub(lambda m: m.group(1) + refusals() + m.group(3), "\n".join(lines) + "\n")
    DOC.write_text(text)


if __name__ == "__main__":
    rewrite() if sys.argv[1:] != ["--check"] else test_every_type_has_a_table_with_its_fields_and_types()
