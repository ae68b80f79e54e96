"""Benchmark: what run.mcap costs a lockstep run (issue: MCAP, Foxglove, ROS 2).

Runs the scenario over Zenoh (netsim + agent processes) with and without the recording, in
turn (A B B A A B ...), and reports ticks/s from each run's metrics.json, the ratio pair by pair
(pairing keeps it meaningful while the machine's speed drifts), the CPU each run took (netsim,
agents and launcher together) and the recording's size.
Usage: python benchmarks/bench_recording.py [--pairs 5] [--scenario wang2019]
Timing only; nothing here is a pass/fail test.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
from datetime import date
from pathlib import Path

from machine import cpu_model  # benchmarks/machine.py


def run(scenario: str, out: Path, record: bool) -> dict:
    cmd = [sys.executable, "-m", "agents", "run", scenario, "--out", str(out), "--port", "0", "--no-plots", "--force",
           "--swarm", f"benchrec{os.getpid()}", *([] if record else ["--no-record"])]
    # The launcher waits for netsim and its agents, so their CPU is in its children's usage.
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    m = json.loads((out / "metrics.json").read_text())
    mcap = out / "run.mcap"
    return {"ticks_per_s": m["ticks_per_s"], "ticks": m["ticks"], "mcap_bytes": mcap.stat().st_size if mcap.exists() else 0,
            "frames": m.get("recording", {}).get("frames", 0),
            "cpu_s": after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime}


def recorder_cost(recording: Path, repeat: int = 3) -> dict:
    """netsim's recording work, alone: every wire frame of a finished run's run.mcap logged again
    and each tick's view (truth, estimates with their error and NEES, links, scene) made again,
    through a fresh Recorder deferred as netsim's is, timed per tick (the frames are decoded
    beforehand: netsim has them decoded already): the calls, which hold the work (netsim makes
    them in its loop), and the drain, which does it (netsim's idle time). The best of `repeat`
    passes, as the least disturbed by the machine."""
    import time

    import msgspec

    from swarmloc import wire
    from swarmloc.experiment import recording as R
    from swarmloc.wire.messages import EstimateMsg, Links, Truth

    run = R.load(recording)
    sc = run.scenario
    ticks: dict[int, list] = {}
    for m in R.messages(recording):
        if m.encoding == R.WIRE_ENCODING:
            ticks.setdefault(m.log_time, []).append((m.topic, m.data))
    order = sorted(ticks)
    work = []
    for lt in order:
        truth, ests, links = {}, [], None
        for topic, data in ticks[lt]:
            if "/truth/" in topic:
                b = wire.decode(data, expect=(Truth,)).body
                truth[int(topic.rsplit("/", 1)[1])] = (b.k, b.t, b.state)
            elif topic.endswith("/estimate"):
                env = wire.decode(data, expect=(EstimateMsg,))
                ests.append((env.src, env.body))
            elif topic.endswith("/netsim/links"):
                links = [msgspec.structs.asdict(r) for r in wire.decode(data, expect=(Links,)).body.links]
        work.append((ticks[lt], truth, ests, links))
    best, best_hold = float("inf"), float("inf")
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeat):
            rec = R.Recorder(Path(tmp) / "again.mcap", {"writer": "bench", "scenario": sc.to_yaml()}, sc, deferred=True)
            hold = 0.0
            t0 = time.perf_counter()
            for frames, truth, ests, links in work:
                t1 = time.perf_counter()
                for topic, data in frames:
                    rec.frame(topic, data, 0.0)
                if truth:
                    k, t, _ = next(iter(truth.values()))
                    rec.truth(k, t, {a: s for a, (_, _, s) in truth.items()}, {})
                    for a, e in ests:
                        rec.estimate(e.algorithm, a, e.k, t, e.mean, e.cov)
                    if links is not None:
                        rec.links(links)
                    rec.end_tick(k, t)
                hold += time.perf_counter() - t1
                rec.drain()
            rec.close()
            best = min(best, time.perf_counter() - t0)
            best_hold = min(best_hold, hold)
    frames = sum(len(w[0]) for w in work)
    return {"ticks": len(work), "frames": frames, "us_per_tick": best / len(work) * 1e6,
            "hold_us_per_tick": best_hold / len(work) * 1e6}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--pairs", type=int, default=5)
    p.add_argument("--scenario", default="wang2019")
    p.add_argument("--cost-only", metavar="RUN_MCAP", help="only the recording's own work, on this recording")
    a = p.parse_args()
    if a.cost_only:
        c = recorder_cost(Path(a.cost_only))
        print(f"{c['us_per_tick']:.0f} us per tick ({c['hold_us_per_tick']:.0f} holding the calls), "
              f"{c['frames'] / c['ticks']:.0f} frames a tick, {c['ticks']} ticks")
        return
    rows = []
    tmp = Path(tempfile.mkdtemp(prefix="bench_recording-"))  # kept: the last recording is timed alone below
    for i in range(a.pairs):
        # A B, then B A: whichever runs second in a pair meets what the first left (page cache,
        # a machine warmed or loaded by it), so neither side always does.
        if i % 2 == 0:
            on = run(a.scenario, tmp / "on", True)
            off = run(a.scenario, tmp / "off", False)
        else:
            off = run(a.scenario, tmp / "off", False)
            on = run(a.scenario, tmp / "on", True)
        rows.append((on, off))
        print(f"pair {i + 1}: recording {on['ticks_per_s']:.1f} ticks/s, none {off['ticks_per_s']:.1f}", file=sys.stderr)
    ratios = [on["ticks_per_s"] / off["ticks_per_s"] for on, off in rows]
    print(f"## run.mcap in a lockstep {a.scenario} run ({date.today()})\n")
    print(f"Machine: {os.cpu_count()} vCPU ({cpu_model()}), Python {platform.python_version()}, "
          f"Linux {platform.release()}. Command: `python benchmarks/bench_recording.py --pairs {a.pairs}`.\n")
    print("| pair | ticks/s with run.mcap | ticks/s with --no-record | ratio | CPU s with | CPU s without |")
    print("|---|---|---|---|---|---|")
    for i, ((on, off), r) in enumerate(zip(rows, ratios), 1):
        print(f"| {i} | {on['ticks_per_s']:.1f} | {off['ticks_per_s']:.1f} | {r:.3f} | {on['cpu_s']:.2f} | "
              f"{off['cpu_s']:.2f} |")
    med = lambda xs: statistics.median(xs)  # noqa: E731
    print(f"| **median** | **{med([on['ticks_per_s'] for on, _ in rows]):.1f}** | "
          f"**{med([off['ticks_per_s'] for _, off in rows]):.1f}** | **{med(ratios):.3f}** | "
          f"**{med([on['cpu_s'] for on, _ in rows]):.2f}** | **{med([off['cpu_s'] for _, off in rows]):.2f}** |")
    cpu = [on["cpu_s"] / off["cpu_s"] for on, off in rows]
    print(f"\nCPU with the recording over CPU without, pair by pair: median {med(cpu):.3f} "
          f"({min(cpu):.3f}-{max(cpu):.3f}).")
    on = rows[-1][0]
    print(f"\nrun.mcap: {on['frames']} wire frames of {on['ticks']} ticks, {on['mcap_bytes'] / 1e6:.2f} MB (lz4).")
    c = recorder_cost(tmp / "on" / "run.mcap")
    tick_us = 1e6 / statistics.median(off["ticks_per_s"] for _, off in rows)
    print(f"\nThe recording's own work in netsim (every frame logged, each tick's view made; "
          f"`recorder_cost`, best of 3): {c['us_per_tick']:.0f} us per tick for {c['frames'] / c['ticks']:.0f} "
          f"frames a tick, {100 * c['us_per_tick'] / tick_us:.1f} % of a tick of the runs without it "
          f"({tick_us:.0f} us); of it, in netsim's loop (the calls, which hold the work for its idle time): "
          f"{c['hold_us_per_tick']:.0f} us, {100 * c['hold_us_per_tick'] / tick_us:.1f} %.")
    shutil.rmtree(tmp)

if __name__ == "__main__":
    main()
