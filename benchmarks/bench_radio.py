"""Benchmark: radio frames routed per second by netsim's Simulation (pure code, no Zenoh).

N agents spread at random over a 400 m square (fixed seed; each circles at 1 m/s on a 10 m
radius, so the geometry stays put however many ticks are run while shadowing evolves) all
broadcast one beacon-sized frame (60 B) per tick. Each tick calls sim.tick() (world step,
positions and jammers into the medium, the per-tick link table) and then
sim.exchange_batch([...RadioTx...]) (lockstep round: offer every frame, resolve to the end, one
outcome per frame and receiver, counted and logged; the deliveries as netsim's server takes
them, without a RadioRx object each). Only that call is "routing"; tick() is timed separately.
--objects times sim.exchange() instead, which makes a RadioRx per delivery (what the in-process
runner takes).

Channel models: log-distance with its default parameters (SINR with interference, shadowing,
CSMA, PER draws) and, for comparison, an infinite-range unit disk.

Usage: .venv/bin/python benchmarks/bench_radio.py [--repeat 3] [--agents 4,8,16,32,64] [--models log-distance,unit-disk]
       [--objects] [--plot docs/img/routing_scaling.png]
The CPU columns are the process's own CPU time (time.process_time) over the same calls: on a
shared machine the wall time includes waiting for a core, the CPU time much less so.
Timing only; nothing here is a pass/fail test.
"""

from __future__ import annotations

import os

from swarmloc.process import pin_blas

pin_blas()  # before numpy loads

import argparse
import platform
import statistics
import sys
import time
from datetime import date
from pathlib import Path

import numpy as np
from machine import code_version, cpu_model  # benchmarks/machine.py

from netsim import tune_gc
from netsim.sim import Simulation
from swarmloc.experiment.scenario import Scenario, parse
from swarmloc.node import RadioTx

MODELS = {
    "log-distance": {"model": "log-distance"},  # every parameter at its default
    "unit-disk": {"model": "unit-disk"},  # infinite range, no latency, no jitter
}
FRAME_BYTES = 60
SQUARE_M = 400.0
DT = 0.5
WARMUP_TICKS = 3
CALLS = {False: "exchange_batch(), as netsim's server calls it", True: "exchange(), a RadioRx per delivery"}
MAX_WALL_S = 120.0  # per configuration and repetition: a hard stop whatever --ticks says


def scenario(n: int, radio: dict, ticks: int, seed: int = 1) -> Scenario:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(0.0, SQUARE_M, size=(n, 2))
    heads = rng.uniform(0.0, 2 * np.pi, size=n)
    agents = [{"id": i + 1, "start": [float(x), float(y)], "heading": float(h),
               "motion": {"kind": "circle", "speed": 1.0, "turn_rate": 0.1}} for i, ((x, y), h) in enumerate(zip(pts, heads))]
    return parse({"version": 1, "name": f"bench-radio-{n}", "seed": seed,
                  "clock": {"mode": "lockstep", "dt": DT, "duration": (ticks + WARMUP_TICKS + 2) * DT},
                  "world": {"agents": agents}, "radio": radio}, source="bench_radio")


def ticks_for(n: int, base: int) -> int:
    # About the same number of receptions per configuration, at least 40 ticks.
    return max(40, base // n)


def run_one(n: int, model: str, ticks: int, objects: bool = False) -> dict:
    sim = Simulation(scenario(n, MODELS[model], ticks))
    payload = bytes(FRAME_BYTES)
    tick_s = exch_s = exch_cpu = tick_cpu = 0.0
    frames = receptions = delivered = done = 0
    started = time.perf_counter()
    for k in range(WARMUP_TICKS + ticks):
        c0, t0 = time.process_time(), time.perf_counter()
        sim.tick()
        c1, t1 = time.process_time(), time.perf_counter()
        batch = [RadioTx(a, None, k, payload) for a in sim.ids]
        log_before = len(sim.radio_log)
        c2, t2 = time.process_time(), time.perf_counter()
        out = sim.exchange(batch) if objects else sim.exchange_batch(batch)
        c3, t3 = time.process_time(), time.perf_counter()
        if k >= WARMUP_TICKS:
            tick_s += t1 - t0
            exch_s += t3 - t2
            tick_cpu += c1 - c0
            exch_cpu += c3 - c2
            frames += len(batch)
            receptions += len(sim.radio_log) - log_before  # one entry per (frame, receiver): delivered or dropped
            delivered += len(out)
            done += 1
        if time.perf_counter() - started > MAX_WALL_S:
            break
    return {"n": n, "model": model, "ticks": done, "frames": frames, "receptions": receptions,
            "delivered": delivered, "tick_s": tick_s, "exch_s": exch_s, "tick_cpu": tick_cpu, "exch_cpu": exch_cpu,
            "drops": dict(sim.radio_summary()["dropped"])}


def plot(summary: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4.2))
    colors = {"log-distance": "tab:blue", "unit-disk": "tab:orange"}
    for model in MODELS:
        rows = [r for r in summary if r["model"] == model]
        n = [r["n"] for r in rows]
        ax1.plot(n, [r["exch_ms_per_tick"] for r in rows], "o-", color=colors[model], label=f"{model}: exchange()")
        ax1.plot(n, [r["tick_ms_per_tick"] for r in rows], "s--", color=colors[model], alpha=0.6,
                 label=f"{model}: tick() (world + link table)")
        ax2.plot(n, [r["us_per_frame"] for r in rows], "o-", color=colors[model], label=f"{model}: per frame offered")
        ax2.plot(n, [r["us_per_rx"] for r in rows], "^:", color=colors[model], label=f"{model}: per reception")
    nmin, nmax = min(r["n"] for r in summary), max(r["n"] for r in summary)
    ref = min(r["exch_ms_per_tick"] for r in summary)
    ns = np.array([nmin, nmax], float)
    ax1.plot(ns, ref * (ns / nmin) ** 2, color="grey", lw=0.8, alpha=0.6, label="slope N$^2$")
    ax1.set(xscale="log", yscale="log", xlabel="agents (all broadcasting, one 60 B frame per tick)",
            ylabel="ms per tick", title="Cost per tick")
    ax2.set(xscale="log", yscale="log", xlabel="agents", ylabel="us", title="exchange() cost per frame / per reception")
    for ax in (ax1, ax2):
        ns_all = sorted({r["n"] for r in summary})
        ax.set_xticks(ns_all, [str(v) for v in ns_all])
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"netsim Simulation routing cost, median of repetitions ({date.today()})", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--agents", default="4,8,16,32,64", help="comma-separated swarm sizes")
    p.add_argument("--models", default=",".join(MODELS), help="comma-separated channel models")
    p.add_argument("--objects", action="store_true",
                   help="time exchange() (a RadioRx per delivery) instead of exchange_batch() (what netsim's server calls)")
    p.add_argument("--ticks", type=int, default=4000, help="measured ticks per config = max(40, TICKS / agents)")
    p.add_argument("--plot", type=Path, default=None, help="write the scaling plot here (PNG)")
    p.add_argument("--default-gc", action="store_true",
                   help="leave Python's garbage collector as it is (the netsim process tunes it: netsim.tune_gc)")
    a = p.parse_args()
    if not a.default_gc:
        tune_gc()
    load_start = os.getloadavg()[0]
    code_start = code_version()
    sizes = [int(v) for v in a.agents.split(",")]
    models = [m for m in a.models.split(",") if m]
    unknown = sorted(set(models) - set(MODELS))
    if unknown:
        p.error(f"unknown model(s) {', '.join(unknown)}: choose from {', '.join(MODELS)}")
    runs: list[dict] = []
    for rep in range(a.repeat):  # repetitions outermost: every configuration is measured side by side, in turn
        for n in sizes:
            for model in models:
                r = run_one(n, model, ticks_for(n, a.ticks), a.objects)
                runs.append(r)
                print(f"rep {rep + 1} n={n:3d} {model:12s} ticks={r['ticks']:4d} exchange {r['exch_s'] / r['ticks'] * 1e3:8.2f} ms/tick"
                      f" (CPU {r['exch_cpu'] / r['ticks'] * 1e3:.2f})  tick() {r['tick_s'] / r['ticks'] * 1e3:8.2f} ms/tick (CPU {r['tick_cpu'] / r['ticks'] * 1e3:.2f})  frames/s {r['frames'] / r['exch_s']:9.0f}"
                      f"  rx/s {r['receptions'] / r['exch_s']:9.0f}  delivered {r['delivered']}/{r['receptions']} drops {r['drops']}",
                      file=sys.stderr, flush=True)
    summary = []
    for n in sizes:
        for model in models:
            rs = [r for r in runs if r["n"] == n and r["model"] == model]
            med = lambda f: statistics.median(f(r) for r in rs)
            summary.append({
                "n": n, "model": model, "ticks": rs[0]["ticks"],
                "frames_per_s": med(lambda r: r["frames"] / r["exch_s"]),
                "rx_per_s": med(lambda r: r["receptions"] / r["exch_s"]),
                "exch_ms_per_tick": med(lambda r: r["exch_s"] / r["ticks"] * 1e3),
                "tick_ms_per_tick": med(lambda r: r["tick_s"] / r["ticks"] * 1e3),
                "exch_cpu_ms_per_tick": med(lambda r: r["exch_cpu"] / r["ticks"] * 1e3),
                "tick_cpu_ms_per_tick": med(lambda r: r["tick_cpu"] / r["ticks"] * 1e3),
                "both_frames_per_s": med(lambda r: r["frames"] / (r["exch_s"] + r["tick_s"])),
                "us_per_frame": med(lambda r: r["exch_s"] / r["frames"] * 1e6),
                "us_per_rx": med(lambda r: r["exch_s"] / r["receptions"] * 1e6),
                "delivered_pct": 100.0 * rs[0]["delivered"] / max(1, rs[0]["receptions"]),
                "spread_pct": 100.0 * (max(r["frames"] / r["exch_s"] for r in rs) - min(r["frames"] / r["exch_s"] for r in rs))
                / med(lambda r: r["frames"] / r["exch_s"]),
            })
    load_end = os.getloadavg()[0]
    argv = " ".join(sys.argv[1:])
    print(f"## Radio routing throughput, pure Simulation ({date.today()})\n")
    print(f"Machine: {os.cpu_count()} vCPU ({cpu_model()}), Python {platform.python_version()}, "
          f"numpy {np.__version__}, Linux {platform.release()}. "
          f"Code (last commit to netsim/, swarmloc/, agents/): {code_start if code_start == code_version() else code_start + ' at start, ' + code_version() + ' at end'}. Command: `.venv/bin/python benchmarks/bench_radio.py{(' ' + argv) if argv else ''}`. "
          f"1-min load average {load_start:.1f} at start, {load_end:.1f} at end (other work shares the machine).\n")
    print(f"{FRAME_BYTES} B broadcast per agent per tick, agents uniform in a {SQUARE_M:.0f} m square (seed 1), "
          f"medians of {a.repeat} repetitions; {WARMUP_TICKS} warm-up ticks not counted; "
          f"{CALLS[a.objects]}.\n")
    print("| agents | model | ticks | frames/s (exchange) | receptions/s (exchange) | exchange ms/tick | exchange CPU ms/tick "
          "| us/frame | us/reception | tick() ms/tick | tick() CPU ms/tick | frames/s incl. tick() | delivered | spread of frames/s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for s in summary:
        print(f"| {s['n']} | {s['model']} | {s['ticks']} | {s['frames_per_s']:,.0f} | {s['rx_per_s']:,.0f} | "
              f"{s['exch_ms_per_tick']:.2f} | {s['exch_cpu_ms_per_tick']:.2f} | {s['us_per_frame']:.0f} | {s['us_per_rx']:.1f} | "
              f"{s['tick_ms_per_tick']:.2f} | {s['tick_cpu_ms_per_tick']:.2f} | "
              f"{s['both_frames_per_s']:,.0f} | {s['delivered_pct']:.1f} % | {s['spread_pct']:.0f} % |")
    if a.plot:
        plot(summary, a.plot)
        print(f"\nPlot: `{a.plot}`.")


if __name__ == "__main__":
    main()
