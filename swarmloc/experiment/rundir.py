"""The run directory: what a run leaves on disk (format: docs/run-format.md).

A run directory is plain files: YAML, JSON and .npz archives without pickled objects, so any
tool with numpy can read it without importing swarmloc. The record and its metrics are
results.py's; the pictures are plots.py's.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from swarmloc.experiment.plots import plot_links, plot_run
from swarmloc.experiment.results import FORMAT_VERSION, RunRecord, metrics, tracks_of


def write_run(out: Path, scenario, record: RunRecord, algorithms: list[str], extra: dict | None = None,
              plots: bool = True, radio: dict[str, np.ndarray] | None = None) -> dict:
    """Write the run directory; returns the metrics written to metrics.json."""
    out = Path(out)
    (out / "estimates").mkdir(parents=True, exist_ok=True)
    (out / "scenario.yaml").write_text(scenario.to_yaml())
    targets = {"target_ids": np.array(record.target_ids), "target_position": np.stack(record.target_truth)} \
        if record.target_ids else {}
    np.savez(out / "truth.npz", ids=np.array(record.ids), k=np.array(record.k), t=np.array(record.t),
             state=record.truth_array(), dims=record.dims, **targets)
    np.savez(out / "sensors.npz", **record.sensor_arrays())
    for alg in algorithms:
        record.trace(alg).save(out / "estimates" / f"{alg}.npz")
    m = metrics(record, algorithms, tracks=tracks_of(scenario))
    m["format_version"] = FORMAT_VERSION
    m["scenario"] = scenario.name
    m["seed"] = scenario.seed
    m["estimator"] = scenario.estimator.name  # what the agents ran; the other estimators are offline references
    m["ground_stations"] = [a.id for a in scenario.world.agents if not a.localized]
    m.update(extra or {})
    (out / "metrics.json").write_text(json.dumps(m, indent=2, default=_jsonable))
    if radio is not None:
        np.savez(out / "radio.npz", **radio)
    if plots:
        plot_run(out, record, algorithms)
        if radio is not None and radio["link_k"].size:
            plot_links(out, radio)
    return m


RECORDING = "run.mcap"


def rebuild_run(out: Path, plots: bool = True, why: str = "") -> dict:
    """metrics.json, estimates, truth and plots of a run that ended before netsim wrote them (netsim
    killed, the launcher killed or stopped), rebuilt from its recording (run.mcap, written as the
    run goes) up to the last tick that was finished: every tick but the last two the recording
    holds, or all of them if netsim's stop clock is in it. RecordingError if there is none."""
    from swarmloc.estimators import REGISTRY
    from swarmloc.experiment import recording
    from swarmloc.experiment.results import compute_references

    out = Path(out)
    path = out / RECORDING
    if not path.is_file():
        raise recording.RecordingError(f"{out}: no metrics.json and no {RECORDING} to rebuild it from")
    run = recording.load(path)
    sc = run.scenario
    if sc is None or not run.ticks:
        raise recording.RecordingError(f"{path}: holds no scenario or no tick")
    # An agent publishes its final estimate of tick k when tick k+1's frame reaches it, before its
    # `done` of k+1: tick k is whole once netsim has started k+2.
    last = run.ticks[-1] if run.stopped else run.ticks[-1] - 2
    run.ticks = [k for k in run.ticks if k <= last]
    run.estimates = [(a, e) for a, e in run.estimates if e.k <= last]
    record = recording.record_of(run, sc)
    compute_references(sc, record)
    algorithms = REGISTRY.order({sc.estimator.name, *sc.reference_names, *record.est})
    if isinstance(run.meta.get("seed"), int) and run.meta["seed"] != sc.seed:  # netsim's --seed
        sc = sc.with_overrides(seed=run.meta["seed"])
    extra = {"transport": f"zenoh-{run.meta.get('mode', sc.clock.mode)}", "wall_time_s": None, "ticks_per_s": None,
             "rebuilt_from": RECORDING, "recording": {"truncated": run.truncated, "bad": run.bad}}
    if last < sc.clock.steps:
        extra["ended_early"] = {"last_tick": last, "ticks_planned": sc.clock.steps + 1,
                                "why": why or "the run ended before netsim wrote its results"}
    return write_run(out, sc, record, algorithms, extra, plots=plots)


def _jsonable(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)
