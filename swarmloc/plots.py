"""Plots of a run: trajectories with estimates, position error against time, and the radio links."""

from __future__ import annotations

import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # runs headless: on CI and on companion computers there is no display
import matplotlib.pyplot as plt
import numpy as np

from swarmloc.faults import INVERSE

DPI = 110


def _style(alg: str) -> tuple[str, str]:
    from swarmloc.estimators import REGISTRY

    return REGISTRY.color(alg), REGISTRY.label(alg)


def plot_run(out: Path, record, algorithms: list[str]) -> list[Path]:
    """plots/trajectories.png (east-north; a panel per agent over the landmark map when the
    record has one), plots/position_error.png, plots/heading_error.png (models with a heading)
    and plots/nees.png."""
    from swarmloc.results import heading_errors, nees_series, position_errors

    out = Path(out) / "plots"
    out.mkdir(parents=True, exist_ok=True)
    truth = record.truth_array()
    t = np.array(record.t)
    traces = {a: record.trace(a) for a in algorithms}
    paths = []

    landmarks = getattr(record, "landmarks", {}) or {}
    # With a landmark map (a replay) the robots criss-cross one arena: a panel per robot.
    panels = record.ids if landmarks else [None]
    cols = min(len(panels), 3)
    rows = -(-len(panels) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(7 if cols == 1 else 5 * cols, 7 if rows == 1 and cols == 1 else 4.2 * rows),
                             squeeze=False)
    for pi, (ax, which) in enumerate(zip(axes.flat, panels)):
        for ci, aid in enumerate(record.ids):
            if which is not None and aid != which:
                continue
            first = ci == 0 or which is not None
            ax.plot(truth[:, ci, 0], truth[:, ci, 1], "k-", lw=1.5, label="truth (Vicon)" if landmarks and first
                    else "truth" if first else None)
            ax.plot(*truth[0, ci, :2], "ko")
            ax.annotate(f"A{aid}", truth[0, ci, :2], textcoords="offset points", xytext=(5, 5))
            for alg, tr in traces.items():
                color, label = _style(alg)
                ax.plot(tr.mean[:, ci, 0], tr.mean[:, ci, 1], color=color, lw=0.8, label=label if first else None)
        if landmarks:
            xy = np.array(list(landmarks.values()))
            ax.plot(xy[:, 0], xy[:, 1], "k^", ms=5, label="landmarks")
            ax.set_title(f"A{which}")
        ax.set_xlabel("x, east (m)")
        ax.set_ylabel("y, north (m)")
        ax.set_aspect("equal", adjustable="datalim")
        if pi == 0:
            ax.legend(loc="best", fontsize="small")
    for ax in axes.flat[len(panels):]:
        ax.axis("off")
    if not landmarks:
        axes[0, 0].set_title("Trajectories: truth and estimates")
    paths.append(out / "trajectories.png")
    fig.savefig(paths[-1], dpi=DPI, bbox_inches="tight")
    plt.close(fig)

    errors = {alg: position_errors(record, tr) for alg, tr in traces.items()}
    paths.append(_per_agent(out / "position_error.png", record, t, errors, "position error (m)"))
    if any(len(record.models[a].layout.att_idx) == 1 for a in record.ids):
        heading = {alg: heading_errors(record, tr) for alg, tr in traces.items()}
        paths.append(_per_agent(out / "heading_error.png", record, t, heading, "heading error (rad)"))
    nees = {alg: nees_series(record, tr) for alg, tr in traces.items()}
    paths.append(_per_agent(out / "nees.png", record, t, nees, "NEES", log=True, bounds=True))
    with_targets = {a: tr for a, tr in traces.items() if tr.target_ids is not None}
    if record.target_ids and with_targets:
        paths.append(plot_targets(out / "targets.png", record, with_targets))
    return paths


def _ellipse(ax, mean, cov, color, label=None, p=0.95):
    """The p-probability ellipse of a 2D Gaussian."""
    import scipy.stats

    vals, vecs = np.linalg.eigh(cov)
    r = np.sqrt(scipy.stats.chi2.ppf(p, 2) * np.clip(vals, 0, None))
    a = np.linspace(0, 2 * np.pi, 90)
    pts = mean[:, None] + vecs @ (r[:, None] * np.vstack([np.cos(a), np.sin(a)]))
    ax.plot(pts[0], pts[1], color=color, lw=1.0, label=label)


def plot_targets(path: Path, record, traces: dict) -> Path:
    """Left: platforms (truth, and the first estimator's estimates), each target's truth and each
    estimator's estimate of it over time (mean over agents), with every agent's final 95%
    ellipse. Right: target error against time, mean over agents."""
    from swarmloc.results import target_errors

    truth, t = record.truth_array(), np.array(record.t)
    targets = np.stack(record.target_truth)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(13, 5.5), gridspec_kw={"width_ratios": [1.2, 1]})
    first = next(iter(traces.values()))
    for ci, aid in enumerate(record.ids):
        ax.plot(truth[:, ci, 0], truth[:, ci, 1], "k-", lw=1.2, label="platforms, truth" if ci == 0 else None)
        ax.annotate(f"A{aid}", truth[0, ci, :2], textcoords="offset points", xytext=(-12, 5))
        ax.plot(first.mean[:, ci, 0], first.mean[:, ci, 1], color="0.55", lw=0.8,
                label=f"platforms, {_style(next(iter(traces)))[1]}" if ci == 0 else None)
    for mi, o in enumerate(record.target_ids):
        ax.plot(targets[:, mi, 0], targets[:, mi, 1], "k*", ms=12, label="target, truth" if mi == 0 else None)
        for alg, tr in traces.items():
            color, label = _style(alg)
            track = np.nanmean(tr.target_mean[:, :, mi], axis=1) if not np.isnan(tr.target_mean[:, :, mi]).all() else None
            if track is None:
                continue
            ax.plot(track[:, 0], track[:, 1], color=color, lw=0.8, alpha=0.7)
            for ci in range(len(record.ids)):
                m, P = tr.target_mean[-1, ci, mi], tr.target_cov[-1, ci, mi]
                if not np.isnan(m).any():
                    ax.plot(*m, "o", color=color, ms=3)
                    _ellipse(ax, m, P, color, f"{label} target, 95%" if (mi == 0 and ci == 0) else None)
    ax.set_xlabel("x, east (m)")
    ax.set_ylabel("y, north (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="best", fontsize=8)
    ax.set_title("Platforms and targets; final target ellipses of every agent")
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


def _per_agent(path: Path, record, t, series: dict, ylabel: str, log: bool = False, bounds: bool = False) -> Path:
    """One panel per agent, one line per estimator; NEES panels also show the 95% band of one
    NEES value (chi-square with the agent's state dimension)."""
    import scipy.stats

    n = len(record.ids)
    cols = min(n, 2)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(6 * cols, 2.6 * rows), sharex=True, squeeze=False)
    for ci, aid in enumerate(record.ids):
        ax = axes[ci // cols][ci % cols]
        for alg, values in series.items():
            color, label = _style(alg)
            ax.plot(t, values[:, ci], color=color, lw=1.0, label=label)
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
    axes[0][0].legend(loc="upper left", fontsize=8)
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
    panels = ([("faults", (max(lv for _, _, lv, _ in labels) + 1) * ROW_IN, 0.0)] if labels else []) \
        + ([("snr", 1.5, 0.12)] if has_snr else []) \
        + ([("receptions", 1.5, 0.2)] if h.reasons else []) + [("links", 1.2, 0.2)] \
        + ([("link rows", rows.size * ROW_IN + 0.1, 0.45)] if rows.size else [])
    lines = _fault_lines(radio)
    # The fault list under the plot, in as many columns as fit (monospace: 0.6 em per character).
    col_w = max(map(len, lines), default=0) * 0.6 * FAULT_FONT / 72 + 0.4
    list_rows = -(-len(lines) // max(1, int((width - left) // col_w)))
    list_h = 0.3 + list_rows * ROW_IN if lines else 0.0
    top, bottom = 0.45, 0.5 + list_h
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
    notes = ([] if has_snr else ["no SNR recorded (unit-disk radio)"]) + ([] if h.reasons else ["no frames sent"]) \
        + ([] if rows.size else ["every link up throughout"])
    fig.suptitle(f"Radio links: {n_agents} agents, {len(h.pairs)} links, {h.t.size} ticks"
                 + "".join(f"; {n}" for n in notes),
                 x=left / width, y=1 - 0.15 / height, ha="left", va="top", fontsize=11)
    if has_snr:
        _snr_panel(axes["snr"], h)
    if h.reasons:
        total = h.outcomes.sum(0)
        with np.errstate(invalid="ignore", divide="ignore"):
            _stacked(axes["receptions"], h.edges, h.outcomes / np.where(total, total, np.nan),
                     [REASONS.get(r, (r, "#bdbdbd")) for r in h.reasons], "receptions per tick\n(fraction)")
        axes["receptions"].set_ylim(0, 1)
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
