"""`swarmloc study`: Monte Carlo sweeps over a process pool or Dask, resumable, deterministic."""

import csv
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from netsim.study import StudyError, load_spec, parse_spec, plan, run_study

SPEC = {"name": "tiny", "scenario": "wang2019", "overrides": {"clock.duration": 5.0}, "estimator": "il",
        "references": ["ukf-ccl"], "sweep": [{"param": "sensors.range.noise", "values": [0.5, 2.0]}],
        "runs": 3, "base_seed": 10, "workers": 2}


def spec(**changes):
    return parse_spec({**SPEC, **changes})


def table(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def baseline(tmp_path_factory):
    out = tmp_path_factory.mktemp("study") / "base"
    return run_study(spec(), out), out


def test_table_has_every_point_run_and_estimator_and_is_deterministic(baseline, tmp_path):
    result, out = baseline
    assert result.complete and result.executed == 6 and result.total == 6
    rows = table(out / "results.csv")
    assert len(rows) == 2 * 3 * 2  # points x runs x estimators
    assert {(r["sensors.range.noise"], r["run"], r["seed"], r["estimator"]) for r in rows} == {
        (n, str(r), str(10 + r), e) for n in ("0.5", "2.0") for r in range(3) for e in ("il", "ukf-ccl")}
    assert all(float(r["mean_error_m"]) > 0 and r["ticks"] == "11" for r in rows)
    assert "wall_s" not in rows[0]  # timings are in timing.csv: results.csv is the same every time
    assert len(table(out / "timing.csv")) == 6 and len(table(out / "summary.csv")) == 4
    s = table(out / "summary.csv")[0]
    assert s["mean_error_m_n"] == "3" and float(s["mean_error_m_ci95"]) > 0
    assert len(list((out / "series").glob("*.npz"))) == 6

    again = run_study(spec(workers=1), tmp_path / "again", plots=False)
    assert again.executed == 6
    assert (tmp_path / "again" / "results.csv").read_bytes() == (out / "results.csv").read_bytes()
    assert (tmp_path / "again" / "summary.csv").read_bytes() == (out / "summary.csv").read_bytes()


def test_tables_carry_the_bound_and_the_ratio_to_it(baseline):
    _, out = baseline
    rows = table(out / "results.csv")
    for r in rows:
        assert float(r["pcrb_m"]) > 0 and float(r["rmse_over_pcrb"]) == pytest.approx(float(r["rmse_m"]) / float(r["pcrb_m"]))
    by_run = {}
    for r in rows:  # the bound is the problem's, not the estimator's: the same for both in a run
        by_run.setdefault((r["point"], r["run"]), set()).add(r["pcrb_m"])
    assert all(len(v) == 1 for v in by_run.values())
    s = table(out / "summary.csv")
    assert {"pcrb_m_mean", "rmse_over_pcrb_mean", "rmse_over_pcrb_ci95"} <= set(s[0])
    assert all(float(r["rmse_over_pcrb_n"]) == 3 for r in s)


@pytest.mark.slow
def test_resume_computes_only_the_missing_runs(baseline, tmp_path):
    _, base = baseline
    out = tmp_path / "resumed"
    first = run_study(spec(), out, max_tasks=2, plots=False)  # an interruption after two runs
    assert not first.complete and first.executed == 2 and first.done == 2
    assert not (out / "results.csv").exists()
    lines = (out / "runs.jsonl").read_text().splitlines()
    (out / "runs.jsonl").write_text(lines[0] + "\n" + lines[1][:20])  # and a torn last line
    second = run_study(spec(), out, plots=False)
    assert second.complete and second.executed == 5 and second.done == 6
    assert (out / "results.csv").read_bytes() == (base / "results.csv").read_bytes()
    third = run_study(spec(), out, plots=False)
    assert third.executed == 0 and third.complete
    more = run_study(spec(), out, runs=4, plots=False)  # more runs per point: the same study, extended
    assert more.executed == 2 and len(table(out / "results.csv")) == 16


@pytest.mark.slow
def test_other_spec_in_the_same_directory_is_an_error_unless_forced(baseline, tmp_path):
    out = tmp_path / "s"
    run_study(spec(), out, max_tasks=1, plots=False)
    other = spec(base_seed=99)
    with pytest.raises(StudyError, match="holds another study"):
        run_study(other, out, plots=False)
    assert run_study(other, out, plots=False, force=True, max_tasks=1).executed == 1


@pytest.mark.slow
def test_dask_cluster_gives_the_same_table(baseline, tmp_path):
    distributed = pytest.importorskip("distributed")
    _, base = baseline
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        result = run_study(spec(), tmp_path / "dask", scheduler=cluster.scheduler_address, plots=False)
    assert result.complete and result.executed == 6
    assert (tmp_path / "dask" / "results.csv").read_bytes() == (base / "results.csv").read_bytes()


def test_importing_the_study_module_does_not_import_dask():
    code = "import sys, netsim.study; assert not any(m.split('.')[0] in ('dask', 'distributed') for m in sys.modules)"
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


@pytest.mark.parametrize("changes, field", [
    ({"sweeps": []}, "sweeps"),
    ({"sweep": [{"param": "sensors.range.noise", "values": []}]}, "sweep.0.values"),
    ({"sweep": [{"param": "sensors.range.noise"}]}, "give exactly one of values and same_as"),
    ({"sweep": [{"param": "sensors.range.max_range", "same_as": "radio.range_m"}]}, "sweep.0.same_as"),
    ({"runs": 0}, "runs"),
    ({"estimator": "nope"}, "estimator"),
    ({"overrides": {"seed": 3}}, "seed"),
])
def test_bad_spec_names_the_field(changes, field):
    with pytest.raises(StudyError, match=field.replace(".", r"\.")):
        spec(**changes)


@pytest.mark.parametrize("changes, field", [
    ({"overrides": {"sensors.range.nose": 1.0}}, "sensors.range.nose"),
    ({"overrides": {"sensor.range.noise": 1.0}}, "overrides.sensor.range.noise"),
    ({"sweep": [{"param": "radio.range", "values": [100]}]}, "radio.range"),
    ({"sweep": [{"param": "sensors.range.noise", "values": [1.0, -2.0]}]}, "sweep point 1"),
    ({"scenario": "no-such-scenario"}, "scenario"),
])
def test_bad_override_fails_before_any_run(changes, field, tmp_path):
    with pytest.raises(StudyError, match=field.replace(".", r"\.")):
        run_study(spec(**changes), tmp_path / "never")
    assert not (tmp_path / "never").exists()


def test_same_as_ties_two_parameters():
    p = plan(spec(sweep=[{"param": "radio.range_m", "values": [100.0, 300.0]},
                         {"param": "sensors.range.max_range", "same_as": "radio.range_m"},
                         {"param": "sensors.range.noise", "values": [0.5, 2.0]}]))
    assert p.points == [{"radio.range_m": r, "sensors.range.max_range": r, "sensors.range.noise": n}
                        for r in (100.0, 300.0) for n in (0.5, 2.0)]


def cli(*args, cwd):
    return subprocess.run([sys.executable, "-m", "agents", "study", *args], capture_output=True, text=True,
                          timeout=120, cwd=cwd)


@pytest.mark.slow
def test_cli_writes_the_tables_and_plots(tmp_path):
    (tmp_path / "spec.yaml").write_text(yaml.safe_dump({**SPEC, "metrics": ["mean_error_m", "nees_mean"]}))
    p = cli("spec.yaml", "--out", "st", "--runs", "2", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert "4 runs computed" in p.stdout and "ukf-ccl" in p.stdout
    assert len(table(tmp_path / "st" / "results.csv")) == 8
    plots = sorted(f.name for f in (tmp_path / "st" / "plots").iterdir())
    # The spec's metrics, then the bound's columns, which every run has (netsim.study.BOUND_COLUMNS).
    assert plots == ["error_vs_time.png", "mean_error_m_vs_sensors.range.noise.png",
                     "nees_mean_vs_sensors.range.noise.png", "pcrb_m_vs_sensors.range.noise.png",
                     "rmse_over_pcrb_vs_sensors.range.noise.png"]
    assert load_spec(tmp_path / "spec.yaml").runs == 3


@pytest.mark.slow
def test_cli_no_plots_and_one_line_errors(tmp_path):
    (tmp_path / "spec.yaml").write_text(yaml.safe_dump(SPEC))
    p = cli("spec.yaml", "--out", "st", "--runs", "2", "--no-plots", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "st" / "results.csv").exists() and not (tmp_path / "st" / "plots").exists()
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump({**SPEC, "overrides": {"clock.durration": 5}}))
    p = cli("bad.yaml", cwd=tmp_path)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: overrides.clock.durration")


def test_progress_lines_when_the_console_is_not_a_terminal(tmp_path):
    import io

    from rich.console import Console

    out = io.StringIO()
    result = run_study(spec(runs=2, sweep=[]), tmp_path / "st", console=Console(file=out, force_terminal=False))
    lines = out.getvalue().splitlines()
    assert result.complete and lines[0].startswith("study tiny: 0/2 runs done")
    assert any(line.startswith("study tiny: 1/2 runs,") for line in lines)  # the first result: a line at once
    assert lines[-1].startswith("study tiny: 2/2 runs,") and "ETA 0:00:00" in lines[-1]


@pytest.mark.slow
def test_sigint_to_the_pid_stops_the_study_with_the_resume_hint(tmp_path):
    """`swarmloc study SPEC & kill -INT $!`: started as a non-interactive shell starts a background
    job (SIGINT ignored), stderr a pipe; the signal to the pid stops it as Ctrl-C does."""
    import os
    import select
    import signal
    import time

    (tmp_path / "spec.yaml").write_text(yaml.safe_dump({**SPEC, "sweep": [], "runs": 40, "workers": 1}))
    p = subprocess.Popen([sys.executable, "-m", "agents", "study", "spec.yaml", "--out", "st", "--no-plots"],
                         cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    seen, deadline = [], time.monotonic() + 120
    try:
        while not any("1/40 runs" in line for line in seen) and time.monotonic() < deadline:
            if select.select([p.stderr], [], [], 1)[0]:
                seen.append(p.stderr.readline())
        assert any("1/40 runs" in line for line in seen), seen  # progress, though stderr is a pipe
        os.kill(p.pid, signal.SIGINT)
        _, err = p.communicate(timeout=60)
    finally:
        p.kill()
    assert p.returncode == 130, err
    assert "resume with: swarmloc study spec.yaml --out st" in err
    done = len((tmp_path / "st" / "runs.jsonl").read_text().splitlines())
    assert 1 <= done < 40


def test_settle_agent_columns_medians_and_list_valued_sweeps(tmp_path):
    """settle leaves the start out of every metric; agents adds a<id>_ columns; summary.csv has
    medians; a swept value may be a list (an agent set), plots included. Neither option changes
    the hash of a spec that does not use it (a finished study stays resumable)."""
    assert plan(spec()).spec_hash == plan(spec(settle=0.0, agents=[])).spec_hash != plan(spec(settle=2.0)).spec_hash
    assert plan(spec()).spec_hash != plan(spec(agents=[1])).spec_hash
    sweep = [{"param": "sensors.gnss.agents", "values": [None, [1, 2]]}]
    late = run_study(spec(sweep=sweep, runs=2, workers=1, settle=2.0, agents=[1], metrics=["mean_error_m", "a1_rmse_m"]),
                     tmp_path / "late")
    early = run_study(spec(sweep=sweep, runs=2, workers=1, agents=[1]), tmp_path / "early", plots=False)
    assert (tmp_path / "late" / "plots" / "mean_error_m_vs_sensors.gnss.agents.png").exists()
    rows = table(tmp_path / "late" / "results.csv")
    assert {"a1_mean_error_m", "a1_rmse_m", "a1_nees_mean"} <= set(rows[0]) and "a2_mean_error_m" not in rows[0]
    base = {(r["point"], r["run"], r["estimator"]): r for r in table(tmp_path / "early" / "results.csv")}
    assert any(r["mean_error_m"] != base[(r["point"], r["run"], r["estimator"])]["mean_error_m"] for r in rows)
    s = table(tmp_path / "late" / "summary.csv")[0]
    vals = sorted(float(r["a1_rmse_m"]) for r in rows if r["point"] == s["point"] and r["estimator"] == s["estimator"])
    assert float(s["a1_rmse_m_median"]) == pytest.approx(sum(vals) / 2)
    assert late.complete and early.complete
