"""Plots of a run: trajectories with estimates, position error against time, and the radio links."""

from __future__ import annotations

import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # runs headless: on CI and on companion computers there is no display
import matplotlib.pyplot as plt
import numpy as np

from swarmloc.experiment.faults import INVERSE

DPI = 110


def _style(alg: str) -> tuple[str, str]:
    from swarmloc.estimators import REGISTRY

    return REGISTRY.color(alg), REGISTRY.label(alg)


def _line_styles(record, traces: dict) -> dict[str, dict]:
    """Each estimator's line: its registry colour and label, solid; one that gave the same
    estimates as an earlier one (results.identical_estimates) is drawn dashed over it, with
    "identical to ..." in the legend, so no line hides under another unsaid."""
    from swarmloc.experiment.results import identical_estimates

    styles = {alg: {"color": _style(alg)[0], "label": _style(alg)[1], "ls": "-"} for alg in traces}
    for a, b, _ in identical_estimates(record, traces):
        styles[b].update(ls=(0, (4, 3)), label=f"{styles[b]['label']} (identical to {styles[a]['label']})")
    return styles


def plot_run(out: Path, record, algorithms: list[str]) -> list[Path]:
    """plots/trajectories.png (east-north; a panel per agent over the landmark map when the
    record has one), plots/position_error.png, plots/heading_error.png (models with a heading)
    and plots/nees.png."""
    from swarmloc.experiment.results import heading_errors, nees_series, position_errors

    out = Path(out) / "plots"
    out.mkdir(parents=True, exist_ok=True)
    truth = record.truth_array()
    t = np.array(record.t)
    traces = {a: record.trace(a) for a in algorithms}
    styles = _line_styles(record, traces)
    paths = []

    landmarks = getattr(record, "landmarks", {}) or {}
    # With a landmark map (a replay) the robots criss-cross one arena: a panel per robot.
    panels = record.ids if landmarks else [None]
    cols = min(len(panels), 3)
    rows = -(-len(panels) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(7 if cols == 1 else 5 * cols, 7 if rows == 1 and cols == 1 else 4.2 * rows),
                             squeeze=False)
    centre = np.nanmean(truth[0, :, :2], axis=0)
    cut = False
    for pi, (ax, which) in enumerate(zip(axes.flat, panels)):
        for ci, aid in enumerate(record.ids):
            if which is not None and aid != which:
                continue
            first = ci == 0 or which is not None
            ax.plot(truth[:, ci, 0], truth[:, ci, 1], "k-", lw=1.5, label="truth (Vicon)" if landmarks and first
                    else "truth" if first else None)
            ax.plot(*truth[0, ci, :2], "ko", ms=4 if len(record.ids) > MAX_PANELS else 6)
            # Away from the swarm's centre: labels of neighbours then spread apart instead of piling up.
            away = truth[0, ci, :2] - centre
            away = away / np.linalg.norm(away) if np.linalg.norm(away) > 0 else np.array([0.7, 0.7])
            ax.annotate(f"A{aid}", truth[0, ci, :2], textcoords="offset points", xytext=tuple(9 * away),
                        ha="left" if away[0] >= 0 else "right", va="bottom" if away[1] >= 0 else "top",
                        fontsize=8 if len(record.ids) > MAX_PANELS else 10)
            for alg, tr in traces.items():
                st = styles[alg]
                xy = _without_jumps(tr.mean[:, ci, :2], truth[:, ci, :2])
                ax.plot(xy[:, 0], xy[:, 1], color=st["color"], ls=st["ls"], lw=0.8,
                        label=st["label"] if first else None)
        if which is None:
            cut = _frame_on_truth(ax, truth[:, :, :2], [tr.mean[:, :, :2] for tr in traces.values()])
        if landmarks:
            xy = np.array(list(landmarks.values()))
            ax.plot(xy[:, 0], xy[:, 1], "k^", ms=5, label="landmarks")
            ax.set_title(f"A{which}")
        for gi, (gid, xy) in enumerate((getattr(record, "ground_stations", None) or {}).items()):
            ax.plot(*xy, "ks", ms=7, mfc="white", label="ground station (not localized)" if gi == 0 else None)
            ax.annotate(f"A{gid}", xy, textcoords="offset points", xytext=(6, -12))
        ax.set_xlabel("x, east (m)")
        ax.set_ylabel("y, north (m)")
        ax.set_aspect("equal", adjustable="box" if which is None and cut else "datalim")  # box: keeps the frame
        if pi == 0:
            ax.legend(loc="best", fontsize="small")
    for ax in axes.flat[len(panels):]:
        ax.axis("off")
    if not landmarks:
        axes[0, 0].set_title("Trajectories: truth and estimates" + ("\n(estimates off the frame cut; jumps of an "
                                                                    "estimate left as gaps)" if cut else ""))
    paths.append(out / "trajectories.png")
    fig.savefig(paths[-1], dpi=DPI, bbox_inches="tight")
    plt.close(fig)

    errors = {alg: position_errors(record, tr) for alg, tr in traces.items()}
    bound = record.bound.position if getattr(record, "bound", None) is not None else None
    paths.append(_per_agent(out / "position_error.png", record, t, errors, "position error (m)", styles=styles,
                            floor=bound))
    if any(len(record.models[a].layout.att_idx) == 1 for a in record.ids):
        heading = {alg: heading_errors(record, tr) for alg, tr in traces.items()}
        paths.append(_per_agent(out / "heading_error.png", record, t, heading, "heading error (rad)", styles=styles))
    nees = {alg: nees_series(record, tr) for alg, tr in traces.items()}
    paths.append(_per_agent(out / "nees.png", record, t, nees, "NEES", log=True, bounds=True, styles=styles))
    with_targets = {a: tr for a, tr in traces.items() if tr.target_ids is not None}
    if record.target_ids and with_targets:
        paths.append(plot_targets(out / "targets.png", record, with_targets))
    return paths


JUMP = 5.0  # an estimate moving this many times as far as the truth (and 3 m more) in one tick has jumped


def _without_jumps(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """An estimate's track (T, 2) with NaN where it jumps (a fix after a long outage, a lost
    agent found again): a jump drawn as a line crosses the map and hides the tracks."""
    step = np.linalg.norm(np.diff(est, axis=0), axis=1)
    moved = np.linalg.norm(np.diff(truth, axis=0), axis=1)
    out = est.copy()
    jumps = np.flatnonzero(step > JUMP * moved + 3.0) + 1
    return np.insert(out, jumps, np.nan, axis=0) if jumps.size else out


def _frame_on_truth(ax, truth: np.ndarray, estimates: list[np.ndarray], pad: float = 0.15) -> bool:
    """Limits around the true tracks (and a margin) when the estimates reach much further (a
    prior hundreds of metres off before a first fix would shrink every track to a corner).
    Whether the frame was set so, cutting estimates off."""
    lo, hi = np.nanmin(truth.reshape(-1, 2), axis=0), np.nanmax(truth.reshape(-1, 2), axis=0)
    margin = pad * max(float(np.max(hi - lo)), 1.0)
    lo, hi = lo - margin, hi + margin
    est = np.concatenate([e.reshape(-1, 2) for e in estimates]) if estimates else np.zeros((0, 2))
    est = est[~np.isnan(est).any(axis=1)]
    if not est.size or ((est >= lo) & (est <= hi)).all():
        return False
    extent = np.maximum(est.max(0), hi) - np.minimum(est.min(0), lo)
    if (extent > 1.25 * (hi - lo)).any():  # the estimates would shrink the tracks to a corner
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        return True
    return False


def _ellipse(ax, mean, cov, color, label=None, p=0.95):
    """The p-probability ellipse of a 2D Gaussian."""
    import scipy.stats

    vals, vecs = np.linalg.eigh(cov)
    r = np.sqrt(scipy.stats.chi2.ppf(p, 2) * np.clip(vals, 0, None))
    a = np.linspace(0, 2 * np.pi, 90)
    pts = mean[:, None] + vecs @ (r[:, None] * np.vstack([np.cos(a), np.sin(a)]))
    ax.plot(pts[0], pts[1], color=color, lw=1.0, label=label)
    return pts


def _target_inset(ax, covered: np.ndarray, platforms: np.ndarray, draw) -> None:
    """A zoom on the targets when their ellipses are small beside the platforms' tracks (a few
    pixels wide on the full map), in the corner of the axes the tracks leave emptiest."""
    covered = covered[~np.isnan(covered).any(axis=1)]
    if not covered.size:
        return
    lo, hi = covered.min(0), covered.max(0)
    span = np.nanmax(platforms.reshape(-1, 2), axis=0) - np.nanmin(platforms.reshape(-1, 2), axis=0)
    half = 0.6 * max(float(np.max(hi - lo)), 2.0)
    if 2 * half > 0.15 * float(np.max(span)):
        return  # large enough to read on the map
    centre = (lo + hi) / 2
    ax.figure.canvas.draw()  # the limits the aspect ratio settled on
    x0, x1 = ax.get_xlim()
    y0, y1 = ax.get_ylim()
    pts = platforms.reshape(-1, 2)
    pts = pts[~np.isnan(pts).any(axis=1)]
    fx, fy = (pts[:, 0] - x0) / (x1 - x0), (pts[:, 1] - y0) / (y1 - y0)
    fc = ((centre[0] - x0) / (x1 - x0), (centre[1] - y0) / (y1 - y0))
    size, places = 0.36, {}
    for cx in np.arange(0.02, 0.98 - size + 1e-9, 0.04):
        for cy in np.arange(0.02, 0.98 - size + 1e-9, 0.04):
            if cx <= fc[0] <= cx + size and cy <= fc[1] <= cy + size:
                continue  # it would hide what it zooms on
            inside = (fx >= cx) & (fx <= cx + size) & (fy >= cy) & (fy <= cy + size)
            near = np.hypot(cx + size / 2 - fc[0], cy + size / 2 - fc[1])
            places[cx, cy] = (int(inside.sum()), near)  # fewest track points, then closest to the targets
    if not places:
        return
    cx, cy = min(places, key=places.get)
    inset = ax.inset_axes((cx, cy, size, size))
    draw(inset, labels=False)
    inset.set_xlim(centre[0] - half, centre[0] + half)
    inset.set_ylim(centre[1] - half, centre[1] + half)
    inset.set_aspect("equal", adjustable="box")
    inset.tick_params(labelsize=7)
    inset.set_title(f"targets, {2 * half:.3g} m across", fontsize=8)
    ax.indicate_inset_zoom(inset, edgecolor="0.4")


def plot_targets(path: Path, record, traces: dict) -> Path:
    """Left: platforms (truth, and the first estimator's estimates), each target's truth and each
    estimator's estimate of it over time (mean over agents), with every agent's final 95%
    ellipse. Right: target error against time, mean over agents."""
    from swarmloc.experiment.results import target_errors

    truth, t = record.truth_array(), np.array(record.t)
    targets = np.stack(record.target_truth)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(13, 5.5), gridspec_kw={"width_ratios": [1.2, 1]})
    first = next(iter(traces.values()))
    for ci, aid in enumerate(record.ids):
        ax.plot(truth[:, ci, 0], truth[:, ci, 1], "k-", lw=1.2, label="platforms, truth" if ci == 0 else None)
        ax.annotate(f"A{aid}", truth[0, ci, :2], textcoords="offset points", xytext=(-12, 5))
        ax.plot(first.mean[:, ci, 0], first.mean[:, ci, 1], color="0.55", lw=0.8,
                label=f"platforms, {_style(next(iter(traces)))[1]}" if ci == 0 else None)
    def draw_targets(ax, labels: bool) -> list[np.ndarray]:
        """Each target's truth, estimated track and final ellipses; the points they cover."""
        covered = []
        for mi, o in enumerate(record.target_ids):
            ax.plot(targets[:, mi, 0], targets[:, mi, 1], "k*", ms=12, label="target, truth" if labels and mi == 0 else None)
            covered.append(targets[:, mi])
            for alg, tr in traces.items():
                color, label = _style(alg)
                if np.isnan(tr.target_mean[:, :, mi]).all():
                    continue
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)  # ticks before the target was first localized
                    track = np.nanmean(tr.target_mean[:, :, mi], axis=1)
                ax.plot(track[:, 0], track[:, 1], color=color, lw=0.8, alpha=0.7)
                for ci in range(len(record.ids)):
                    m, P = tr.target_mean[-1, ci, mi], tr.target_cov[-1, ci, mi]
                    if not np.isnan(m).any():
                        ax.plot(*m, "o", color=color, ms=3)
                        pts = _ellipse(ax, m, P, color, f"{label} target, 95%" if labels and mi == 0 and ci == 0 else None)
                        covered.append(pts.T)
        return covered

    covered = draw_targets(ax, labels=True)
    ax.set_xlabel("x, east (m)")
    ax.set_ylabel("y, north (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=3, fontsize=8, frameon=False)
    ax.set_title("Platforms and targets; final target ellipses of every agent")
    _target_inset(ax, np.concatenate(covered), truth[:, :, :2], draw_targets)
    for alg, tr in traces.items():
        color, label = _style(alg)
        err, _ = target_errors(record, tr)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # ticks before a target was first localized
            ax2.plot(t, np.nanmean(err, axis=(1, 2)), color=color, label=label)
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel("target error (m), mean over agents")
    ax2.set_yscale("log")
    ax2.grid(alpha=0.3)
    ax2.legend()
    fig.savefig(path, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return path


PCRB_LABEL = "PCRB (RMS bound)"
MAX_PANELS = 8  # more agents than this: one panel of the spread over agents, not a panel each
LOG_SPAN = 100.0  # data spanning more than this factor (1st to 99th percentile) get a log axis


def _wide(values: list[np.ndarray]) -> bool:
    """Whether positive data span so many decades that a linear axis shows only the largest."""
    v = np.concatenate([x[np.isfinite(x) & (x > 0)] for x in values]) if values else np.array([])
    if v.size < 10:
        return False
    lo, hi = np.percentile(v, [1, 99])
    return lo > 0 and hi / lo > LOG_SPAN


def _per_agent(path: Path, record, t, series: dict, ylabel: str, log: bool = False, bounds: bool = False,
               styles: dict | None = None, floor: np.ndarray | None = None) -> Path:
    """One panel per agent, one line per estimator; NEES panels also show the 95% band of one
    NEES value (chi-square with the agent's state dimension). More than MAX_PANELS agents: one
    panel, each estimator's median over the agents and the band of 10 to 90 % of them. A log
    axis when asked (NEES) or when the values span more than LOG_SPAN. `floor` (T, N), the run's
    PCRB on the RMS position error, is drawn dashed (its median over the agents in the one panel)."""
    import scipy.stats

    styles = styles or {alg: {"color": _style(alg)[0], "label": _style(alg)[1], "ls": "-"} for alg in series}
    log = log or _wide(list(series.values()))
    n = len(record.ids)
    if n > MAX_PANELS:
        return _spread_panel(path, record, t, series, ylabel, log, bounds, styles, floor)
    cols = min(n, 2)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(6 * cols, 2.6 * rows), sharex=True, squeeze=False)
    for ci, aid in enumerate(record.ids):
        ax = axes[ci // cols][ci % cols]
        for alg, values in series.items():
            st = styles[alg]
            ax.plot(t, values[:, ci], color=st["color"], ls=st["ls"], lw=1.0, label=st["label"])
        if floor is not None:
            ax.plot(t, floor[:, ci], "k--", lw=1.0, label=PCRB_LABEL)
        if bounds:
            lo, hi = scipy.stats.chi2.ppf([0.025, 0.975], int(record.dims[ci]))
            ax.axhspan(lo, hi, color="0.85", zorder=0, label="95% of one value")
        if log:
            ax.set_yscale("log")
        ax.set_title(f"A{aid}")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    for extra in axes.flat[n:]:
        extra.set_visible(False)
    # Above the panels, not in one: a legend inside the first panel hides its lines.
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=min(len(labels), 4), fontsize=8,
               frameon=False)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return path


def _spread_panel(path: Path, record, t, series: dict, ylabel: str, log: bool, bounds: bool, styles: dict,
                  floor: np.ndarray | None = None) -> Path:
    import scipy.stats

    fig, ax = plt.subplots(figsize=(11, 4.5))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # ticks where no agent has a value
        for alg, values in series.items():
            st = styles[alg]
            lo, med, hi = np.nanpercentile(values, [10, 50, 90], axis=1)
            ax.fill_between(t, lo, hi, color=st["color"], alpha=0.15, lw=0)
            ax.plot(t, med, color=st["color"], ls=st["ls"], lw=1.4, label=st["label"])
        if floor is not None:
            ax.plot(t, np.nanmedian(floor, axis=1), "k--", lw=1.2, label=PCRB_LABEL + ", median over the agents")
    if bounds:
        dims = sorted({int(d) for d in record.dims})
        lo, hi = scipy.stats.chi2.ppf([0.025, 0.975], dims[0])
        ax.axhspan(lo, hi, color="0.85", zorder=0, label="95% of one value" + (f" ({dims[0]} dof)" if len(dims) > 1 else ""))
    if log:
        ax.set_yscale("log")
    ax.set_title(f"{len(record.ids)} agents: median over the agents (line) and 10 to 90 % of them (band)"
                 + ("; log scale" if log and not bounds else ""), fontsize=10)
    ax.set_xlabel("time (s)")
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3, which="both" if log else "major")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1), fontsize=8, frameon=False)
    fig.savefig(path, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_links(out: Path, radio: dict) -> Path:
    """Write plots/links.png (links_figure) into the run directory out."""
    out = Path(out) / "plots"
    out.mkdir(parents=True, exist_ok=True)
    fig = links_figure(radio)
    path = out / "links.png"
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


UP, DOWN, FAULT_DOWN = range(3)
LINK_STATES = {UP: ("up", "#c7e9c0"), DOWN: ("down (channel)", "#969696"), FAULT_DOWN: ("down (fault)", "#d62728")}
# Reception outcomes of radio.npz in legend order: delivered, the channel's drops, the fault overlay's.
REASONS = {"": ("delivered", "#c7e9c0"), "distance": ("distance", "#6baed6"), "sinr": ("SINR", "#3182bd"),
           "collision": ("collision", "#08519c"), "half-duplex": ("half-duplex", "#9ecae1"),
           "queue": ("queue full", "#756bb1"), "fault": ("cut", "#d62728"), "partition": ("partition", "#ff7f0e"),
           "radio-off": ("radio off", "#8c564b"), "jammed": ("jammed", "#e377c2"), "loss": ("extra loss", "#fdae6b"),
           "down": ("agent down", "#525252")}
# Drops that mean the link was taken down by a fault rather than by the channel: what
# netsim.sim.Simulation.link_state reports for a blocked link. radio.npz does not record why a
# link was down, so the reception rows of the pair in that tick are the evidence.
LINK_FAULT_REASONS = ("fault", "partition", "radio-off", "jammed", "down")
LINK_FAULTS = ("cut", "radio-off", "partition", "jammer", "kill")  # the faults behind those reasons
MAX_LINK_ROWS = 40  # about 7 in of rows; past that a row is hard to follow (the links panel counts them all)
MAX_FAULT_LEVELS = 6  # a taller stack of labels no longer reads as one moment
ROW_IN = 0.17  # inches per link row and per fault-label level: room for 7-8 pt text
FAULT_FONT = 8
SOURCE_NOTE = {"live": " (live)", "duration": " (its duration ran out)"}


class LinkHistory:
    """radio.npz on a (tick, pair) grid: time, SNR, link state, reception outcomes per tick."""

    def __init__(self, radio: dict):
        ticks, ti = np.unique(radio["link_k"], return_inverse=True)
        self.pairs, pi = np.unique(np.stack([radio["link_a"], radio["link_b"]], 1), axis=0, return_inverse=True)
        shape = (ticks.size, len(self.pairs))
        self.t = np.zeros(ticks.size)
        self.t[ti] = radio["link_t"]
        dt = float(np.median(np.diff(self.t))) if ticks.size > 1 else 1.0
        self.edges = np.r_[self.t, self.t[-1] + dt]  # tick i spans edges[i] .. edges[i + 1]
        self.snr = np.full(shape, np.nan)
        self.snr[ti, pi] = np.where(np.isfinite(radio["link_snr_db"]), radio["link_snr_db"], np.nan)
        up = np.ones(shape, bool)
        up[ti, pi] = radio["link_up"]

        # Receptions onto the same grid; those of ticks or pairs the link table lacks are left out.
        base = 1 + int(self.pairs.max())
        keys = self.pairs[:, 0] * base + self.pairs[:, 1]
        rkey = np.minimum(radio["src"], radio["receiver"]) * base + np.maximum(radio["src"], radio["receiver"])
        rt = np.clip(np.searchsorted(ticks, radio["k"]), 0, ticks.size - 1)
        rp = np.clip(np.searchsorted(keys, rkey), 0, keys.size - 1)
        ok = (ticks[rt] == radio["k"]) & (keys[rp] == rkey)
        rt, rp, reason = rt[ok], rp[ok], radio["reason"][ok]
        found, which = np.unique(reason, return_inverse=True)
        self.reasons = [r for r in REASONS if r in found] + [r for r in found.tolist() if r not in REASONS]
        self.outcomes = np.zeros((len(self.reasons), ticks.size))  # receptions per reason and tick
        np.add.at(self.outcomes, (np.array([self.reasons.index(r) for r in found.tolist()], int)[which], rt), 1)

        delivered, fault_seen = np.zeros(shape, bool), np.zeros(shape, bool)
        delivered[rt[reason == ""], rp[reason == ""]] = True
        faulty = np.isin(reason, LINK_FAULT_REASONS)
        fault_seen[rt[faulty], rp[faulty]] = True
        # netsim checks faults only on frames the channel let through, so a down tick whose frames
        # all died in the channel (or that had none) says nothing about faults: it takes the cause
        # of the last tick that did. A tick up or with a frame delivered, or a fault clearing (it
        # may have freed this pair), says "not a fault"; a link fault applying just as the pair
        # went down says "fault".
        def applied(actions):
            return np.isin(ticks, radio["fault_k"][np.isin(radio["fault_action"], actions)])[:, None]

        onset, clearing = applied(LINK_FAULTS), applied([INVERSE[a] for a in LINK_FAULTS])
        was_up = np.vstack([np.zeros((1, shape[1]), bool), up[:-1]])
        fault = ~up & (fault_seen | (onset & was_up & ~delivered))
        evidence = up | delivered | fault_seen | onset | clearing
        last = np.maximum.accumulate(np.where(evidence, np.arange(shape[0])[:, None], 0), axis=0)
        by_fault = fault[last, np.arange(shape[1])]
        self.state = np.where(up, UP, np.where(by_fault, FAULT_DOWN, DOWN))

    def binned_outcomes(self, max_bins: int = 300) -> tuple[np.ndarray, np.ndarray, float]:
        """Receptions per reason over bins of whole ticks, the bins' edges and their width (s):
        wide enough that a bin holds frames wherever the ticks that carry any are regular
        (beacons once a second at ticks of 0.1 s would otherwise leave nine empty ticks of ten,
        drawn as nothing), and at most max_bins of them. A short last bin keeps the width for
        rates: its frames are those of a whole bin's period."""
        busy = np.flatnonzero(self.outcomes.sum(0))
        gap = int(np.median(np.diff(busy))) if busy.size > 1 else 1
        w = max(1, gap, -(-self.t.size // max_bins))
        starts = np.arange(0, self.t.size, w)
        edges = np.r_[self.edges[starts], self.edges[-1]]
        width = float(np.median(np.diff(self.edges))) * w
        return np.add.reduceat(self.outcomes, starts, axis=1), edges, width


def stagger(left, right, pad: float = 0.0) -> list[int]:
    """Level (0 = lowest) for each label spanning [left, right]: the lowest level where it clears
    by pad every label already placed there, placing them from left to right."""
    ends: list[float] = []  # right edge of the last label placed on each level
    levels = [0] * len(left)
    for i in sorted(range(len(left)), key=lambda i: left[i]):
        level = next((j for j, end in enumerate(ends) if left[i] >= end + pad), len(ends))
        ends[level:level + 1] = [right[i]]
        levels[i] = level
    return levels


def fault_labels(fault_t, width, pad: float,
                 max_levels: int = MAX_FAULT_LEVELS) -> list[tuple[str, float, int, list[int]]]:
    """The fault numbers above the panels as (text, time, level, fault indices); width(text) and
    pad in seconds. Labels that would overlap are stacked; a burst that needs more than
    max_levels levels gets labels "first-last" for neighbours (the list under the plot has each fault)."""
    groups = [[i] for i in np.argsort(fault_t, kind="stable")]
    while True:
        text = [str(g[0] + 1) if len(g) == 1 else f"{min(g) + 1}-{max(g) + 1}" for g in groups]
        x = np.array([(fault_t[g].min() + fault_t[g].max()) / 2 for g in groups])
        half = np.array([width(s) / 2 for s in text])
        levels = stagger(x - half, x + half, pad)
        if max(levels) < max_levels:
            return list(zip(text, x.tolist(), levels, groups))
        i = int(np.argmin(np.diff(x)))  # merge the two closest neighbours, and try again
        groups[i:i + 2] = [sorted(groups[i] + groups[i + 1])]


def link_rows(state: np.ndarray, max_rows: int = MAX_LINK_ROWS) -> np.ndarray:
    """Pairs worth a row, in pair order: those ever down; beyond max_rows, those down longest
    because of a fault, then down longest at all."""
    down, by_fault = (state != UP).sum(0), (state == FAULT_DOWN).sum(0)
    rows = np.flatnonzero(down)
    if rows.size > max_rows:
        rows = np.sort(rows[np.lexsort((-down[rows], -by_fault[rows]))[:max_rows]])
    return rows


def links_figure(radio: dict) -> plt.Figure:
    """Link quality over time from radio.npz arrays: fault markers, interference-free SNR (if the
    model has one), reception outcomes, links up, and one row per link that was ever down."""
    h = LinkHistory(radio)
    fault_t = np.asarray(radio["fault_t"], float)
    has_snr = bool(np.isfinite(h.snr).any())
    rows = link_rows(h.state)
    span = (h.edges[0], h.edges[-1])
    width, left, right = 11.0, 0.8, 2.2  # inches; the right margin holds the legends
    axis_w = width - left - right
    fig = plt.figure(figsize=(width, 1.0), dpi=DPI)

    labels = []
    if fault_t.size:
        # Labels are placed in time units, so their widths are measured and converted first.
        prop = matplotlib.font_manager.FontProperties(size=FAULT_FONT, weight="bold")
        renderer = fig.canvas.get_renderer()
        s_per_px = (span[1] - span[0]) / (axis_w * DPI)
        labels = fault_labels(fault_t, lambda s: renderer.get_text_width_height_descent(s, prop, False)[0] * s_per_px,
                              pad=3 * DPI / 72 * s_per_px)

    # Laid out by hand in inches rather than by a layout engine: a link row and a label level keep
    # their size however many there are, and the axis width the label widths were measured
    # against stays put. Panels top to bottom: (name, height, gap above).
    # Nothing went wrong (no fault, no drop, every link up): fractions of 1 and a full bar of links
    # up would be two blank panels; the traffic is what there is to see.
    quiet = not fault_t.size and set(h.reasons) <= {""} and not rows.size
    panels = ([("faults", (max(lv for _, _, lv, _ in labels) + 1) * ROW_IN, 0.0)] if labels else []) \
        + ([("snr", 1.5, 0.12)] if has_snr else []) \
        + ([("traffic", 1.5, 0.2)] if quiet and h.reasons else []) \
        + ([("receptions", 1.5, 0.2)] if h.reasons and not quiet else []) \
        + ([] if quiet and h.reasons else [("links", 1.2, 0.2)]) \
        + ([("link rows", rows.size * ROW_IN + 0.1, 0.45)] if rows.size else [])
    notes = ([] if has_snr else ["no SNR recorded (unit-disk radio)"]) + ([] if h.reasons else ["no frames sent"]) \
        + ([] if rows.size else ["every link up throughout"]) \
        + (["every frame delivered, no fault"] if quiet and h.reasons else [])
    lines = _fault_lines(radio)
    # The fault list under the plot, in as many columns as fit (monospace: 0.6 em per character).
    col_w = max(map(len, lines), default=0) * 0.6 * FAULT_FONT / 72 + 0.4
    list_rows = -(-len(lines) // max(1, int((width - left) // col_w)))
    list_h = 0.3 + list_rows * ROW_IN if lines else 0.0
    top, bottom = 0.45 + (0.25 if notes else 0.0), 0.5 + list_h
    height = top + bottom + sum(ph + gap for _, ph, gap in panels)
    fig.set_size_inches(width, height)

    axes, y = {}, height - top
    for name, ph, gap in panels:
        y -= gap + ph
        ax = fig.add_axes((left / width, y / height, axis_w / width, ph / height),
                          sharex=next(iter(axes.values()), None), label=name)
        ax.tick_params(labelbottom=False, labelsize=8)
        axes[name] = ax
    last = list(axes.values())[-1]
    last.tick_params(labelbottom=True)
    last.set_xlabel("time (s)")
    last.set_xlim(*span)

    n_agents = np.unique(h.pairs).size
    fig.suptitle(f"Radio links: {n_agents} agents, {len(h.pairs)} link{'s' if len(h.pairs) != 1 else ''}, "
                 f"{h.t.size} ticks" + ("\n" + "; ".join(notes) if notes else ""),
                 x=left / width, y=1 - 0.15 / height, ha="left", va="top", fontsize=11, linespacing=1.5)
    if has_snr:
        _snr_panel(axes["snr"], h)
    outcomes, edges, bin_s = h.binned_outcomes() if h.reasons else (None, None, None)
    per = "tick" if edges is None or edges.size - 1 == h.t.size else f"{bin_s:g} s"
    if "receptions" in axes:
        total = outcomes.sum(0)
        with np.errstate(invalid="ignore", divide="ignore"):
            _stacked(axes["receptions"], edges, outcomes / np.where(total, total, np.nan),
                     [REASONS.get(r, (r, "#bdbdbd")) for r in h.reasons], f"receptions per {per}\n(fraction)")
        axes["receptions"].set_ylim(0, 1)
    if "traffic" in axes:
        rate = outcomes.sum(0) / bin_s
        _stacked(axes["traffic"], edges, rate[None], [REASONS[""]], "frames delivered\nper second")
        axes["traffic"].set_ylim(0, 1.15 * rate.max())
    if "links" in axes:
        counts = np.stack([(h.state == s).sum(1) for s in LINK_STATES])
        _stacked(axes["links"], h.edges, counts, list(LINK_STATES.values()), "links")
        axes["links"].set_ylim(0, len(h.pairs))
    if rows.size:
        _link_rows_panel(axes["link rows"], h, rows)
    for name, ax in axes.items():
        if name != "faults":
            ax.grid(alpha=0.3, axis="x")
            for ft, act in zip(fault_t, radio["fault_action"]):
                ax.axvline(ft, **_fault_style(act))
    if fault_t.size:
        _fault_strip(axes["faults"], fault_t, radio["fault_action"], labels)
        fig.text(left / width, (list_h - 0.05) / height,
                 "Faults (numbered at the top; dashed: applied, dotted: cleared)", fontsize=9, va="top")
        for i, (line, act) in enumerate(zip(lines, radio["fault_action"])):
            fig.text((left + i // list_rows * col_w) / width, (list_h - 0.3 - i % list_rows * ROW_IN) / height, line,
                     fontsize=FAULT_FONT, family="monospace", va="top", color=_fault_style(act)["color"])
    return fig


def _fault_style(action: str) -> dict:
    cleared = action in INVERSE.values()
    return {"color": "0.45" if cleared else "black", "ls": ":" if cleared else "--", "lw": 0.8}


def _fault_lines(radio: dict) -> list[str]:
    return [f"{i + 1:>3} {t:8.1f} s  {act}{SOURCE_NOTE.get(src, '')}"
            for i, (t, act, src) in enumerate(zip(radio["fault_t"], radio["fault_action"], radio["fault_source"]))]


def _fault_strip(ax, fault_t, actions, labels) -> None:
    ax.set_ylim(0, max(level for _, _, level, _ in labels) + 1)
    ax.axis("off")
    for text, x, level, members in labels:
        styles = [_fault_style(actions[i]) for i in members]
        for i, style in zip(members, styles):
            ax.vlines(fault_t[i], 0, level + 0.1, color=style["color"], ls=style["ls"], lw=style["lw"])
        ax.text(x, level + 0.5, text, ha="center", va="center", fontsize=FAULT_FONT, weight="bold",
                color=styles[0]["color"] if len(members) == 1 else "black", gid="fault-label",
                bbox={"fc": "white", "ec": "none", "pad": 0.3})  # hides the stems of higher labels


def _stacked(ax, edges, layers, styles, ylabel: str) -> None:
    """Layers (one row per layer, one column per tick) stacked as steps over the ticks' spans."""
    steps = np.concatenate([layers, layers[:, -1:]], axis=1)
    ax.stackplot(edges, steps, step="post", colors=[c for _, c in styles], labels=[n for n, _ in styles], lw=0)
    ax.set_ylabel(ylabel, fontsize=9)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1), fontsize=8, frameon=False)


def _snr_panel(ax, h: LinkHistory) -> None:
    if len(h.pairs) <= 6:
        for (a, b), snr in zip(h.pairs, h.snr.T):
            ax.plot(h.t, snr, lw=1.0, label=f"{a}-{b}")
    else:  # a line per pair is a tangle: the spread over pairs instead
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # ticks where no pair has an SNR
            lo, p10, med, p90, hi = np.nanpercentile(h.snr, [0, 10, 50, 90, 100], axis=1)
        ax.fill_between(h.t, lo, hi, color="tab:blue", alpha=0.15, lw=0, label="min-max over links")
        ax.fill_between(h.t, p10, p90, color="tab:blue", alpha=0.35, lw=0, label="10-90 % of links")
        ax.plot(h.t, med, color="tab:blue", lw=1.2, label="median link")
    ax.set_ylabel("SNR without\ninterference (dB)", fontsize=9)
    ax.grid(alpha=0.3, axis="y")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1), fontsize=8, frameon=False)


def _link_rows_panel(ax, h: LinkHistory, rows: np.ndarray) -> None:
    ax.set_facecolor(LINK_STATES[UP][1])
    for r, col in enumerate(h.state[:, rows].T):
        for s in (DOWN, FAULT_DOWN):
            change = np.diff(np.r_[0, (col == s).astype(int), 0])
            start, end = np.flatnonzero(change == 1), np.flatnonzero(change == -1)
            ax.broken_barh(list(zip(h.edges[start], h.edges[end] - h.edges[start])), (r + 0.1, 0.8),
                           color=LINK_STATES[s][1], lw=0)
    ax.set_ylim(rows.size, 0)
    ax.set_yticks(np.arange(rows.size) + 0.5, [f"{a}-{b}" for a, b in h.pairs[rows]], fontsize=7)
    ax.tick_params(axis="y", length=0)
    ever = int(((h.state != UP).sum(0) > 0).sum())
    shown = f"{rows.size} of the {ever} links ever down: those down longest by a fault, then at all" \
        if rows.size < ever else f"links ever down: {ever} of {len(h.pairs)}"
    always = len(h.pairs) - ever
    ax.set_title(shown + (f"; {always} up throughout, not shown" if always else ""), fontsize=9, loc="left")
