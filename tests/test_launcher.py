"""`swarmloc run` as a supervisor: crashed agents, a dying launcher, the run directory, the
runtime file that lets control commands find a swarm by name."""

import json
import os
import signal
import stat
import subprocess
import time

import numpy as np
import pytest
from conftest import agent_pid, netsim_pid, swarm_pids

from swarmloc.experiment import scenario as S


def scenario_file(tmp_path, duration):
    path = tmp_path / f"wang2019-{duration:g}.yaml"
    path.write_text(S.load("wang2019").with_overrides(**{"clock.duration": duration}).to_yaml())
    return path


def eventually(predicate, what, timeout=15.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


def test_default_out_never_collides(tmp_path, monkeypatch):
    from agents.launcher import make_out

    monkeypatch.chdir(tmp_path)
    outs = [make_out(None, "wang2019") for _ in range(3)]
    assert len(set(outs)) == 3 and all((o / "logs").is_dir() for o in outs)


def test_force_empties_an_old_run_directory(tmp_path):
    from agents.launcher import check_out, make_out

    out = tmp_path / "run"
    (out / "plots").mkdir(parents=True)
    (out / "plots" / "old.png").write_bytes(b"")
    (out / "metrics.json").write_text("{}")
    check_out(out, force=True)
    assert make_out(out, "x") == out
    assert [p.name for p in out.iterdir()] == ["logs"]


@pytest.mark.slow
def test_a_crashed_agent_is_reported_and_the_run_completes(cli, tmp_path):
    out = tmp_path / "run"
    run = cli.start_run(str(scenario_file(tmp_path, 150.0)), out)
    cli.wait_tick(30, run)
    os.kill(agent_pid(cli.swarm, 3), signal.SIGKILL)
    stdout, stderr = run.communicate(timeout=300)
    assert run.returncode == 0, stderr
    assert "agent-3 crashed (exit code -9: SIGKILL" in stderr and "the run goes on without it" in stderr
    assert "agent-3 crashed" in stdout and "left out" in stdout  # and in the summary
    m = json.loads((out / "metrics.json").read_text())
    assert m["crashes"] == [{"agent": 3, "returncode": -9, "restarted": False}]
    with np.load(out / "estimates" / "ukf-dcl.npz") as e:
        mean = e["mean"]
    assert np.isnan(mean[-1, 2]).all() and not np.isnan(mean[:, [0, 1, 3]]).any()


@pytest.mark.slow
def test_restart_crashed_brings_the_agent_back_from_its_checkpoint(cli, tmp_path):
    out = tmp_path / "run"
    run = cli.start_run(str(scenario_file(tmp_path, 150.0)), out, "--restart-crashed")
    cli.wait_tick(30, run)
    os.kill(agent_pid(cli.swarm, 3), signal.SIGKILL)
    stdout, stderr = run.communicate(timeout=300)
    assert run.returncode == 0, stderr
    assert "restarting it from its checkpoint" in stderr
    m = json.loads((out / "metrics.json").read_text())
    assert m["crashes"] == [{"agent": 3, "returncode": -9, "restarted": True}]
    assert "resumed from its checkpoint" in (out / "logs" / "agent-3.log").read_text()
    with np.load(out / "estimates" / "ukf-dcl.npz") as e:
        assert not np.isnan(e["mean"][-1]).any()


@pytest.mark.slow
def test_a_crashed_netsim_still_fails_the_run(cli, tmp_path):
    run = cli.start_run(str(scenario_file(tmp_path, 1000.0)), tmp_path / "run")
    cli.wait_tick(30, run)
    os.kill(netsim_pid(cli.swarm), signal.SIGKILL)
    stdout, stderr = run.communicate(timeout=60)
    assert run.returncode == 1
    assert stderr.startswith("error: netsim failed (exit code -9: SIGKILL)")
    # What the recording held is rebuilt (test_trust checks it bit for bit) and marked as a run
    # that ended early; a recording not yet flushed leaves no metrics.json and says so.
    metrics = tmp_path / "run" / "metrics.json"
    if "rebuilt from" in stderr:
        m = json.loads(metrics.read_text())
        steps = S.load("wang2019").with_overrides(**{"clock.duration": 1000.0}).clock.steps
        assert m["ticks"] == m["ended_early"]["last_tick"] + 1 < steps
    else:
        assert "nothing to rebuild the results from" in stderr and not metrics.exists()
    eventually(lambda: not swarm_pids(cli.swarm), "the agents to stop")


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGHUP])
def test_the_swarm_dies_with_its_launcher(cli, tmp_path, sig):
    run = cli.start_run(str(scenario_file(tmp_path, 1000.0)), tmp_path / "run")
    cli.wait_tick(30, run)
    assert len(swarm_pids(cli.swarm)) == 6  # the launcher, netsim and 4 agents
    run.send_signal(sig)
    stdout, stderr = run.communicate(timeout=30)
    if sig == signal.SIGHUP:  # a closed terminal: the launcher stops the swarm itself
        assert run.returncode == 128 + sig and "interrupted (SIGHUP)" in stderr
    eventually(lambda: not swarm_pids(cli.swarm), f"every process of the swarm to go after {sig.name}")
    # The port and the swarm name are free again: a new run on them starts and completes.
    again = cli.start_run(str(scenario_file(tmp_path, 10.0)), tmp_path / "again")
    stdout, stderr = again.communicate(timeout=120)
    assert again.returncode == 0, stderr


@pytest.mark.slow
def test_control_commands_find_the_swarm_by_name(cli, tmp_path, monkeypatch):
    # Not the runs' working directory: a `swarmloc` folder there would shadow the package.
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "xdg"))
    entry = tmp_path / "xdg" / "swarmloc" / f"{cli.swarm}.json"
    out = tmp_path / "run"
    run = cli.start_run(str(scenario_file(tmp_path, 1000.0)), out)
    cli.wait_tick(10, run)
    info = json.loads(entry.read_text())
    assert info["endpoint"] == cli.endpoint and info["pid"] == run.pid and info["out"] == str(out)
    assert stat.S_IMODE(entry.stat().st_mode) == 0o600

    p = cli.run("status", "--json", "--swarm", cli.swarm)  # no --connect
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout)["k"] >= 10

    taken = cli.run("run", "wang2019", "--port", "0", "--swarm", cli.swarm, "--out", str(tmp_path / "second"))
    assert taken.returncode == 2 and f"swarm '{cli.swarm}' is already running" in taken.stderr

    # Into a pipe, --watch writes one plain line per refresh, as it goes.
    watch = subprocess.Popen(cli.cmd("status", "--watch", "--interval", "0.2", "--swarm", cli.swarm),
                             stdout=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        lines = [watch.stdout.readline() for _ in range(2)]
    finally:
        watch.terminate()
        watch.wait(10)
    for line in lines:
        assert line.startswith("tick ") and "agents alive 4/4" in line and "links up 6 down 0" in line, lines

    run.terminate()
    run.communicate(timeout=60)
    assert not entry.exists()


def test_netsim_slow_to_listen_is_waited_for_and_a_dead_one_is_not():
    import socket
    import sys

    from agents.launcher import _wait_listening

    with socket.socket() as s:  # listening: at once
        s.bind(("127.0.0.1", 0))
        s.listen()
        sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
        try:
            assert _wait_listening(s.getsockname()[1], sleeper, timeout=5.0)
        finally:
            sleeper.kill()
            sleeper.wait()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # bound, not listening: nobody answers
        sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
        try:
            assert not _wait_listening(port, sleeper, timeout=0.5)  # alive but not listening: the time is up
        finally:
            sleeper.kill()
            sleeper.wait()
        dead = subprocess.Popen([sys.executable, "-c", "pass"])
        dead.wait()
        assert not _wait_listening(port, dead, timeout=5.0)  # ended: no wait at all
