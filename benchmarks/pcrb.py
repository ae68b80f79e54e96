"""RMSE against the posterior Cramér-Rao bound, per built-in scenario and estimator (docs/estimators.md).

Usage: python benchmarks/pcrb.py [SCENARIO ...] [--seeds N] [--set PATH=VALUE ...] [--replay DIR] [--out FILE]
                                [--plot PNG]

Each scenario runs in-process (swarmloc.experiment.runner.InProcessRunner on netsim.sim.Simulation: the
numbers a lockstep `swarmloc run` writes), with the scenario's estimator on the agents and its
references offline, then `swarmloc.experiment.results.metrics`: per estimator the position RMSE over every
agent and tick 1.., the RMS of the run's PCRB over the same cells and their ratio. With --seeds
N, seeds 1..N of each scenario, and the ratio pooled over them: sqrt(sum of squared errors /
sum of squared bounds), one number whose expectation is >= 1 when the bound holds. --set: a
scenario override (a dotted path as in a study spec, the value read as YAML), e.g.
--set clock.duration=30; the table names the overrides. --alone: the bound of each platform
alone instead of the run's (its own motion inputs, prior and, a vehicle, attitude sensor; no
fix, nothing relative), the check for dead reckoning. --replay:
also the MR.CLAM recording DIR, replayed as `swarmloc replay DIR` does (its noise fitted
against its Vicon truth). No scenario named: every built-in (none with --replay). Writes a markdown table to --out
(default: print only). Timings are the wall time of each run and of its bound, on this machine.
--plot: one panel per scenario, each estimator's RMS position error over agents and seeds
against time beside the RMS of the bound over the same cells (dashed).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from swarmloc.process import pin_blas

pin_blas()  # before numpy loads

import numpy as np  # noqa: E402
import yaml  # noqa: E402
from msgspec.structs import replace  # noqa: E402

from netsim.sim import Simulation  # noqa: E402
from swarmloc.estimators import REGISTRY  # noqa: E402
from swarmloc.experiment import scenario as S  # noqa: E402
from swarmloc.experiment.replay import replay_scenario  # noqa: E402
from swarmloc.experiment.results import RunRecord, compute_bound, compute_references, metrics, position_errors  # noqa: E402
from swarmloc.experiment.runner import InProcessRunner, make_nodes  # noqa: E402


def alone(record) -> RunRecord:
    """The run with every platform alone: its motion inputs, its prior and (a vehicle) its own
    attitude sensor; no fix, nothing relative, no target."""
    out = RunRecord(record.ids, dict(record.models))
    for ti, (k, t, frames) in enumerate(zip(record.k, record.t, record.sensors)):
        own = {a: replace(f, ranges=[], relpos=[], rb=[], landmarks=[], targets=[], gnss=None, pseudoranges=None,
                          vehicle=f.vehicle and replace(f.vehicle, seen=[]))
               for a, f in frames.items()}
        out.add_tick(k, t, own, {a: record.truth[ti][i, :record.dims[i]] for i, a in enumerate(record.ids)})
    return out


def one(sc, by_itself=False):
    t0 = time.perf_counter()
    record = InProcessRunner(Simulation(sc), make_nodes(sc.estimator.name, sc)).run()
    refs = sc.reference_names
    compute_references(sc, record, refs)  # the bound too; its time below is measured apart
    t1 = time.perf_counter()
    record.bound = None
    if by_itself:
        lone = alone(record)
        compute_bound(sc, lone)
        record.bound = lone.bound
    else:
        compute_bound(sc, record)
    t2 = time.perf_counter()
    algs = REGISTRY.order([sc.estimator.name, *refs])
    sums, per_tick = {}, {}
    for alg in algs:
        e = position_errors(record, record.trace(alg))[1:]
        B = record.bound.position[1:] if record.bound is not None else np.full(e.shape, np.nan)
        ok = np.isfinite(e) & np.isfinite(B)
        sums[alg] = (float((e[ok] ** 2).sum()), float((B[ok] ** 2).sum()), int(ok.sum()))
        # Per tick, over the agents: the same sums, for --plot.
        per_tick[alg] = (np.where(ok, e, 0.0) ** 2).sum(1), (np.where(ok, B, 0.0) ** 2).sum(1), ok.sum(1)
    return metrics(record, algs), sums, t1 - t0, t2 - t1, record, per_tick


def plot(path: Path, curves: list) -> None:
    """curves: (scenario label, t (T-1,), {alg: (sum e^2, sum B^2, n) per tick}) per panel."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from swarmloc.experiment.plots import _style

    fig, axes = plt.subplots(len(curves), 1, figsize=(8, 3.2 * len(curves)), squeeze=False)
    for ax, (label, t, per) in zip(axes[:, 0], curves):
        bound = None
        for alg, (e2, b2, n) in per.items():
            with np.errstate(invalid="ignore", divide="ignore"):
                color, name = _style(alg)
                ax.plot(t, np.sqrt(e2 / n), color=color, lw=1.0, label=name)
                bound = np.sqrt(b2 / n) if bound is None else bound
        ax.plot(t, bound, "k--", lw=1.2, label="PCRB (RMS bound)")
        ax.set_title(label, fontsize=10)
        ax.set_ylabel("RMS position error (m)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, ncol=2)
    axes[-1, 0].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenarios", nargs="*")
    p.add_argument("--seeds", type=int, default=0, help="seeds 1..N instead of the scenario's own")
    p.add_argument("--alone", action="store_true", help="the bound of each platform alone (its motion inputs and "
                   "prior, a vehicle's attitude; no fix, nothing relative), what dead reckoning can do, instead of "
                   "the run's")
    p.add_argument("--set", action="append", default=[], metavar="PATH=VALUE", help="a scenario override")
    p.add_argument("--replay", type=Path, help="an MR.CLAM dataset directory to replay as well")
    p.add_argument("--out", type=Path)
    p.add_argument("--plot", type=Path, help="a PNG: error and bound against time, one panel per scenario")
    a = p.parse_args(argv)
    names = a.scenarios or ([] if a.replay else S.builtin_names())
    overrides = {}
    for item in a.set:
        path, sep, value = item.partition("=")
        if not sep:
            p.error(f"--set {item}: expected PATH=VALUE")
        overrides[path] = yaml.safe_load(value)
    label = "".join(f", {k}={v}" for k, v in overrides.items()) + (", bound of each platform alone" if a.alone else "")
    jobs = [(n + label, S.load(n).with_overrides(**overrides) if overrides else S.load(n)) for n in names]
    if a.replay:
        jobs.append((f"replay {a.replay.name}", replay_scenario(a.replay)))
    lines = ["| scenario | seeds | estimator | RMSE (m) | PCRB (m) | RMSE / PCRB | run (s) | bound (s) |",
             "|---|---|---|---|---|---|---|---|"]
    curves = []
    for name, base in jobs:
        seeds = [base.seed] if not a.seeds or name.startswith("replay") else list(range(1, a.seeds + 1))
        pooled: dict[str, list] = {}
        wall = bound_s = 0.0
        over_seeds: dict[str, list] = {}
        for seed in seeds:
            sc = base.with_overrides(seed=seed) if seed != base.seed else base
            m, sums, w, b, record, per_tick = one(sc, a.alone)
            for alg, sums_t in per_tick.items():
                have = over_seeds.setdefault(alg, [0.0, 0.0, 0])
                over_seeds[alg] = [x + y for x, y in zip(have, sums_t)]
            wall, bound_s = wall + w, bound_s + b
            if "error" in m.get("pcrb", {}):
                print(f"{name} seed {seed}: no bound: {m['pcrb']['error']}", file=sys.stderr)
            for alg, s in sums.items():
                pooled.setdefault(alg, []).append(s)
            extra = ", ".join(f"{k}: {v}" for k, v in (record.bound.skipped if record.bound else {}).items())
            ratios = ", ".join(f"{alg} {np.sqrt(e2 / b2):.3f}" for alg, (e2, b2, n) in sums.items() if n)
            print(f"{name} seed {seed}: {len(record.k)} ticks, run {w:.1f} s, bound {b:.1f} s; RMSE / PCRB {ratios}"
                  + (f"; skipped {extra}" if extra else ""), flush=True)
        for alg, rows in pooled.items():
            e2, b2, n = (sum(r[i] for r in rows) for i in range(3))
            if n == 0:
                continue
            rmse, pcrb = np.sqrt(e2 / n), np.sqrt(b2 / n)
            which = f"{seeds[0]}..{seeds[-1]}" if len(seeds) > 1 else f"seed {seeds[0]}"
            line = (f"| {name} | {which} | {alg} | {rmse:.4g} | {pcrb:.4g} | "
                    f"{rmse / pcrb:.3f} | {wall:.0f} | {bound_s:.1f} |")
            lines.append(line)
            print(line, flush=True)
        seeds_label = f"seeds {seeds[0]}..{seeds[-1]}" if len(seeds) > 1 else f"seed {seeds[0]}"
        curves.append((f"{name}, {seeds_label}", np.asarray(record.t[1:], float), over_seeds))
    text = "\n".join(lines) + "\n"
    if a.out:
        a.out.write_text(text)
    if a.plot:
        plot(a.plot, curves)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
