"""Plots of a run: trajectories with estimates, and position error against time."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # runs headless: on CI and on companion computers there is no display
import matplotlib.pyplot as plt
import numpy as np

STYLE = {"il": ("tab:red", "IL (dead reckoning)"), "ukf-dcl": ("tab:green", "UKF-DCL"), "ukf-ccl": ("tab:blue", "UKF-CCL")}


def plot_run(out: Path, record, algorithms: list[str]) -> list[Path]:
    out = Path(out) / "plots"
    out.mkdir(parents=True, exist_ok=True)
    truth = record.truth_array()
    t = np.array(record.t)
    traces = {a: record.trace(a) for a in algorithms}
    paths = []

    fig, ax = plt.subplots(figsize=(7, 7))
    for ci, aid in enumerate(record.ids):
        ax.plot(truth[:, ci, 0], truth[:, ci, 1], "k-", lw=1.5, label="truth" if ci == 0 else None)
        ax.plot(*truth[0, ci, :2], "ko")
        ax.annotate(f"A{aid}", truth[0, ci, :2], textcoords="offset points", xytext=(5, 5))
        for alg in ("il", "ukf-dcl"):
            if alg in traces:
                color, label = STYLE.get(alg, ("gray", alg))
                m = traces[alg].mean
                ax.plot(m[:, ci, 0], m[:, ci, 1], color=color, lw=0.8, label=label if ci == 0 else None)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="best")
    ax.set_title("Trajectories: truth and estimates")
    paths.append(out / "trajectories.png")
    fig.savefig(paths[-1], dpi=110, bbox_inches="tight")
    plt.close(fig)

    n = len(record.ids)
    cols = min(n, 2)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(6 * cols, 2.6 * rows), sharex=True, squeeze=False)
    for ci, aid in enumerate(record.ids):
        ax = axes[ci // cols][ci % cols]
        for alg, tr in traces.items():
            color, label = STYLE.get(alg, ("gray", alg))
            err = np.linalg.norm(tr.mean[:, ci, :2] - truth[:, ci, :2], axis=-1)
            ax.plot(t, err, color=color, lw=1.0, label=label, ls="--" if alg == "ukf-ccl" else "-")
        ax.set_title(f"A{aid}")
        ax.set_ylabel("position error (m)")
        ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    for extra in axes.flat[n:]:
        extra.set_visible(False)
    axes[0][0].legend(loc="upper left", fontsize=8)
    paths.append(out / "position_error.png")
    fig.savefig(paths[-1], dpi=110, bbox_inches="tight")
    plt.close(fig)
    return paths


def plot_links(out: Path, radio: dict) -> Path:
    """Link quality over time: modelled SNR, up/down, and delivery ratio per tick, faults marked."""
    out = Path(out) / "plots"
    out.mkdir(parents=True, exist_ok=True)
    t, a, b = radio["link_t"], radio["link_a"], radio["link_b"]
    pairs = sorted(set(zip(a.tolist(), b.tolist())))
    fig, (ax_snr, ax_up, ax_pdr) = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    rk, rs, rr, rd = radio["k"], radio["src"], radio["receiver"], radio["delivered"]
    tick_t = {int(k): float(tt) for k, tt in zip(radio["link_k"], t)}
    for i, (pa, pb) in enumerate(pairs):
        sel = (a == pa) & (b == pb)
        ax_snr.plot(t[sel], radio["link_snr_db"][sel], lw=0.8, label=f"{pa}-{pb}")
        ax_up.plot(t[sel], radio["link_up"][sel] * 0.8 + i, lw=1.0)
        pair = ((rs == pa) & (rr == pb)) | ((rs == pb) & (rr == pa))
        if pair.any():
            ks = np.unique(rk[pair])
            ratio = [rd[pair & (rk == k)].mean() for k in ks]
            ax_pdr.plot([tick_t.get(int(k), np.nan) for k in ks], ratio, ".", ms=2)
    for ft, act in zip(radio["fault_t"], radio["fault_action"]):
        for ax in (ax_snr, ax_up, ax_pdr):
            ax.axvline(ft, color="k", lw=0.5, ls=":")
        ax_snr.annotate(str(act), (ft, 1.0), xycoords=("data", "axes fraction"), rotation=90, fontsize=7, va="top")
    ax_snr.set_ylabel("SNR without interference (dB)")
    ax_up.set_ylabel("link up (one row per pair)")
    ax_up.set_yticks(range(len(pairs)), [f"{pa}-{pb}" for pa, pb in pairs], fontsize=7)
    ax_pdr.set_ylabel("delivered fraction per tick")
    ax_pdr.set_xlabel("time (s)")
    if len(pairs) <= 12:
        ax_snr.legend(fontsize=7, ncol=4)
    for ax in (ax_snr, ax_up, ax_pdr):
        ax.grid(alpha=0.3)
    path = out / "links.png"
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path
