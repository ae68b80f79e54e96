"""A study's tables: results.csv (one row per run), summary.csv (mean and 95 % interval per
point), timing.csv, and the summary printed at the end."""

from __future__ import annotations

import csv
import math
from pathlib import Path

from netsim.study.spec import BOUND_COLUMNS, RUN_COLUMNS, TIMING_COLUMNS, Plan, StudyError, StudyResult, cell_text


def json_default(o):
    import numpy as np

    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    raise TypeError(type(o).__name__)


def _write_csv(path: Path, columns: list[str], rows: list[dict]) -> Path:
    with open(path, "w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(columns)
        for r in rows:
            w.writerow([cell_text(r.get(c)) for c in columns])
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


def ci95(values: list[float]) -> tuple[float, float, float, int]:
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


def _median(values: list[float]) -> float:
    import numpy as np

    x = [v for v in values if v is not None and not math.isnan(v)]
    return float(np.median(x)) if x else math.nan


def summarized(metrics: list[str], columns: list[str]) -> list[str]:
    """The columns summary.csv summarizes: the spec's metrics, then the bound's (BOUND_COLUMNS)
    where results.csv has them."""
    return [*metrics, *(c for c in BOUND_COLUMNS if c in columns and c not in metrics)]


def write_tables(out: Path, p: Plan, records: list[dict], metrics: list[str]) -> tuple[list[dict], list[dict], list[Path]]:
    """results.csv (deterministic), timing.csv (wall and CPU time per run) and summary.csv (the
    spec's metrics and the PCRB columns, `summarized`)."""
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
    metrics = summarized(metrics, columns)
    summary = []
    algs = list(dict.fromkeys(r["estimator"] for r in rows))
    for pt, values in enumerate(p.points):
        for alg in algs:
            mine = [r for r in rows if r["point"] == pt and r["estimator"] == alg]
            if not mine:
                continue
            s = {"point": pt, **values, "estimator": alg}
            for m in metrics:
                vals = [r.get(m) for r in mine]
                s[f"{m}_mean"], s[f"{m}_std"], s[f"{m}_ci95"], s[f"{m}_n"] = ci95(vals)
                s[f"{m}_median"] = _median(vals)
            summary.append(s)
    cols = ["point", *p.params, "estimator",
            *[f"{m}_{x}" for m in metrics for x in ("mean", "std", "ci95", "n", "median")]]
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
        t.add_row(*[cell_text(s[q]) for q in params], s["estimator"], *cells)
    return t
