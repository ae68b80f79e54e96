"""Consistency at scale by Monte Carlo (issue 29, item 4): is an estimator's NEES at N platforms
that of a consistent filter, judged by independent runs rather than by one run's average?

A run's metrics give its NEES averaged over platforms and ticks, with the 95 % bounds of a mean of
that many independent chi-square values (swarmloc.experiment.results.chi2_bounds). The values of
one run are not independent: platforms share measurements and every tick carries the last one's
error, so that band is narrower than the spread of a consistent filter's own runs. This script
runs the scale scenario of benchmarks/bench_scale.py (in process, lockstep) for M seeds and
judges the estimator and UKF-CCL (the exact centralized filter, computed offline on the same
sensor data: the control) three ways:

1. each run's average with the pooled band (what metrics.json says);
2. the spread of the run averages over seeds: the estimator's mean over seeds against UKF-CCL's,
   and each seed's difference between the two (the same sensor data, so the difference is the
   estimator's own);
3. the textbook Monte Carlo test (Bar-Shalom, Li, Kirubarajan 2001, section 5.4.2): for every
   platform and tick, the NEES averaged over the M independent runs, M times which is
   chi-square with M*d degrees of freedom if the filter is consistent; the share of
   (platform, tick) cells inside the two-sided 95 % band, and the shares above it
   (overconfident) and below it (pessimistic). A consistent filter puts 2.5 % above and 2.5 %
   below.

Usage: python benchmarks/nees_mc.py [--n 256] [--seeds 10] [--duration 30] [--estimator rdl]
                                     [--json PATH] [--code TEXT]
Markdown to stdout, progress to stderr. Not a test.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

from machine import code_version, cpu_model  # benchmarks/machine.py

from swarmloc.process import pin_blas

pin_blas()  # before numpy loads

import numpy as np  # noqa: E402
import scipy.stats  # noqa: E402
from bench_scale import DT, parse_config, scenario  # noqa: E402

from netsim.sim import Simulation  # noqa: E402
from swarmloc.estimators import make_nodes  # noqa: E402
from swarmloc.experiment.results import chi2_bounds, compute_references, nees_series  # noqa: E402
from swarmloc.experiment.runner import InProcessRunner  # noqa: E402
from swarmloc.experiment.scenario import parse  # noqa: E402


def log(msg: str) -> None:
    print(f"[{datetime.now():%H:%M:%S}] {msg}", file=sys.stderr, flush=True)


def one_run(n: int, name: str, bound, duration: float, seed: int) -> dict:
    """NEES per tick and platform (T, N) of the estimator and of UKF-CCL, and the dof."""
    sc = parse(scenario(n, name, bound, duration, seed), source="nees_mc")
    sim = Simulation(sc)
    t0 = time.perf_counter()
    record = InProcessRunner(sim, make_nodes(name, sc)).run()
    wall = time.perf_counter() - t0
    compute_references(sc, record, ["ukf-ccl"], bound=False)
    out = {"wall_s": wall, "dof": int(record.dims[0])}
    for alg in (name, "ukf-ccl"):
        out[alg] = nees_series(record, record.trace(alg))
    return out


def pooled(values: np.ndarray, dof: int) -> tuple[float, float, float]:
    v = values[np.isfinite(values)]
    lo, hi = chi2_bounds(dof * v.size)
    return float(v.mean()), lo / v.size, hi / v.size


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=256, help="platforms")
    p.add_argument("--seeds", type=int, default=10, help="independent runs, seeds 1..M")
    p.add_argument("--duration", type=float, default=30.0, help="simulated seconds a run")
    p.add_argument("--estimator", type=parse_config, default=("rdl", None), help="as bench_scale's --estimators")
    p.add_argument("--skip-ticks", type=int, default=1,
                   help="ticks left out at the start (tick 0 is the prior, whose error the scenario sets)")
    p.add_argument("--json", type=Path)
    p.add_argument("--code", help="what code is measured, when this checkout has no git metadata (e.g. a git archive)")
    a = p.parse_args()
    code = code_version() if code_version() != "unknown" or not a.code else a.code
    name, bound = a.estimator
    command = "python " + " ".join(shlex.quote(x) for x in sys.argv)
    started, load0, t0 = f"{datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC", os.getloadavg(), time.perf_counter()
    runs = []
    for seed in range(1, a.seeds + 1):
        log(f"seed {seed}: N={a.n} {name}, {int(round(a.duration / DT)) + 1} ticks")
        r = one_run(a.n, name, bound, a.duration, seed)
        runs.append(r)
        log(f"  {r['wall_s']:.1f} s; NEES {name} {np.nanmean(r[name][a.skip_ticks:]):.3f}, "
            f"ukf-ccl {np.nanmean(r['ukf-ccl'][a.skip_ticks:]):.3f}")
    dof, M = runs[0]["dof"], len(runs)
    lines = [f"## NEES at N={a.n} by Monte Carlo: {name} against UKF-CCL, {M} independent runs", "",
             f"Machine: {cpu_model()}, {os.cpu_count()} CPUs, Python {sys.version.split()[0]}; code {code}; "
             f"{started}; load average at start {load0[0]:.1f}; {(time.perf_counter() - t0) / 60:.1f} min.  ",
             f"Command: `{command}`", "",
             f"The scale scenario of benchmarks/bench_scale.py at N={a.n}, seeds 1..{M} (each seed draws the platforms, "
             f"their walks and every measurement anew), {int(round(a.duration / DT)) + 1} ticks, in process; ticks "
             f"before {a.skip_ticks} left out; NEES of the position and anything else in the state ({dof} dof).", "",
             "| seed | " + name + " NEES, run average [pooled 95 % band] | UKF-CCL NEES, run average | "
             + name + " - UKF-CCL |", "|---|---|---|---|"]
    per_seed = {name: [], "ukf-ccl": []}
    for seed, r in enumerate(runs, 1):
        m, lo, hi = pooled(r[name][a.skip_ticks:], dof)
        c, clo, chi = pooled(r["ukf-ccl"][a.skip_ticks:], dof)
        per_seed[name].append(m)
        per_seed["ukf-ccl"].append(c)
        lines.append(f"| {seed} | {m:.3f} [{lo:.3f}, {hi:.3f}]{'' if lo <= m <= hi else ' outside'} | "
                     f"{c:.3f}{'' if clo <= c <= chi else ' (outside)'} | {m - c:+.3f} |")
    est, ccl = np.array(per_seed[name]), np.array(per_seed["ukf-ccl"])
    diff = est - ccl
    _, lo1, hi1 = pooled(runs[0][name][a.skip_ticks:], dof)
    lines += ["", f"Over the {M} runs: {name} {est.mean():.3f} (runs {est.min():.3f} to {est.max():.3f}, std "
              f"{est.std(ddof=1):.3f}); UKF-CCL {ccl.mean():.3f} ({ccl.min():.3f} to {ccl.max():.3f}, std "
              f"{ccl.std(ddof=1):.3f}); the pooled band's half-width for one run is "
              f"{(hi1 - lo1) / 2:.3f}. "
              f"{name} - UKF-CCL, seed by seed: mean {diff.mean():+.3f}, std {diff.std(ddof=1):.3f}, "
              f"{int((diff > 0).sum())} of {M} above; {name} / UKF-CCL {np.mean(est / ccl):.3f}.", ""]
    # The mean of M run averages against the band a consistent filter's would keep, with the
    # run-to-run spread taken from the control's runs (the pooled band assumes independence).
    half = scipy.stats.t.ppf(0.975, M - 1) * ccl.std(ddof=1) / np.sqrt(M)
    lines += [f"The mean of the {M} run averages against {dof:g} +- {half:.3f}, the 95 % band of a mean of {M} runs "
              f"whose averages spread as UKF-CCL's do (t with {M - 1} dof): {name} {est.mean():.3f} "
              f"{'inside' if abs(est.mean() - dof) <= half else 'outside'}, UKF-CCL {ccl.mean():.3f} "
              f"{'inside' if abs(ccl.mean() - dof) <= half else 'outside'}.", ""]
    # The Monte Carlo test, cell by cell.
    lo, hi = (x / M for x in chi2_bounds(M * dof))
    lines += [f"Monte Carlo test: each (platform, tick) cell's NEES averaged over the {M} runs, 95 % band "
              f"[{lo:.3f}, {hi:.3f}] (chi-square with {M * dof} dof, over {M}):", "",
              "| filter | cells | inside | above (overconfident) | below (pessimistic) | mean of the cell averages |",
              "|---|---|---|---|---|---|"]
    result = {"command": command, "date": started, "machine": cpu_model(), "code": code, "n": a.n,
              "seeds": M, "dof": dof, "per_seed": per_seed, "band": [lo, hi], "mc": {}}
    for alg in (name, "ukf-ccl"):
        cells = np.mean([r[alg][a.skip_ticks:] for r in runs], axis=0)
        cells = cells[np.isfinite(cells)]
        inside, above, below = ((lo <= cells) & (cells <= hi)).mean(), (cells > hi).mean(), (cells < lo).mean()
        result["mc"][alg] = {"cells": int(cells.size), "inside": inside, "above": above, "below": below,
                             "mean": float(cells.mean())}
        lines.append(f"| {alg} | {cells.size} | {100 * inside:.1f} % | {100 * above:.1f} % | {100 * below:.1f} % | "
                     f"{cells.mean():.3f} |")
    # How far from consistent the estimator can be and still pass: the shares a filter whose NEES
    # is k times a consistent one's would show (its cell averages k * chi2(M d) / M).
    sens = []
    for k in (1.0, 1.05, 1.1, 1.2):
        d = scipy.stats.chi2(M * dof)
        sens.append(f"{k:g}x: {100 * d.sf(hi * M / k):.1f} % above, {100 * d.cdf(lo * M / k):.1f} % below")
    lines += ["", "What the test can see: a filter whose NEES is k times a consistent one's would put, in "
              "expectation, " + "; ".join(sens) + "."]
    print("\n".join(lines) + "\n", flush=True)
    if a.json:
        a.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
