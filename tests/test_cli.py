"""The command line without a running swarm: listings and clear errors."""

import subprocess
import sys


def swarmloc(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "agents", *args], capture_output=True, text=True, timeout=60, cwd=cwd)


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


def test_inject_without_a_swarm_says_so():
    from conftest import free_port

    p = swarmloc("inject", "cut", "1", "2", "--connect", f"tcp/127.0.0.1:{free_port()}")
    assert p.returncode != 0
    assert "cannot reach netsim" in p.stderr or "no netsim answered" in p.stderr


def test_agent_needs_a_start():
    p = swarmloc("agent", "--id", "1")
    assert p.returncode == 2 and "--scenario or --start" in p.stderr
