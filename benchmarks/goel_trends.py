"""Accuracy figures and plots quoted in docs/ekf-ci.md (not timings): the EKF family on the
goel scenarios, in process (the same nodes the agent processes run).

Usage: python benchmarks/goel_trends.py [2node 10 20 10r dist]   (a few minutes; writes docs/img/goel*.png)
"""

from __future__ import annotations

from swarmloc.process import pin_blas

pin_blas()  # before numpy loads

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from netsim.sim import Simulation  # noqa: E402
from swarmloc.estimators import REGISTRY  # noqa: E402
from swarmloc.experiment import scenario as S  # noqa: E402
from swarmloc.experiment.results import RunRecord, compute_references, position_errors  # noqa: E402
from swarmloc.experiment.runner import InProcessRunner, make_nodes  # noqa: E402

IMG = Path(__file__).resolve().parent.parent / "docs" / "img"


def run(sc, estimator: str | None, refs: list[str]):
    """(record, {name: position errors (T, N)}): the agents' estimator in process, then references."""
    if estimator is None:
        sim = Simulation(sc)
        record = RunRecord.for_scenario(sc)
        for _ in range(sim.steps + 1):
            k, t, frames = sim.tick()
            record.add_tick(k, t, frames, sim.truth())
    else:
        record = InProcessRunner(Simulation(sc), make_nodes(estimator, sc)).run()
    compute_references(sc, record, refs)
    names = ([estimator] if estimator else []) + refs
    return record, {n: position_errors(record, record.trace(n)) for n in names}


def plot(path: Path, t, curves: dict, title: str, shade=None, log=False) -> None:
    fig, ax = plt.subplots(figsize=(7, 3.4))
    for label, (y, color, ls) in curves.items():
        ax.plot(t, y, color=color, ls=ls, lw=1.2, label=label)
    if shade:
        ax.axvspan(*shade, color="0.9", zorder=0, label="UAS 2 without GNSS")
    if log:
        ax.set_yscale("log")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("position error (m)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def goel2node() -> None:
    print("goel2node: UAS 2 without GNSS 10-50 s; centralized EKF (ekf-ccl = the fusion centre's solution)")
    rec, e = run(S.load("goel2node"), None, ["ekf", "ekf-ccl"])
    _, r = run(S.load("goel2node").with_overrides(**{"sensors.range.all_pairs": False, "sensors.relpos.enabled": True}),
               None, ["ekf-ccl"])
    t = np.array(rec.t)
    rows = {"no sharing": e["ekf"][:, 1], "ranges shared": e["ekf-ccl"][:, 1], "relative position shared": r["ekf-ccl"][:, 1]}
    print(f"  {'UAS 2 error (m)':28s} {'t=30 s':>8s} {'t=49.9 s':>9s} {'max 10-50 s':>12s} {'mean 55-60 s':>13s}")
    for name, y in rows.items():
        print(f"  {name:28s} {y[300]:8.3f} {y[499]:9.3f} {y[100:500].max():12.3f} {y[550:].mean():13.3f}")
    plot(IMG / "goel-2node.png", t, {"no sharing": (rows["no sharing"], REGISTRY.color("ekf"), "-"),
                                     "ranges shared": (rows["ranges shared"], "tab:blue", "-"),
                                     "relative position shared": (rows["relative position shared"], "tab:green", "-")},
         "goel2node: the outage UAS (centralized EKF)", shade=(10, 50), log=True)


def goel_n(name: str, half: list[int]) -> None:
    for label, gnss in (("GNSS on all", None), (f"GNSS on {half}", half)):
        sc = S.load(name).with_overrides(**{"sensors.gnss.agents": gnss})
        rec, e = run(sc, None, ["ekf", "ekf-ccl"])
        err = e["ekf-ccl"]
        print(f"{name}, {label}: centralized EKF max error {err[1:].max():.3f} m (after 10 s: {err[100:].max():.3f} m), "
              f"mean {np.nanmean(err[1:]):.3f} m; alone (ekf) max {e['ekf'][1:].max():.2f} m")
        if gnss is not None:
            t = np.array(rec.t)
            fig, ax = plt.subplots(figsize=(7, 3.4))
            for ci, aid in enumerate(rec.ids):
                ax.plot(t, err[:, ci], lw=0.9, ls="-" if aid in half else "--", label=f"UAS {aid}" + ("" if aid in half else " (no GNSS)"))
            ax.set_xlabel("time (s)")
            ax.set_ylabel("position error (m)")
            ax.set_title(f"{name}: centralized EKF, {label}")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=6, ncol=2)
            fig.savefig(IMG / f"{name}-half.png", dpi=110, bbox_inches="tight")
            plt.close(fig)


def goel_n_ranges(name: str, half: list[int]) -> None:
    """Fig. 6 as the paper sets it up: ranges between all nodes, GNSS on half."""
    rec, e = run(S.load(name), None, ["ekf-ccl"])
    err, t = e["ekf-ccl"], np.array(rec.t)
    without = [ci for ci, a in enumerate(rec.ids) if a not in half]
    print(f"{name}: centralized EKF, nodes without GNSS: max {err[1:, without].max():.3f} m, after 10 s "
          f"{err[100:, without].max():.3f} m; nodes with GNSS after 10 s {np.delete(err[100:], without, axis=1).max():.3f} m")
    # Horizontal against vertical: ranges within a formation at nearly one altitude say little about height.
    d = rec.trace("ekf-ccl").mean[100:, :, :3] - rec.truth_array()[100:, :, :3]
    h, v = np.linalg.norm(d[..., :2], axis=-1), np.abs(d[..., 2])
    for label, cols in (("without GNSS", without), ("with GNSS", [c for c in range(len(rec.ids)) if c not in without])):
        print(f"  after 10 s, nodes {label}: horizontal max {h[:, cols].max():.3f} m, mean {h[:, cols].mean():.3f} m; "
              f"vertical max {v[:, cols].max():.3f} m, mean {v[:, cols].mean():.3f} m")
    fig, ax = plt.subplots(figsize=(7, 3.4))
    for ci, aid in enumerate(rec.ids):
        ax.plot(t, err[:, ci], lw=0.9, ls="-" if aid in half else "--", label=f"UAS {aid}" + ("" if aid in half else " (no GNSS)"))
    ax.set_xlabel("time (s)")
    ax.set_ylabel("position error (m)")
    ax.set_title(f"{name}: centralized EKF, 2 cm ranges between all nodes, GNSS on {len(half)}")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6, ncol=2)
    fig.savefig(IMG / f"{name}-half.png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    # Fig. 5, GNSS on every node: the same split (the paper's "about 2 cm" maximum).
    rec, _ = run(S.load(name).with_overrides(**{"sensors.gnss.agents": None}), None, ["ekf-ccl"])
    d = rec.trace("ekf-ccl").mean[100:, :, :3] - rec.truth_array()[100:, :, :3]
    h, v = np.linalg.norm(d[..., :2], axis=-1), np.abs(d[..., 2])
    print(f"  GNSS on all, after 10 s: horizontal max {h.max():.3f} m, mean {h.mean():.3f} m; "
          f"vertical max {v.max():.3f} m, mean {v.mean():.3f} m")


def goel_dist() -> None:
    for label, gnss in (("GNSS on both", None), ("GNSS on UAS 1 only", [1])):
        out = {}
        for crit in ("trace", "det"):
            sc = S.load("goel-dist").with_overrides(**{"sensors.gnss.agents": gnss, "estimator.params": {"criterion": crit}})
            rec, e = run(sc, "ekf-ci", ["ekf", "ekf-ccl"])
            out[f"ekf-ci ({crit})"] = e["ekf-ci"][:, 1]
        out["ekf-naive"] = run(S.load("goel-dist").with_overrides(**{"sensors.gnss.agents": gnss}), "ekf-naive", [])[1]["ekf-naive"][:, 1]
        out["centralized (ekf-ccl)"], out["alone (ekf)"] = e["ekf-ccl"][:, 1], e["ekf"][:, 1]
        print(f"goel-dist, {label}: UAS 2 position error (m), mean over 10-60 s and max")
        for n, y in out.items():
            print(f"  {n:24s} {y[100:].mean():8.3f} {y[100:].max():8.3f}")
        if gnss is not None:
            t = np.array(rec.t)
            styles = {"ekf-ci (trace)": ("tab:green", "-"), "ekf-ci (det)": ("tab:green", "--"), "ekf-naive": ("tab:red", "-"),
                      "centralized (ekf-ccl)": ("tab:olive", "-"), "alone (ekf)": ("tab:gray", "-")}
            plot(IMG / "goel-dist.png", t, {n: (y, *styles[n]) for n, y in out.items()},
                 "goel-dist, GNSS on UAS 1 only: UAS 2", log=True)


def main() -> None:
    which = sys.argv[1:] or ["2node", "10", "20", "10r", "dist"]
    if "2node" in which:
        goel2node()
    if "10" in which:
        goel_n("goel10", [3, 5, 6, 7, 8])
    if "20" in which:
        goel_n("goel20", list(range(2, 21, 2)))
    if "10r" in which:
        goel_n_ranges("goel10-ranges", [3, 5, 6, 7, 8])
    if "dist" in which:
        goel_dist()


if __name__ == "__main__":
    main()
