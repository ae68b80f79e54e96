"""MR.CLAM replay (Leung et al., IJRR 2011): every estimator on a whole recording, against Vicon.

Usage: python benchmarks/mrclam_replay.py [--path ../shared/data/mrclam/MRCLAM_Dataset6] [--dt 0.1]
       [--duration S] [--workers 2] [--out benchmarks/out_mrclam.md] [--fig-dir docs/img]

Configurations of the same replay (`swarmloc.scenario.replay_scenario`, noise fitted against
Vicon, chi-square gate 0.999):
  landmarks: odometry, the known landmark map and the robots' observations of each other;
  robots only: odometry and the robots' observations of each other (no landmark observation);
  each again with the odometry noise fitted to its drift over 10 s instead of tick by tick.
Agent estimators (ukf-dcl, ekf-ci) run their nodes in process over netsim's replay world and
radio (InProcessRunner: the lockstep agent processes compute the same, bit for bit); the
references (il, ekf, ekf-ccl, ukf-ccl) run offline on the same frames. Reported per robot and
estimator: position RMSE, heading RMSE, average NEES (3 dof); the wall time of each estimator
against the recording's length. Progress to stderr, the markdown report to --out, figures
docs/img/mrclam_trajectories.png and docs/img/mrclam_error.png. Not a test.
"""

from __future__ import annotations

from swarmloc import pin_blas

pin_blas()  # before numpy loads

import argparse  # noqa: E402
import multiprocessing  # noqa: E402
import shlex  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from datetime import datetime, timezone  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from machine import code_version, cpu_model  # noqa: E402  benchmarks/machine.py

ROOT = Path(__file__).resolve().parent.parent
AGENT = ("ukf-dcl", "ekf-ci")
REFERENCES = ("il", "ekf", "ekf-ccl", "ukf-ccl")
CONFIGS = {"landmarks": {"landmarks": True}, "robots only": {"landmarks": False},
           "landmarks, odometry noise fitted over 10 s": {"landmarks": True, "odometry_horizon": 10.0},
           "robots only, odometry noise fitted over 10 s": {"landmarks": False, "odometry_horizon": 10.0}}
# Which estimators each configuration runs: every one in the first two, the consistency
# trade-off of the 10 s fit shown on the centralized EKF and the dead reckoning it starts from.
RUNS = {"landmarks": REFERENCES + AGENT, "robots only": ("il", "ekf-ccl", "ukf-ccl") + AGENT,
        "landmarks, odometry noise fitted over 10 s": ("il", "ekf", "ekf-ccl"),
        "robots only, odometry noise fitted over 10 s": ("ekf-ccl",)}


def log(msg: str) -> None:
    print(f"[{datetime.now():%H:%M:%S}] {msg}", file=sys.stderr, flush=True)


def scenario(args, config: str, estimator: str):
    from swarmloc.scenario import replay_scenario

    return replay_scenario(args.path, estimator=estimator, dt=args.dt, duration=args.duration, **CONFIGS[config])


def job(task) -> tuple:
    """One estimator in one configuration: (config, name, per-robot metrics, pooled, wall s, trace, truth)."""
    args, config, name = task
    from netsim.sim import Simulation
    from swarmloc.estimators import REGISTRY
    from swarmloc.results import RunRecord, metrics
    from swarmloc.runner import InProcessRunner, make_nodes

    if name in AGENT:
        sc = scenario(args, config, name)
        start = time.perf_counter()
        record = InProcessRunner(Simulation(sc), make_nodes(name, sc)).run(RunRecord.for_scenario(sc))
        wall = time.perf_counter() - start
    else:
        sc = scenario(args, config, "il" if name != "il" else "ukf-dcl")
        record = InProcessRunner(Simulation(sc), {}).run(RunRecord.for_scenario(sc))
        ref = REGISTRY[name].make_reference(sc, record.ids)
        start = time.perf_counter()
        for frames in record.sensors:
            ref.step(frames)
            for a in record.ids:
                record.add_estimate(name, a, ref.estimate(a))
        wall = time.perf_counter() - start
    m = metrics(record, [name])["estimators"][name]
    tr = record.trace(name)
    log(f"{config:12s} {name:8s} RMSE {m['rmse_m']:.3f} m, {m['heading_rmse_rad']:.3f} rad, NEES "
        f"{m['nees']['mean']:.2f}; {wall:.1f} s")
    return config, name, m, wall, tr.mean, record.truth_array(), np.array(record.t), record.ids, sc.clock.duration, tr.cov


def fmt_cell(e: dict) -> str:
    nees = e.get("nees")
    return (f"{e['rmse_m']:.3f} / {e['heading_rmse_rad']:.3f} / {nees['mean']:.1f}" if e.get("rmse_m") is not None
            else "-")


def range_structure(rec, dt: float, lags: dict) -> list[str]:
    """How much of each robot's landmark-range error a smooth function of its bearing and range
    explains: the robust spread of the residuals before and after a least-squares fit of
    a + b cos(bearing) + c range (a camera that reads ranges by the size of a barcode in its
    image errs by where the barcode sits in the image)."""
    from swarmloc import mrclam

    steps = int(rec.duration / dt)
    rows = ["| robot | landmark observations | range error, robust std (m) | after the fit (m) |", "|---|---|---|---|"]
    for r in rec.robots:
        tk = mrclam.ticked(rec, r, rec.t0, dt, steps, lags[r])
        at = tk.truth[tk.tick]
        mark = np.isin(tk.subject, list(rec.landmarks))
        other = np.array([rec.landmarks[s].xy if s in rec.landmarks else (np.nan, np.nan) for s in tk.subject])
        d = other - at[:, :2]
        true_r = np.hypot(d[:, 0], d[:, 1])
        true_b = np.arctan2(d[:, 1], d[:, 0]) - at[:, 2]
        dr = tk.range - true_r
        ok = mark & np.isfinite(dr) & (np.abs(dr) < 0.5)  # gross errors are the gate's, not this fit's
        A = np.column_stack([np.ones(ok.sum()), np.cos(true_b[ok]), true_r[ok]])
        coef, *_ = np.linalg.lstsq(A, dr[ok], rcond=None)
        rows.append(f"| Robot{r} | {ok.sum()} | {mrclam.robust_std(dr[ok]):.3f} | "
                    f"{mrclam.robust_std(dr[ok] - A @ coef):.3f} |")
    return rows


def report(args, results, fit, lags, slow, structure) -> str:
    ids = results[0][7]
    lines = [f"# MR.CLAM replay: {Path(args.path).name}", "",
             f"Machine: {cpu_model()}, {multiprocessing.cpu_count()} CPUs; date "
             f"{datetime.now(timezone.utc):%Y-%m-%d}; code {code_version()}.", "",
             f"Command: `python benchmarks/{Path(__file__).name} {shlex.join(sys.argv[1:])}`", "",
             f"Ticks of {args.dt:g} s over {results[0][8]:g} s of recording. Noise fitted against Vicon "
             f"(`swarmloc.mrclam.fit_noise`, robust std): speed {fit.speed:.4f} m/s, turn rate {fit.turn_rate:.4f} "
             f"rad/s, range {fit.range:.4f} m, bearing {fit.bearing:.4f} rad (plain std of the same residuals: "
             f"{fit.plain['speed']:.4f}, {fit.plain['turn_rate']:.4f}, {fit.plain['range']:.4f}, "
             f"{fit.plain['bearing']:.4f}). Odometry lags (s): "
             + ", ".join(f"Robot{r} {v:.3f}" for r, v in lags.items()) + f". Fitted over 10 s the odometry noise "
             f"is {slow.speed:.4f} m/s and {slow.turn_rate:.4f} rad/s.", "",
             "Range errors against the bearing (`range_structure`; observations off by more than 0.5 m left out):", "",
             *structure, "",
             "Cells: position RMSE (m) / heading RMSE (rad) / average NEES (3 dof: 3.0 when consistent). NIS: the "
             "average NIS of the range-bearing updates (2 dof: 2.0 when consistent; none for dead reckoning, and "
             "none for EKF-CI's fusions, whose innovation covariance is unknown by design).", ""]
    for config in CONFIGS:
        lines += [f"## {config}", "", "| estimator | " + " | ".join(f"Robot{a}" for a in ids)
                  + " | all | NIS | wall (s) | x real time |", "|---|" + "---|" * (len(ids) + 4)]
        for c, name, m, wall, *_rest in results:
            if c != config:
                continue
            dur = _rest[4]
            nis = f"{m['nis']['mean']:.2f}" if m.get("nis") else "-"
            lines.append(f"| {name} | " + " | ".join(fmt_cell(m["agents"][str(a)]) for a in ids)
                         + f" | {fmt_cell(m)} | {nis} | {wall:.1f} | {dur / wall:.0f} |")
        lines.append("")
        both = {r[1]: r for r in results if r[0] == config and r[1] in ("ukf-dcl", "ukf-ccl")}
        if len(both) == 2:
            d, c = both["ukf-dcl"], both["ukf-ccl"]
            lines += [f"UKF-DCL against UKF-CCL, largest difference over every robot and tick: "
                      f"{np.nanmax(np.abs(d[4] - c[4])):.1e} in a mean, {np.nanmax(np.abs(d[9] - c[9])):.1e} in a "
                      "covariance entry.", ""]
    return "\n".join(lines)


def figures(results, fig_dir: Path, landmarks) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from swarmloc.estimators import REGISTRY

    sel = {name: r for r in results if r[0] == "landmarks" for name in [r[1]]}
    show = [n for n in ("il", "ekf", "ukf-dcl", "ekf-ccl") if n in sel]
    ids = results[0][7]
    truth, t = sel[show[0]][5], sel[show[0]][6]
    fig, axes = plt.subplots(2, 3, figsize=(15, 8.4), squeeze=False)
    for ax, (ci, aid) in zip(axes.flat, enumerate(ids)):
        ax.plot(truth[:, ci, 0], truth[:, ci, 1], "k-", lw=1.2, label="Vicon")
        for n in show:
            ax.plot(sel[n][4][:, ci, 0], sel[n][4][:, ci, 1], lw=0.7, color=REGISTRY.color(n), label=REGISTRY.label(n))
        ax.plot(landmarks[:, 0], landmarks[:, 1], "k^", ms=5, label="landmarks")
        ax.set_title(f"Robot{aid}")
        ax.set_aspect("equal", adjustable="datalim")
    axes.flat[0].legend(fontsize="small")
    for ax in axes.flat[len(ids):]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(fig_dir / "mrclam_trajectories.png", dpi=90)
    plt.close(fig)
    fig, axes = plt.subplots(len(ids), 1, figsize=(10, 2.0 * len(ids)), sharex=True)
    for ax, (ci, aid) in zip(np.atleast_1d(axes), enumerate(ids)):
        for n, r in sel.items():
            err = np.linalg.norm(r[4][:, ci, :2] - truth[:, ci, :2], axis=-1)
            ax.semilogy(t, err, lw=0.7, color=REGISTRY.color(n), label=REGISTRY.label(n))
        ax.set_ylabel(f"Robot{aid} (m)")
    np.atleast_1d(axes)[0].legend(ncol=6, fontsize="small")
    np.atleast_1d(axes)[-1].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(fig_dir / "mrclam_error.png", dpi=90)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--path", type=Path, default=ROOT.parent / "shared" / "data" / "mrclam" / "MRCLAM_Dataset6")
    ap.add_argument("--dt", type=float, default=0.1)
    ap.add_argument("--duration", type=float, default=None)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "out_mrclam.md")
    ap.add_argument("--fig-dir", type=Path, default=ROOT / "docs" / "img")
    args = ap.parse_args()
    from swarmloc import mrclam
    from swarmloc.scenario import recording

    rec = recording(str(args.path.resolve()))
    lags, fit = mrclam.odometry_lags(rec), mrclam.fit_noise(rec, args.dt)
    slow = mrclam.fit_noise(rec, args.dt, lags, horizon=10.0)
    tasks = [(args, c, n) for c in CONFIGS for n in RUNS[c]]
    with multiprocessing.get_context("forkserver").Pool(args.workers) as pool:
        results = pool.map(job, tasks, chunksize=1)
    text = report(args, results, fit, lags, slow, range_structure(rec, args.dt, lags))
    args.out.write_text(text + "\n")
    print(text)
    figures(results, args.fig_dir, np.array([m.xy for m in rec.landmarks.values()]))


if __name__ == "__main__":
    main()
