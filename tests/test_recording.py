"""run.mcap (swarmloc/experiment/recording.py): the format, reading an unfinished file, the
recorded world (netsim/world/recorded.py: McapWorld) and `swarmloc rerun`."""

import json
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from conftest import camera_view, framed
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from msgspec.structs import replace

from netsim.sim import Simulation
from swarmloc import wire
from swarmloc.experiment import recording as R
from swarmloc.experiment import scenario as S
from swarmloc.experiment.results import compute_references, metrics
from swarmloc.experiment.runner import InProcessRunner, make_nodes
from swarmloc.wire.messages import Clock, Truth

SWARM = "rec"


def _short(duration=8.0, **changes):
    return S.load("wang2019").with_overrides(**{"clock.duration": duration, **changes})


def record_in_process(sc, path, estimator="ukf-dcl"):
    """An in-process run that records what netsim would put on the wire for the world (clock,
    sensor frames, truth) and its view: the fast stand-in for netsim's recording."""
    sim = Simulation(sc)
    rec = R.Recorder(path, {"writer": "test", "scenario": sc.to_yaml(), "seed": sc.seed}, sc)
    keys = wire.Keys(SWARM)

    def on_tick(k, frames):
        t = sim.t
        rec.frame(keys.clock, wire.encode(Clock(k, t, "lockstep", sc.clock.dt), 0, k), t)
        truth = sim.truth()
        rec.truth(k, t, truth, sim.targets())
        for a in sc.agent_ids:
            rec.frame(keys.sensors(a), wire.encode(frames[a], 0, k), t)
            rec.frame(keys.truth(a), wire.encode(Truth(k, t, truth[a]), 0, k), t)
        rec.end_tick(k, t)

    nodes = make_nodes(estimator, sc)
    record = InProcessRunner(sim, nodes).run(on_tick=on_tick)
    for a, node in nodes.items():  # the view's series need estimates: the agents' last ones
        e = node.estimate()
        rec.estimate(estimator, a, e.k, sim.t, e.mean, e.cov)
    rec.fault({"k": 3, "t": 1.5, "source": "live", "action": "cut", "link": [1, 2], "direction": "both"},
              [{"id": 1, "action": "cut", "args": {"link": [1, 2], "direction": "both"}, "since": 1.5, "until": None}])
    rec.end_tick(sc.clock.steps, sim.t)
    rec.close()
    return record


def test_recording_reads_back_with_plain_mcap_tools(tmp_path):
    sc = _short()
    path = tmp_path / "run.mcap"
    record_in_process(sc, path)
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        chans = {c.topic: (c.message_encoding, summary.schemas[c.schema_id].name if c.schema_id else None)
                 for c in summary.channels.values()}
        assert chans[f"swarmloc/{SWARM}/agent/1/sensors"] == ("msgpack", None)
        assert chans["/scene"] == ("protobuf", "foxglove.SceneUpdate")
        assert chans["/faults"] == ("protobuf", "foxglove.Log")
        assert chans["/metrics/ukf-dcl/1"] == ("json", "swarmloc.metrics")
        assert summary.statistics.message_count >= (1 + 2 * len(sc.agent_ids)) * (sc.clock.steps + 1)  # clock, sensors, truth
        scenes = [m for _, _, _, m in reader.iter_decoded_messages(topics=["/scene"])]
        assert len(scenes) == sc.clock.steps + 2
        last = {e.id: e for e in scenes[-1].entities}
        assert len(last["truth"].spheres) == 4 and len(last["estimate/ukf-dcl"].cylinders) == 4  # 95 % ellipses
        assert "#1 cut link=[1,2]" in last["faults"].texts[0].text
        logs = [m for _, _, _, m in reader.iter_decoded_messages(topics=["/faults"])]
        assert logs[0].message == "t=1.5 s: cut link=[1,2] direction=both (live)"
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert json.loads(meta["swarmloc"]["format_version"]) == R.FORMAT_VERSION
    assert S.parse(__import__("yaml").safe_load(meta["swarmloc"]["scenario"])).name == sc.name


def test_in_process_rerun_is_bit_for_bit_and_another_estimator_gets_the_same_inputs(tmp_path):
    sc = _short()
    path = tmp_path / "run.mcap"
    first = record_in_process(sc, path)
    again = R.rerun_scenario([path])
    assert again.world.source == "mcap" and again.seed == sc.seed
    sim = Simulation(again)
    second = InProcessRunner(sim, make_nodes("ukf-dcl", again)).run()
    a, b = first.trace("ukf-dcl"), second.trace("ukf-dcl")
    assert np.array_equal(a.mean, b.mean) and np.array_equal(a.cov, b.cov)
    assert np.array_equal(first.truth_array(), second.truth_array())
    assert sim.world.steps == sc.clock.steps
    # The same frames to dead reckoning: exactly the run's own IL reference, computed offline.
    il = R.rerun_scenario([path], "il")
    third = InProcessRunner(Simulation(il), make_nodes("il", il)).run()
    compute_references(sc, first, ["il"])
    x, y = first.trace("il"), third.trace("il")
    assert np.allclose(x.mean[1:], y.mean[1:], rtol=0, atol=1e-9) and np.allclose(x.cov[1:], y.cov[1:], atol=1e-9)
    assert not np.allclose(third.trace("il").mean[-1], second.trace("ukf-dcl").mean[-1], atol=0.01)


def test_record_rebuilt_from_the_recording(tmp_path):
    sc = _short()
    path = tmp_path / "run.mcap"
    first = record_in_process(sc, path)
    run = R.load(path)
    rebuilt = R.record_of(run)
    assert rebuilt.k == first.k and np.array_equal(rebuilt.truth_array(), first.truth_array())
    assert [wire.encode(f[a], 0, 0) for f in rebuilt.sensors for a in sc.agent_ids] == \
        [wire.encode(f[a], 0, 0) for f in first.sensors for a in sc.agent_ids]
    compute_references(sc, rebuilt, ["ukf-ccl"])
    compute_references(sc, first, ["ukf-ccl"])
    assert metrics(rebuilt, ["ukf-ccl"])["estimators"] == metrics(first, ["ukf-ccl"])["estimators"]


WRITER = textwrap.dedent("""
    import os, signal, sys, time
    from swarmloc import wire
    from swarmloc.experiment import recording as R
    from swarmloc.wire.messages import Clock
    rec = R.Recorder(sys.argv[1], {"writer": "test"}, flush_period=0.0)
    keys = wire.Keys("crash")
    for k in range(200):
        rec.frame(keys.clock, wire.encode(Clock(k, k * 0.1, "lockstep", 0.1), 0, k), k * 0.1)
        rec.end_tick(k, k * 0.1)  # flush_period 0: a chunk per tick
    rec.frame(keys.clock, wire.encode(Clock(200, 20.0, "lockstep", 0.1), 0, 200), 20.0)  # never flushed
    os.kill(os.getpid(), signal.SIGKILL)
""")


def test_a_recording_cut_by_kill_9_reads_to_its_last_chunk(tmp_path):
    path = tmp_path / "run.mcap"
    p = subprocess.run([sys.executable, "-c", WRITER, str(path)], capture_output=True, text=True, timeout=60)
    assert p.returncode == -signal.SIGKILL, p.stderr
    scan = R.Scan()
    clocks = [wire.decode(m.data).body.k for m in R.messages(path, scan)]
    assert clocks == list(range(200)) and scan.truncated
    assert R.load(path).ticks == list(range(200))
    # A file cut anywhere inside a chunk reads to the chunk before.
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    scan = R.Scan()
    got = [wire.decode(m.data).body.k for m in R.messages(cut, scan)]
    assert scan.truncated and 0 < len(got) < 200 and got == list(range(len(got)))


def test_not_a_recording(tmp_path):
    bad = tmp_path / "x.mcap"
    bad.write_bytes(b"not mcap at all")
    with pytest.raises(R.RecordingError):
        R.metadata(bad)
    empty = tmp_path / "y.mcap"
    R.Recorder(empty, {"writer": "test"}).close()
    with pytest.raises(R.RecordingError, match="no scenario"):
        R.rerun_scenario([empty])


@pytest.mark.slow
def test_swarmloc_rerun_over_agent_processes_is_bit_for_bit(cli, tmp_path):
    """`swarmloc run` records run.mcap; `swarmloc rerun` of it gives the same estimates bit for bit,
    its metrics rebuild from the recording alone, and `--estimator` runs another one on the same
    frames."""
    sc = _short(duration=20.0)
    (tmp_path / "s.yaml").write_text(sc.to_yaml())
    cli.run("run", "s.yaml", "--out", "r1", "--port", "0", "--swarm", cli.swarm, "--no-plots", check=True)
    cli.run("rerun", "r1/run.mcap", "--out", "r2", "--port", "0", "--swarm", cli.swarm + "b", "--no-plots",
            check=True)
    for alg in ("ukf-dcl", "ukf-ccl", "il"):
        a, b = np.load(tmp_path / "r1/estimates" / f"{alg}.npz"), np.load(tmp_path / "r2/estimates" / f"{alg}.npz")
        assert np.array_equal(a["mean"], b["mean"], equal_nan=True) and np.array_equal(a["cov"], b["cov"], equal_nan=True)
    m1 = json.loads((tmp_path / "r1/metrics.json").read_text())
    run = R.load(tmp_path / "r1/run.mcap")
    rebuilt = R.record_of(run)
    compute_references(run.scenario, rebuilt)
    again = metrics(rebuilt, list(m1["estimators"]))
    assert again["estimators"] == m1["estimators"]
    assert m1["recording"]["frames"] > 0 and not run.truncated
    # The Foxglove layout beside it frames every position the platforms took.
    assert m1["recording"]["layout"] == R.LAYOUT
    lay = json.loads((tmp_path / "r1" / R.LAYOUT).read_text())
    assert framed(lay["configById"]["3D!swarmloc"]["cameraState"], rebuilt.truth_array()[:, :, :2].reshape(-1, 2))
    plotted = {p["value"].rsplit(".", 1)[0] for p in lay["configById"]["Plot!swarmloc"]["paths"]}
    assert plotted == {R.metrics_topic("ukf-dcl", a) for a in sc.localized_ids}
    assert plotted <= {m.topic for m in R.messages(tmp_path / "r1/run.mcap")}  # series the file has
    cli.run("rerun", "r1/run.mcap", "--estimator", "il", "--out", "r3", "--port", "0", "--swarm", cli.swarm + "c",
            "--no-plots", check=True)
    il_agents = np.load(tmp_path / "r3/estimates/il.npz")
    il_ref = np.load(tmp_path / "r1/estimates/il.npz")
    assert np.allclose(il_agents["mean"][1:], il_ref["mean"][1:], atol=1e-9)


@pytest.mark.slow
def test_an_agents_own_recording_and_ros2_output(tmp_path):
    """`swarmloc agent --config` with outputs.record and a ros2 section, replaying a recording:
    its run.mcap holds the frames it stepped on and the estimates it published, and its
    estimates go out on its ROS 2 pose topic as well."""
    import threading
    import time
    import uuid

    import yaml
    import zenoh
    from conftest import free_port

    from swarmloc.wire import ros2
    from swarmloc.wire.messages import EstimateMsg, Sensors

    sc = _short(duration=10.0)
    record = InProcessRunner(Simulation(sc), make_nodes("il", sc)).run()
    np.savez(tmp_path / "sensors.npz", **record.sensor_arrays())
    aid = 2
    here = f"tcp/127.0.0.1:{free_port()}"
    swarm = "a" + uuid.uuid4().hex[:8]
    cfg = {"version": 1, "id": aid, "swarm": swarm, "estimator": {"name": "il"}, "model": "planar-speed-heading",
           "prior": {"position": sc.prior(aid)[0].tolist(), "std": sc.estimation.initial_std},
           "zenoh": {"mode": "peer", "connect": [here]}, "ros2": {"domain_id": 4},
           "sensors": [{"kind": "file", "path": "sensors.npz", "speed": "as_fast_as_possible"}],
           "outputs": {"record": "out/agent.mcap"}}
    (tmp_path / "agent.yaml").write_text(yaml.safe_dump(cfg))
    poses = []
    with zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("peer", [here], []))) as session:
        sub = session.declare_subscriber(ros2.topic_key(4, f"/swarmloc/agent{aid}/pose", ros2.POSE),
                                         lambda s: poses.append(s.payload.to_bytes()))
        p = subprocess.Popen([sys.executable, "-m", "agents", "agent", "--config", "agent.yaml", "-v"],
                             stderr=subprocess.PIPE, text=True, cwd=tmp_path)
        lines = []
        threading.Thread(target=lambda: lines.extend(p.stderr), daemon=True).start()
        deadline = time.monotonic() + 60
        while not any("replayed" in line for line in lines) and time.monotonic() < deadline:
            assert p.poll() is None, "".join(lines)
            time.sleep(0.05)
        time.sleep(0.5)
        p.send_signal(signal.SIGTERM)
        assert p.wait(20) in (0, 143), "".join(lines)
        del sub
    path = tmp_path / "out/agent.mcap"
    meta = R.metadata(path)
    assert meta["writer"] == "agent" and meta["id"] == aid and meta["config"]["ros2"]["domain_id"] == 4
    frames, estimates = [], []
    for m in R.messages(path):
        if m.topic == f"swarmloc/{swarm}/agent/{aid}/sensors":
            frames.append(wire.decode(m.data, expect=(Sensors,)).body)
        elif m.topic == f"swarmloc/{swarm}/agent/{aid}/estimate":
            estimates.append(wire.decode(m.data, expect=(EstimateMsg,)).body)
    assert [wire.encode(f, 0, 0) for f in frames] == [wire.encode(f[aid], 0, 0) for f in record.sensors]
    assert [e.k for e in estimates] == record.k
    assert all(np.array_equal(e.mean, record.est["il"][e.k][aid].mean) for e in estimates)
    assert len(poses) == len(record.k)


def test_agents_own_recordings_rerun_together(tmp_path):
    """Agents' own recordings (outputs.record, one file each, frames on the swarm clock) rerun
    as one swarm: the scenario built from their configurations hands each node the frames it
    recorded, so the estimates equal a run on those frames with those priors, bit for bit."""
    sc = _short(**{"estimation.initial_error": False, "radio": {"model": "unit-disk", "range_m": float("inf")}})
    first = InProcessRunner(Simulation(sc), make_nodes("ukf-dcl", sc)).run()
    paths = []
    for a in sc.agent_ids:
        cfg = {"id": a, "model": "planar-speed-heading", "estimator": {"name": "ukf-dcl", "params": {}},
               "prior": {"position": sc.agent(a).start, "heading": None, "std": sc.estimation.initial_std,
                         "heading_std": sc.estimation.initial_heading_std}, "landmarks": [], "gate": None,
               "gate_open_after": 10}
        path = tmp_path / f"agent{a}.mcap"
        rec = R.Recorder(path, {"writer": "agent", "id": a, "config": cfg}, start_ns=0)
        for frames in first.sensors:  # on the swarm clock: ticks 1000.., as from a shared epoch
            f = frames[a]
            f = replace(f, k=f.k + 1000, t=f.t + 500.0)
            rec.frame(wire.Keys("hw").sensors(a), wire.encode(f, a, f.k), f.t)
        rec.close()
        paths.append(path)
    again = R.rerun_scenario(paths)
    assert again.clock.dt == sc.clock.dt and again.clock.steps == sc.clock.steps and again.references == []
    second = InProcessRunner(Simulation(again), make_nodes("ukf-dcl", again)).run()
    x, y = first.trace("ukf-dcl"), second.trace("ukf-dcl")
    assert np.array_equal(x.mean, y.mean) and np.array_equal(x.cov, y.cov)
    with pytest.raises(R.RecordingError, match="same agent"):
        R.rerun_scenario([paths[0], paths[0]])


def test_netsims_deferred_recording_writes_what_an_immediate_one_writes(tmp_path):
    """netsim holds its recording's work and does it while its loop would wait (`deferred`,
    `drain` in slices): the file is message for message, byte for byte, the one the same calls
    make at once, wherever the drains fall (some before any work, some mid-tick)."""
    import time

    from swarmloc.models.motion import MOTION_MODELS

    sc = S.load("wang2022")
    drains = np.random.default_rng(11)

    def write(path, deferred):
        rec = R.Recorder(path, {"writer": "test"}, sc, start_ns=0, deferred=deferred)
        r = np.random.default_rng(3)
        for k in range(40):
            t = 0.5 * k
            states = {a.id: r.normal(size=MOTION_MODELS[a.model].state_dim) * 50 for a in sc.world.agents}
            rec.truth(k, t, states, {0: r.normal(size=2) * 30})
            rec.frame(f"swarmloc/x/agent/{k % 4 + 1}/done", r.bytes(40), t)
            if k % 7 == 3:
                rec.event(t, f"agent 2 left the swarm at tick {k}", "warning")
                rec.fault({"k": k, "t": t, "source": "schedule", "action": "cut", "link": [1, 2]},
                          [{"id": 1, "action": "cut", "args": {"link": [1, 2]}}])
            for a in sc.world.agents:
                n = MOTION_MODELS[a.model].state_dim
                A = r.normal(size=(n, n))
                rec.estimate("csl-ctl", a.id, k, t, states[a.id] + r.normal(size=n), A @ A.T + np.eye(n),
                             ((0, r.normal(size=2), np.eye(2) * 2.0),))
            rec.links([{"a": 1, "b": 2, "up": True, "snr_db": 10.0}])
            rec.end_tick(k, t)
            if deferred and drains.random() < 0.6:
                rec.drain(time.perf_counter() + drains.choice([-1.0, 1e-5, 1e-3]))  # nothing, a slice, more
        rec.close()
        return [(m.topic, m.log_time, bytes(m.data)) for m in R.messages(path)]

    now, held = write(tmp_path / "now.mcap", False), write(tmp_path / "held.mcap", True)
    assert len(now) > 250 and now == held


def test_the_foxglove_layout_frames_the_run_from_above_with_its_scene_on():
    """`layout`: Foxglove's (and Lichtblick's) import format, a 3D panel with /scene and
    /scene/static switched on (off by default there), looking straight down, x east to the
    right, framed on every point with a margin and no more; the log panel on /faults; with the
    agents' estimator, a plot of its error (the /metrics series' `error_m`) per agent."""
    r = np.random.default_rng(5)
    for xy in (r.uniform([-300, 40], [500, 90], (200, 2)), r.uniform([0, -800], [30, 900], (200, 2)),
               np.array([[12.0, -3.0]]), np.array([[np.nan, np.nan], [0.0, 0.0], [4.0, 1.0]])):
        lay = R.layout(xy)
        panel = lay["configById"]["3D!swarmloc"]
        cam = panel["cameraState"]
        assert panel["topics"] == {R.SCENE: {"visible": True}, R.STATIC: {"visible": True}}
        assert cam["phi"] < 1 and cam["thetaOffset"] == 0 and cam["perspective"] and panel["followTf"] == "map"
        assert framed(cam, xy[np.isfinite(xy).all(axis=1)])
        assert cam["far"] > cam["distance"]
        # Tight: along one axis the view is the points' extent (at least 10 m) with only the margin.
        seen = camera_view(cam)
        needed = np.maximum(np.ptp(xy[np.isfinite(xy).all(axis=1)], axis=0) / 2, 5.0)
        assert (seen / needed).min() <= R.LAYOUT_MARGIN * 1.001
        assert lay["configById"]["RosOut!swarmloc"]["topicToRender"] == R.FAULTS
        assert lay["layout"]["first"] == "3D!swarmloc" and lay["layout"]["second"] == "RosOut!swarmloc"
        assert json.loads(json.dumps(lay)) == lay  # plain JSON
    # With the agents' estimator: its error plotted for the first 8 agents, under the log.
    lay = R.layout(np.zeros((1, 2)), "ukf-dcl", [12, 3, 5, 1, 2, 4, 6, 7, 8, 9])
    paths = lay["configById"]["Plot!swarmloc"]["paths"]
    assert [p["value"] for p in paths] == [f"{R.metrics_topic('ukf-dcl', a)}.error_m" for a in (1, 2, 3, 4, 5, 6, 7, 8)]
    assert lay["layout"]["second"] == {"first": "RosOut!swarmloc", "second": "Plot!swarmloc", "direction": "column",
                                       "splitPercentage": 40}
