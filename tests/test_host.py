"""Several agents in one process (agents/host.py, `swarmloc run --agents-per-process K`): the
same swarm on the wire as one process each, bit for bit in lockstep; one agent's failure or
kill leaves its hostmates running."""

import json
import os
import signal
import time

import numpy as np
import pytest
import zenoh
from conftest import swarm_pids
from helpers import in_process
from test_determinism import sixteen_agents

from agents.daemon import AgentConfig
from agents.host import Host, Hosted
from swarmloc import wire
from swarmloc.estimators import REGISTRY
from swarmloc.experiment import scenario as S
from swarmloc.wire.messages import Reply, Sensors


@pytest.mark.slow
def test_k_agents_per_process_equal_in_process_bit_for_bit(cli, tmp_path):
    # Hosts of 5, 5, 5 and 1: uneven groups, and the partition's halves split across hosts.
    path = sixteen_agents(tmp_path)
    out = tmp_path / "run"
    cli.run("run", str(path), "--out", str(out), "--port", str(cli.port), "--swarm", cli.swarm, "--no-plots",
            "--agents-per-process", "5", check=True, timeout=400)
    assert sorted(p.name for p in (out / "logs").glob("host-*.log")) == [
        "host-1-5.log", "host-11-15.log", "host-16-16.log", "host-6-10.log"]
    assert not list((out / "logs").glob("agent-*.log"))
    m = json.loads((out / "metrics.json").read_text())
    assert m["unresponsive_agents"] == [] and len(m["agent_stats"]) == 16
    assert sum(s["outsider_commits"] for s in m["agent_stats"].values()) > 0  # the partition split the chains
    record, _, _ = in_process(S.load(str(path)))
    with np.load(out / "estimates" / "ukf-dcl.npz") as f:
        assert np.array_equal(f["mean"], record.trace("ukf-dcl").mean)
        assert np.array_equal(f["cov"], record.trace("ukf-dcl").cov)


def _scenario(tmp_path, faults, duration=40.0):
    sc = S.load("wang2019").with_overrides(**{"clock.duration": duration}, faults=faults)
    path = tmp_path / "sc.yaml"
    path.write_text(sc.to_yaml())
    return path


@pytest.mark.slow
def test_a_kill_fault_stops_one_agent_of_a_host_and_restarts_it(cli, tmp_path):
    out = tmp_path / "run"
    path = _scenario(tmp_path, [{"at": 10.0, "action": "kill", "node": 3, "duration": 5.0}])
    run = cli.start_run(str(path), out, "--agents-per-process", "2")
    stdout, stderr = run.communicate(timeout=300)
    assert run.returncode == 0, stderr
    assert "killed agent-3 (fault)" in stdout and "restarted agent-3 (fault)" in stdout
    assert "resumed from its checkpoint" in (out / "logs" / "host-3-4.log").read_text()
    with np.load(out / "estimates" / "ukf-dcl.npz") as e:
        mean = e["mean"]
    # Agent 3 was down for a while, its hostmate 4 never: an estimate at every tick; 3 is back at the end.
    assert np.isnan(mean[:, 2]).any() and not np.isnan(mean[:, [0, 1, 3]]).any()
    assert not np.isnan(mean[-1]).any()


@pytest.mark.slow
def test_a_crashed_host_is_every_agent_of_it_crashed_and_restarted(cli, tmp_path):
    out = tmp_path / "run"
    run = cli.start_run(str(_scenario(tmp_path, [], duration=150.0)), out, "--agents-per-process", "2",
                        "--restart-crashed")
    cli.wait_tick(30, run)
    host = next(pid for pid in swarm_pids(cli.swarm)
                if b"agents.host" in open(f"/proc/{pid}/cmdline", "rb").read() and
                b"1=" not in open(f"/proc/{pid}/cmdline", "rb").read())
    os.kill(host, signal.SIGKILL)
    stdout, stderr = run.communicate(timeout=300)
    assert run.returncode == 0, stderr
    m = json.loads((out / "metrics.json").read_text())
    assert m["crashes"] == [{"agent": 3, "returncode": -9, "restarted": True},
                            {"agent": 4, "returncode": -9, "restarted": True}]
    with np.load(out / "estimates" / "ukf-dcl.npz") as e:
        assert not np.isnan(e["mean"][-1]).any()


# ---------------------------------------------------------------------------- in one process, real sessions


def _stats(session, swarm: str, aid: int, timeout: float = 10.0) -> dict | None:
    """The agent's stats, asked until it answers (a session just opened takes a moment to be
    routed to) or `timeout` passes."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for reply in session.get(wire.Keys(swarm).stats(aid), timeout=1.0):
            if reply.ok is not None:
                return wire.decode(reply.ok.payload.to_bytes(), expect=(Reply,)).body.data
        time.sleep(0.1)
    return None


@pytest.mark.slow
def test_one_agents_failure_leaves_its_hostmates_running(tmp_path):
    """Agent 1's loop fails outright (not a node error, which the daemon counts): the host says
    `crashed 1`, agent 2 goes on answering; `kill 2` takes agent 2's token away, `start 2`
    brings it back from its checkpoint."""
    port = __import__("conftest").free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    router = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("router", listen=[endpoint])))
    swarm = "host" + str(os.getpid())
    sc = S.load("wang2019")
    info = REGISTRY[sc.estimator.name]
    settings = info.settings(sc.estimator.params)
    agents = []
    for aid in (1, 2):
        spec = tmp_path / f"agent-{aid}.node.json"
        spec.write_text(info.node_spec(sc, aid, settings).dumps())
        agents.append(Hosted(aid, spec, AgentConfig(swarm=swarm, connect=(endpoint,),
                                                    state_file=tmp_path / f"agent-{aid}.state.npy")))
    said: list[str] = []
    host = Host(agents, report=lambda line, why: said.append(line))
    try:
        host.command("start 1")
        host.command("start 2")
        host.command("start x")  # not a command: logged, ignored
        assert _stats(router, swarm, 1)["id"] == 1 and _stats(router, swarm, 2)["id"] == 2

        def fail():
            raise RuntimeError("the loop itself fails")

        host.agents[1].daemon._publish_estimate = fail  # the next input acknowledged ends agent 1's loop
        frame = wire.encode(Sensors(k=1, t=0.5, odometry=None, ranges=[]), 0, 1)
        router.put(wire.Keys(swarm).sensors(1), frame)
        deadline = time.monotonic() + 10
        while not host.agents[1].ended.is_set() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert said == ["crashed 1"]
        assert _stats(router, swarm, 1, timeout=1.0) is None
        assert _stats(router, swarm, 2)["id"] == 2  # its hostmate goes on
        host.agents[2].daemon._checkpoint()
        host.command("kill 2")
        assert _stats(router, swarm, 2, timeout=1.0) is None and not host.done()  # waits for `start 2`
        host.command("start 2")
        assert host.agents[2].daemon.resumed and _stats(router, swarm, 2)["id"] == 2
    finally:
        host.stop()
        router.close()
