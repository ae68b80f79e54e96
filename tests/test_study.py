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
    assert plots == ["error_vs_time.png", "mean_error_m_vs_sensors.range.noise.png",
                     "nees_mean_vs_sensors.range.noise.png"]
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
