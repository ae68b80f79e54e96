"""MR.CLAM replay (Leung et al., IJRR 2011): every estimator against Vicon, scored on data its
noise model was not fitted to, before and after calibration.

Usage: python benchmarks/mrclam_replay.py [--path ../shared/data/mrclam/MRCLAM_Dataset6] [--dt 0.1]
       [--workers 2] [--out benchmarks/out_mrclam.md] [--fig-dir docs/img] [--no-agents]
       [--agents ukf-dcl,ekf-ci]

The recording is cut in two halves, A (the first) and B. Each is scored twice:
  before: the white noise fitted before calibration (`replay_scenario(calibration="none")`:
          pooled over the robots against the whole recording's Vicon, so fitted on the scored
          data too);
  after:  the noise model `swarmloc.datasets.calibrate.calibrate` fits on the other half.
Scoring A with B's model and B with A's scores the whole recording on data its model was not
fitted to. Configurations: landmarks (odometry, the known map, the robots' observations of each
other) and robots only (no landmark observation). Agent estimators (ukf-dcl, ekf-ci) run their
nodes in process over netsim's replay world and radio (InProcessRunner: the lockstep agent
processes compute the same, bit for bit); the references (il, ekf, ekf-ccl, ukf-ccl) run
offline on the same frames. Reported per robot and estimator: position RMSE, heading RMSE,
average NEES (3 dof), and over both halves together. Then what the calibration's two choices
do, on the references scoring B: the horizon of the white-equivalent stds and the
cross-validation of the residuals behind them (folds 1: in sample). Progress to stderr, the
markdown report to --out, figures docs/img/mrclam_trajectories.png and docs/img/mrclam_error.png
(B scored after calibration on A, with landmarks). Not a test.
"""

from __future__ import annotations

from swarmloc.process import pin_blas

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

from netsim.study import odometry_bias  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
AGENT = ("ukf-dcl", "ekf-ci")
REFERENCES = ("il", "ekf", "ekf-ccl", "ukf-ccl")
CONFIGS = {"landmarks": {"landmarks": True}, "robots only": {"landmarks": False}}
RUNS = {"landmarks": REFERENCES + AGENT, "robots only": ("il", "ekf-ccl", "ukf-ccl") + AGENT}
WHITE_ESTIMATORS = ("il", "ekf", "ekf-ccl")
ABLATION = {"horizons": (0.1, 1.0, 3.0, 10.0, 30.0), "folds": (1, 2), "estimators": ("il", "ekf", "ekf-ccl")}
BIAS_SECTION = "## Odometry bias states"


def log(msg: str) -> None:
    print(f"[{datetime.now():%H:%M:%S}] {msg}", file=sys.stderr, flush=True)


def scenario(args, config: str, estimator: str, span, model):
    from swarmloc.experiment.replay import replay_scenario

    lo, hi = span
    kw = {"noise": model} if model is not None else {"calibration": "none"}  # model: a NoiseModel or a NoiseFit
    return replay_scenario(args.path, estimator=estimator, dt=args.dt, offset=lo, duration=hi - lo,
                           **CONFIGS[config], **kw)


def job(task) -> list[tuple]:
    """One configuration, half and model: every reference on one stream of frames, or one agent
    estimator. Rows (config, half, kind, name, metrics, wall s, trace mean, truth, t, ids, trace cov)."""
    args, config, half, kind, span, model, names = task
    from netsim.sim import Simulation
    from swarmloc.estimators import REGISTRY
    from swarmloc.experiment.results import RunRecord, metrics
    from swarmloc.experiment.runner import InProcessRunner, make_nodes

    rows = []
    if names[0] in AGENT:
        name = names[0]
        sc = scenario(args, config, name, span, model)
        start = time.perf_counter()
        record = InProcessRunner(Simulation(sc), make_nodes(name, sc)).run(RunRecord.for_scenario(sc))
        walls = {name: time.perf_counter() - start}
    else:
        sc = scenario(args, config, "ukf-dcl", span, model)
        record = InProcessRunner(Simulation(sc), {}).run(RunRecord.for_scenario(sc))
        walls = {}
        for name in names:
            ref = REGISTRY[name].make_reference(sc, record.ids)
            start = time.perf_counter()
            for frames in record.sensors:
                ref.step(frames)
                for a in record.ids:
                    record.add_estimate(name, a, ref.estimate(a))
            walls[name] = time.perf_counter() - start
    for name, wall in walls.items():
        m = metrics(record, [name])["estimators"][name]
        tr = record.trace(name)
        log(f"{config:11s} {half} {kind:6s} {name:8s} RMSE {m['rmse_m']:.3f} m, {m['heading_rmse_rad']:.3f} rad, "
            f"NEES {m['nees']['mean']:.2f}; {wall:.1f} s")
        rows.append((config, half, kind, name, m, wall, tr.mean, record.truth_array(), np.array(record.t), record.ids,
                     tr.cov))
    return rows


def fmt_cell(e: dict) -> str:
    nees = e.get("nees")
    return (f"{e['rmse_m']:.3f} / {e['heading_rmse_rad']:.3f} / {nees['mean']:.1f}" if e.get("rmse_m") is not None
            else "-")


def model_table(models: dict) -> list[str]:
    rows = ["| model | robot | lags v / w (s) | speed std (m/s) | turn-rate std (rad/s) | table cells | "
            "landmarks: range a3 / std per m / bearing std | robots: range a3 / std per m / bearing std |",
            "|---|---|---|---|---|---|---|---|"]
    for name, m in models.items():
        for r, n in m.robots.items():
            o = n.odometry

            def cam(c):
                return "-" if c is None else f"{c.range_bias[3]:.3f} / {c.range_std_per_m:.4f} / {c.bearing_std:.4f}"

            rows.append(f"| {name} | Robot{r} | {o.speed_lag:.3f} / {o.turn_rate_lag:.3f} | {o.speed_std:.4f} | "
                        f"{o.turn_rate_std:.4f} | {len(o.table)} | {cam(n.landmarks)} | {cam(n.robots)} |")
    return rows


def report(args, results, models, spans, fit, ablation, white) -> str:
    ids = results[0][9]
    a, b = spans["A"], spans["B"]
    lines = [f"# MR.CLAM replay: {Path(args.path).name}", "",
             f"Machine: {cpu_model()}, {multiprocessing.cpu_count()} CPUs; date "
             f"{datetime.now(timezone.utc):%Y-%m-%d}; code {code_version()}.", "",
             f"Command: `python benchmarks/{Path(__file__).name} {shlex.join(sys.argv[1:])}`", "",
             f"Ticks of {args.dt:g} s. Half A: {a[0]:.1f}-{a[1]:.1f} s of the recording, half B: {b[0]:.1f}-{b[1]:.1f} s. "
             f"**before**: the white noise of `replay_scenario(calibration=\"none\")` (`swarmloc.datasets.mrclam.fit_noise`, "
             f"robust std pooled over the robots against the whole recording's Vicon: speed {fit.speed:.4f} m/s, turn "
             f"rate {fit.turn_rate:.4f} rad/s, range {fit.range:.4f} m, bearing {fit.bearing:.4f} rad). **after**: the "
             f"noise model `swarmloc.datasets.calibrate.calibrate` fits on the *other* half (horizon "
             f"{models['A'].horizon:g} s, {models['A'].folds} cross-validation folds).", "",
             "The fitted models (`a3`: the range error's r b^2 coefficient, the camera reading the distance along its "
             "axis, r cos b ~ r (1 - b^2 / 2), instead of the range):", "", *model_table(models), "",
             "Cells: position RMSE (m) / heading RMSE (rad) / average NEES (3 dof: 3.0 when consistent). NIS: the "
             "average NIS of the range-bearing updates (2 dof; none for dead reckoning, and none for EKF-CI's "
             "fusions, whose innovation covariance is unknown by design).", ""]
    for config in CONFIGS:
        names = RUNS[config]
        lines += [f"## {config}: both halves, each scored with the other's model", "",
                  "| estimator | before: RMSE (m) | after | change | before: heading (rad) | after | before: NEES | "
                  "after |", "|---|---|---|---|---|---|---|---|"]
        for name in names:
            got = {kind: [r[4] for r in results if r[0] == config and r[2] == kind and r[3] == name]
                   for kind in ("before", "after")}
            if any(len(v) != 2 for v in got.values()):
                continue
            p, q = odometry_bias.pooled(got["before"]), odometry_bias.pooled(got["after"])
            lines.append(f"| {name} | {p['rmse_m']:.3f} | {q['rmse_m']:.3f} | {100 * (q['rmse_m'] / p['rmse_m'] - 1):+.0f} % | "
                         f"{p['heading_rmse_rad']:.3f} | {q['heading_rmse_rad']:.3f} | {p['nees']['mean']:.1f} | "
                         f"**{q['nees']['mean']:.2f}** |")
        lines.append("")
        for half in ("B", "A"):
            other = "A" if half == "B" else "B"
            lines += [f"### {config}: half {half} scored, calibrated on {other}", "",
                      "| estimator | model | " + " | ".join(f"Robot{i}" for i in ids) + " | all | NIS | wall (s) |",
                      "|---|---|" + "---|" * (len(ids) + 3)]
            for name in names:
                for kind in ("before", "after"):
                    for r in results:
                        if r[:4] == (config, half, kind, name):
                            m = r[4]
                            nis = f"{m['nis']['mean']:.2f}" if m.get("nis") else "-"
                            lines.append(f"| {name} | {kind} | " + " | ".join(fmt_cell(m["agents"][str(i)]) for i in ids)
                                         + f" | {fmt_cell(m)} | {nis} | {r[5]:.1f} |")
            lines.append("")
            both = {r[3]: r for r in results if r[:3] == (config, half, "after") and r[3] in ("ukf-dcl", "ukf-ccl")}
            if len(both) == 2:
                d, c = both["ukf-dcl"], both["ukf-ccl"]
                lines += [f"UKF-DCL against UKF-CCL (after), largest difference over every robot and tick: "
                          f"{np.nanmax(np.abs(d[6] - c[6])):.1e} in a mean, {np.nanmax(np.abs(d[10] - c[10])):.1e} in a "
                          "covariance entry.", ""]
    if white:
        lines += ["## Before calibration: the white fit per tick or over 10 s, fitted on A, scoring B", "",
                  "`swarmloc.datasets.mrclam.fit_noise` on an excerpt of half A alone (`write_excerpt`), its odometry "
                  "noise fitted tick by tick or to its drift over 10 s (`horizon`); the replay of B with that noise.", "",
                  "| configuration | odometry fit | speed, turn rate (m/s, rad/s) | "
                  + " | ".join(f"{n}: RMSE / NEES" for n in WHITE_ESTIMATORS) + " |", "|---|---|---|" + "---|" * len(WHITE_ESTIMATORS)]
        for (config, h), (ms, f) in white.items():
            lines.append(f"| {config} | {'per tick' if h is None else f'over {h:g} s'} | {f.speed:.4f}, {f.turn_rate:.4f} | "
                         + " | ".join(f"{ms[n]['rmse_m']:.3f} / {ms[n]['nees']['mean']:.1f}" if n in ms else "-"
                                      for n in WHITE_ESTIMATORS) + " |")
        lines.append("")
    if ablation:
        lines += ["## The calibration's choices (landmarks, half B scored, calibrated on A)", "",
                  "Horizon: the span over which the stds are white-equivalent (0.1 s: one tick, the residuals' plain "
                  "RMS). Folds: 1, the residuals of the fit itself (in sample); 2, each half of A's residuals from "
                  "the corrections fitted on the other half (cross-validated, the default).", "",
                  "| horizon (s) | folds | " + " | ".join(f"{n}: RMSE / NEES" for n in ABLATION["estimators"]) + " |",
                  "|---|---|" + "---|" * len(ABLATION["estimators"])]
        for (h, f), ms in sorted(ablation.items()):
            lines.append(f"| {h:g} | {f} | " + " | ".join(f"{ms[n]['rmse_m']:.3f} / {ms[n]['nees']['mean']:.2f}"
                                                          for n in ABLATION["estimators"]) + " |")
        lines.append("")
    return "\n".join(lines)


def figures(results, fig_dir: Path, landmarks) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from swarmloc.estimators import REGISTRY

    sel = {r[3]: r for r in results if r[:3] == ("landmarks", "B", "after")}
    show = [n for n in ("il", "ekf", "ukf-dcl", "ekf-ccl") if n in sel]
    ids = results[0][9]
    truth, t = sel[show[0]][7], sel[show[0]][8]
    fig, axes = plt.subplots(2, 3, figsize=(15, 8.4), squeeze=False)
    for ax, (ci, aid) in zip(axes.flat, enumerate(ids)):
        ax.plot(truth[:, ci, 0], truth[:, ci, 1], "k-", lw=1.2, label="Vicon")
        for n in show:
            ax.plot(sel[n][6][:, ci, 0], sel[n][6][:, ci, 1], lw=0.7, color=REGISTRY.color(n), label=REGISTRY.label(n))
        ax.plot(landmarks[:, 0], landmarks[:, 1], "k^", ms=5, label="landmarks")
        ax.set_title(f"Robot{aid}")
        ax.set_aspect("equal", adjustable="datalim")
    axes.flat[0].legend(fontsize="small")
    for ax in axes.flat[len(ids):]:
        ax.axis("off")
    fig.suptitle("second half of the recording, noise calibrated on the first")
    fig.tight_layout()
    fig.savefig(fig_dir / "mrclam_trajectories.png", dpi=90)
    plt.close(fig)
    fig, axes = plt.subplots(len(ids), 1, figsize=(10, 2.0 * len(ids)), sharex=True)
    for ax, (ci, aid) in zip(np.atleast_1d(axes), enumerate(ids)):
        for n, r in sel.items():
            err = np.linalg.norm(r[6][:, ci, :2] - truth[:, ci, :2], axis=-1)
            ax.semilogy(t, err, lw=0.7, color=REGISTRY.color(n), label=REGISTRY.label(n))
            if n == "ekf-ccl":  # the error it claims: the position covariance's trace
                ax.semilogy(t, np.sqrt(np.trace(r[10][:, ci, :2, :2], axis1=1, axis2=2)), "--", lw=0.7,
                            color=REGISTRY.color(n), label=f"{REGISTRY.label(n)}: its std")
        ax.set_ylabel(f"Robot{aid} (m)")
    np.atleast_1d(axes)[0].legend(ncol=4, fontsize="small")
    np.atleast_1d(axes)[-1].set_xlabel("time since the start of the scored half (s)")
    fig.tight_layout()
    fig.savefig(fig_dir / "mrclam_error.png", dpi=90)
    plt.close(fig)


def bias_job(task):
    """odometry_bias.score on one replay: (configuration, scored span, noise model)."""
    args, config, span, model, grid = task
    rows = odometry_bias.score(scenario(args, config, "ukf-dcl", span, model), grid)
    for name, params, m, _ in rows:
        log(f"bias {config:11s} {span[0]:.0f}-{span[1]:.0f} s {name} {odometry_bias.label(params)}: RMSE "
            f"{m['rmse_m']:.3f} m, NEES {m['nees']['mean']:.2f}")
    return rows


def bias_heading(args) -> str:
    """The section's heading: the calibration's horizon named when it is not the default."""
    from swarmloc.datasets import calibrate

    return BIAS_SECTION + ("" if args.horizon == calibrate.HORIZON else f", calibration horizon {args.horizon:g} s")


def bias_study(args, pool, spans, models) -> str:
    """The bias section: per configuration and half's model, the grid scored on that half (in
    sample, to pick a setting) and on the other (held out)."""
    grid, other, halves = odometry_bias.grid(), {"A": "B", "B": "A"}, ("A", "B")
    keys = [(c, f, h) for c in CONFIGS for f in halves for h in halves]
    runs = dict(zip(keys, pool.map(bias_job, [(args, c, spans[h], models[f], grid) for c, f, h in keys], chunksize=1)))
    picks = {(c, f): odometry_bias.pick(runs[(c, f, f)]) for c in CONFIGS for f in halves}
    lines = [bias_heading(args), "",
             f"Command: `python benchmarks/{Path(__file__).name} {shlex.join(sys.argv[1:])}` (machine "
             f"{cpu_model()}, date {datetime.now(timezone.utc):%Y-%m-%d}, code {code_version()}).", "",
             "EKF-CCL and UKF-CCL with `odometry_bias` (swarmloc.models.motion.PlanarPoseBias: each robot's pose "
             "augmented with a scale factor on its speed and a bias on its turn rate, random walks; walks: their "
             "intensities, speed scale (1/s) / turn-rate bias ((rad/s)^2/s); priors 0.05 and 0.02 rad/s). The noise "
             f"model is the calibration's (horizon {args.horizon:g} s, 2 folds) of one half. **picked**: per configuration and "
             "estimator, the setting chosen on that calibration half scored in sample (the smallest position RMSE "
             f"among those with mean NEES <= {odometry_bias.NEES_TARGET:g}), then scored on the other half, which neither "
             "the noise model nor the pick saw. Cells: position RMSE (m) / heading RMSE (rad) / mean NEES [the 95 % "
             "bounds of a consistent filter's mean NEES, as if the ticks were independent] / share of robot-ticks "
             "whose NEES is under chi2(3)'s 97.5 % quantile (9.35; 97.5 % if consistent).", "",
             "### Both halves held out, each with the other's model and pick", "",
             "| configuration | estimator | setting | RMSE (m) | heading (rad) | mean NEES | picked on A / on B |",
             "|---|---|---|---|---|---|---|"]
    for c in CONFIGS:
        for name in odometry_bias.ESTIMATORS:
            for kind, sel in (("off", lambda f: odometry_bias.OFF), ("picked", lambda f: picks[(c, f)][name])):
                ms = [next(m for n, p, m, _ in runs[(c, f, other[f])] if n == name and p == sel(f)) for f in halves]
                q = odometry_bias.pooled(ms)
                chosen = " / ".join(odometry_bias.label(picks[(c, f)][name]) for f in halves) if kind == "picked" else "-"
                lines.append(f"| {c} | {name} | {kind} | {q['rmse_m']:.3f} | {q['heading_rmse_rad']:.3f} | "
                             f"**{q['nees']['mean']:.2f}** | {chosen} |")
    lines.append("")

    def cell(m, inside):
        b = m["nees"]["bounds"]
        return (f"{m['rmse_m']:.3f} / {m['heading_rmse_rad']:.3f} / {m['nees']['mean']:.2f} [{b[0]:.2f}, {b[1]:.2f}] / "
                f"{100 * inside:.0f} %")

    for c in CONFIGS:
        for f in halves:
            h = other[f]
            lines += [f"### {c}: the sweep, noise model fitted on {f}", "",
                      f"| estimator | walks | scored on {f} (in sample: the pick's data) | scored on {h} (held out) |",
                      "|---|---|---|---|"]
            for name in odometry_bias.ESTIMATORS:
                for params in grid:
                    got = [next((m, i) for n, p, m, i in runs[(c, f, s)] if n == name and p == params) for s in (f, h)]
                    mark = " (picked)" if params == picks[(c, f)][name] else ""
                    lines.append(f"| {name} | {odometry_bias.label(params)}{mark} | {cell(*got[0])} | {cell(*got[1])} |")
            lines.append("")
    return "\n".join(lines)


def replace_section(text: str, section: str, heading: str) -> str:
    """text with its `heading` section (to the next '## ' heading or the end) replaced by section."""
    lines = text.split("\n")
    if heading not in lines:
        return text.rstrip("\n") + "\n\n" + section
    i = lines.index(heading)
    j = next((k for k in range(i + 1, len(lines)) if lines[k].startswith("## ")), len(lines))
    return "\n".join(lines[:i] + section.split("\n") + lines[j:])


def white_job(task):
    """The white noise of before calibration fitted on half A alone (per tick, or its odometry
    over 10 s), scoring B: the old choice between the two, on data it was not fitted to."""
    import tempfile

    args, config, horizon, window, span = task
    from swarmloc.datasets import mrclam
    from swarmloc.experiment.scenario import recording

    rec = recording(str(args.path.resolve()))
    with tempfile.TemporaryDirectory() as tmp:
        part = mrclam.load(mrclam.write_excerpt(rec, Path(tmp) / rec.source.name, rec.t0 + window[0], rec.t0 + window[1]))
        fit = mrclam.fit_noise(part, args.dt, horizon=horizon)
    rows = job((args, config, "B", "white" if horizon is None else f"white{horizon:g}", span, fit, WHITE_ESTIMATORS))
    return (config, horizon), {r[3]: r[4] for r in rows}, fit


def ablation_job(task):
    args, h, folds, window, span = task
    from swarmloc.datasets import calibrate
    from swarmloc.experiment.scenario import recording

    model = calibrate.calibrate(recording(str(args.path.resolve())), [window], args.dt, horizon=h, folds=folds)
    rows = job((args, "landmarks", "B", f"h{h:g}f{folds}", span, model, ABLATION["estimators"]))
    return (h, folds), {r[3]: r[4] for r in rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--path", type=Path, default=ROOT.parent / "shared" / "data" / "mrclam" / "MRCLAM_Dataset6")
    ap.add_argument("--dt", type=float, default=0.1)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "out_mrclam.md")
    ap.add_argument("--fig-dir", type=Path, default=ROOT / "docs" / "img")
    ap.add_argument("--no-agents", action="store_true", help="references only (no ukf-dcl, ekf-ci)")
    ap.add_argument("--agents", default=",".join(AGENT), help="the agent estimators to run (ukf-dcl computes what "
                    "ukf-ccl does, to 1e-13, at 30 times the time)")
    ap.add_argument("--no-ablation", action="store_true", help="skip the horizon and folds table")
    ap.add_argument("--horizon", type=float, default=None, help="the calibration's horizon (s; default "
                    "calibrate.HORIZON)")
    ap.add_argument("--bias-only", action="store_true", help="only the odometry-bias sweep: its section of --out "
                    "is replaced, the rest of the file kept")
    args = ap.parse_args()
    from swarmloc.datasets import calibrate, mrclam

    args.horizon = calibrate.HORIZON if args.horizon is None else args.horizon
    from swarmloc.experiment.scenario import recording

    rec = recording(str(args.path.resolve()))
    (a0, a1), (b0, b1) = calibrate.held_out_split(rec.duration)
    spans = {"A": (a0, a1), "B": (b0, b1)}
    models = {h: calibrate.calibrate(rec, [spans[h]], args.dt, horizon=args.horizon) for h in ("A", "B")}
    log(f"calibrated on A and on B (horizon {args.horizon:g} s)")
    if args.bias_only:
        with multiprocessing.get_context("forkserver").Pool(args.workers) as pool:
            section = bias_study(args, pool, spans, models)
        old = args.out.read_text() if args.out.exists() else ""
        args.out.write_text(replace_section(old, section, bias_heading(args)).rstrip("\n") + "\n")
        print(section)
        return
    fit = mrclam.fit_noise(rec, args.dt)
    tasks = []
    for config in CONFIGS:
        refs = tuple(n for n in RUNS[config] if n not in AGENT)
        agents = () if args.no_agents else tuple(n for n in RUNS[config] if n in AGENT and n in args.agents.split(","))
        for half, other in (("B", "A"), ("A", "B")):
            for kind, model in (("before", None), ("after", models[other])):
                tasks += [(args, config, half, kind, spans[half], model, refs)]
                tasks += [(args, config, half, kind, spans[half], model, (n,)) for n in agents]
    tasks.sort(key=lambda t: t[6][0] not in AGENT)  # the long ones first
    ablation, white = {}, {}
    with multiprocessing.get_context("forkserver").Pool(args.workers) as pool:
        pending = pool.map_async(job, tasks, chunksize=1)
        if not args.no_ablation:
            white = {key: (m, f) for key, m, f in pool.map(white_job, [(args, c, h, spans["A"], spans["B"]) for c in CONFIGS
                                                                     for h in (None, 10.0)], chunksize=1)}
            ablation = dict(pool.map(ablation_job, [(args, h, f, spans["A"], spans["B"]) for h in ABLATION["horizons"]
                                                    for f in ABLATION["folds"]], chunksize=1))
        results = [row for rows in pending.get() for row in rows]
        bias = bias_study(args, pool, spans, models)
    text = report(args, results, models, spans, fit, ablation, white) + "\n" + bias
    args.out.write_text(text + "\n")
    print(text)
    figures(results, args.fig_dir, np.array([m.xy for m in rec.landmarks.values()]))


if __name__ == "__main__":
    main()
