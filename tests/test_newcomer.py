"""What a newcomer's scripts see (issue 27): the real `swarmloc` with stdout to a pipe, not a
terminal, prints every table whole (rich would lay it out for 80 columns and cut cells with
'…'), and `calibrate`, like every table command, prints JSON for scripts with --json."""

import json
import os
import re
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
from test_sources import agents  # noqa: F401  (the fixture that starts `swarmloc agent --config` processes)

from swarmloc.datasets import calibrate

ROOT = Path(__file__).resolve().parents[1]
EXCERPT = ROOT / "tests" / "data" / "mrclam_excerpt"


def piped(*args, cwd, timeout=120) -> subprocess.CompletedProcess:
    """`swarmloc ARGS` as a script runs it: stdout and stderr pipes, and no COLUMNS, which would
    hand rich a width a pipe does not have."""
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
    p = subprocess.run([sys.executable, "-m", "agents", *args], capture_output=True, text=True, timeout=timeout,
                       cwd=cwd, env=env)
    assert p.returncode == 0, f"swarmloc {' '.join(args)} failed ({p.returncode}):\n{p.stdout}\n{p.stderr}"
    return p


def header_cells(stdout: str, first: str) -> list[str]:
    """The column titles of the table whose header starts with `first`, a title over several
    lines joined by spaces ("ukf-dcl agents mean")."""
    lines = stdout.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("┃") and line.strip("┃ ").startswith(first))
    head = []
    for line in lines[start:]:
        if not line.startswith("┃"):
            break
        head.append([c.strip() for c in line.strip("┃").split("┃")])
    return [" ".join(filter(None, parts)) for parts in zip(*head)]


def body_rows(stdout: str, first: str) -> list[list[str]]:
    """The body lines of that table, as cells: a cell that wrapped is a line of its own here."""
    lines = stdout.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("┃") and line.strip("┃ ").startswith(first))
    body = []
    for line in lines[start + 1:]:
        if line.startswith("└"):
            break
        if line.startswith("│"):
            body.append([c.strip() for c in line.strip("│").split("│")])
    return body


def test_calibrate_prints_its_model_as_json_for_scripts(tmp_path):
    out = tmp_path / "noise.yaml"
    p = piped("calibrate", str(EXCERPT), "-o", str(out), "--json", cwd=tmp_path)
    # stdout is the model and nothing else: the file's model, field for field.
    assert calibrate.NoiseModel.parse(json.loads(p.stdout)) == calibrate.NoiseModel.load(out)
    assert f"wrote {out}" in p.stderr.replace("\n", "")
    # Without --json, the table, whole in a pipe: its headers alone are wider than 80 columns.
    p = piped("calibrate", str(EXCERPT), "-o", str(out), "--force", cwd=tmp_path)
    assert "…" not in p.stdout
    assert "landmarks: range std / m, bearing std (rad)" in header_cells(p.stdout, "robot")
    assert [r[0] for r in body_rows(p.stdout, "robot")] == [f"Robot{r}" for r in range(1, 6)]


def test_replay_output_in_a_pipe_is_complete(tmp_path):
    """The issue's `replay DATASET | cat` showed `0.3…` and `ukf-c…`: here 3 s of the excerpt
    (about 5 s of agent processes), every estimator's name whole and each row on one line."""
    out = tmp_path / "run"
    p = piped("replay", str(EXCERPT), "--duration", "3", "--out", str(out), "--no-plots", "--port", "0",
              "--swarm", "n" + uuid.uuid4().hex[:8], cwd=tmp_path, timeout=180)
    assert "…" not in p.stdout
    m = json.loads((out / "metrics.json").read_text())
    names = list(m["estimators"])
    assert {"ukf-dcl", "ukf-ccl", "ekf-ccl"} <= set(names)
    titles = header_cells(p.stdout, "")  # the position table: the first, its top-left cell empty
    assert {t.split()[0] for t in titles[1:]} - {"PCRB"} == set(names), titles
    rows = body_rows(p.stdout, "")
    assert [r[0] for r in rows] == [f"A{a}" for a in m["agents"]] + ["all"]
    assert sorted(r[0] for r in body_rows(p.stdout, "estimator")) == sorted(names)  # consistency: one line each
    # Numbers whole: A1's mean error as metrics.json has it.
    a1 = m["estimators"]["ukf-dcl"]["agents"]["1"]["mean_error_m"]
    assert float(rows[0][titles.index("ukf-dcl agents mean")]) == pytest.approx(a1, abs=0.005)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """Agent 1's sensor frames (wang2019, 10 s) under a long directory name: the `sources` cell
    of status is then wider than an 80-column layout gives it."""
    from netsim.sim import Simulation
    from swarmloc.experiment.runner import InProcessRunner, make_nodes
    from swarmloc.experiment.scenario import load as load_scenario

    sc = load_scenario("wang2019").with_overrides(**{"clock.duration": 10.0})
    record = InProcessRunner(Simulation(sc), make_nodes("il", sc)).run()
    path = tmp_path_factory.mktemp("recording") / ("sensor-frames-of-a-recorded-run-" + "x" * 40) / "sensors.npz"
    path.parent.mkdir()
    np.savez(path, **record.sensor_arrays())
    return path, sc.prior(1)[0].tolist()


def test_status_output_in_a_pipe_is_complete(tmp_path, agents, recording):  # noqa: F811
    path, prior = recording
    agent = agents(tmp_path, estimator={"name": "ukf-dcl"}, prior={"position": prior},
                   sensors=[{"kind": "file", "path": str(path), "speed": 1.0}])
    agent.wait_for("INFO agent 1 up")
    end = time.monotonic() + 10
    while True:  # the first frame goes in at once; the stats say so within a poll
        p = piped("status", "--swarm", agent.swarm, "--connect", agent.endpoint, cwd=tmp_path, timeout=30)
        if "frames" in p.stdout or time.monotonic() > end:
            break
        time.sleep(0.2)
    assert "…" not in p.stdout
    names = header_cells(p.stdout, "agent")
    (row,) = body_rows(p.stdout, "agent")  # one line: no cell wrapped
    row = dict(zip(names, row))
    assert row["estimator"] == "ukf-dcl"
    assert re.fullmatch(rf"file {re.escape(str(path))}: \d+/21 frames(, \d+ skipped)?", row["sources"]), row
