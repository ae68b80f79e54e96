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


@pytest.mark.slow
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


@pytest.mark.slow
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
    from swarmloc.experiment import scenario as S

    assert S.load(tmp_path / "mine.yaml") == S.load("goel-dist")


# ------------------------------------------------------------------ what a newcomer trips on


def test_tables_in_a_pipe_are_complete():
    """Off a terminal nothing is cut to 80 columns: every name and description whole, no "…"."""
    from swarmloc.estimators import REGISTRY
    from swarmloc.experiment import scenario as S

    p = swarmloc("scenarios")
    assert p.returncode == 0 and "…" not in p.stdout
    for name in S.builtin_names():
        line = next(line for line in p.stdout.splitlines() if f" {name} " in line)
        assert S.load(name).description in line  # on one line, whole
    p = swarmloc("estimators")
    assert p.returncode == 0 and "…" not in p.stdout
    assert all(e.description in p.stdout for e in REGISTRY)


def test_table_commands_print_json():
    from swarmloc.estimators import REGISTRY
    from swarmloc.experiment import scenario as S

    rows = json.loads(invoke("scenarios", "--json").output)
    assert [r["name"] for r in rows] == S.builtin_names() and rows[0]["duration_s"] > 0
    rows = json.loads(invoke("estimators", "--json").output)
    assert [r["name"] for r in rows] == [e.name for e in REGISTRY]
    import typer

    from agents.cli import app

    commands = typer.main.get_command(app).commands
    for name in ("run", "demo", "replay", "calibrate", "status", "faults", "study", "scenarios", "estimators"):
        assert any("--json" in p.opts for p in commands[name].params), name


def invoke(*args):
    """The command in this process (typer's runner: output not a terminal), for checks without a run."""
    from typer.testing import CliRunner

    from agents.cli import app

    return CliRunner().invoke(app, list(args))


def test_run_sets_the_clock_from_the_command_line():
    for command in ("run", "demo"):
        text = invoke(command, "--help").output
        for opt in ("--realtime", "--lockstep", "--speed", "--duration"):
            assert opt in text, (command, opt)
    from agents.cli.common import load_scenario

    sc = load_scenario("wang2019", realtime=True, speed=4.0, duration=60.0)
    assert (sc.clock.mode, sc.clock.speed, sc.clock.duration, sc.clock.steps) == ("realtime", 4.0, 60.0, 120)
    assert load_scenario("wang2019").clock.mode == "lockstep"


@pytest.mark.parametrize("args, says", [
    (["run", "wang2019", "--speed", "2"], "--speed"),  # lockstep has no speed
    (["run", "wang2019", "--duration", "-5"], "--duration"),
    (["run", "wang2019", "--estimator", "csl-ctl"], "--estimator: csl-ctl needs targets"),
    (["run", "random7", "--estimator", "il-ctl"], "--estimator: il-ctl needs targets"),
    (["replay", "nowhere", "--estimator", "csl-ctl"], "--estimator"),
    (["replay", "nowhere", "--estimator", "il-ctl"], "an MR.CLAM recording has none"),
    (["replay", "nowhere", "--speed", "5"], "add --realtime"),
    (["inject", "cut", "1"], "Missing argument 'B'"),  # as the help names it: swarmloc inject cut A B
    (["inject", "kill"], "Missing argument 'NODE'"),
    (["run", "wang2019", "--seed", "x"], "--seed': must be a whole number"),
])
def test_errors_name_what_the_user_typed(args, says):
    r = invoke(*args)
    lines = r.output.strip().splitlines()
    assert r.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error: "), r.output
    assert says in lines[0] and "Input should" not in lines[0]


def test_replay_errors_name_its_options(tmp_path):
    import mrclam_synth

    data = mrclam_synth.write(tmp_path / "MRCLAM_Synthetic", seed=4)
    for args, option in ((["--offset", "99999"], "--offset: the recording spans"),
                         (["--duration", "99999"], "--duration: the recording has"),
                         (["--robots", "1,9"], "--robots: the recording has robots")):
        r = invoke("replay", str(data), *args)
        assert r.exit_code == 2 and option in r.output, r.output
        assert "world." not in r.output and "clock." not in r.output and len(r.output.strip().splitlines()) == 1


def test_a_second_run_takes_the_next_free_swarm_name(tmp_path, monkeypatch):
    from agents.control import Registration, SwarmTaken

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "xdg"))
    first = Registration("default", endpoint="tcp/127.0.0.1:7447")
    try:
        with pytest.raises(SwarmTaken):  # a --swarm given is taken or refused, never renamed
            Registration("default", endpoint="tcp/127.0.0.1:7448")
        second, taken = Registration.first_free("default", endpoint="tcp/127.0.0.1:7448")
        third, taken3 = Registration.first_free("default", endpoint="tcp/127.0.0.1:7449")
        assert (second.swarm, third.swarm) == ("default-2", "default-3")
        assert [t["swarm"] for t in taken] == ["default"] and [t["swarm"] for t in taken3] == ["default", "default-2"]
        second.remove()
        again, _ = Registration.first_free("default", endpoint="tcp/127.0.0.1:7450")
        assert again.swarm == "default-2"  # a name is free again once its run has ended
    finally:
        for r in (first, third, again):
            r.remove()


def test_status_says_what_alive_and_responsive_mean():
    import io

    from rich.console import Console

    from agents.cli.status import _status_view

    s = {"scenario": "x", "mode": "lockstep", "radio": "unit-disk", "k": 10, "steps": 800, "t": 5.0, "links": [],
         "agents": {"1": {"alive": True, "responsive": True, "done_k": 10},
                    "3": {"alive": False, "responsive": True, "done_k": 4},
                    "4": {"alive": False, "responsive": True, "done_k": 4},
                    "2": {"alive": True, "responsive": False, "done_k": 2}},
         "faults": [{"id": 5, "action": "kill", "args": {"node": 3}, "since": 2.0, "until": 22.0}]}
    out = io.StringIO()
    Console(file=out, width=100_000, soft_wrap=True).print(_status_view(s))
    rows = {line.split("│")[1].strip(): line for line in out.getvalue().splitlines() if line.startswith("│")}
    assert "killed by fault #5 until t = 22.0 s" in rows["3"]
    assert "no process" in rows["4"] and "given up" in rows["2"] and "running" in rows["1"]
    assert "alive: its process holds its Zenoh liveliness token" in out.getvalue()


@pytest.mark.parametrize("fault, words", [
    ({"action": "kill", "duration": 10.0, "node": 3}, "kill node 3, for 10 s"),
    ({"action": "cut", "link": [3, 4], "direction": "forward"}, "cut link 3-4, direction forward"),
    ({"action": "partition", "groups": [[1, 2], [3, 4]]}, "partition groups (1-2, 3-4)"),
    ({"action": "jammer", "name": "j1", "position": [40.0, 60.0], "power_dbm": 30.0, "velocity": [0.0, 0.5],
      "radius_m": 50.0}, "jammer name j1, position (40, 60), power 30 dBm, velocity (0, 0.5), radius 50 m"),
    ({"action": "clear-loss"}, "clear-loss"),
])
def test_inject_says_the_fault_in_words(fault, words):
    from agents.cli.faults import describe_fault

    assert describe_fault(fault) == words
