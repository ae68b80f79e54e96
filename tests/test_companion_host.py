"""Several agents of configuration files in one process (`swarmloc agent --config A --config B`,
agents/host.py): under netsim, bit for bit the swarm of one process each; one agent's bad frames
or failure leave its hostmates running; files that cannot share a process are refused, saying
which field and why. Real processes, real Zenoh sessions on 127.0.0.1."""

import os
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
import yaml
import zenoh
from conftest import free_port
from test_host import _stats

from agents.config import load
from agents.host import Host
from swarmloc import wire
from swarmloc.experiment import scenario as S
from swarmloc.wire.messages import OdometryMsg, Reply, Sensors


def swarmloc(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "agents", *args], capture_output=True, text=True, timeout=60, cwd=cwd)


def companion(tmp_path, aid: int, swarm: str, **fields) -> str:
    """Agent aid's configuration file: a planar robot on dead reckoning, unless `fields` say otherwise."""
    data = {"version": 1, "id": aid, "swarm": swarm, "estimator": {"name": "il"}, "model": "planar-speed-heading",
            "prior": {"position": [float(aid), 0.0]}, **fields}
    path = tmp_path / f"a{aid}.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


# ---------------------------------------------------------------------------- lockstep, bit for bit


def _rehearsal(sc, tmp_path, swarm: str, endpoint: str) -> list[str]:
    """Every agent of the scenario as an agent configuration under netsim (radio: netsim): the
    node the scenario's own agent would be (its prior, estimator and settings)."""
    paths = []
    for aid in sc.agent_ids:
        mean, _ = sc.prior(aid)
        paths.append(companion(tmp_path, aid, swarm, estimator={"name": sc.estimator.name,
                                                                "params": sc.estimator.params},
                               prior={"position": mean.tolist(), "std": sc.estimation.initial_std},
                               gate=sc.estimation.gate, gate_open_after=sc.estimation.gate_open_after,
                               zenoh={"mode": "client", "connect": [endpoint]}, radio="netsim"))
    return paths


def _lockstep(scenario_file, out, groups: list[list[str]], swarm: str, endpoint: str, tmp_path) -> dict:
    """netsim's lockstep run of the scenario with one `swarmloc agent` process per group of
    configuration files; its estimates."""
    procs = [subprocess.Popen([sys.executable, "-m", "netsim", str(scenario_file), "--swarm", swarm, "--listen",
                               endpoint, "--out", str(out), "--no-plots", "--no-record"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)]
    try:
        # netsim's port open first: a client with nothing to connect to gives up.
        port, deadline = int(endpoint.rsplit(":", 1)[1]), time.monotonic() + 60
        while time.monotonic() < deadline and procs[0].poll() is None:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                time.sleep(0.1)
        for i, group in enumerate(groups):
            procs.append(subprocess.Popen([sys.executable, "-m", "agents", "agent",
                                           *(a for path in group for a in ("--config", path))],
                                          stderr=open(tmp_path / f"{out.name}-host{i}.log", "w"), cwd=tmp_path))
        _, err = procs[0].communicate(timeout=300)
        assert procs[0].returncode == 0, err
        for p in procs[1:]:
            assert p.wait(30) == 0, (tmp_path / f"{out.name}-host{procs.index(p) - 1}.log").read_text()
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    with np.load(out / "estimates" / "ukf-dcl.npz") as f:
        return {k: f[k] for k in ("mean", "cov")}


@pytest.mark.slow
def test_configured_agents_in_one_process_equal_one_process_each_bit_for_bit(tmp_path):
    sc = S.load("wang2019").with_overrides(**{"clock.duration": 20.0, "estimation.initial_error": False})
    scenario_file = tmp_path / "sc.yaml"
    scenario_file.write_text(sc.to_yaml())
    runs = {}
    for name, grouping in (("alone", lambda p: [[x] for x in p]), ("hosted", lambda p: [p[:3], p[3:]])):
        swarm, endpoint = "c" + uuid.uuid4().hex[:8], f"tcp/127.0.0.1:{free_port()}"
        (tmp_path / name).mkdir()
        paths = _rehearsal(sc, tmp_path / name, swarm, endpoint)
        runs[name] = _lockstep(scenario_file, tmp_path / f"out-{name}", grouping(paths), swarm, endpoint, tmp_path)
    alone, hosted = runs["alone"], runs["hosted"]
    assert alone["mean"].shape == (sc.clock.steps + 1, 4, 2) and not np.isnan(alone["mean"]).any()
    assert np.array_equal(alone["mean"], hosted["mean"]) and np.array_equal(alone["cov"], hosted["cov"])
    # Not a swarm of dead reckoners that agree trivially: the ranges moved the estimates.
    assert not np.array_equal(alone["cov"][-1, 0], alone["cov"][-1, 1])


# ---------------------------------------------------------------------------- isolation


def _frame(aid: int, k: int) -> bytes:
    return wire.encode(Sensors(k, 0.5 * k, OdometryMsg(0.5, 1.0, 0.0, 0.1, 0.01), []), aid, k)


@pytest.mark.slow
def test_bad_frames_for_one_agent_leave_its_hostmate_alone(tmp_path):
    """Garbage, random bytes and a frame of the wrong type on agent 1's sensor key, three per
    tick: counted and dropped by agent 1, which steps on its good frames, while agent 2 in the
    same process steps on every frame it is sent and drops nothing."""
    swarm, here = "c" + uuid.uuid4().hex[:8], f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("peer", [here], []))) as session:
        paths = [companion(tmp_path, aid, swarm, zenoh={"mode": "peer", "connect": [here]}) for aid in (1, 2)]
        p = subprocess.Popen([sys.executable, "-m", "agents", "agent", "--config", paths[0], "--config", paths[1]],
                             stderr=subprocess.PIPE, text=True, cwd=tmp_path)
        try:
            assert _stats(session, swarm, 1, 30) and _stats(session, swarm, 2, 10)
            keys = wire.Keys(swarm)
            bad = [b"\x00garbage", os.urandom(300), wire.encode(Reply(True, "", {}), 1, 0)]
            for k in range(1, 6):
                session.put(keys.sensors(1), _frame(1, k))
                session.put(keys.sensors(2), _frame(2, k))
                for data in bad:
                    session.put(keys.sensors(1), data)
            deadline = time.monotonic() + 10
            # Until all is handled: a stats query may overtake the last bad frames (another
            # subscription, another Zenoh callback thread), so their count is waited for too.
            while time.monotonic() < deadline:
                s1, s2 = _stats(session, swarm, 1), _stats(session, swarm, 2)
                if s1["ticks"] == 5 and s2["ticks"] == 5 and s1["rejected"].get("malformed") == 15:
                    break
                time.sleep(0.1)
            assert s1["ticks"] == 5 and s2["ticks"] == 5, (s1, s2)
            assert s1["rejected"]["malformed"] == 15 and not s2["rejected"], (s1, s2)
            assert p.poll() is None
        finally:
            p.terminate()
            _, err = p.communicate(timeout=10)
    assert p.returncode == 143, err


@pytest.mark.slow
def test_one_configured_agents_failure_leaves_its_hostmate_running(tmp_path):
    """Agent 1's loop fails outright (a node error would be counted, as above): the host says
    why in one line and agent 2, built from its file in the same host, goes on stepping."""
    from agents.cli.deploy import _configured_agents

    swarm, here = "c" + uuid.uuid4().hex[:8], f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("router", listen=[here])))
    paths = [companion(tmp_path, aid, swarm, zenoh={"mode": "client", "connect": [here]}) for aid in (1, 2)]

    class Ctx:  # what _configured_agents reads of typer's context: no option but --config given
        class command:
            params = []

    said = []
    host = Host(_configured_agents(Ctx, [Path(p) for p in paths], False), lambda line, why: said.append(why))
    try:
        host.command("start 1")
        host.command("start 2")
        assert _stats(router, swarm, 1)["id"] == 1 and _stats(router, swarm, 2)["id"] == 2

        def fail():
            raise RuntimeError("the loop itself fails")

        host.agents[1].daemon._publish_estimate = fail
        router.put(wire.Keys(swarm).sensors(1), _frame(1, 1))
        assert host.agents[1].ended.wait(10)
        assert said == ["agent 1: its loop failed (RuntimeError: the loop itself fails); the other agents of this "
                        "process go on"]
        assert _stats(router, swarm, 1, timeout=1.0) is None
        router.put(wire.Keys(swarm).sensors(2), _frame(2, 1))
        deadline = time.monotonic() + 10
        while (_stats(router, swarm, 2) or {}).get("ticks") != 1 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert _stats(router, swarm, 2)["ticks"] == 1 and not host.done()
    finally:
        host.stop()
        router.close()


# ---------------------------------------------------------------------------- what cannot share a process


def test_two_files_of_one_id_are_refused(tmp_path):
    a = companion(tmp_path, 3, "s")
    (tmp_path / "b").mkdir()
    b = companion(tmp_path / "b", 3, "other")
    p = swarmloc("agent", "--config", a, "--config", b)
    assert p.returncode == 2 and p.stdout == ""
    assert p.stderr.splitlines() == [
        f"error: {b}: id: 3 is {a}'s id too: the agents of one process are told apart by their ids (their threads, "
        "log lines and checkpoints agent-<id>.state.npy)"]


def test_what_one_process_cannot_hold_twice_is_named(tmp_path):
    a = companion(tmp_path, 1, "s", zenoh={"listen": ["tcp/0.0.0.0:7449"]},
                  sensors=[{"kind": "mavlink", "url": "udpin:0.0.0.0:14540"}], outputs={"log": "est.jsonl"})
    b = companion(tmp_path, 2, "s", zenoh={"listen": ["tcp/127.0.0.1:7449"]},
                  sensors=[{"kind": "mavlink", "url": "udpin:127.0.0.1:14540"}], outputs={"log": "./est.jsonl"})
    c = companion(tmp_path, 3, "s", zenoh={"listen": ["tcp/127.0.0.1:7450"]},
                  sensors=[{"kind": "mavlink", "url": "udpin:0.0.0.0:14541"}], outputs={"log": "est-3.jsonl"})
    p = swarmloc("agent", "--config", a, "--config", b, "--config", c, "--check-config")
    assert p.returncode == 2 and p.stdout == ""
    log = tmp_path / "est.jsonl"
    assert p.stderr.splitlines() == [
        f"error: {b}: zenoh.listen.0: tcp/127.0.0.1:7449 is {a}'s zenoh.listen.0 too (tcp/0.0.0.0:7449): two Zenoh "
        "sessions cannot listen on one port",
        f"error: {b}: sensors.0.url: udpin:127.0.0.1:14540 is {a}'s sensors.0.url too (udpin:0.0.0.0:14540): a flight "
        "controller link is one agent's (a serial device or a UDP port opens once, and a flight controller follows "
        "one companion's estimate)",
        f"error: {b}: outputs.log: {log} is {a}'s outputs.log too: two agents cannot write one file"]
    p = swarmloc("agent", "--config", a, "--config", c, "--check-config")
    assert p.returncode == 0, p.stderr
    assert [line for line in p.stdout.splitlines() if not line.startswith(" ")] == [
        f"{a}: a valid agent configuration", f"{c}: a valid agent configuration"]


def test_every_bad_file_is_listed_before_anything_starts(tmp_path):
    a = companion(tmp_path, 1, "s", gate=2)
    b = companion(tmp_path, 2, "s", radio="carrier-pigeon")
    p = swarmloc("agent", "--config", a, "--config", b)
    assert p.returncode == 2
    assert [line.split(": ")[1:3] for line in p.stderr.splitlines()] == [[a, "gate"], [b, "radio"]]


def test_netsim_radio_takes_frames_from_netsim_only(tmp_path):
    from agents.config import ConfigError

    path = companion(tmp_path, 1, "s", radio="netsim", sensors=[{"kind": "zenoh", "key": "drivers/uwb/1"}])
    with pytest.raises(ConfigError) as info:
        load(path)
    assert info.value.lines == ["sensors.0.key: radio netsim: sensor frames come from netsim, on "
                                "swarmloc/s/agent/1/sensors (null), not drivers/uwb/1"]
    cfg = load(companion(tmp_path, 1, "s", radio="netsim", sensors=[{"kind": "zenoh"}]))
    from agents.config import daemon_config

    assert daemon_config(cfg).direct is False and daemon_config(load(companion(tmp_path, 1, "s"))).direct is True
