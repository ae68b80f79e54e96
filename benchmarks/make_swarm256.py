"""Writes the built-in scenario `swarm256` (swarmloc/experiment/scenarios/swarm256.yaml), so it
can be made again and checked: `python benchmarks/make_swarm256.py` rewrites the file;
`--check` exits 1 if the file differs from what this script writes.

The shape is `swarm32`'s and bench_scale.py's at constant density: N planar platforms uniform
in a square of side 40*sqrt(N) m (640 m for 256), random walks at 1 m/s, ranges within 80 m in N
slots per step with probability 0.5 (about one platform in two measures a neighbour per step),
a 120 m unit-disk radio; real time at dt 0.5 s for 60 s. Its estimator is RDL (pairwise: a
range costs the two platforms involved only), the one that keeps up at this size
(docs/benchmarks.md, "swarm256"), with a beacon every 3 ticks (about half the deliveries).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "swarmloc" / "experiment" / "scenarios" / "swarm256.yaml"
N, SEED = 256, 7

HEADER = """\
# 256 platforms over a 640 m square in real time (dt 0.5 s, 60 s): issue 29's `swarm256`.
# Written by benchmarks/make_swarm256.py (seed {seed}); edit that script, not this file.
# swarm32's shape at the same density: ranges within 80 m, about one platform in two measures
# one neighbour per step, a 120 m unit-disk radio. RDL (pairwise decentralized localization,
# docs/rdl.md): a range updates only the two platforms involved, so a platform's cost does not
# grow with the swarm. A beacon every 3 ticks (staggered): the same estimates with half the
# deliveries (docs/rdl.md#beacons). Run it several agents to a process: `swarmloc run swarm256
# --agents-per-process 32` (one process per agent would not fit in memory).
"""


def text() -> str:
    rng = np.random.default_rng(SEED)
    side = 40.0 * math.sqrt(N)
    pts, heads = rng.uniform(0, side, (N, 2)), rng.uniform(0, 2 * np.pi, N)
    lines = [HEADER.format(seed=SEED).rstrip("\n"),
             "version: 1",
             "name: swarm256",
             'description: "256 platforms in real time, RDL (pairwise: a range costs only the two platforms '
             'involved)"',
             f"seed: {SEED}",
             "clock: {mode: realtime, dt: 0.5, duration: 60}",
             "world:",
             "  agents:"]
    for i, ((x, y), h) in enumerate(zip(pts, heads)):
        lines.append(f"    - {{id: {i + 1}, start: [{x:.1f}, {y:.1f}], heading: {h:.2f}, "
                     "motion: {kind: random, speed: 1.0, turn_rate_std: 0.08}}")
    lines += ["sensors:",
              "  odometry: {speed_noise: 0.5, turn_rate_noise: 0.001}",
              f"  range: {{noise: 1.0, probability: 0.5, max_per_step: {N}, max_range: 80}}",
              "radio: {model: unit-disk, range_m: 120}",
              "estimation: {initial_std: 0.1}",
              "estimator: {name: rdl, params: {beacon_every: 3}}",
              "references: [il, ukf-ccl]"]
    return "\n".join(lines) + "\n"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="compare, do not write")
    a = p.parse_args()
    t = text()
    if a.check:
        same = OUT.is_file() and OUT.read_text() == t
        print(f"{OUT}: {'as written by this script' if same else 'DIFFERS from what this script writes'}")
        return 0 if same else 1
    OUT.write_text(t)
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
