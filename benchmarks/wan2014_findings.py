"""The dNBP paper's figures from finished `swarmloc study` runs: tables for docs/dnbp.md and the
plots copied into docs/img.

Run the studies first (benchmarks/studies/wan2014-*.yaml), e.g.

    swarmloc study benchmarks/studies/wan2014-fig6b.yaml --runs 10
    .venv/bin/python benchmarks/wan2014_findings.py --out benchmarks/out_wan2014.md

For each study: per point and estimator, the mean error over the GNSS-denied (tick, UAV) pairs
(`no_gnss_mean_error_m`) with its 95% confidence half-width over runs, and the mean error of all
UAVs over the last third of the run (from the per-tick series), once the start-up from the 300 m
prior is over.
"""

from __future__ import annotations

import argparse
import csv
import shutil
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
STUDIES = {
    "wan2014-ring-kernel": ("estimator.params.ring_scale", "The ring's kernel: std in units of the ring's thickness "
                            "(0: Silverman's rule)"),
    "wan2014-fig6a": ("sensors.gnss.normal_share", "Fig. 6(a): share of normal UAVs (GPS switching off)"),
    "wan2014-fig6b": ("radio.range_m", "Fig. 6(b): communication range R (m)"),
    "wan2014-fig6c": ("sensors.gnss.noise", "Fig. 6(c): GPS noise std (m), at R = 500 m"),
    "wan2014-fig6d": ("sensors.range.noise", "Fig. 6(d): range noise std (m), at R = 500 m"),
    "wan2014-fig6c-r300": ("sensors.gnss.noise", "Fig. 6(c) at the scenario's R = 300 m"),
    "wan2014-fig6d-r300": ("sensors.range.noise", "Fig. 6(d) at the scenario's R = 300 m"),
    "wan2014-table1": ("estimator.params.M", "Table 1: samples M"),
}


# The plots docs/dnbp.md shows, copied from the studies' plots/.
FIGURES = {
    "wan2014-fig6a": {"no_gnss_mean_error_m_vs_sensors.gnss.normal_share.png": "wan2014_fig6a.png"},
    "wan2014-fig6b": {"no_gnss_mean_error_m_vs_radio.range_m.png": "wan2014_fig6b.png",
                      "error_vs_time.png": "wan2014_error_vs_time.png"},
    "wan2014-fig6c": {"no_gnss_mean_error_m_vs_sensors.gnss.noise.png": "wan2014_fig6c.png"},
    "wan2014-fig6d": {"no_gnss_mean_error_m_vs_sensors.range.noise.png": "wan2014_fig6d.png"},
    "wan2014-table1": {"no_gnss_mean_error_m_vs_estimator.params.M.png": "wan2014_table1.png"},
}


def steady(study: Path, point: int, alg: str) -> tuple[float, int]:
    """Mean error of all UAVs over the last third of the ticks, averaged over the point's runs."""
    vals = []
    for f in sorted((study / "series").glob(f"{point}-*.npz")):
        with np.load(f) as s:
            if alg in s.files:
                e = s[alg]
                vals.append(float(np.nanmean(e[len(e) * 2 // 3:])))
    return (float(np.mean(vals)) if vals else float("nan")), len(vals)


def table(study: Path, param: str) -> list[str]:
    rows = list(csv.DictReader(open(study / "summary.csv")))
    nees = "nees_mean_mean" in rows[0]
    lines = [f"| {param} | estimator | no-GPS mean error (m), 95% CI | all UAVs, last third (m) |"
             + (" NEES (2 if consistent) |" if nees else "") + " runs |",
             "|---|---|---|---|" + ("---|" if nees else "") + "---|"]
    for r in rows:
        s, n = steady(study, int(r["point"]), r["estimator"])
        lines.append(f"| {r[param]} | {r['estimator']} | {float(r['no_gnss_mean_error_m_mean']):.1f} "
                     f"± {float(r['no_gnss_mean_error_m_ci95']):.1f} | {s:.1f} |"
                     + (f" {float(r['nees_mean_mean']):.3g} |" if nees else "") + f" {r['no_gnss_mean_error_m_n']} |")
    return lines


def step_times(study: Path) -> list[str]:
    """Table 1: time per filtering step, from the nodes' counters of every run."""
    by_m: dict[str, list[float]] = {}
    for r in csv.DictReader(open(study / "results.csv")):
        if r["estimator"] != "dnbp":
            continue
        slices = float(r["stat_slices_normal"]) + float(r["stat_slices_fault"])
        by_m.setdefault(r["estimator.params.M"], []).append(1e3 * float(r["stat_step_s"]) / slices)
    return ["| M | ms per slice and UAV (mean over runs) |", "|---|---|"] + \
        [f"| {m} | {np.mean(v):.2f} |" for m, v in by_m.items()]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--studies", type=Path, default=ROOT / "studies")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "out_wan2014.md")
    ap.add_argument("--img", type=Path, default=ROOT / "docs" / "img")
    args = ap.parse_args()
    out = ["## dNBP (Wan et al. 2014): Fig. 6 and Table 1 from `swarmloc study`", ""]
    for name, (param, title) in STUDIES.items():
        study = args.studies / name
        if not (study / "summary.csv").exists():
            continue
        out += [f"### {title}", "", f"Study `{name}` (benchmarks/studies).", ""] + table(study, param) + [""]
        if name == "wan2014-table1":
            out += step_times(study) + [""]
        for png, to in FIGURES.get(name, {}).items():
            if (study / "plots" / png).exists():
                shutil.copy(study / "plots" / png, args.img / to)
    args.out.write_text("\n".join(out) + "\n")
    print("\n".join(out))


if __name__ == "__main__":
    main()
