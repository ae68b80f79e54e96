"""`swarmloc status` for a swarm without netsim: `swarmloc agent --config` processes on a direct
radio, Zenoh peers on 127.0.0.1, and `status` asking each agent for its own counters."""

import json
import os
import signal
import subprocess
import sys
import threading
import time
import uuid

import numpy as np
import pytest
from conftest import free_port
from test_sources import agents  # noqa: F401  (the fixture that starts `swarmloc agent --config` processes)


def swarmloc(*args, timeout=30):
    # Wide enough that rich wraps no cell: the rows are read back below.
    return subprocess.run([sys.executable, "-m", "agents", *args], capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "COLUMNS": "300"})


def one_line_error(p: subprocess.CompletedProcess) -> str:
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in p.stderr, p.stderr
    return lines[0]


def table(stdout: str) -> dict[str, dict[str, str]]:
    """The agents table's rows, by agent id, each by column name."""
    head = next(line for line in stdout.splitlines() if line.startswith("┃ agent"))
    names = [c.strip() for c in head.strip("┃").split("┃")]
    rows = [[c.strip() for c in line.strip("│").split("│")] for line in stdout.splitlines() if line.startswith("│")]
    return {r[0]: dict(zip(names, r)) for r in rows}


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """Sensor frames of agents 1..4 (wang2019, 60 s at 0.5 s a tick) from an in-process run."""
    from netsim.sim import Simulation
    from swarmloc.experiment.runner import InProcessRunner, make_nodes
    from swarmloc.experiment.scenario import load as load_scenario

    sc = load_scenario("wang2019")
    sc = sc.model_copy(update={"clock": sc.clock.model_copy(update={"duration": 60.0})})
    record = InProcessRunner(Simulation(sc), make_nodes("il", sc)).run()
    path = tmp_path_factory.mktemp("recording") / "sensors.npz"
    np.savez(path, **record.sensor_arrays())
    return path, {aid: sc.prior(aid)[0].tolist() for aid in record.ids}


@pytest.fixture
def swarm(tmp_path, agents, recording):  # noqa: F811
    """Agents 1 and 2 replaying the recording in real time, agent 3 without sensor frames; each
    dials the peers of lower ids (docs/deploy.md#peers-and-routers). Returns the swarm name, the
    agents and their endpoints."""
    path, priors = recording
    name = "d" + uuid.uuid4().hex[:8]
    ports = {aid: free_port() for aid in (1, 2, 3)}
    started = {}
    for aid in (1, 2, 3):
        started[aid] = agents(tmp_path, id=aid, swarm=name, prior={"position": priors[aid]},
                              zenoh={"mode": "peer", "listen": [f"tcp/127.0.0.1:{ports[aid]}"],
                                     "connect": [f"tcp/127.0.0.1:{ports[b]}" for b in ports if b < aid]},
                              sensors=[{"kind": "file", "path": str(path), "speed": 1.0}] if aid < 3 else
                              [{"kind": "zenoh"}])
    # Each has seen the other two's liveliness tokens: the mesh is whole.
    for aid, agent in started.items():
        for other in {1, 2, 3} - {aid}:
            agent.wait_for(f"peer {other} joined")
    return name, started, {aid: f"tcp/127.0.0.1:{p}" for aid, p in ports.items()}


@pytest.mark.slow
def test_status_shows_every_agent_without_netsim(swarm):
    name, started, endpoints = swarm
    # Agent 3's endpoint: a client of any one peer reaches the whole mesh.
    connect = ["--swarm", name, "--connect", endpoints[3]]
    end = time.monotonic() + 10
    while True:  # the clock offsets need a time.sync each way (one a second): a few seconds after joining
        p = swarmloc("status", *connect)
        assert p.returncode == 0, p.stderr
        cells = [r.get("clock offset to peers", "-") for r in table(p.stdout).values()]
        if (len(cells) == 3 and all(c.count(":") == 2 for c in cells)) or time.monotonic() > end:
            break
        time.sleep(0.5)
    assert f"swarm {name}: 3/3 agents answer on swarmloc/{name}/agent/*/stats" in p.stdout
    rows = table(p.stdout)
    assert set(rows) == {"1", "2", "3"}, p.stdout
    for aid, row in rows.items():
        assert row["estimator"] == "il" and int(row["tick"]) >= -1 and row["alive"] == "yes", row
        assert row["rejected"] == "0" and row["heard"].endswith(" ms"), row
    for aid in ("1", "2"):  # replaying: the first frame goes in at once
        assert int(rows[aid]["tick"]) >= 0 and "sensors.npz: " in rows[aid]["sources"], rows[aid]
        assert rows[aid]["sources"].endswith("/121 frames"), rows[aid]
    assert rows["3"]["tick"] == "-1" and rows["3"]["sources"] == "-"
    # Each agent's estimate of the others' clocks (time.sync every second): one machine, one clock.
    for aid, row in rows.items():
        offsets = dict(cell.split(": ") for cell in row["clock offset to peers"].split(", "))
        assert set(offsets) == {"1", "2", "3"} - {aid}, row
        for text in offsets.values():  # "+0.1±0.7 ms"
            offset, half = map(float, text.removesuffix(" ms").split("±"))
            assert abs(offset) - half < 10.0, row

    p = swarmloc("status", *connect, "--json")
    assert p.returncode == 0, p.stderr
    answers = json.loads(p.stdout)
    assert set(answers) == {"1", "2", "3"}
    for aid, data in answers.items():
        assert data["id"] == int(aid) and data["algorithm"] == "il" and isinstance(data["k"], int)
    (source,) = answers["1"]["sources"]
    assert source.startswith("file ") and source.endswith("sensors.npz") and answers["1"]["sources"][source]["of"] == 121
    assert "sources" not in answers["3"]

    # --agents skips netsim; the answer is the same table.
    p = swarmloc("status", *connect, "--agents")
    assert p.returncode == 0 and set(table(p.stdout)) == {"1", "2", "3"}, p.stderr

    # Another swarm's name on the same endpoint: the session opens, nobody of that swarm answers.
    p = swarmloc("status", "--swarm", "nobody", "--connect", endpoints[3])
    assert p.returncode == 1
    assert one_line_error(p) == f"error: no swarm 'nobody' answers on {endpoints[3]}: neither netsim nor any agent"


@pytest.mark.slow
def test_status_watch_keeps_an_agent_that_left(swarm):
    name, started, endpoints = swarm
    watch = subprocess.Popen([sys.executable, "-m", "agents", "status", "--swarm", name, "--connect", endpoints[1],
                              "--watch", "--interval", "0.2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(watch.stdout), daemon=True).start()

    def wait_line(text: str) -> str:
        end = time.monotonic() + 10
        while time.monotonic() < end:
            hit = [line for line in lines if text in line]
            if hit:
                return hit[-1]
            assert watch.poll() is None, watch.stderr.read()
            time.sleep(0.05)
        raise AssertionError(f"no {text!r} in {lines}")

    try:
        line = wait_line("agents answer 3/3")
        assert "1 il tick" in line and "2 il tick" in line and "3 il tick -1" in line, line
        assert started[3].stop() in (0, 143)
        line = wait_line("3 silent for")
        assert line.startswith("agents answer 2/3:") and "1 il tick" in line, line
        watch.send_signal(signal.SIGINT)
        assert watch.wait(10) == 0
    finally:
        if watch.poll() is None:
            watch.kill()
            watch.wait()
    assert "Traceback" not in watch.stderr.read()


def test_status_with_nobody_there_says_so():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    for extra in ([], ["--agents"], ["--json"]):
        p = swarmloc("status", "--swarm", "nobody", "--connect", endpoint, *extra)
        assert p.returncode == 1, (extra, p.stderr)
        assert one_line_error(p) == f"error: no swarm 'nobody' answers on {endpoint}: neither netsim nor any agent"
        assert p.stdout == ""


@pytest.mark.slow
def test_a_host_whose_clock_is_off_is_named(tmp_path, agents):  # noqa: F811
    """Agent 2's host clock 50 ms ahead (time.time in its process): each agent estimates the
    other's offset from time.sync to within half the round trip (NTP's bound: exact arithmetic,
    no tolerance for the machine), counts it beyond the 10 ms bound, logs the warning that says
    what to fix, and `status` shows the offset; agent 3 on the true clock sees none of it with
    agent 1."""
    name = "d" + uuid.uuid4().hex[:8]
    ports = {aid: free_port() for aid in (1, 2, 3)}
    started = {aid: agents(tmp_path, id=aid, swarm=name, prior={"position": [float(aid), 0.0]},
                           clock_skew=0.05 if aid == 2 else 0.0, sensors=[{"kind": "zenoh"}],
                           zenoh={"mode": "peer", "listen": [f"tcp/127.0.0.1:{ports[aid]}"],
                                  "connect": [f"tcp/127.0.0.1:{ports[b]}" for b in ports if b < aid]})
               for aid in (1, 2, 3)}
    line = started[1].wait_for("peer 2's clock is", timeout=30)
    print(f"\n{line.strip()}")
    assert "beyond the 10 ms bound" in line and "docs/deploy.md#clock-offsets" in line, line
    assert "peer 1's clock is -" in started[2].wait_for("peer 1's clock is", timeout=30)
    connect = ["--swarm", name, "--connect", f"tcp/127.0.0.1:{ports[3]}"]
    end = time.monotonic() + 15
    pairs = ((1, 2, 50.0), (2, 1, -50.0), (3, 2, 50.0), (2, 3, -50.0), (1, 3, 0.0), (3, 1, 0.0))
    while True:  # every agent has an estimate of both others, and one (rt < 80 ms) past the bound for agent 2's
        p = swarmloc("status", *connect, "--json")
        assert p.returncode == 0, p.stderr
        answers = json.loads(p.stdout)
        clocks = {(me, other): answers.get(str(me), {}).get("clock_offset_ms", {}).get(str(other)) for me, other, _ in pairs}
        if all(c is not None and (c["exceeded"] > 0 or truth == 0.0) for (_, c), (*_, truth) in zip(clocks.items(), pairs)):
            break
        assert time.monotonic() < end, answers
        time.sleep(0.5)
    for me, other, truth in pairs:
        c = clocks[me, other]
        assert abs(c["offset_ms"] - truth) <= c["round_trip_ms"] / 2 + 1e-6, (me, other, c)
        if truth == 0.0:  # within half the round trip of 0, so never past the bound by more than that
            assert c["exceeded"] == 0, (me, other, c)
    assert answers["1"]["clock_exceeded"] > 0 and answers["3"]["clock_exceeded"] == answers["3"]["clock_offset_ms"]["2"]["exceeded"]
    out = swarmloc("status", *connect).stdout
    print(out)
    row = table(out)["1"]
    offsets = dict(cell.split(": ") for cell in row["clock offset to peers"].split(", ")[:2])
    assert abs(float(offsets["2"].split("±")[0]) - 50.0) < 25.0, row  # "+50.2±0.4 ms"
    assert "beyond 10 ms" in row["clock offset to peers"], row
