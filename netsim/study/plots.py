"""A study's plots: each metric against each swept parameter, and error against time."""

from __future__ import annotations

import math
import numbers
import warnings
from pathlib import Path

from netsim.study.spec import MAX_TIME_LINES, Plan, cell_text, point_label

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

    from swarmloc.experiment.plots import DPI

    d = out / "plots"
    d.mkdir(exist_ok=True)
    files = []
    axes = [s.param for s in p.spec.sweep if s.values is not None]
    tied = {s.param: s.same_as for s in p.spec.sweep if s.same_as is not None}
    algs = list(dict.fromkeys(s["estimator"] for s in summary))
    for m in metrics:
        for x in axes:
            others = [a for a in axes if a != x]
            # Values by their text: a swept value may be a list (an agent set, a graph), not hashable.
            keys = list(dict.fromkeys(cell_text(pt[x]) for pt in p.points))
            xs = [next(pt[x] for pt in p.points if cell_text(pt[x]) == k) for k in keys]
            numeric = all(isinstance(v, numbers.Real) and not isinstance(v, bool) for v in xs)
            pos = {k: (v if numeric else i) for i, (k, v) in enumerate(zip(keys, xs))}
            groups = list(dict.fromkeys(tuple(cell_text(pt[o]) for o in others) for pt in p.points))
            panels = algs if others else [None]
            fig, axs = plt.subplots(1, len(panels), figsize=(6 * len(panels), 4.5), squeeze=False)
            for ax, panel in zip(axs[0], panels):
                lines = [(alg, g) for alg in (algs if panel is None else [panel]) for g in groups]
                for alg, g in lines:
                    rows = [s for s in summary if s["estimator"] == alg and tuple(cell_text(s[o]) for o in others) == g]
                    rows.sort(key=lambda s: keys.index(cell_text(s[x])))
                    color, label = _style(alg)
                    if others:
                        color, label = None, ", ".join(f"{o}={v}" for o, v in zip(others, g))
                    ax.errorbar([pos[cell_text(s[x])] for s in rows], [s[f"{m}_mean"] for s in rows],
                                yerr=[0 if math.isnan(s[f"{m}_ci95"]) else s[f"{m}_ci95"] for s in rows],
                                marker="o", capsize=3, color=color, label=label)
                if not numeric:
                    ax.set_xticks(range(len(xs)), keys)
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
                ax.plot(t, e, lw=1.2, label=f"{point_label(p.points[pt]) or p.scenario_name} ({n} runs)")
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
