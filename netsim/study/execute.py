"""Running a study: each run in process, on the local process pool or a Dask cluster, resumable
from OUT/runs.jsonl; the tables and plots once every run is done."""

from __future__ import annotations

import json
import math
import numbers
import os
import shutil
import time
import uuid
import warnings
from pathlib import Path
from typing import Callable, Iterable

from netsim.study.plots import write_plots
from netsim.study.spec import (
    NESTED,
    STUDY_FORMAT,
    Plan,
    RunFailed,
    StudyError,
    StudyResult,
    StudySpec,
    build_scenario,
    load_spec,
    plan,
)
from netsim.study.tables import json_default, result_rows, summarized, write_tables

# ------------------------------------------------------------------------------------ one run


def _flat(est: dict, agents: Iterable[int] = ()) -> dict:
    """Every numeric top-level metric of an estimator, and the mean of its NEES and NIS averages;
    for each of `agents`, its own metrics the same way, prefixed a<id>_."""
    out = {}
    for a in agents:
        mine = (est.get("agents") or {}).get(str(a))
        if mine is not None:
            out.update({f"a{a}_{k}": v for k, v in _flat(mine).items()})
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
    from swarmloc.experiment.results import compute_references, metrics, position_errors, tracks_of
    from swarmloc.experiment.runner import InProcessRunner

    wall, cpu = time.perf_counter(), time.process_time()
    sc = build_scenario(task["scenario"], task["source"], task["overrides"], task["seed"])
    nodes = make_nodes(sc.estimator.name, sc)
    record = InProcessRunner(Simulation(sc), nodes).run()
    refs = sc.reference_names
    compute_references(sc, record, refs)
    algs = [sc.estimator.name, *refs]
    m = metrics(record, algs, since=task.get("settle", 0.0), tracks=tracks_of(sc))
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
            "estimators": {alg: _flat(m["estimators"][alg], task.get("agents", ())) for alg in algs},
            "series": series}


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
        # The run's modules, not netsim.study.__main__: a worker imports the parent's main module
        # itself, and preloaded it would be there twice (runpy warns).
        ctx.set_forkserver_preload(["netsim.study.execute", "netsim.sim", "swarmloc.estimators",
                                    "swarmloc.experiment.runner", "swarmloc.experiment.results"])
        return ctx
    return multiprocessing.get_context("spawn")


def _run_local(tasks: list[dict], workers: int, on_result: Callable[[dict], None], say: Callable[[str], None]) -> None:
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures import as_completed as completed

    from swarmloc.process import pin_blas

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
            log.write(json.dumps(res, default=json_default) + "\n")
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
        result.metrics = summarized(spec.metrics, result_rows(p, records)[0])
        if plots:
            result.files += write_plots(out, p, result.summary, result.metrics, runs)
    return result


PLAIN_EVERY_S = 10.0  # off a terminal: a progress line at most this often (and after the last run)


def _clock(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "-:--:--"
    m, s = divmod(int(seconds + 0.5), 60)
    return f"{m // 60}:{m % 60:02d}:{s:02d}"


class _progress:
    """A rich progress bar (completed/total, elapsed, ETA) on a terminal; elsewhere (a pipe, a
    log file), where rich draws no bar, a plain line now and then; or nothing."""

    def __init__(self, console, total: int, completed: int, name: str):
        self.console, self.total, self.completed, self.name = console, total, completed, name
        self.bar = None

    def _plain(self):
        start, last, done = time.monotonic(), -math.inf, self.completed

        def advance():
            nonlocal last, done
            done += 1
            now = time.monotonic()
            if now - last < PLAIN_EVERY_S and done < self.total:
                return
            last, elapsed = now, now - start
            eta = elapsed / (done - self.completed) * (self.total - done)
            self.console.print(f"study {self.name}: {done}/{self.total} runs, {_clock(elapsed)} elapsed, "
                               f"ETA {_clock(eta)}", highlight=False)

        self.console.print(f"study {self.name}: {done}/{self.total} runs done; a line every {PLAIN_EVERY_S:g} s "
                           "(rich's bar needs a terminal)", highlight=False)
        return advance

    def __enter__(self):
        if self.console is None:
            return lambda: None
        if not self.console.is_terminal:
            return self._plain()
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

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
