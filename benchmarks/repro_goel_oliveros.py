"""Goel et al. 2016 (EKF-CI) and Oliveros & Ashrafiuon 2023 (EKF-CL) from finished `swarmloc
study` runs: the tables of docs/ekf-ci.md and docs/oliveros.md (medians over the runs, with the
interquartile range) and their plots in docs/img.

Run the studies first (benchmarks/studies/goel*.yaml, oliveros*.yaml), each into studies/<name>/:

    swarmloc study benchmarks/studies/goel10-ranges.yaml
    ...
    python benchmarks/repro_goel_oliveros.py

(--studies DIR if they were run with --out DIR/<name>). A study not run yet is skipped (and said
so). The CSL-CTL and dNBP papers have theirs in benchmarks/repro_findings.py.

Per point and estimator: the median of each metric over the runs and its quartiles; for a
comparison of two estimators or two settings on the same seeds (common random numbers), the
median of the per-seed ratio and in how many seeds it is below 1.

Beside the errors, the run's posterior Cramér-Rao bound (issue 24; docs/estimators.md), where
the runs have it: `pcrb_m`, the bound on the position RMSE of every node over every tick counted
(after the study's settle), and `rmse_over_pcrb`, the estimator's `rmse_m` over the same cells
divided by it; their medians and quartiles, and the pooled ratio sqrt(sum rmse^2 / sum pcrb^2)
over the runs (what a bound that holds keeps at 1 or more). For a study with per-agent columns
(`agents:` in its spec) whose metrics include an agent's position error (`a2_mean_error_m`),
that agent's own bound too (`a2_pcrb_m`, `a2_rmse_over_pcrb`). The bound is about position
errors: it says nothing about a jitter or a tracking error, and `no_gnss_*` columns (the nodes
without GNSS only) have none of their own.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent

# study -> (what it sweeps, in words; the metrics of its table; the plot: x parameter, metric, y label, log y,
# log x, the estimators shown (None: all))
STUDIES = {
    "goel10-ranges": ("Figs. 5 and 6, ten UAS ranging all pairs (the headline)",
                      ["no_gnss_max_error_m", "max_error_m", "no_gnss_mean_error_m", "mean_error_m"], None),
    "goel10-ranges-settle": ("the same from t = 0 (the start-up in), and with a perfect alignment",
                             ["no_gnss_max_error_m", "max_error_m", "mean_error_m"], None),
    "goel10-ranges-rate": ("the GNSS rate (ranges at the same epochs)",
                           ["no_gnss_max_error_m", "max_error_m", "mean_error_m"],
                           ("sensors.epoch", "max_error_m", "largest error of any node (m)", True, True, ["ekf-ccl"])),
    "goel10-ranges-range-rate": ("the range rate alone (GNSS at 1 Hz)",
                                 ["no_gnss_max_error_m", "no_gnss_mean_error_m"],
                                 ("sensors.relative_epoch", "no_gnss_max_error_m",
                                  "nodes without GNSS: largest error (m)", False, True, ["ekf-ccl"])),
    "goel10-ranges-noise": ("the range noise, and each pair ranged once or from both ends",
                            ["no_gnss_max_error_m", "no_gnss_mean_error_m"],
                            ("sensors.range.noise", "no_gnss_max_error_m", "nodes without GNSS: largest error (m)", True, True, ["ekf-ccl"])),
    "goel10-ranges-imu": ("the accelerometers' turn-on bias",
                          ["no_gnss_max_error_m", "no_gnss_mean_error_m"],
                          ("sensors.imu.accel_bias_sigma0", "no_gnss_max_error_m",
                           "nodes without GNSS: largest error (m)", False, True, ["ekf-ccl"])),
    "goel10-ranges-formation": ("the formation: the ring spread over 20-80 m of altitude instead of 45-55 m",
                                ["no_gnss_max_error_m", "max_error_m", "no_gnss_mean_error_m", "mean_error_m"], None),
    "goel20-ranges": ("twenty UAS ranging all pairs, GNSS on half", ["no_gnss_max_error_m", "max_error_m",
                                                                      "no_gnss_mean_error_m", "mean_error_m"], None),
    "goel-fig2": ("Fig. 2: relative position shared, GNSS on both, the GNSS rate",
                  ["mean_error_m", "rmse_m", "max_error_m"], ("sensors.epoch", "mean_error_m", "mean error (m)", False, True)),
    "goel-fig2-range": ("Fig. 2: range shared, GNSS on both: range noise and rate",
                        ["mean_error_m", "rmse_m", "max_error_m"], None),
    "goel-fig2-relpos": ("Fig. 2: relative position shared, GNSS on both: its noise and rate",
                         ["mean_error_m", "rmse_m", "max_error_m"], None),
    "goel-dist-gnss": ("sections 5.2-5.3: distributed EKF-CI, GNSS on both or on UAS 1 only",
                       ["a2_mean_error_m", "a2_max_error_m", "mean_error_m"], None),
    "oliveros-case4-orientation": ("Table 1 cases 1 and 4: the orientation noise",
                                   ["jitter_m", "rmse_m", "a1_jitter_m", "a4_jitter_m"],
                                   ("sensors.vehicle.attitude_noise", "jitter_m", "jitter (m per tick)", True, True)),
    "oliveros-case4-actuator": ("Table 1 cases 1 and 4: the moment noise (world)",
                                ["jitter_m", "rmse_m", "a1_jitter_m", "a4_jitter_m"],
                                ("sensors.vehicle.moment_noise", "jitter_m", "jitter (m per tick)", True, True)),
    "oliveros-case4-filter-q": ("Table 1 cases 1 and 4: the filters' process noise",
                                ["jitter_m", "rmse_m", "a1_jitter_m", "a4_jitter_m"], None),
    "oliveros-chain-control": ("Table 2 case 1 (one caravan), with CL and without (raw)",
                               ["a1_tracking_rmse_m", "a2_tracking_rmse_m", "a3_tracking_rmse_m", "a4_tracking_rmse_m",
                                "jitter_m", "rmse_m"], None),
    "oliveros-chain-control-filter": ("Table 2 case 1 (one caravan), the paper's filter assumptions over a good IMU",
                                      ["a1_tracking_rmse_m", "a2_tracking_rmse_m", "a3_tracking_rmse_m",
                                       "a4_tracking_rmse_m", "jitter_m", "rmse_m"], None),
}
# Paired comparisons on common seeds: (study, the parameter that differs, value a, value b, metrics).
PAIRS = {
    "goel10-ranges": ("estimator", "ekf", "ekf-ccl", ["no_gnss_max_error_m", "mean_error_m"]),
    "goel-fig2": ("estimator", "ekf", "ekf-ccl", ["mean_error_m", "rmse_m"]),
    "goel-fig2-range": ("estimator", "ekf", "ekf-ccl", ["mean_error_m", "rmse_m"]),
    "goel-fig2-relpos": ("estimator", "ekf", "ekf-ccl", ["mean_error_m", "rmse_m"]),
    "goel-dist-gnss": ("estimator", "ekf", "ekf-ci", ["a2_mean_error_m", "mean_error_m"]),
    "oliveros-case4-orientation": ("sensors.vehicle.graph", 0, 1, ["jitter_m", "rmse_m", "a1_jitter_m", "a4_jitter_m"]),
    "oliveros-case4-actuator": ("sensors.vehicle.graph", 0, 1, ["jitter_m", "rmse_m", "a1_jitter_m", "a4_jitter_m"]),
    "oliveros-case4-filter-q": ("sensors.vehicle.graph", 0, 1, ["jitter_m", "rmse_m", "a1_jitter_m", "a4_jitter_m"]),
    "oliveros-chain-control": ("estimator.name", "ekf-cl", "raw",
                               ["a1_tracking_rmse_m", "a2_tracking_rmse_m", "a3_tracking_rmse_m", "a4_tracking_rmse_m",
                                "jitter_m"]),
    "oliveros-chain-control-filter": ("estimator.name", "ekf-cl", "raw",
                                      ["a1_tracking_rmse_m", "a2_tracking_rmse_m", "a3_tracking_rmse_m",
                                       "a4_tracking_rmse_m", "jitter_m"]),
}
CASE = {0: "case 1 (1 -> 5)", 1: "case 4 (4 -> 8)"}


def load(study: Path) -> tuple[list[str], list[dict]]:
    meta = json.loads((study / "study.json").read_text())
    with open(study / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    return meta["params"], rows


def num(v: str) -> float:
    return float(v) if v not in ("", None) else float("nan")


def label(param: str, v: str, values: list[str]) -> str:
    if param == "sensors.vehicle.graph":
        return CASE.get(values.index(v), v)
    if param == "sensors.gnss.agents":
        return "GNSS on all" if v == "" else f"GNSS on {v}"
    return f"{param.rsplit('.', 1)[-1]}={v if v != '' else 'null'}"


def quartiles(x: list[float]) -> tuple[float, float, float, int]:
    a = np.array([v for v in x if not np.isnan(v)])
    if not a.size:
        return (float("nan"),) * 3 + (0,)
    q1, m, q3 = np.percentile(a, [25, 50, 75])
    return float(m), float(q1), float(q3), int(a.size)


def fmt(v: float) -> str:
    if np.isnan(v):
        return "-"
    return f"{v:.3g}" if abs(v) < 100 else f"{v:.0f}"


def groups(params: list[str], rows: list[dict]) -> dict:
    """(point values..., estimator) -> rows, in the study's order."""
    out: dict = {}
    for r in rows:
        out.setdefault((*[r[p] for p in params], r["estimator"]), []).append(r)
    return out


def bounds_of(metrics: list[str], rows: list[dict]) -> list[str]:
    """The bound's prefixes shown beside `metrics`: "" (the whole swarm's `pcrb_m`) when the runs
    have it, and "a<id>_" for each agent whose position error is among the metrics and whose
    bound the runs have. [] for a study run before the PCRB existed."""
    have = rows[0].keys() if rows else ()
    out = [""] if "pcrb_m" in have and any(r["pcrb_m"] not in ("", None) for r in rows) else []
    for m in metrics:
        head, _, rest = m.partition("_")
        if head[:1] == "a" and head[1:].isdigit() and rest in ("mean_error_m", "rmse_m", "max_error_m") \
                and f"{head}_pcrb_m" in have and f"{head}_" not in out:
            out.append(f"{head}_")
    return out


def pooled(rs: list[dict], prefix: str) -> float:
    """sqrt(sum rmse^2 / sum pcrb^2) over the runs: the ratio a bound that holds keeps >= 1 in
    expectation (one run's can fall below it by chance)."""
    p = np.array([num(r.get(f"{prefix}pcrb_m", "")) for r in rs])
    e = p * np.array([num(r.get(f"{prefix}rmse_over_pcrb", "")) for r in rs])
    ok = np.isfinite(p) & np.isfinite(e)
    return float(np.sqrt(np.sum(e[ok] ** 2) / np.sum(p[ok] ** 2))) if ok.any() else float("nan")


def table(name: str, params: list[str], rows: list[dict], metrics: list[str]) -> list[str]:
    values = {p: list(dict.fromkeys(r[p] for r in rows)) for p in params}
    bounds = bounds_of(metrics, rows)
    cols = [*metrics, *[f"{b}{c}" for b in bounds for c in ("pcrb_m", "rmse_over_pcrb")]]
    head = [*params, "estimator", *[f"{m} median [q1, q3]" for m in cols],
            *[f"{b}rmse_over_pcrb pooled" for b in bounds], "runs"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for key, rs in groups(params, rows).items():
        cells = [label(p, v, values[p]) for p, v in zip(params, key[:-1])] + [key[-1]]
        n = 0
        for i, m in enumerate(cols):
            med, q1, q3, k = quartiles([num(r.get(m, "")) for r in rs])
            n = k if i < len(metrics) else n
            cells.append(f"{fmt(med)} [{fmt(q1)}, {fmt(q3)}]")
        cells += [fmt(pooled(rs, b)) for b in bounds]
        lines.append("| " + " | ".join(cells) + f" | {n} |")
    return lines


def paired(params: list[str], rows: list[dict], spec) -> list[str]:
    """Per-seed ratio b / a of each metric, a and b two values of one parameter (or estimator) on
    the same seed and otherwise the same point: median ratio and the seeds with b < a."""
    what, a, b, metrics = spec
    # An estimator compared with another: the reference column of the rows, or the swept
    # estimator.name (each row's estimator is then the point's).
    own = what in ("estimator", "estimator.name")
    values = {p: list(dict.fromkeys(r[p] for r in rows)) for p in params}
    if not own and isinstance(a, int):
        a, b = values[what][a], values[what][b]
    other = [p for p in params if p != what]
    key = (lambda r: r["estimator"]) if own else (lambda r: r[what])
    rest = (lambda r: tuple(r[p] for p in other)) if own else \
        (lambda r: (*[r[p] for p in other], r["estimator"]))
    by: dict = {}
    for r in rows:
        by.setdefault(rest(r), {}).setdefault(key(r), {})[r["seed"]] = r
    name_a = a if own else label(what, a, values.get(what, [a, b]))
    name_b = b if own else label(what, b, values.get(what, [a, b]))
    head = [*other] + ([] if own else ["estimator"]) + \
        [f"{m}: {name_b} / {name_a}, median (seeds below 1)" for m in metrics]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for k, per in by.items():
        if a not in per or b not in per:
            continue
        cells = [label(p, v, values[p]) for p, v in zip(other, k)] + ([] if own else [k[-1]])
        for m in metrics:
            ratios = [num(per[b][s].get(m, "")) / num(per[a][s].get(m, "")) for s in per[a] if s in per[b]]
            ratios = [x for x in ratios if not np.isnan(x)]
            cells.append(f"{np.median(ratios):.3f} ({sum(x < 1 for x in ratios)}/{len(ratios)})" if ratios else "-")
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def plot(path: Path, name: str, params: list[str], rows: list[dict], x: str, metric: str, ylabel: str, log: bool,
         logx: bool = False, only: list[str] | None = None):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    values = {p: list(dict.fromkeys(r[p] for r in rows)) for p in params}
    others = [p for p in params if p != x]
    xs = values[x]
    numeric = all(v not in ("",) and v.replace(".", "", 1).replace("e-", "", 1).isdigit() for v in xs)
    pos = {v: (float(v) if numeric else i) for i, v in enumerate(xs)}
    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    lines: dict = {}
    for r in rows:
        if only is None or r["estimator"] in only:
            lines.setdefault((tuple(r[p] for p in others), r["estimator"]), {}).setdefault(r[x], []).append(num(r.get(metric, "")))
    for (rest, alg), by in lines.items():
        pts = [(pos[v], *quartiles(by[v])[:3]) for v in xs if v in by]
        if not pts or all(np.isnan(p[1]) for p in pts):
            continue
        px, med, q1, q3 = map(np.array, zip(*pts))
        lab = ", ".join([alg] + [label(p, v, values[p]) for p, v in zip(others, rest)])
        ax.errorbar(px, med, yerr=[med - q1, q3 - med], marker="o", capsize=3, label=lab)
    if not numeric:
        ax.set_xticks(range(len(xs)), [label(x, v, xs) for v in xs])
    if log:
        ax.set_yscale("log")
    if logx and numeric:
        ax.set_xscale("log")
    ax.set_xlabel(x)
    ax.set_ylabel(ylabel)
    n = max(len(v) for by in lines.values() for v in by.values())
    ax.set_title(f"{name}: median and quartiles over {n} runs", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--studies", type=Path, default=Path("studies"), help="where the studies' directories are")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "out_goel_oliveros.md")
    ap.add_argument("--img", type=Path, default=ROOT / "docs" / "img")
    args = ap.parse_args()
    args.img.mkdir(parents=True, exist_ok=True)
    given = "" if args.studies == ap.get_default("studies") else f" --studies {args.studies}"
    into = "" if args.studies == ap.get_default("studies") else f" -o {args.studies}/<name>"
    lines = ["# Goel et al. 2016 and Oliveros & Ashrafiuon 2023 from their own setups", "",
             f"From the studies of benchmarks/studies/ (`swarmloc study benchmarks/studies/<name>.yaml{into}`), by "
             f"`python benchmarks/repro_goel_oliveros.py{given}`. Medians over the runs with the quartiles; ratios "
             "are per seed (the points share their seeds).", "",
             "The bound (issue 24): `pcrb_m` is the run's posterior Cramér-Rao bound on the position RMSE of every "
             "node over every tick counted (the same ticks as the errors); `rmse_over_pcrb` is the estimator's "
             "`rmse_m` (every node, those ticks) over it, and `pooled` is sqrt(sum rmse^2 / sum pcrb^2) over the "
             "runs, which a bound that holds keeps at 1 or more (one run can fall below it by chance). `a2_pcrb_m`, "
             "`a2_rmse_over_pcrb`: the same for UAS 2 alone. The bound is the same for every estimator of a run "
             "(its cells aside); in a closed loop (Oliveros section 6.3) each estimator's runs fly their own "
             "trajectories and have their own. It says nothing about the `no_gnss_*` columns in particular (they "
             "are the nodes without GNSS only), a jitter or a tracking error.", ""]
    for name, (what, metrics, fig) in STUDIES.items():
        d = args.studies / name
        if not (d / "results.csv").exists():
            print(f"{name}: not run (no {d / 'results.csv'}), skipped")
            continue
        params, rows = load(d)
        lines += [f"## {name}: {what}", "", f"`swarmloc study benchmarks/studies/{name}.yaml`", ""]
        lines += table(name, params, rows, metrics) + [""]
        if name in PAIRS:
            lines += paired(params, rows, PAIRS[name]) + [""]
        if fig is not None:
            out = args.img / f"{name}.png"
            plot(out, name, params, rows, *fig)
            lines += [f"![{name}](../docs/img/{name}.png)", ""]
    args.out.write_text("\n".join(lines) + "\n")
    print(args.out.read_text())


if __name__ == "__main__":
    main()
