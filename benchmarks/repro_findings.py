"""The CSL-CTL and dNBP papers reproduced from their own setups: median tables and plots from
finished `swarmloc study` runs of benchmarks/studies/wang2022-paper*.yaml and
wan2014-paper-*.yaml.

Run the studies first (10 runs per point, their default), from the repository root:

    for s in benchmarks/studies/wang2022-paper*.yaml benchmarks/studies/wan2014-paper-*.yaml; do
        swarmloc study $s; done
    python benchmarks/repro_findings.py

For every point: each estimator's median of the study's headline metric over the runs, with its
interquartile range, and in how many runs the paper's method beats its baseline (the same seed:
the points of a study share their seeds). Writes benchmarks/out_repro.md and one plot per study
in docs/img/ (median and interquartile band against the swept parameter). Not a test. The
Goel (EKF-CI) and Oliveros (EKF-CL) papers have theirs in benchmarks/repro_goel_oliveros.py.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent

# study -> (headline metric, (method, baseline), other estimators to show, extra metrics, title)
CTL = ("target_final_error_m", ("csl-ctl", "il-ctl"), (), ("mean_error_m",))
NBP = ("no_gnss_mean_error_m", ("dnbp", "ls"), (), ("mean_error_m", "nees_mean"))
# A sweep leaves out the scenario's own value, which another study already ran with the same
# seeds: (that study, the swept values its runs have, which of its points to take).
CTL_BASE = "wang2022-paper"
NBP_BASE = "wan2014-paper-fig6b"
STUDIES = {
    "wang2022-paper": (*CTL, "CSL-CTL, the paper's setup: final target error", None),
    "wang2022-paper-start": (*CTL, "CSL-CTL: start distance from the target (m)",
                             (CTL_BASE, {"world.formation.radius": 400.0}, {})),
    "wang2022-paper-spread": (*CTL, "CSL-CTL: angular spread of the agents seen from the target (deg)",
                              (CTL_BASE, {"world.formation.spread_deg": 40.0}, {})),
    "wang2022-paper-gyro": (*CTL, "CSL-CTL: gyro noise std (rad/s)",
                            (CTL_BASE, {"sensors.odometry.turn_rate_noise": 0.05}, {})),
    "wang2022-paper-agent-ranges": (*CTL, "CSL-CTL: probability of a range among agents per tick",
                                    (CTL_BASE, {"sensors.range.probability": 0.5}, {})),
    "wang2022-paper-table4": (*CTL, "CSL-CTL, Table 4's five noise settings: target range noise std (m)",
                              (CTL_BASE, {"sensors.target_range.noise": 10.0}, {})),
    "wan2014-paper-fig6b": (*NBP, "dNBP, Fig. 6(b): communication range R (m)", None),
    "wan2014-paper-motion": (*NBP, "dNBP: odometry speed noise std (m/s), the motion model's strength",
                             (NBP_BASE, {"sensors.odometry.speed_noise": 2.0}, {"radio.range_m": (300.0, 700.0)})),
    "wan2014-paper-prior": (*NBP, "dNBP: initial position std (m)",
                            (NBP_BASE, {"estimation.initial_std": 3.0}, {"radio.range_m": (300.0, 700.0)})),
    "wan2014-paper-fig6c": (*NBP, "dNBP, Fig. 6(c): GPS noise std (m), R = 500 m",
                            (NBP_BASE, {"sensors.gnss.noise": 3.0}, {"radio.range_m": (500.0,)})),
    "wan2014-paper-samples": (*NBP, "dNBP, Table 1: samples M, R = 500 m",
                              (NBP_BASE, {"estimator.params.M": 300.0}, {"radio.range_m": (500.0,)})),
}
# The papers' own numbers, drawn as dotted lines: Table 4's medians (CSL-CTL 1.23 m, IL-CTL
# 10.38 m over its five rows) and Table 1's "error of 3 meters" with 300 samples.
PAPER_LINES = {"csl-ctl": [(1.2316, "paper Table 4 median, CSL-CTL"), (10.3814, "paper Table 4 median, IL-CTL")],
               "dnbp": [(3.0, "paper Table 1: 3 m at M = 300")]}
SHORT = {"world.formation.radius": "start distance (m)", "world.formation.spread_deg": "spread (deg)",
         "sensors.odometry.turn_rate_noise": "gyro std (rad/s)", "sensors.range.probability": "agent-range p",
         "sensors.target_range.noise": "target range std (m)", "radio.range_m": "R (m)",
         "sensors.odometry.speed_noise": "speed std (m/s)", "estimation.initial_std": "start std (m)",
         "estimator.params.M": "M", "sensors.gnss.noise": "GPS std (m)"}


def num(v: str):
    try:
        return float(v) if v != "" else math.nan
    except ValueError:
        return v


def load(study: Path) -> tuple[list[str], list[dict]]:
    info = json.loads((study / "study.json").read_text())
    params = [p for p in info["params"] if not any(s.get("same_as") and s["param"] == p for s in info["spec"]["sweep"])]
    with open(study / "results.csv") as f:
        rows = [{k: num(v) if k not in ("estimator",) else v for k, v in r.items()} for r in csv.DictReader(f)]
    return params, rows


def fmt(x: float, nd: int = 2) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{nd}f}"


def with_base(studies: Path, params: list[str], rows: list[dict], base) -> list[dict]:
    """The study's rows and, where it left out the scenario's own value, the other study's runs
    of that value (same seeds), filtered to the points that match."""
    if base is None or not (studies / base[0] / "results.csv").exists():
        return rows
    name, values, where = base
    _, theirs = load(studies / name)
    keep = [dict(r, **values) for r in theirs if all(r[k] in v for k, v in where.items())]
    return rows + keep


def summarize(params: list[str], rows: list[dict], metric: str, pair: tuple[str, str], extra) -> list[dict]:
    out = []
    for key in sorted({tuple(r[p] for p in params) for r in rows}):
        mine = [r for r in rows if tuple(r[p] for p in params) == key]
        s = dict(zip(params, key))
        by = {}
        for alg in pair:
            runs = {int(r["run"]): r for r in mine if r["estimator"] == alg}
            by[alg] = runs
            v = np.array([r[metric] for r in runs.values()], float)
            v = v[~np.isnan(v)]
            s[alg] = (float(np.median(v)), float(np.percentile(v, 25)), float(np.percentile(v, 75)), v.size) if v.size \
                else (math.nan, math.nan, math.nan, 0)
            for m in extra:
                e = np.array([r[m] for r in runs.values()], float)
                s[f"{alg}:{m}"] = float(np.nanmedian(e)) if (~np.isnan(e)).any() else math.nan
        common = sorted(set(by[pair[0]]) & set(by[pair[1]]))
        s["wins"] = sum(by[pair[0]][r][metric] < by[pair[1]][r][metric] for r in common)
        s["n"] = len(common)
        out.append(s)
    return out


def table(name: str, params: list[str], summ: list[dict], metric: str, pair, extra) -> list[str]:
    a, b = pair
    head = [SHORT.get(p, p) for p in params] + [f"{a} median [IQR]", f"{b} median [IQR]", f"{a} better"]
    head += [f"{alg} {m} (median)" for m in extra for alg in pair]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for s in summ:
        cells = [fmt(s[p], 4).rstrip("0").rstrip(".") if isinstance(s[p], float) else str(s[p]) for p in params]
        for alg in pair:
            med, q1, q3, _ = s[alg]
            cells.append(f"{fmt(med)} [{fmt(q1)}, {fmt(q3)}]")
        cells.append(f"{s['wins']}/{s['n']}")
        cells += [fmt(s[f"{alg}:{m}"]) for m in extra for alg in pair]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def plot(name: str, params: list[str], summ: list[dict], metric: str, pair, title: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    x, groups = params[0], params[1:]
    keys = sorted({tuple(s[g] for g in groups) for s in summ})
    colors = {pair[0]: "tab:green", pair[1]: "tab:red"}
    styles = ["-", "--", ":", "-."]
    for gi, key in enumerate(keys):
        pts = sorted((s for s in summ if tuple(s[g] for g in groups) == key), key=lambda s: s[x])
        xs = np.array([s[x] for s in pts], float)
        for alg in pair:
            med = np.array([s[alg][0] for s in pts])
            lo, hi = np.array([s[alg][1] for s in pts]), np.array([s[alg][2] for s in pts])
            lab = alg + "".join(f", {SHORT.get(g, g)} = {v:g}" for g, v in zip(groups, key))
            ax.plot(xs, med, styles[gi % 4], marker="o", color=colors[alg], label=lab)
            ax.fill_between(xs, lo, hi, color=colors[alg], alpha=0.12)
    for i, (y, lab) in enumerate(PAPER_LINES.get(pair[0], [])):
        ax.axhline(y, color="0.35", ls=(0, (1, 2 + 2 * i)), lw=1.2, label=lab)
    ax.set_xlabel(SHORT.get(x, x))
    ax.set_ylabel(f"{metric} (m)\nmedian, band: interquartile range", fontsize=8)
    ax.set_yscale("log")
    ax.grid(alpha=0.3, which="both")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--studies", type=Path, default=ROOT / "studies", help="where the studies' output directories are")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "out_repro.md")
    ap.add_argument("--fig-dir", type=Path, default=ROOT / "docs" / "img")
    a = ap.parse_args()
    md = ["## CSL-CTL and dNBP from the papers' own setups", "",
          "Made by `python benchmarks/repro_findings.py` from the finished studies "
          "(`swarmloc study benchmarks/studies/NAME.yaml`, 10 runs per point). Medians over the runs, "
          "interquartile range in brackets; 'better' counts the runs (same seed) in which the paper's method "
          "has the lower headline error.", ""]
    for name, (metric, pair, _, extra, title, base) in STUDIES.items():
        study = a.studies / name
        if not (study / "results.csv").exists():
            md += [f"### {name}", "", "(not run)", ""]
            continue
        params, rows = load(study)
        rows = with_base(a.studies, params, rows, base)
        summ = summarize(params, rows, metric, pair, extra)
        also = f" and `{base[0]}` (the scenario's value)" if base else ""
        md += [f"### {name}: {title}", "", f"`swarmloc study benchmarks/studies/{name}.yaml`{also}; headline `{metric}`.", ""]
        md += table(name, params, summ, metric, pair, extra) + [""]
        if params:
            plot(name, params, summ, metric, pair, title, a.fig_dir / f"{name}.png")
            md += [f"Plot: `docs/img/{name}.png`.", ""]
    a.out.write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
