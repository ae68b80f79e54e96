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

Beside the errors, the run's posterior Cramér-Rao bound (issue 24; docs/estimators.md): `PCRB`
is the median over the runs of `pcrb_m`, the bound on the agents' position RMSE over the run
(every agent, every tick counted; the same estimation problem for every estimator), and
`RMSE/PCRB` the median of each run's `rmse_over_pcrb`, the estimator's `rmse_m` (the agents'
position errors over the same cells) over that bound, with the pooled ratio
sqrt(sum rmse^2 / sum pcrb^2) over the runs in brackets. Both are about the agents' own
positions: neither is CSL-CTL's headline (the target's final error) nor dNBP's (only the UAVs
without GPS). Studies run before the PCRB existed have no such columns, and the table leaves
them out.
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
# The run's PCRB columns of results.csv (netsim/study/spec.py BOUND_COLUMNS): the bound on the
# agents' position RMSE over the run, and each estimator's rmse_m over it.
BOUND = ("pcrb_m", "rmse_over_pcrb")
# `--target-bound`: the targets' final PCRB of each run, cached in the study's directory.
TARGET_BOUND_FILE = "target_final_pcrb.csv"
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
    tb = study / TARGET_BOUND_FILE
    if tb.exists():  # `--target-bound`: the targets' final PCRB of each run, by (point, run)
        with open(tb) as f:
            final = {(int(r["point"]), int(r["run"])): num(r["target_final_pcrb_m"]) for r in csv.DictReader(f)}
        for r in rows:
            r["target_final_pcrb_m"] = final.get((int(r["point"]), int(r["run"])), math.nan)
    return params, rows


def target_bounds(study: Path, spec_path: Path) -> None:
    """Each run's target bound at the last tick, into study/target_final_pcrb.csv (once): the
    study's runs are run again in process (a run depends only on its scenario and seed, so the
    sensor stream is the study's) and their PCRB computed (swarmloc.experiment.results
    .compute_bound); `target_final_pcrb_m` is the mean over the targets of each target's bound at
    the last tick (sqrt of the trace of its 2 x 2 block), the bound on the RMS of
    `target_final_error_m`. The study keeps only the agents' bound (`pcrb_m`), hence this."""
    out = study / TARGET_BOUND_FILE
    if out.exists() or not (study / "results.csv").exists():
        return
    from netsim.sim import Simulation
    from netsim.study.spec import build_scenario, load_spec, plan
    from swarmloc.estimators import make_nodes
    from swarmloc.experiment.results import compute_bound
    from swarmloc.experiment.runner import InProcessRunner

    with open(study / "results.csv") as f:
        done = sorted({(int(r["point"]), int(r["run"])) for r in csv.DictReader(f)})
    pl = plan(load_spec(spec_path))
    lines = ["point,run,seed,ticks,target_final_pcrb_m"]
    for point, run in done:
        task = pl.task(point, run)
        sc = build_scenario(task["scenario"], task["source"], task["overrides"], task["seed"])
        record = InProcessRunner(Simulation(sc), make_nodes(sc.estimator.name, sc)).run()
        compute_bound(sc, record)
        b = record.bound
        v = float(np.nanmean(b.target_position[-1])) if b is not None and b.target_ids else math.nan
        lines.append(f"{point},{run},{task['seed']},{len(record.k)},{v!r}")
        print(f"{study.name}: point {point} run {run}: target's final PCRB {v:.3f} m", flush=True)
    out.write_text("\n".join(lines) + "\n")


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
            for m in (*extra, *BOUND):
                e = np.array([r.get(m, math.nan) for r in runs.values()], float)
                s[f"{alg}:{m}"] = float(np.nanmedian(e)) if (~np.isnan(e)).any() else math.nan
            if metric == "target_final_error_m":  # the headline against the target's own bound
                tb = np.array([r.get("target_final_pcrb_m", math.nan) for r in runs.values()], float)
                te = np.array([r[metric] for r in runs.values()], float)
                ok = np.isfinite(tb) & np.isfinite(te)
                s[f"{alg}:tpcrb"] = float(np.median(tb[ok])) if ok.any() else math.nan
                s[f"{alg}:tratio"] = float(np.median(te[ok] / tb[ok])) if ok.any() else math.nan
                s[f"{alg}:tpooled"] = float(np.sqrt(np.sum(te[ok] ** 2) / np.sum(tb[ok] ** 2))) if ok.any() else math.nan
            # The pooled ratio sqrt(sum rmse^2 / sum pcrb^2) over the runs: what a bound that
            # holds keeps at 1 or more in expectation (one run can fall below it by chance).
            p = np.array([r.get("pcrb_m", math.nan) for r in runs.values()], float)
            e = p * np.array([r.get("rmse_over_pcrb", math.nan) for r in runs.values()], float)
            ok = np.isfinite(p) & np.isfinite(e)
            s[f"{alg}:pooled"] = float(np.sqrt(np.sum(e[ok] ** 2) / np.sum(p[ok] ** 2))) if ok.any() else math.nan
        common = sorted(set(by[pair[0]]) & set(by[pair[1]]))
        s["wins"] = sum(by[pair[0]][r][metric] < by[pair[1]][r][metric] for r in common)
        s["n"] = len(common)
        out.append(s)
    return out


def bound_columns(summ: list[dict], pair) -> tuple[list[str], list[str]] | None:
    """The PCRB columns' headers and, per row, the keys of their values: one PCRB column when
    both estimators' runs have the same bound (their cells are the same, as every estimator has
    an estimate at every tick), one each otherwise; then each estimator's RMSE/PCRB. None when
    no run has a bound (a study run before the PCRB existed)."""
    a, b = pair
    if all(math.isnan(s[f"{alg}:pcrb_m"]) for s in summ for alg in pair):
        return None
    same = all(math.isclose(s[f"{a}:pcrb_m"], s[f"{b}:pcrb_m"], rel_tol=1e-9)
               or (math.isnan(s[f"{a}:pcrb_m"]) and math.isnan(s[f"{b}:pcrb_m"])) for s in summ)
    head, keys = (["PCRB (m, median)"], [f"{a}:pcrb_m"]) if same else \
        ([f"{alg} PCRB (m, median)" for alg in pair], [f"{alg}:pcrb_m" for alg in pair])
    head += [f"{alg} RMSE/PCRB median (pooled)" for alg in pair]
    keys += [(f"{alg}:rmse_over_pcrb", f"{alg}:pooled") for alg in pair]
    return head, keys


def table(name: str, params: list[str], summ: list[dict], metric: str, pair, extra, target: bool = False) -> list[str]:
    """target: show the target's final bound (the study has its `--target-bound` file)."""
    a, b = pair
    head = [SHORT.get(p, p) for p in params] + [f"{a} median [IQR]", f"{b} median [IQR]", f"{a} better"]
    target = target and metric == "target_final_error_m"
    if target:
        head += ["target PCRB, final (m, median)"] + [f"{alg} final target error / PCRB median (pooled)" for alg in pair]
    head += [f"{alg} {m} (median)" for m in extra for alg in pair]
    bound = bound_columns(summ, pair)
    if bound:
        head += bound[0]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for s in summ:
        cells = [fmt(s[p], 4).rstrip("0").rstrip(".") if isinstance(s[p], float) else str(s[p]) for p in params]
        for alg in pair:
            med, q1, q3, _ = s[alg]
            cells.append(f"{fmt(med)} [{fmt(q1)}, {fmt(q3)}]")
        cells.append(f"{s['wins']}/{s['n']}")
        if target:
            cells += [fmt(s[f"{a}:tpcrb"])] + [f"{fmt(s[f'{alg}:tratio'])} ({fmt(s[f'{alg}:tpooled'])})" for alg in pair]
        cells += [fmt(s[f"{alg}:{m}"]) for m in extra for alg in pair]
        if bound:
            cells += [fmt(s[k]) if isinstance(k, str) else f"{fmt(s[k[0]])} ({fmt(s[k[1]])})" for k in bound[1]]
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
    ap.add_argument("--target-bound", nargs="*", metavar="STUDY",
                    help="CSL-CTL studies (these, or with no name all of them): run each run again in process for its "
                         f"target's final PCRB (cached in the study's directory, {TARGET_BOUND_FILE}) and show it beside "
                         "the final target error; a study with that file shows it without the option")
    a = ap.parse_args()
    if a.target_bound is not None:
        for name, (metric, *_rest) in STUDIES.items():
            if metric == "target_final_error_m" and (not a.target_bound or name in a.target_bound):
                target_bounds(a.studies / name, ROOT / "benchmarks" / "studies" / f"{name}.yaml")
    given = ("" if a.studies == ap.get_default("studies") else f" --studies {a.studies}") + \
        ("" if a.target_bound is None else " --target-bound" + "".join(f" {n}" for n in a.target_bound))
    into = "" if a.studies == ap.get_default("studies") else f" -o {a.studies}/NAME"
    md = ["## CSL-CTL and dNBP from the papers' own setups", "",
          f"Made by `python benchmarks/repro_findings.py{given}` from the finished studies "
          f"(`swarmloc study benchmarks/studies/NAME.yaml{into}`, 10 runs per point). Medians over the runs, "
          "interquartile range in brackets; 'better' counts the runs (same seed) in which the paper's method "
          "has the lower headline error. PCRB: the median over the runs of the posterior Cramér-Rao bound on the "
          "agents' position RMSE over the run (`pcrb_m`: every agent, every tick; the same problem for every "
          "estimator); RMSE/PCRB: the median of each run's `rmse_over_pcrb`, the estimator's position RMSE over "
          "all agents and ticks (`rmse_m`) divided by that bound, and in brackets the pooled ratio "
          "sqrt(sum rmse^2 / sum pcrb^2) over the runs. Both are about the agents' own positions, not "
          "the headline (CSL-CTL: the target's final error; dNBP: the UAVs without GPS only). A pooled ratio "
          "below 1 is impossible for a bound that holds (one run can fall below it by chance); where the "
          "linearisation at truth fails it is no bound (docs/estimators.md, the PCRB's assumptions)."
          + (" Target PCRB, final (`--target-bound`, CSL-CTL): the median over the runs of the target's own bound "
             "at the last tick, the bound on the RMS of the final target error, from the same runs run again in "
             "process; then each estimator's final target error over it, the median of the per-run ratio and the "
             "pooled ratio in brackets; in the tables of the studies it was computed for."
             if any((a.studies / n / TARGET_BOUND_FILE).exists() for n in STUDIES) else ""), ""]
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
        md += table(name, params, summ, metric, pair, extra, (study / TARGET_BOUND_FILE).exists()) + [""]
        if params:
            plot(name, params, summ, metric, pair, title, a.fig_dir / f"{name}.png")
            md += [f"Plot: `docs/img/{name}.png`.", ""]
    a.out.write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
