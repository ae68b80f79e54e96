"""The command line without a running swarm: listings and clear errors."""

import json
import os
import select
import subprocess
import sys

import pytest

from conftest import free_port


def swarmloc(*args, cwd=None, env=None):
    return subprocess.run([sys.executable, "-m", "agents", *args], capture_output=True, text=True, timeout=60, cwd=cwd,
                          env=env)


def one_line_error(p: subprocess.CompletedProcess) -> str:
    """The single `error: ...` line of a failed command; no traceback, no Rust source path."""
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), p.stderr
    assert "Traceback" not in p.stderr and ".rs:" not in p.stderr and "Error:" not in p.stderr
    return lines[0]


def test_scenarios_lists_builtins():
    p = swarmloc("scenarios")
    assert p.returncode == 0
    assert "wang2019" in p.stdout and "random7" in p.stdout


def test_bad_scenario_names_the_field(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("version: 1\nname: x\nworld:\n  agents:\n    - {id: 1, start: [0, 0]}\nsensors:\n  range: {probability: 2}\n")
    p = swarmloc("run", str(bad), cwd=tmp_path)
    assert p.returncode == 2
    assert "sensors.range.probability" in p.stderr


def test_unknown_scenario():
    p = swarmloc("run", "nope")
    assert p.returncode == 2 and "neither a scenario file nor a built-in" in p.stderr


def test_agent_needs_a_start():
    p = swarmloc("agent", "--id", "1")
    assert p.returncode == 2 and "--scenario, --start or --spec" in p.stderr


@pytest.mark.parametrize("args, named", [
    (["run", "wang2019", "--seed", "-1"], "--seed"),
    (["run", "wang2019", "--port", "99999"], "--port"),
    (["run", "wang2019", "--port", "-1"], "--port"),
    (["run", "wang2019", "--port", "seven"], "--port"),
    (["demo", "--port", "70000"], "--port"),
    (["run", "wang2019", "--swarm", "a/b"], "--swarm"),
    (["status", "--interval", "-1", "--watch"], "--interval"),
    (["status", "--interval", "nan", "--watch"], "--interval"),
    (["status", "--connect", "localhost"], "--connect"),
    (["inject", "cut", "1", "2", "--for", "-5"], "duration"),
    (["inject", "loss", "-0.1"], "probability"),
    (["inject", "loss", "0.1", "--link", "1"], "--link"),
    (["inject", "partition", "1,x", "3"], "GROUPS"),
    (["inject", "jammer", "-40", "10", "--velocity", "1"], "--velocity"),
    (["inject", "jammer", "-40", "10", "--velocity", "nan,0"], "--velocity"),
    (["agent", "--id", "1", "--start", "0,0", "--initial-std", "-1"], "--initial-std"),
    (["agent", "--id", "1", "--start", "0,inf"], "--start"),
    (["agent", "--id", "1", "--start", "0,0", "--mode", "router"], "--mode"),
    (["agent", "--id", "1", "--start", "0,0", "--estimator", "kalman"], "--estimator"),
    (["agent", "--id", "1", "--start", "0,0", "--estimator", "ekf-ci"], "--estimator"),
    (["run", "wang2019", "--estimator", "ekf-ci"], "--estimator ekf-ci runs on models"),
    (["agent", "--id", "9", "--scenario", "wang2019"], "--id"),
])
def test_a_bad_argument_is_one_line_naming_it(tmp_path, args, named):
    p = swarmloc(*args, cwd=tmp_path)
    assert p.returncode == 2, p.stderr
    assert named in one_line_error(p)
    assert not (tmp_path / "runs").exists()


def test_an_unusable_out_is_one_line(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("")
    for out in (afile, afile / "run"):
        p = swarmloc("run", "wang2019", "--out", str(out), "--port", "0", "--swarm", f"t{os.getpid()}", cwd=tmp_path)
        assert p.returncode == 2
        assert "--out" in one_line_error(p)


def test_a_non_empty_out_needs_force_and_force_only_empties_a_run_directory(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    p = swarmloc("run", "wang2019", "--out", str(out), cwd=tmp_path)
    assert p.returncode == 2 and "--force" in one_line_error(p)
    p = swarmloc("run", "wang2019", "--out", str(out), "--force", cwd=tmp_path)
    assert p.returncode == 2 and "not a swarmloc run directory" in one_line_error(p)
    assert (out / "notes.txt").read_text() == "mine"


def test_control_commands_without_a_swarm_say_so(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    for args in (["status"], ["status", "--watch"], ["faults"], ["clear", "3"], ["inject", "cut", "1", "2"]):
        p = swarmloc(*args, "--swarm", "nobody", "--connect", endpoint, cwd=tmp_path)
        assert p.returncode == 1, (args, p.stderr)
        # status also asks the agents themselves (a swarm without netsim), so says nobody answered
        want = (f"error: no swarm 'nobody' answers on {endpoint}: neither netsim nor any agent" if args[0] == "status"
                else f"error: no swarm 'nobody' is running on {endpoint} (start one with `swarmloc run`)")
        assert one_line_error(p) == want


def runtime_env(tmp_path) -> dict:
    # Not the working directory itself: a `swarmloc` folder there would shadow the package
    # for `python -m` (the current directory comes first on sys.path).
    return {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path / "xdg")}


def test_control_commands_find_a_registered_swarm_and_drop_a_stale_entry(tmp_path):
    (tmp_path / "xdg" / "swarmloc").mkdir(parents=True)
    entry = tmp_path / "xdg" / "swarmloc" / "reg.json"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    entry.write_text(json.dumps({"swarm": "reg", "pid": os.getpid(), "endpoint": endpoint}))  # a live pid
    p = swarmloc("status", "--swarm", "reg", env=runtime_env(tmp_path))
    assert p.returncode == 1 and endpoint in one_line_error(p)
    assert entry.exists()

    dead = subprocess.Popen(["true"])
    dead.wait()
    entry.write_text(json.dumps({"swarm": "reg", "pid": dead.pid, "endpoint": endpoint}))
    p = swarmloc("faults", "--swarm", "reg", env=runtime_env(tmp_path))
    assert p.returncode == 1 and "tcp/127.0.0.1:7447" in one_line_error(p)
    assert not entry.exists()


def test_every_option_and_argument_has_help():
    import typer

    from agents.cli import app

    def walk(cmd, path):
        for name, sub in getattr(cmd, "commands", {}).items():
            yield from walk(sub, [*path, name])
        for param in cmd.params:
            yield " ".join(path), param

    missing = [f"{path}: {param.name}" for path, param in walk(typer.main.get_command(app), ["swarmloc"])
               if not getattr(param, "help", None)]
    assert not missing


def test_demo_takes_the_options_of_run():
    p = swarmloc("demo", "--help")
    for opt in ("--port", "--seed", "--swarm", "--force", "--no-plots", "--out"):
        assert opt in p.stdout


def test_agent_logs_what_it_waits_for(tmp_path):
    listen, nowhere = (f"tcp/127.0.0.1:{free_port()}" for _ in range(2))
    p = subprocess.Popen([sys.executable, "-m", "agents", "agent", "--id", "1", "--start", "0,0", "--direct", "-v",
                          "--mode", "peer", "--listen", listen, "--connect", nowhere, "--swarm", f"w{os.getpid()}"],
                         stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        ready, _, _ = select.select([p.stderr], [], [], 30)
        line = p.stderr.readline() if ready else ""
    finally:
        p.terminate()
        p.wait(10)
    assert "INFO" in line and "peer mode" in line and listen in line and nowhere in line
    assert f"swarmloc/w{os.getpid()}/agent/1/sensors" in line and "radio/rx/all" in line


def test_a_built_in_scenario_prints_as_yaml_that_loads_back(tmp_path):
    p = swarmloc("scenarios", "goel-dist", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    (tmp_path / "mine.yaml").write_text(p.stdout)
    from swarmloc import scenario as S

    assert S.load(tmp_path / "mine.yaml") == S.load("goel-dist")
