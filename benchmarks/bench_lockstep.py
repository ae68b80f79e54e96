"""Benchmark: the full wang2019 run over Zenoh in lockstep (netsim + 4 agent processes).

Reports wall time, ticks per second and per-hop radio latency (agent publish -> netsim ->
receiving agent's loop) for several repetitions, plus the in-process runner on the same
scenario for scale. Usage: python benchmarks/bench_lockstep.py [--repeat 3] [--scenario wang2019]
Timing only; nothing here is a pass/fail test.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

from machine import cpu_model  # benchmarks/machine.py

from swarmloc.process import pin_blas

pin_blas()  # before numpy loads


def zenoh_run(scenario: str, out: Path) -> dict:
    cmd = [sys.executable, "-m", "agents", "run", scenario, "--out", str(out), "--port", "0", "--no-plots",
           "--swarm", f"bench{os.getpid()}"]
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    return json.loads((out / "metrics.json").read_text())


def in_process(scenario: str) -> float:
    from netsim.sim import Simulation
    from swarmloc.experiment import scenario as S
    from swarmloc.experiment.runner import InProcessRunner, make_nodes

    sc = S.load(scenario)
    t0 = time.perf_counter()
    InProcessRunner(Simulation(sc), make_nodes("ukf-dcl", sc)).run()
    return time.perf_counter() - t0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--scenario", default="wang2019")
    a = p.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(a.repeat):
            m = zenoh_run(a.scenario, Path(tmp) / f"r{i}")
            st = m["agent_stats"].values()
            rows.append({
                "wall_s": m["wall_time_s"], "ticks": m["ticks"], "ticks_per_s": m["ticks_per_s"],
                "frames": m["radio"]["delivered"],
                "hop_med_us": statistics.median(s["hop_us_median"] for s in st),
                "hop_p99_us": max(s["hop_us_p99"] for s in st),
                "netsim_med_us": m["radio"]["netsim_hop_us_median"], "netsim_p99_us": m["radio"]["netsim_hop_us_p99"],
            })
            print(f"run {i + 1}: {json.dumps({k: round(v, 1) for k, v in rows[-1].items()})}", file=sys.stderr)
    ip = [in_process(a.scenario) for _ in range(a.repeat)]
    med = lambda k: statistics.median(r[k] for r in rows)
    print(f"## {a.scenario} over Zenoh, lockstep ({date.today()})\n")
    print(f"Machine: {os.cpu_count()} vCPU ({cpu_model()}), Python {platform.python_version()}, "
          f"Linux {platform.release()}. Command: `python benchmarks/bench_lockstep.py --repeat {a.repeat}`.\n")
    print("| run | wall (s) | ticks | ticks/s | frames delivered | hop median (us) | hop p99 (us) | netsim internal median / p99 (us) |")
    print("|---|---|---|---|---|---|---|---|")
    for i, r in enumerate(rows, 1):
        print(f"| {i} | {r['wall_s']:.2f} | {r['ticks']} | {r['ticks_per_s']:.0f} | {r['frames']} | {r['hop_med_us']:.0f} | "
              f"{r['hop_p99_us']:.0f} | {r['netsim_med_us']:.0f} / {r['netsim_p99_us']:.0f} |")
    print(f"| **median** | **{med('wall_s'):.2f}** | | **{med('ticks_per_s'):.0f}** | | **{med('hop_med_us'):.0f}** | "
          f"**{med('hop_p99_us'):.0f}** | {med('netsim_med_us'):.0f} / {med('netsim_p99_us'):.0f} |")
    print(f"\nIn-process runner, same scenario and seed (same node code, no transport): median "
          f"{statistics.median(ip):.2f} s, i.e. {statistics.median(ip) / med('wall_s'):.2f}x the Zenoh wall time.")


if __name__ == "__main__":
    main()
