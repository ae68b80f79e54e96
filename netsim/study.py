"""Monte Carlo studies: sweep scenario parameters, many seeded runs per point (docs/study.md).

A study spec (YAML, the pydantic models below; their field descriptions are the documentation)
names a scenario, fixed overrides, the swept parameters and the number of runs. Every run is
one in-process run (swarmloc.runner.InProcessRunner over netsim.sim.Simulation) of the
scenario with the point's overrides and seed `base_seed + run`, followed by the offline
references and `swarmloc.results.metrics`. A run depends on nothing else, so the same spec
gives the same results.csv whoever executes it: the local process pool (default) or a Dask
distributed cluster (`scheduler`). Dask is imported only when a scheduler is given.

Finished runs are appended to OUT/runs.jsonl one line each (flushed and fsynced), so an
interrupted study resumes where it stopped; the tables and plots are written when every run
is done.
"""

from __future__ import annotations

import csv
import hashlib
import itertools
import json
import math
import numbers
import os
import shutil
import time
import uuid
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

STUDY_FORMAT = 1
PATH_PATTERN = r"^[A-Za-z0-9_-]+(\.[A-Za-z0-9_-]+)*$"
# Nested metric dicts reported by their mean: NEES and NIS averages (results._average_with_bounds).
NESTED = ("nees", "nis")
RUN_COLUMNS = ("ticks",)  # deterministic per-run columns of results.csv (the stat_* columns follow)
TIMING_COLUMNS = ("wall_s", "cpu_s")  # never the same twice: timing.csv, not results.csv
MAX_TIME_LINES = 8  # error_vs_time.png: one line per point up to this many points, else the first point only


class StudyError(ValueError):
    """A study spec or output directory that cannot be used; the message names the field."""


class RunFailed(RuntimeError):
    """A run raised: the study stops (finished runs are kept; rerun to retry)."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class SweepParam(_Strict):
    param: str = Field(pattern=PATH_PATTERN, description="dotted path of a scenario field, as in `overrides` "
                       "(e.g. radio.range_m, sensors.range.noise, estimator.params.M)")
    values: list[Any] | None = Field(None, min_length=1, description="the values it takes; the study's points are "
                                     "the cartesian product of every parameter's values")
    same_as: str | None = Field(None, pattern=PATH_PATTERN, description="instead of values: take the value of "
                                "this other swept parameter at every point (tied parameters add no grid axis)")

    @model_validator(mode="after")
    def _one_source(self):
        if (self.values is None) == (self.same_as is None):
            raise ValueError(f"{self.param}: give exactly one of values and same_as")
        return self


class StudySpec(_Strict):
    name: str = Field(pattern=r"^[A-Za-z0-9_.-]+$", description="study name; default output directory studies/<name>/")
    scenario: str = Field(description="built-in scenario name (`swarmloc scenarios`) or a YAML file, relative to the "
                          "spec file's directory")
    overrides: dict[str, Any] = Field(default_factory=dict, description="fixed overrides of every run, dotted path: "
                                      "value (e.g. {clock.duration: 60, radio.range_m: 300})")
    estimator: str | None = Field(None, description="the estimator the agents run, with its default settings "
                                  "(set estimator.params.* in overrides); null: the scenario's")
    references: list[str] | None = Field(None, description="offline references computed from each run's sensor "
                                         "stream; null: the scenario's")
    sweep: list[SweepParam] = Field(default_factory=list, description="swept parameters, each with values or "
                                    "same_as; empty: one point, the scenario with its overrides")
    runs: int = Field(10, ge=1, description="Monte Carlo runs per point (`--runs` overrides)")
    base_seed: int = Field(0, ge=0, description="run r of every point has seed base_seed + r")
    metrics: list[str] = Field(["mean_error_m"], min_length=1, description="columns of results.csv summarized in "
                               "summary.csv and plotted against each swept parameter (results.csv has them all)")
    workers: int | None = Field(None, ge=1, description="local worker processes (`--workers` overrides); null: "
                                "the CPU count")
    scheduler: str | None = Field(None, description="address of a Dask distributed scheduler, e.g. "
                                  "tcp://10.0.0.5:8786 (`--scheduler` overrides); null: the local process pool")

    @field_validator("overrides")
    @classmethod
    def _paths(cls, v):
        import re

        for path in v:
            if not re.fullmatch(PATH_PATTERN, path):
                raise ValueError(f"{path!r} is not a dotted path like sensors.range.noise")
            if path == "seed":
                raise ValueError("seed is set per run (base_seed + run), not an override")
        return v

    @field_validator("estimator")
    @classmethod
    def _known_estimator(cls, v):
        from swarmloc.estimators import REGISTRY

        if v is not None and v not in REGISTRY.running():
            raise ValueError(f"unknown estimator {v!r}; agents run one of {sorted(REGISTRY.running())}")
        return v

    @field_validator("references")
    @classmethod
    def _known_references(cls, v):
        from swarmloc.estimators import REGISTRY

        bad = [r for r in v or () if r not in REGISTRY.references()]
        if bad:
            raise ValueError(f"unknown references {bad}; known: {sorted(REGISTRY.references())}")
        return v

    @model_validator(mode="after")
    def _sweep_consistent(self):
        names = [p.param for p in self.sweep]
        for i, p in enumerate(self.sweep):
            if names.index(p.param) != i:
                raise ValueError(f"sweep.{i}.param: {p.param} is swept twice")
            if p.param == "seed":
                raise ValueError(f"sweep.{i}.param: seed is set per run (base_seed + run), not swept")
            if p.param in self.overrides:
                raise ValueError(f"sweep.{i}.param: {p.param} is also a fixed override")
            if p.same_as is not None:
                src = next((q for q in self.sweep if q.param == p.same_as), None)
                if src is None or src.values is None:
                    raise ValueError(f"sweep.{i}.same_as: {p.same_as} is not a swept parameter with values "
                                     f"(swept: {', '.join(q.param for q in self.sweep if q.values is not None) or 'none'})")
        return self


def _validation_lines(exc: ValidationError) -> list[str]:
    out = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"])
        msg = err["msg"].removeprefix("Value error, ")
        out.append(f"{loc}: {msg}" if loc else msg)
    return out


def parse_spec(data, source: str = "<study>", base: Path | None = None) -> StudySpec:
    """A validated spec; a relative scenario path is taken relative to `base` (the spec's directory)."""
    if not isinstance(data, dict):
        raise StudyError(f"{source}: a study spec is a YAML mapping, got {type(data).__name__}")
    try:
        spec = StudySpec.model_validate(data)
    except ValidationError as exc:
        raise StudyError(f"{source}: " + "; ".join(_validation_lines(exc))) from None
    p = Path(spec.scenario)
    if base is not None and not p.is_absolute() and (p.suffix in (".yaml", ".yml") or (base / p).exists()):
        spec = spec.model_copy(update={"scenario": str(base / p)})
    return spec


def load_spec(path: str | Path) -> StudySpec:
    path = Path(path)
    if not path.is_file():
        raise StudyError(f"{path}: no such study spec")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise StudyError(f"{path}: not valid YAML: {exc}") from None
    return parse_spec(data, str(path), path.parent)


# ------------------------------------------------------------------------------------ the plan


@dataclass
class Plan:
    """A spec resolved against its scenario: the points, the overrides of each, the hash."""

    spec: StudySpec
    scenario_name: str
    scenario_data: dict  # the base scenario (Scenario.model_dump()): what every task starts from
    params: list[str]  # swept parameters, in sweep order (tied ones included)
    points: list[dict[str, Any]]  # param -> value
    fixed: dict[str, Any]  # overrides common to every point, estimator and references included
    spec_hash: str

    def overrides(self, point: int) -> list[tuple[str, Any]]:
        """Ordered (path, value) overrides of a point: a changed estimator first (with default settings)."""
        changes = {**self.fixed, **self.points[point]}
        out = []
        name = changes.pop("estimator.name", None)
        if name is not None and name != self.scenario_data["estimator"]["name"]:
            out.append(("estimator", {"name": name, "params": {}}))
        elif name is not None:
            out.append(("estimator.name", name))
        if "estimator" in changes:
            out.insert(0, ("estimator", changes.pop("estimator")))
        return out + list(changes.items())

    def task(self, point: int, run: int) -> dict:
        return {"scenario": self.scenario_data, "source": self.scenario_name, "overrides": self.overrides(point),
                "seed": self.spec.base_seed + run, "point": point, "run": run}


def _grid(spec: StudySpec) -> list[dict[str, Any]]:
    axes = [p for p in spec.sweep if p.values is not None]
    points = []
    for combo in itertools.product(*(p.values for p in axes)):
        chosen = dict(zip((p.param for p in axes), combo))
        points.append({p.param: chosen[p.param if p.values is not None else p.same_as] for p in spec.sweep})
    return points


def _canonical(obj) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)


def _missing_field(data: dict, path: str, scenario: str) -> str | None:
    """Why a dotted path cannot be set in the scenario, if an intermediate field is missing."""
    node, done = data, []
    for part in path.split(".")[:-1]:
        if not isinstance(node, dict):
            return f"{'.'.join(done)} is a {type(node).__name__}, not a mapping: no field {part} in it"
        if part not in node:
            where = ".".join(done) or "the top level"
            return f"scenario {scenario} has no field {'.'.join([*done, part])} ({where} has: {', '.join(node)})"
        node = node[part]
        done.append(part)
    if not isinstance(node, dict):
        return f"{'.'.join(done)} is a {type(node).__name__}, not a mapping"
    return None


def _scenario_error(exc: Exception) -> str:
    lines = [ln.strip() for ln in str(exc).splitlines()[1:]] or [str(exc)]
    return "; ".join(lines)


def _build(data: dict, source: str, overrides: Iterable[tuple[str, Any]], seed: int):
    from swarmloc import scenario as S

    return S.parse(data, source=source).with_overrides(**dict(overrides), seed=seed)


def plan(spec: StudySpec) -> Plan:
    """Resolve a spec: load its scenario and check every override path and every point before
    any run (an error names the field)."""
    from swarmloc import scenario as S

    try:
        base = S.load(spec.scenario)
    except S.ScenarioError as exc:
        raise StudyError(f"scenario: {exc}") from None
    data = base.model_dump()
    fixed: dict[str, Any] = {}
    if spec.estimator is not None:
        fixed["estimator.name"] = spec.estimator
    if spec.references is not None:
        fixed["references"] = list(spec.references)
    fixed.update(spec.overrides)
    points = _grid(spec)
    h = hashlib.sha256(_canonical({"format": STUDY_FORMAT, "scenario": data, "fixed": fixed,
                                   "sweep": [p.model_dump() for p in spec.sweep],
                                   "base_seed": spec.base_seed}).encode()).hexdigest()[:16]
    p = Plan(spec, base.name, data, [s.param for s in spec.sweep], points, fixed, h)
    _check(p)
    return p


def _check(p: Plan) -> None:
    from netsim.sim import channel_of

    from swarmloc.scenario import ScenarioError

    seed, name = p.spec.base_seed, p.scenario_name
    est = _only(p).overrides(0)  # the estimator and references alone

    def attempt(where: str, overrides: list[tuple[str, Any]]) -> None:
        try:
            channel_of(_build(p.scenario_data, name, overrides, seed))
        except (ScenarioError, KeyError, TypeError) as exc:
            raise StudyError(f"{where}: {_scenario_error(exc)}") from None

    for path, value in p.spec.overrides.items():
        why = _missing_field(p.scenario_data, path, name)
        if why:
            raise StudyError(f"overrides.{path}: {why}")
        attempt(f"overrides.{path}", [*est, (path, value)])
    for i, s in enumerate(p.spec.sweep):
        why = _missing_field(p.scenario_data, s.param, name)
        if why:
            raise StudyError(f"sweep.{i}.param ({s.param}): {why}")
    for i, point in enumerate(p.points):
        attempt(f"sweep point {i} ({_label(point) or 'no sweep'})", p.overrides(i))


def _only(p: Plan) -> Plan:
    """The plan with only its estimator and references as overrides, and one empty point."""
    fixed = {k: v for k, v in p.fixed.items() if k in ("estimator.name", "references")}
    return Plan(p.spec, p.scenario_name, p.scenario_data, [], [{}], fixed, p.spec_hash)


def _label(point: dict) -> str:
    return ", ".join(f"{k}={_text(v)}" for k, v in point.items())


# ------------------------------------------------------------------------------------ one run


def _flat(est: dict) -> dict:
    """Every numeric top-level metric of an estimator, and the mean of its NEES and NIS averages."""
    out = {}
    for key, v in est.items():
        if isinstance(v, bool) or key == "agents":
            continue
        if isinstance(v, numbers.Integral):
            out[key] = int(v)
        elif isinstance(v, numbers.Real):
            out[key] = float(v)
        elif isinstance(v, dict) and isinstance(v.get("mean"), numbers.Real) and not isinstance(v.get("mean"), bool):
            out[f"{key}_mean"] = float(v["mean"])
        elif v is None:
            out[f"{key}_mean" if key in NESTED else key] = None
    return out


def run_task(task: dict) -> dict:
    """One run of a study: a plain dict in, a plain dict out (picklable, for any executor).

    Depends only on the task's scenario, overrides and seed, so it gives the same numbers on
    any machine (timings aside)."""
    import numpy as np

    from netsim.sim import Simulation
    from swarmloc.estimators import make_nodes
    from swarmloc.results import compute_references, metrics, position_errors
    from swarmloc.runner import InProcessRunner

    wall, cpu = time.perf_counter(), time.process_time()
    sc = _build(task["scenario"], task["source"], task["overrides"], task["seed"])
    nodes = make_nodes(sc.estimator.name, sc)
    record = InProcessRunner(Simulation(sc), nodes).run()
    refs = sc.reference_names
    compute_references(sc, record, refs)
    algs = [sc.estimator.name, *refs]
    m = metrics(record, algs)
    stats: dict[str, float] = {}
    for aid in sorted(nodes):
        for key, v in (getattr(nodes[aid], "stats", None) or {}).items():
            if isinstance(v, numbers.Real) and not isinstance(v, bool):
                stats[key] = stats.get(key, 0) + v
    series = {"t": np.asarray(record.t, float)}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a tick without any estimate: NaN
        for alg in algs:
            series[alg] = np.nanmean(position_errors(record, record.trace(alg)), axis=1)
    return {"point": task["point"], "run": task["run"], "seed": task["seed"], "ticks": int(m["ticks"]),
            "wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu,
            "stats": {k: stats[k] for k in sorted(stats)},
            "estimators": {alg: _flat(m["estimators"][alg]) for alg in algs}, "series": series}


# ------------------------------------------------------------------------------------ executors


def _worker_init() -> None:
    # Ctrl-C reaches the whole process group: the parent decides (cancel pending, let running
    # runs finish); a worker interrupted while idle would die with a traceback instead.
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _pool_context():
    """forkserver: workers fork from a clean, single-threaded server that has imported the run's
    modules once, so they start fast and inherit no threads (rich's refresh thread, a Zenoh or
    Dask client in the caller) whose locks a plain fork could copy held; spawn where there is
    no forkserver."""
    import multiprocessing

    if "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        # Not this module: run as `python -m netsim.study`, a worker imports it as the parent's
        # main module, and preloaded it would be there twice (runpy warns).
        ctx.set_forkserver_preload(["netsim.sim", "swarmloc.estimators", "swarmloc.runner", "swarmloc.results"])
        return ctx
    return multiprocessing.get_context("spawn")


def _run_local(tasks: list[dict], workers: int, on_result: Callable[[dict], None], say: Callable[[str], None]) -> None:
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures import as_completed as completed

    from swarmloc import pin_blas

    pin_blas()  # the pool's workers: one BLAS thread each (set before the forkserver starts)
    ex = ProcessPoolExecutor(max_workers=workers, mp_context=_pool_context(), initializer=_worker_init)
    pending, running = iter(tasks), {}
    try:
        def fill():
            while len(running) < 2 * workers:
                t = next(pending, None)
                if t is None:
                    return
                running[ex.submit(run_task, t)] = t

        fill()
        while running:
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for f in done:
                t = running.pop(f)
                on_result(_result_of(f.result, t))
            fill()
    except KeyboardInterrupt:
        busy = [f for f in running if not f.cancel()]
        if busy:
            say(f"interrupted: waiting for the {len(busy)} runs already handed to workers (Ctrl-C again to abandon them)")
            try:
                for f in completed(busy):
                    if f.exception() is None:
                        on_result(f.result())
            except KeyboardInterrupt:
                _kill_workers(ex)
        raise
    finally:
        ex.shutdown(wait=True, cancel_futures=True)


def _kill_workers(ex) -> None:
    terminate = getattr(ex, "terminate_workers", None)  # Python >= 3.14
    if terminate is not None:
        terminate()
        return
    for proc in list((getattr(ex, "_processes", None) or {}).values()):
        proc.terminate()


def _result_of(get: Callable[[], dict], task: dict) -> dict:
    try:
        return get()
    except KeyboardInterrupt:
        raise
    except Exception as exc:
        raise RunFailed(f"run {task['run']} (seed {task['seed']}) of point {task['point']} failed: "
                        f"{type(exc).__name__}: {exc}") from exc


def _run_dask(tasks: list[dict], address: str, on_result: Callable[[dict], None], say: Callable[[str], None]) -> None:
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise StudyError("scheduler: Dask distributed is not installed (pip install 'dask[distributed]')") from None
    try:
        client = Client(address, timeout="20s")
    except (OSError, TimeoutError) as exc:
        raise StudyError(f"scheduler: cannot reach the Dask scheduler at {address}: {exc}") from None
    with client:
        token = uuid.uuid4().hex[:8]
        keys = [f"swarmloc-study-p{t['point']}-r{t['run']}-{token}" for t in tasks]
        futures = client.map(run_task, tasks, key=keys, pure=False)
        by_key = {k: t for k, t in zip(keys, tasks)}
        try:
            for f in as_completed(futures):
                on_result(_result_of(f.result, by_key[f.key]))
        except BaseException:
            client.cancel(futures)
            raise


# ------------------------------------------------------------------------------------ the study


@dataclass
class StudyResult:
    out: Path
    total: int  # runs in the study (points x runs)
    done: int  # runs finished, this call and earlier ones
    executed: int  # runs this call computed
    complete: bool  # every run done: the tables (and plots) are written
    rows: list[dict] = field(default_factory=list)  # results.csv as dicts (only when complete)
    summary: list[dict] = field(default_factory=list)  # summary.csv as dicts (only when complete)
    files: list[Path] = field(default_factory=list)


def _prepare_out(out: Path, p: Plan, force: bool) -> None:
    meta = out / "study.json"
    if meta.exists():
        old = json.loads(meta.read_text())
        if old.get("spec_hash") != p.spec_hash:
            if not force:
                raise StudyError(f"{out} holds another study ({old.get('name')}, spec hash {old.get('spec_hash')}; "
                                 f"this spec {p.spec_hash}): choose another --out, or --force to discard its runs")
            for name in ("runs.jsonl", "results.csv", "timing.csv", "summary.csv", "study.json"):
                (out / name).unlink(missing_ok=True)
            for name in ("series", "plots"):
                shutil.rmtree(out / name, ignore_errors=True)
    elif out.exists() and any(out.iterdir()) and not force:
        raise StudyError(f"{out} is not empty and holds no study.json: choose another --out (or --force to write "
                         "into it anyway)")
    (out / "series").mkdir(parents=True, exist_ok=True)
    meta.write_text(json.dumps({"format": STUDY_FORMAT, "name": p.spec.name, "spec_hash": p.spec_hash,
                                "scenario": p.scenario_name, "params": p.params, "points": p.points,
                                "spec": p.spec.model_dump()}, indent=2, default=str) + "\n")


def _finished(out: Path, p: Plan) -> dict[tuple[int, int], dict]:
    """The finished runs in runs.jsonl; a torn last line (a kill mid-write) is dropped."""
    done: dict[tuple[int, int], dict] = {}
    path = out / "runs.jsonl"
    if not path.exists():
        return done
    lines = path.read_text().splitlines()
    good = []
    for i, line in enumerate(lines):
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            if i == len(lines) - 1:
                break  # torn last line: rewrite the file without it
            raise StudyError(f"{path}: line {i + 1} is not JSON") from None
        good.append(line)
        if row.get("point", -1) < len(p.points):
            done[(row["point"], row["run"])] = row
    if len(good) != len(lines):
        path.write_text("".join(g + "\n" for g in good))
    return done


def run_study(spec: StudySpec | str | Path, out: str | Path | None = None, *, runs: int | None = None,
              workers: int | None = None, scheduler: str | None = None, plots: bool = True, force: bool = False,
              console=None, max_tasks: int | None = None) -> StudyResult:
    """Run (or resume) a study; write OUT/results.csv, timing.csv, summary.csv and plots when done.

    runs, workers, scheduler override the spec's. console: a rich Console for the progress bar
    and messages (None: quiet). max_tasks: compute at most this many runs, then return with
    complete=False (what an interruption leaves). Ctrl-C: pending runs are cancelled, finished
    ones kept, and KeyboardInterrupt propagates."""
    if not isinstance(spec, StudySpec):
        spec = load_spec(spec)
    p = plan(spec)
    runs = runs if runs is not None else spec.runs
    if runs < 1:
        raise StudyError(f"runs must be >= 1, got {runs}")
    workers = workers or spec.workers or os.cpu_count() or 1
    scheduler = scheduler or spec.scheduler
    out = Path(out) if out is not None else Path("studies") / spec.name
    _prepare_out(out, p, force)
    done = _finished(out, p)
    wanted = [(pt, r) for r in range(runs) for pt in range(len(p.points))]  # run-major: points stay balanced
    todo = [p.task(pt, r) for pt, r in wanted if (pt, r) not in done]
    if max_tasks is not None:
        todo = todo[:max_tasks]
    total = len(wanted)
    have = total - sum(1 for w in wanted if w not in done)
    say = (lambda msg: console.print(msg, highlight=False)) if console is not None else (lambda msg: None)
    if have:
        say(f"resuming {out}: {have} of {total} runs already done")
    executed = 0
    series_dir = out / "series"

    with open(out / "runs.jsonl", "a") as log, _progress(console, total, have, spec.name) as advance:
        def on_result(res: dict) -> None:
            nonlocal executed
            import numpy as np

            series = res.pop("series")
            tmp = series_dir / f".{res['point']}-{res['run']}.npz"
            np.savez(tmp, **series)
            os.replace(tmp, series_dir / f"{res['point']}-{res['run']}.npz")
            res["values"] = p.points[res["point"]]
            log.write(json.dumps(res, default=_json_default) + "\n")
            log.flush()
            os.fsync(log.fileno())
            done[(res["point"], res["run"])] = res
            executed += 1
            advance()

        if todo:
            if scheduler:
                say(f"{len(todo)} runs on the Dask cluster at {scheduler}")
                _run_dask(todo, scheduler, on_result, say)
            else:
                _run_local(todo, min(workers, len(todo)), on_result, say)

    finished = sum(1 for w in wanted if w in done)
    result = StudyResult(out, total, finished, executed, finished == total)
    if result.complete:
        records = [done[w] for w in sorted(wanted)]
        result.rows, result.summary, result.files = write_tables(out, p, records, spec.metrics)
        if plots:
            result.files += write_plots(out, p, result.summary, spec.metrics, runs)
    return result


class _progress:
    """A rich progress bar (completed/total, elapsed, ETA) or nothing."""

    def __init__(self, console, total: int, completed: int, name: str):
        self.console, self.total, self.completed, self.name = console, total, completed, name
        self.bar = None

    def __enter__(self):
        if self.console is None:
            return lambda: None
        from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                                   TimeRemainingColumn)

        self.bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                            TextColumn("runs"), TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
                            console=self.console)
        self.bar.__enter__()
        task = self.bar.add_task(f"study {self.name}", total=self.total, completed=self.completed)
        return lambda: self.bar.advance(task)

    def __exit__(self, *exc):
        if self.bar is not None:
            self.bar.__exit__(*exc)
        return False


def _json_default(o):
    import numpy as np

    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    raise TypeError(type(o).__name__)


# ------------------------------------------------------------------------------------ tables


def _text(v) -> str:
    """A CSV cell: floats as repr (round-trips, so equal numbers give equal files), missing empty."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, (int, float, str)):
        return repr(v) if isinstance(v, float) else str(v)
    return json.dumps(v, sort_keys=True)


def _write_csv(path: Path, columns: list[str], rows: list[dict]) -> Path:
    with open(path, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(columns)
        for r in rows:
            w.writerow([_text(r.get(c)) for c in columns])
    return path


def result_rows(p: Plan, records: list[dict]) -> tuple[list[str], list[dict]]:
    """results.csv: one row per point x run x estimator, its columns in a fixed order."""
    metric_cols: list[str] = []
    stat_cols = sorted({f"stat_{k}" for rec in records for k in rec.get("stats", {})})
    rows = []
    for rec in records:
        for alg, ms in rec["estimators"].items():
            for k in ms:
                if k not in metric_cols:
                    metric_cols.append(k)
            rows.append({"point": rec["point"], **rec["values"], "run": rec["run"], "seed": rec["seed"],
                         "estimator": alg, **ms, "ticks": rec["ticks"],
                         **{f"stat_{k}": v for k, v in rec.get("stats", {}).items()},
                         "wall_s": rec.get("wall_s"), "cpu_s": rec.get("cpu_s")})
    columns = ["point", *p.params, "run", "seed", "estimator", *metric_cols, *RUN_COLUMNS, *stat_cols]
    return columns, rows


def _ci95(values: list[float]) -> tuple[float, float, float, int]:
    import numpy as np
    import scipy.stats

    x = np.array([v for v in values if v is not None and not math.isnan(v)], float)
    n = int(x.size)
    if n == 0:
        return math.nan, math.nan, math.nan, 0
    mean = float(x.mean())
    if n == 1:
        return mean, math.nan, math.nan, 1
    std = float(x.std(ddof=1))
    return mean, std, float(scipy.stats.t.ppf(0.975, n - 1) * std / math.sqrt(n)), n


def write_tables(out: Path, p: Plan, records: list[dict], metrics: list[str]) -> tuple[list[dict], list[dict], list[Path]]:
    """results.csv (deterministic), timing.csv (wall and CPU time per run) and summary.csv."""
    columns, rows = result_rows(p, records)
    known = set(columns) | set(TIMING_COLUMNS)
    bad = [m for m in metrics if m not in known]
    if bad:
        numeric = [c for c in columns if c not in ("point", *p.params, "run", "seed", "estimator")]
        raise StudyError(f"metrics: no column {', '.join(bad)} in the results; they have: "
                         f"{', '.join([*numeric, *TIMING_COLUMNS])}")
    files = [_write_csv(out / "results.csv", columns, rows)]
    files.append(_write_csv(out / "timing.csv", ["point", *p.params, "run", "seed", "ticks", *TIMING_COLUMNS],
                            [{"point": r["point"], **r["values"], "run": r["run"], "seed": r["seed"],
                              "ticks": r["ticks"], "wall_s": r.get("wall_s"), "cpu_s": r.get("cpu_s")}
                             for r in records]))
    summary = []
    algs = list(dict.fromkeys(r["estimator"] for r in rows))
    for pt, values in enumerate(p.points):
        for alg in algs:
            mine = [r for r in rows if r["point"] == pt and r["estimator"] == alg]
            if not mine:
                continue
            s = {"point": pt, **values, "estimator": alg}
            for m in metrics:
                s[f"{m}_mean"], s[f"{m}_std"], s[f"{m}_ci95"], s[f"{m}_n"] = _ci95([r.get(m) for r in mine])
            summary.append(s)
    cols = ["point", *p.params, "estimator",
            *[f"{m}_{x}" for m in metrics for x in ("mean", "std", "ci95", "n")]]
    files.append(_write_csv(out / "summary.csv", cols, summary))
    return rows, summary, files


def summary_table(result: StudyResult, metrics: list[str], params: list[str]):
    """The summary as a rich table: mean +- 95% CI half-width (n) per point and estimator."""
    from rich.table import Table

    t = Table(*params, "estimator", *metrics, title=f"{result.out}/summary.csv: mean ± 95% CI (n runs)")
    for s in result.summary:
        cells = []
        for m in metrics:
            mean, ci, n = s[f"{m}_mean"], s[f"{m}_ci95"], s[f"{m}_n"]
            cells.append("-" if math.isnan(mean) else f"{mean:.4g} ± {ci:.2g} ({n})" if not math.isnan(ci)
                         else f"{mean:.4g} ({n})")
        t.add_row(*[_text(s[q]) for q in params], s["estimator"], *cells)
    return t


# ------------------------------------------------------------------------------------ plots


def _style(alg: str) -> tuple[str | None, str]:
    from swarmloc.estimators import REGISTRY

    try:
        return REGISTRY.color(alg), REGISTRY.label(alg)
    except Exception:
        return None, alg


def write_plots(out: Path, p: Plan, summary: list[dict], metrics: list[str], runs: int) -> list[Path]:
    """plots/<metric>_vs_<param>.png for each chosen metric and each grid parameter (one line per
    estimator, or per estimator panel one line per value of the other parameters), with 95% CI
    error bars; and plots/error_vs_time.png."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from swarmloc.plots import DPI

    d = out / "plots"
    d.mkdir(exist_ok=True)
    files = []
    axes = [s.param for s in p.spec.sweep if s.values is not None]
    tied = {s.param: s.same_as for s in p.spec.sweep if s.same_as is not None}
    algs = list(dict.fromkeys(s["estimator"] for s in summary))
    for m in metrics:
        for x in axes:
            others = [a for a in axes if a != x]
            xs = list(dict.fromkeys(pt[x] for pt in p.points))
            numeric = all(isinstance(v, numbers.Real) and not isinstance(v, bool) for v in xs)
            pos = {v: (v if numeric else i) for i, v in enumerate(xs)}
            groups = list(dict.fromkeys(tuple(pt[o] for o in others) for pt in p.points))
            panels = algs if others else [None]
            fig, axs = plt.subplots(1, len(panels), figsize=(6 * len(panels), 4.5), squeeze=False)
            for ax, panel in zip(axs[0], panels):
                lines = [(alg, g) for alg in (algs if panel is None else [panel]) for g in groups]
                for alg, g in lines:
                    rows = [s for s in summary if s["estimator"] == alg and tuple(s[o] for o in others) == g]
                    rows.sort(key=lambda s: xs.index(s[x]))
                    color, label = _style(alg)
                    if others:
                        color, label = None, ", ".join(f"{o}={_text(v)}" for o, v in zip(others, g))
                    ax.errorbar([pos[s[x]] for s in rows], [s[f"{m}_mean"] for s in rows],
                                yerr=[0 if math.isnan(s[f"{m}_ci95"]) else s[f"{m}_ci95"] for s in rows],
                                marker="o", capsize=3, color=color, label=label)
                if not numeric:
                    ax.set_xticks(range(len(xs)), [_text(v) for v in xs])
                also = [q for q, src in tied.items() if src == x]
                ax.set_xlabel(" = ".join([x, *also]))
                ax.set_ylabel(m)
                ax.set_title(f"{p.spec.name}: {_style(panel)[1] if panel else m} ({runs} runs per point, 95% CI)")
                ax.grid(alpha=0.3)
                ax.legend(fontsize=8)
            path = d / f"{m}_vs_{x}.png"
            fig.savefig(path, dpi=DPI, bbox_inches="tight")
            plt.close(fig)
            files.append(path)

    # error against time: mean over runs of each run's per-tick error (mean over agents)
    shown = list(range(len(p.points))) if len(p.points) <= MAX_TIME_LINES else [0]
    curves: dict[str, dict[int, tuple]] = {}
    for pt in shown:
        acc: dict[str, list] = {}
        t = None
        for r in range(runs):
            f = out / "series" / f"{pt}-{r}.npz"
            if not f.exists():
                continue
            with np.load(f, allow_pickle=False) as z:
                t = z["t"]
                for alg in z.files:
                    if alg != "t":
                        acc.setdefault(alg, []).append(z[alg])
        for alg, series in acc.items():
            n = min(len(s) for s in series)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                curves.setdefault(alg, {})[pt] = (t[:n], np.nanmean([s[:n] for s in series], axis=0), len(series))
    if curves:
        fig, axs = plt.subplots(len(curves), 1, figsize=(8, 3.2 * len(curves)), squeeze=False, sharex=True)
        for ax, (alg, by_point) in zip(axs[:, 0], curves.items()):
            for pt, (t, e, n) in by_point.items():
                ax.plot(t, e, lw=1.2, label=f"{_label(p.points[pt]) or p.scenario_name} ({n} runs)")
            ax.set_ylabel("position error (m)")
            ax.set_title(f"{_style(alg)[1]}: mean over runs" + ("" if len(shown) == len(p.points)
                                                               else f" (first of {len(p.points)} points)"))
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
        axs[-1, 0].set_xlabel("t (s)")
        path = d / "error_vs_time.png"
        fig.savefig(path, dpi=DPI, bbox_inches="tight")
        plt.close(fig)
        files.append(path)
    return files


def main(argv=None) -> int:
    """`python -m netsim.study SPEC`: what `swarmloc study` runs (docs/study.md)."""
    import argparse
    import sys

    from rich.console import Console

    p = argparse.ArgumentParser(prog="swarmloc study", description=__doc__.splitlines()[0])
    p.add_argument("spec", type=Path)
    p.add_argument("--out", "-o", type=Path)
    p.add_argument("--runs", type=int)
    p.add_argument("--workers", type=int)
    p.add_argument("--scheduler")
    p.add_argument("--no-plots", action="store_true")
    p.add_argument("--force", action="store_true")
    a = p.parse_args(argv)
    err, out = Console(stderr=True), a.out
    try:
        s = load_spec(a.spec)
        out = out or Path("studies") / s.name
        result = run_study(s, out, runs=a.runs, workers=a.workers, scheduler=a.scheduler, plots=not a.no_plots,
                           force=a.force, console=err)
    except StudyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except RunFailed as exc:
        print(f"error: {exc}; the finished runs are kept in {out}/runs.jsonl", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        again = " ".join(["swarmloc study", str(a.spec), "--out", str(out), *(["--runs", str(a.runs)] if a.runs else []),
                          *(["--scheduler", a.scheduler] if a.scheduler else [])])
        print(f"interrupted: the finished runs are kept in {out}/runs.jsonl; resume with: {again}", file=sys.stderr)
        return 130
    Console().print(summary_table(result, s.metrics, [q.param for q in s.sweep]))
    print(f"{result.executed} runs computed, {result.done - result.executed} taken from {out}/runs.jsonl; "
          f"wrote {', '.join(str(f.relative_to(out)) for f in result.files)} in {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
