"""Oliveros & Ashrafiuon 2023 reproduced: the double caravan (Table 1), the caravan of quadrotors in
closed loop (Table 2), the three-vehicle network, and a relative-position link cut.

Every run is an in-process lockstep run of a built-in scenario (the same frames, estimates and,
in closed loop, commands as over agent processes: tests/test_vehicle_processes.py), EKF-CL (the
paper's centralized EKF in the fusion-centre role) and, side by side on the same scenario and
seed, EKF-CI and `ekf-local` (CL without cross-covariances). Writes the tables to benchmarks/out_oliveros.md and the
figures to docs/img/oliveros-*.png.

    .venv/bin/python benchmarks/oliveros.py [--duration S] [--workers N]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from swarmloc.process import pin_blas  # noqa: E402

# Before numpy loads, and the workers are forked with it: two workers with a BLAS pool each on
# two vCPUs ran the 104-state joint filter 5x slower.
pin_blas()

import numpy as np  # noqa: E402

sys.path.insert(0, str(ROOT / "benchmarks"))
from machine import code_version, cpu_model  # noqa: E402  benchmarks/machine.py

ESTIMATORS = ("ekf-cl", "ekf-ci", "ekf-local")
# ekf-local is CL without the cross-covariances; the paper's "without CL" is `raw` (the studies
# benchmarks/studies/oliveros-chain-control*.yaml).
LABEL = {"ekf-cl": "EKF-CL", "ekf-ci": "EKF-CI", "ekf-local": "EKF-local"}
CUT = {"at": 60.0, "action": "cut", "link": [3, 4], "duration": 30.0}


def job(name: str, estimator: str, duration: float | None, faults: list | None = None) -> dict:
    from netsim.sim import Simulation
    from swarmloc.experiment import scenario
    from swarmloc.experiment.results import position_errors
    from swarmloc.experiment.runner import InProcessRunner, make_nodes
    from swarmloc.models.vehicles import CircleReference

    over = {"estimator": {"name": estimator, "params": {}}}
    if duration is not None:
        over["clock.duration"] = duration
    if faults is not None:
        over["faults"] = faults
    sc = scenario.load(name).with_overrides(**over)
    sim = Simulation(sc)
    started = time.perf_counter()
    record = InProcessRunner(sim, make_nodes(estimator, sc)).run()
    wall = time.perf_counter() - started
    ids = record.ids
    t = np.array(record.t)
    est = position_errors(record, record.trace(estimator))
    truth = record.truth_array()
    track = np.zeros_like(est)
    for ci, a in enumerate(ids):
        m = sc.agent(a).motion
        ref = CircleReference(tuple(m.center), m.radius, m.period, m.phase, m.yaw)
        want = np.array([ref.derivatives(tk, 0)[0] for tk in t])
        track[:, ci] = np.linalg.norm(truth[:, ci, :3] - want, axis=1)
    edges = {}
    for frames in record.sensors:
        for b, f in frames.items():
            for r in (f.vehicle.seen if f.vehicle is not None else []):
                edges.setdefault(f"{b}->{r.target}", []).append(f.t)
    from swarmloc.experiment.results import metrics

    agents = metrics(record, [estimator])["estimators"][estimator]["agents"]
    nees = {a: (agents[str(a)]["nees"]["mean"], agents[str(a)]["nees"]["dof"]) for a in ids}
    return {"name": name, "estimator": estimator, "ids": ids, "t": t.tolist(), "est": est.tolist(), "nees": nees,
            "track": track.tolist(), "wall_s": wall, "ticks": len(t), "edges": edges, "commands": sim.commands,
            "gps": [f[4].gnss is not None if 4 in f else False for f in record.sensors]}


def window(r: dict, lo: float, hi: float, key: str = "est") -> np.ndarray:
    t = np.array(r["t"])
    sel = (t >= lo) & (t < hi)
    return np.sqrt(np.mean(np.array(r[key])[sel] ** 2, axis=0))


def fmt(v) -> str:
    return f"{v:.3f}" if v < 100 else f"{v:.0f}"


def plot_errors(path, runs: list[dict], labels: list[str], title: str, key: str = "est", shade=None,
                ylabel="position error (m)"):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ids = runs[0]["ids"]
    cols = 4 if len(ids) > 4 else len(ids)
    rows = -(-len(ids) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 2.6 * rows), sharex=True, squeeze=False)
    for ci, a in enumerate(ids):
        ax = axes.flat[ci]
        for r, lab in zip(runs, labels):
            ax.semilogy(r["t"], np.maximum(np.array(r[key])[:, ci], 1e-4), lw=0.8, label=lab)
        if shade:
            for lo, hi in shade:
                ax.axvspan(lo, hi, color="tab:purple", alpha=0.12, lw=0)
        ax.set_title(f"vehicle {a}", fontsize=9)
        ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("t (s)")
    for ax in axes[:, 0]:
        ax.set_ylabel(ylabel)
    axes.flat[0].legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_three(path, r: dict):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    t = np.array(r["t"])
    for ci, ax in enumerate(axes):
        a = r["ids"][ci]
        ax.semilogy(t, np.maximum(np.array(r["est"])[:, ci], 1e-4), lw=0.8, color="k", label="EKF-CL error")
        for level, edge, color in ((2e-4, "1->2", "tab:red"), (4e-4, "1->3", "tab:green"), (8e-4, "2->3", "tab:blue")):
            on = np.isin(t, r["edges"].get(edge, []))
            ax.plot(t[on], np.full(on.sum(), level), ".", ms=1, color=color, label=f"{edge} measured")
        ax.set_ylabel(f"vehicle {a} error (m)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, ncol=4)
    axes[1].set_xlabel("t (s)")
    fig.suptitle("oliveros3: quadrotors 1 and 2; robot 3 has GPS (flags: which relative positions were measured)",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=None, help="override every scenario's duration (s)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "out_oliveros.md")
    ap.add_argument("--img", type=Path, default=ROOT / "docs" / "img")
    args = ap.parse_args()
    jobs = [(f"oliveros-caravan-control-{c}", e, args.duration) for c in (1, 2) for e in ESTIMATORS]
    jobs += [(f"oliveros-caravan-{c}", e, args.duration) for c in (1, 2, 3, 4) for e in ESTIMATORS]
    jobs += [("oliveros3", "ekf-cl", args.duration), ("oliveros-caravan-control-1", "ekf-cl", args.duration, [CUT])]
    started = time.perf_counter()
    with ProcessPoolExecutor(args.workers) as pool:
        futures = [pool.submit(job, *j) for j in jobs]
        results = []
        for i, f in enumerate(futures):
            results.append(f.result())
            print(f"[{i + 1}/{len(jobs)}] {jobs[i][0]} {jobs[i][1]}: {results[-1]['wall_s']:.0f} s", flush=True)
    total = time.perf_counter() - started
    by = {(r["name"], r["estimator"], "cut" if i == len(results) - 1 else ""): r for i, r in enumerate(results)}
    args.img.mkdir(parents=True, exist_ok=True)
    lines = ["# Oliveros & Ashrafiuon 2023 reproduced", "", f"Machine: {cpu_model()}, 2 vCPUs; date {time.strftime('%Y-%m-%d')}; code {code_version()}", "",
             f"Command: `.venv/bin/python benchmarks/oliveros.py{'' if args.duration is None else f' --duration {args.duration:g}'}`"
             f" ({total:.0f} s on {args.workers} workers)", ""]

    # Table 1: the double caravan
    ids = by[("oliveros-caravan-1", "ekf-cl", "")]["ids"]
    lines += ["## Double caravan (Table 1), EKF-CL", "",
              "RMS position error (m) over the whole run, per vehicle, EKF-CL and side by side on the same runs "
              "the distributed EKF-CI and EKF without CL:", "",
              "| case | " + " | ".join(f"v{a}" for a in ids) + " | all |", "|---|" + "---|" * (len(ids) + 1)]
    for c in (1, 2, 3, 4):
        for e in ESTIMATORS:
            r = by[(f"oliveros-caravan-{c}", e, "")]
            rms = window(r, 0, 1e9)
            lines.append(f"| {c} {LABEL[e]} | " + " | ".join(fmt(v) for v in rms)
                         + f" | {fmt(float(np.sqrt(np.mean(rms ** 2))))} |")
    lines += ["", "Consistency: mean NEES over the run, per vehicle (state dimension: 7 for a robot, 13 for a "
              "quadrotor; a filter that knows its error reads about its dimension):", "",
              "| case | " + " | ".join(f"v{a}" for a in ids) + " |", "|---|" + "---|" * len(ids)]
    for c in (1, 2, 3, 4):
        for e in ESTIMATORS:
            r = by[(f"oliveros-caravan-{c}", e, "")]
            lines.append(f"| {c} {LABEL[e]} | " + " | ".join(f"{r['nees'][a][0]:.3g}" for a in ids) + " |")
    end = by[("oliveros-caravan-1", "ekf-cl", "")]["t"][-1]
    lines += ["", "EKF-CL error growth, RMS over windows (m), cases 1 and 4 (no GPS):", "",
              "| case | window | " + " | ".join(f"v{a}" for a in ids) + " |", "|---|---|" + "---|" * len(ids)]
    for c in (1, 4):
        r = by[(f"oliveros-caravan-{c}", "ekf-cl", "")]
        for lo, hi in ((0, end / 4), (end / 4, end / 2), (end / 2, 3 * end / 4), (3 * end / 4, end + 1)):
            lines.append(f"| {c} | {lo:.0f}-{min(hi, end):.0f} s | " + " | ".join(fmt(v) for v in window(r, lo, hi)) + " |")
    r3 = by[("oliveros-caravan-3", "ekf-cl", "")]
    lines += ["", "Case 3, vehicle 4's GPS 40 s on / 40 s off after the first 40 s: RMS error (m) in each window:", "",
              "| window | GPS | " + " | ".join(f"v{a}" for a in ids) + " |", "|---|---|" + "---|" * len(ids)]
    for lo, hi, gps in ((0, 40, "off"), (30, 40, "off (last 10 s)"), (40, 45, "on (first 5 s)"), (45, 80, "on"),
                        (110, 120, "off (last 10 s)"), (120, 125, "on (first 5 s)"), (125, 160, "on")):
        if lo < end:
            lines.append(f"| {lo}-{hi} s | {gps} | " + " | ".join(fmt(v) for v in window(r3, lo, hi)) + " |")
    plot_errors(args.img / "oliveros-caravan.png", [by[(f"oliveros-caravan-{c}", "ekf-cl", "")] for c in (1, 2, 3, 4)],
                [f"case {c}" for c in (1, 2, 3, 4)], "Double caravan, EKF-CL: position error, Table 1 cases 1-4 "
                "(shaded: vehicle 4's GPS in case 3)", shade=[(40, 80), (120, 160)])

    # Table 2: closed loop
    lines += ["", "## Double caravan of quadrotors in closed loop (Table 2)", "",
              "Tracking error (m, RMS of |true position - reference| over t >= 10 s) and estimation error (m, RMS over "
              "t >= 10 s), with CL (EKF-CL), with the distributed EKF-CI, and with `ekf-local`:", ""]
    for c in (1, 2):
        runs = {e: by[(f"oliveros-caravan-control-{c}", e, "")] for e in ESTIMATORS}
        cl, no = runs["ekf-cl"], runs["ekf-local"]
        lines += [f"Case {c} ({'continuous' if c == 1 else 'intermittent, 40 s on / 40 s off'} GPS on vehicle 4):", "",
                  "| | " + " | ".join(f"v{a}" for a in cl["ids"]) + " |", "|---|" + "---|" * len(cl["ids"])]
        track = {e: window(r, 10, 1e9, "track") for e, r in runs.items()}
        lines += [f"| tracking, {LABEL[e]} | " + " | ".join(fmt(v) for v in track[e]) + " |" for e in ESTIMATORS]
        lines += ["| tracking, EKF-local / EKF-CL | " + " | ".join(f"{b / a:.2f}" for a, b in zip(track["ekf-cl"],
                                                                                         track["ekf-local"])) + " |"]
        lines += [f"| estimation, {LABEL[e]} | " + " | ".join(fmt(v) for v in window(r, 10, 1e9)) + " |"
                  for e, r in runs.items()]
        lines.append("")
        shade = [(0, 40), (80, 120), (160, 200)] if c == 2 else None
        plot_errors(args.img / f"oliveros-control-{c}.png", [cl, runs["ekf-ci"], no], ["EKF-CL", "EKF-CI", "EKF-local"],
                    f"Caravan of quadrotors in closed loop, case {c}: tracking error", key="track", shade=shade,
                    ylabel="tracking error (m)")
    # Three vehicles
    r = by[("oliveros3", "ekf-cl", "")]
    lines += ["## Three vehicles (section 6.2.1), EKF-CL", "",
              "RMS position error (m): " + ", ".join(f"vehicle {a}: {fmt(v)}" for a, v in zip(r["ids"], window(r, 0, 1e9))),
              "", "Seconds each relative position was measured: "
              + ", ".join(f"{e}: {len(ts) * (r['t'][1] - r['t'][0]):.0f}" for e, ts in sorted(r["edges"].items())), ""]
    plot_three(args.img / "oliveros3.png", r)
    # The cut
    cut, base = by[("oliveros-caravan-control-1", "ekf-cl", "cut")], by[("oliveros-caravan-control-1", "ekf-cl", "")]
    lines += ["## A relative-position link cut", "",
              f"Quadrotors in closed loop, Table 2 case 1 (vehicle 4 with GPS), link 3-4 cut from {CUT['at']:.0f} s for "
              f"{CUT['duration']:.0f} s: vehicles 1-3 lose their path to vehicle 4 (5-8 keep theirs through 8 -> 4). "
              "RMS estimation error (m) per window, EKF-CL:", "",
              "| window | " + " | ".join(f"v{a}" for a in cut["ids"]) + " |", "|---|" + "---|" * len(cut["ids"])]
    for lo, hi in ((30, 60), (60, 90), (80, 90), (95, 120)):
        lines.append(f"| {lo}-{hi} s | " + " | ".join(fmt(v) for v in window(cut, lo, hi)) + " |")
    lines += ["", "Tracking error (m, RMS) in the same windows:", "",
              "| window | " + " | ".join(f"v{a}" for a in cut["ids"]) + " |", "|---|" + "---|" * len(cut["ids"])]
    for lo, hi in ((30, 60), (60, 90), (80, 90), (95, 120)):
        lines.append(f"| {lo}-{hi} s | " + " | ".join(fmt(v) for v in window(cut, lo, hi, "track")) + " |")
    plot_errors(args.img / "oliveros-cut.png", [base, cut], ["no fault", "link 3-4 cut 60-90 s"],
                "Quadrotors in closed loop (case 1), EKF-CL, with and without the cut of link 3-4", shade=[(60, 90)])
    lines += ["", "## Wall time", "", "| scenario | estimator | ticks | wall (s) | ticks/s |", "|---|---|---|---|---|"]
    for r in results:
        lines.append(f"| {r['name']} | {r['estimator']} | {r['ticks']} | {r['wall_s']:.1f} | {r['ticks'] / r['wall_s']:.0f} |")
    args.out.write_text("\n".join(lines) + "\n")
    (args.out.with_suffix(".json")).write_text(json.dumps(
        {f"{r['name']}/{r['estimator']}{'/cut' if i == len(results) - 1 else ''}":
         {"rms": window(r, 0, 1e9).tolist(), "track_rms_after_10s": window(r, 10, 1e9, "track").tolist(),
          "commands": r["commands"], "wall_s": r["wall_s"]} for i, r in enumerate(results)}, indent=1))
    print(args.out.read_text())


if __name__ == "__main__":
    main()
