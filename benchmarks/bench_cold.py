"""Benchmark: netsim's radio path for one frame, hot and with a pause between frames.

A real-time netsim sleeps between frames; a loop of calls back to back does not. This times
`Simulation.offer` and `Simulation.advance` of one unicast (the scalar path) on
bench_latency.py's two-agent scenario (unit disk, no modelled latency), in passes that
alternate: no pause, then `--sleep` seconds between frames, and so on. Medians of each call's
wall time over every frame of a kind. Timing only; nothing here is a pass/fail test.

Usage: .venv/bin/python benchmarks/bench_cold.py [--frames 1000] [--sleep 0.002] [--passes 3]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import tempfile
import time
from datetime import date
from pathlib import Path

from machine import cpu_model  # benchmarks/machine.py

from swarmloc.process import pin_blas

pin_blas()  # before numpy loads

import numpy as np  # noqa: E402
from bench_latency import scenario_yaml  # noqa: E402

from netsim.sim import Simulation  # noqa: E402
from swarmloc import wire  # noqa: E402
from swarmloc.experiment import scenario as S  # noqa: E402
from swarmloc.node import RadioTx  # noqa: E402
from swarmloc.wire.messages import Beacon  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=1000, help="frames a pass")
    p.add_argument("--sleep", type=float, default=0.002, help="s between frames in the paused passes")
    p.add_argument("--passes", type=int, default=3, help="passes of each kind, alternating")
    a = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "s.yaml"
        path.write_text(scenario_yaml(2, "realtime", 0.1, 1e6))
        sim = Simulation(S.load(str(path)))
    sim.tick()
    data = wire.encode(Beacon(0, np.zeros(2), np.eye(2), {}), 1, 1, 2)
    t, seq = 0.001, 0
    times: dict[str, tuple[list[float], list[float]]] = {"hot": ([], []), "paused": ([], [])}
    for kind in ["hot", "paused"] * a.passes:
        offer, advance = times[kind]
        for _ in range(a.frames):
            if kind == "paused":
                time.sleep(a.sleep)
            seq += 1
            t += 1e-5
            t0 = time.perf_counter()
            sim.offer(RadioTx(1, 2, seq, data), t)
            t1 = time.perf_counter()
            t += 1e-6
            got = sim.advance(t)
            t2 = time.perf_counter()
            assert len(got) == 1 and got[0].receiver == 2  # delivered: the path measured is the whole one
            offer.append(t1 - t0)
            advance.append(t2 - t1)
    print(f"# bench_cold ({date.today()}, {cpu_model()}, Python {platform.python_version()})\n")
    print(f"One unicast, `offer` then `advance`, {a.frames} frames a pass, {a.passes} passes of each kind "
          f"alternating; paused: {a.sleep * 1e3:g} ms between frames. Median us per call.\n")
    print("| frames | offer | advance | both |\n|---|---|---|---|")
    for kind, (offer, advance) in times.items():
        both = [x + y for x, y in zip(offer, advance)]
        print(f"| {kind} | {statistics.median(offer) * 1e6:.1f} | {statistics.median(advance) * 1e6:.1f} | "
              f"{statistics.median(both) * 1e6:.1f} |")


if __name__ == "__main__":
    main()
