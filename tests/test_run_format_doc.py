"""docs/run-format.md, "run.mcap": the standalone read_mcap.py of "Reading run.mcap without
swarmloc", taken from the doc as it stands, run on a small recording made in process, and the
channels of that recording against the doc's tables of wire and view channels.

The recording is the fast stand-in for netsim's (as in tests/test_recording.py): an in-process
lockstep run whose world frames (clock, sensors, truth, links, events), agents' frames (radio
frames sent and delivered, estimates, done) and view inputs (truth, estimates, a fault, events)
go to a Recorder on the keys netsim uses (swarmloc.wire.Keys)."""

import ast
import json
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
from mcap.reader import make_reader

from netsim.sim import Simulation
from swarmloc import wire
from swarmloc.experiment import recording as R
from swarmloc.experiment import scenario as S
from swarmloc.experiment.runner import InProcessRunner, make_nodes
from swarmloc.wire.messages import Clock, Done, EstimateMsg, Event, LinkMsg, Links, Truth

DOC = Path(__file__).resolve().parents[1] / "docs" / "run-format.md"
SWARM = "docrf"
ESTIMATOR = "ukf-dcl"
KILLED = 3  # its process "down" at ticks 2 and 3: its frames withheld, as netsim records them
FAULT = {"k": 2, "t": 1.0, "source": "scenario", "action": "cut", "link": [1, 2], "direction": "both"}
FAULT_TEXT = "t=1 s: cut link=[1,2] direction=both (scenario)"
NOT_RECORDED = {"command"}  # the doc's rows this planar run cannot have: a vehicle's actuator commands


def _section(text: str, heading: str) -> str:
    """From the heading line to the next heading of the same or a higher level."""
    level = heading.split(" ")[0]
    start = text.index(heading + "\n")
    nxt = re.compile(rf"^#{{1,{len(level)}}} ", re.M).search(text, start + len(heading) + 1)
    return text[start:nxt.start() if nxt else len(text)]


def _table(section: str) -> list[list[str]]:
    """The rows of the section's first Markdown table, its header and rule left out, as cells."""
    lines = [ln for ln in section.splitlines() if ln.startswith("|")]
    return [[c.strip() for c in ln.strip("|").split(" | ")] for ln in lines[2:]]


def _channel_pattern(cell: str) -> re.Pattern:
    """`.../agent/<id>/sensors` -> the key of any agent; `/metrics/<estimator>/<id>` likewise."""
    name = cell.strip("`")
    rx = re.escape(name.replace("...", f"swarmloc/{SWARM}", 1))
    rx = rx.replace(re.escape("<id>"), r"\d+").replace(re.escape("<estimator>"), r"[a-z0-9-]+")
    return re.compile(rx + r"\Z")


def _script(text: str) -> str:
    """The python block that follows "`read_mcap.py`:"."""
    m = re.search(r"`read_mcap\.py`:\s*\n```python\n(.*?)\n```", text, re.S)
    assert m, "docs/run-format.md: no read_mcap.py block"
    return m.group(1)


def _record(path: Path):
    """A 2-second lockstep run of wang2019, recorded: (scenario, wire frames per key after the
    swarm prefix, the last estimate per agent, truth per (tick, agent), ticks)."""
    sc = S.load("wang2019").with_overrides(**{"clock.duration": 2.0})
    sim = Simulation(sc)
    keys = wire.Keys(SWARM)
    rec = R.Recorder(path, {"writer": "netsim", "swarm": SWARM, "scenario": sc.to_yaml(), "seed": sc.seed,
                            "mode": "lockstep", "dt": sc.clock.dt, "agents": sc.agent_ids}, sc)
    counts: Counter = Counter()
    truth: dict = {}
    last: dict = {}

    def put(key: str, data: bytes, t: float) -> None:
        rec.frame(key, data, t)
        counts[key.split("/", 2)[2]] += 1

    exchange = sim.exchange

    def recorded_exchange(sent):  # the radio as netsim records it: what was sent, what was delivered
        for tx in sent:
            put(keys.radio_tx(tx.src), tx.data, sim.t)
        rxs = exchange(sent)
        for rx in rxs:
            put(keys.radio_rx(rx.receiver), rx.data if rx.nack is None else wire.encode(rx.nack, 0, 0), sim.t)
        return rxs

    sim.exchange = recorded_exchange
    nodes = make_nodes(ESTIMATOR, sc)

    def on_tick(k, frames):
        t = sim.t
        put(keys.clock, wire.encode(Clock(k, t, "lockstep", sc.clock.dt), 0, 2 * k + 1), t)
        states = sim.truth()
        rec.truth(k, t, states, sim.targets())
        if k == 2:
            rec.fault(FAULT, [{"id": 1, "action": "cut", "args": {"link": [1, 2], "direction": "both"}}])
            put(keys.events, wire.encode(Event("kill", KILLED, t), 0, 0), t)
            rec.event(t, f"kill agent {KILLED}", "warning")
        for a in sc.agent_ids:
            truth[(k, a)] = states[a]
            put(keys.truth(a), wire.encode(Truth(k, t, states[a]), 0, 2 * k + 2), t)
            if a == KILLED and k in (2, 3):
                put(R.withheld_key(keys, a), wire.encode(frames[a], 0, 0), t)
            else:
                put(keys.sensors(a), wire.encode(frames[a], 0, 2 * k + 2, a), t)
        for a, node in nodes.items():
            e = node.estimate()
            if k == 1:  # an earlier estimate of the tick, 100 m off: the tick's last one is scored
                rec.estimate(ESTIMATOR, a, e.k, e.k * sc.clock.dt, e.mean + 100.0, e.cov)
            put(keys.estimate(a), wire.encode(EstimateMsg(e.k, ESTIMATOR, e.mean, e.cov), a, k + 1), t)
            rec.estimate(ESTIMATOR, a, e.k, e.k * sc.clock.dt, e.mean, e.cov)
            put(keys.done(a), wire.encode(Done(k, 1, 0), a, k + 1), t)
            last[a] = e
        if k % max(1, round(1 / sc.clock.dt)) == 0:
            rows = sim.link_table()
            put(keys.links, wire.encode(Links(k, [LinkMsg(**row) for row in rows]), 0, 0), t)
            rec.links(rows)
        rec.end_tick(k, t)

    record = InProcessRunner(sim, nodes).run(on_tick=on_tick)
    put(keys.clock, wire.encode(Clock(sim.k, sim.t, "stop", sc.clock.dt), 0, 0), sim.t)
    rec.close()
    return sc, counts, last, truth, list(record.k)


def test_read_mcap_of_the_doc_reads_a_recording_as_the_doc_says(tmp_path):
    text = DOC.read_text()
    script = tmp_path / "read_mcap.py"
    script.write_text(_script(text))
    path = tmp_path / "run.mcap"
    sc, counts, last, truth, ticks = _record(path)

    p = subprocess.run([sys.executable, str(script), str(path)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    out = p.stdout.splitlines()
    assert out[0] == f"writer netsim format {R.FORMAT_VERSION} seed {sc.seed} scenario name: {sc.name}"
    # Its channel table: every wire channel and its number of frames, as recorded.
    assert out[1].startswith("frames: ")
    frames = ast.literal_eval(out[1][len("frames: "):])
    assert frames == dict(sorted(counts.items()))
    for i, a in enumerate(sorted(last)):
        e = last[a]
        err = np.linalg.norm(e.mean[:2] - truth[(e.k, a)][:2])
        assert out[2 + i] == (f"agent {a}: {ESTIMATOR} tick {e.k} at {np.round(e.mean, 2).tolist()}, "
                              f"error {err:.2f} m")
    assert out[2 + len(last):] == [f"{len(ticks)} scene updates; faults:", f"  {FAULT_TEXT}"]

    # The channels it counted are the doc's wire channels, and the doc's wire table lists no
    # channel this run could have and did not record.
    wire_rows = _table(_section(text, "### The wire channels"))
    patterns = {row[0]: _channel_pattern(row[0]) for row in wire_rows}
    seen = Counter()
    for key in frames:
        matched = [cell for cell, rx in patterns.items() if rx.match(f"swarmloc/{SWARM}/{key}")]
        assert len(matched) == 1, (key, matched)
        seen[matched[0]] += 1
    assert {cell for cell in patterns if not seen[cell]} == {f"`.../agent/<id>/{k}`" for k in NOT_RECORDED}


def test_every_channel_of_a_recording_is_in_the_doc_tables_as_they_describe_it(tmp_path):
    text = DOC.read_text()
    path = tmp_path / "run.mcap"
    sc, *_ = _record(path)
    wire_cells = [row[0] for row in _table(_section(text, "### The wire channels"))]
    view = {row[0]: row[1:] for row in _table(_section(text, "### The view channels"))}  # schema, what
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert reader.get_header().profile == "swarmloc"
        view_seen = set()
        for ch in summary.channels.values():
            schema = summary.schemas.get(ch.schema_id)
            if ch.message_encoding == "msgpack":  # a wire channel: no schema, metadata swarmloc: wire
                assert ch.schema_id == 0 and ch.metadata == {"swarmloc": "wire"}, ch
                assert sum(bool(_channel_pattern(c).match(ch.topic)) for c in wire_cells) == 1, ch.topic
                continue
            cells = [c for c in view if _channel_pattern(c).match(ch.topic)]
            assert len(cells) == 1, (ch.topic, cells)
            named = re.search(r"`([^`]+)`", view[cells[0]][0]).group(1)
            assert schema.name == named, (ch.topic, schema.name, named)
            if view[cells[0]][0].startswith("JSON"):
                assert (ch.message_encoding, schema.encoding) == ("json", "jsonschema")
                js = json.loads(schema.data)
                assert js["type"] == "object" and js["title"] == named
            else:
                assert (ch.message_encoding, schema.encoding) == ("protobuf", "protobuf")
            view_seen.add(cells[0])
        # wang2019 has no targets, and a channel that carried nothing is not in the file.
        assert set(view) - view_seen == {"`/truth/targets`"}
        # /metrics: one message per agent and tick (the last estimate of the tick), with the
        # doc's fields; the earlier estimate 100 m off at tick 1 was not scored.
        doc_fields = re.search(r"`(\{[^`]+\})`", view["`/metrics/<estimator>/<id>`"][1]).group(1)
        msgs = [(c.topic, json.loads(m.data), m.log_time) for _, c, m in
                reader.iter_messages(topics=[R.metrics_topic(ESTIMATOR, a) for a in sc.agent_ids])]
    assert set(json.loads("[" + doc_fields.strip("{}") + "]")) == set(msgs[0][1])
    per = Counter((topic, d["k"]) for topic, d, _ in msgs)
    assert set(per.values()) == {1}
    assert all(d["error_m"] < 50 and d["dof"] == 2 and d["t"] == d["k"] * sc.clock.dt for _, d, _ in msgs)
    start = min(lt for _, _, lt in msgs) - int(round(min(d["t"] for _, d, _ in msgs) * 1e9))
    assert all(lt == start + int(round(d["t"] * 1e9)) for _, d, lt in msgs)  # log_time: the estimate's tick
