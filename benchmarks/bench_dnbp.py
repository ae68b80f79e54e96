"""dNBP cost: one filtering step of a fault UAV against M and its neighbours, and the bytes and
airtime of a belief on the wire.

One filtering step is what a fault UAV computes in one time slice (Wan et al. 2014, Table 1's
"time per step"): the particle-filter prediction, a ring message for each neighbour's belief,
and the belief by mixture importance sampling (`DnbpNode.step` then `receive` of each
neighbour's belief, with the send of its own). Medians of repeated steps on fresh nodes.

    .venv/bin/python benchmarks/bench_dnbp.py
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402

from benchmarks.machine import code_version, cpu_model  # noqa: E402
from netsim.channel import LogDistance  # noqa: E402
from swarmloc import wire  # noqa: E402
from swarmloc.estimators.nbp import mixtures as nbp
from swarmloc.estimators.nbp.dnbp import DnbpNode  # noqa: E402
from swarmloc.wire.messages import NbpBelief, OdometryMsg, RangeMsg, Sensors  # noqa: E402


def belief_of(centre: np.ndarray, M: int, rng, d: int = 2) -> NbpBelief:
    g = nbp.GaussianMixture.from_samples(centre + rng.normal(0.0, 3.0, (M, d)))
    return NbpBelief(1, 0, True, g.means.astype(np.float32), g.weights.astype(np.float32), g.bandwidth)


def one_step(M: int, k: int, rng, seed: int) -> float:
    """Seconds of one slice of a fault UAV at the origin with k normal neighbours 150 m away."""
    node = DnbpNode(99, np.zeros(2), np.eye(2) * 300.0**2, M=M, iterations=1, seed=seed)
    node.step(Sensors(0, 0.0, OdometryMsg(0.0, 0.0, 0.0, 0.0, 0.0), []))
    angles = 2 * np.pi * np.arange(k) / k + 0.3
    where = 150.0 * np.column_stack([np.cos(angles), np.sin(angles)])
    frame = Sensors(1, 1.0, OdometryMsg(1.0, 10.0, 0.4, 0.5, 0.01),
                    [RangeMsg(j, float(np.linalg.norm(w)) + rng.normal(0, 2.0), 2.0) for j, w in enumerate(where)])
    beliefs = [belief_of(w, M, rng) for w in where]
    t0 = time.perf_counter()
    node.step(frame)
    for j, b in enumerate(beliefs):
        node.receive(j, b)
    if not node.final:
        node._form(late=True)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=15)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    print("## dNBP: one filtering step of a fault UAV, and a belief on the wire\n")
    print(f"Machine: {cpu_model()}, {os.cpu_count()} CPUs, Python {platform.python_version()}, numpy {np.__version__}, "
          f"one BLAS thread; code {code_version()}; {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC.  ")
    print(f"Command: `python benchmarks/bench_dnbp.py --reps {args.reps}`; median of {args.reps} steps, each on a "
          "fresh node (prediction, a ring per neighbour, the belief, and its send).\n")
    print("| M | neighbours | step ms (median) | min ms |")
    print("|---|---|---|---|")
    for M in (100, 300, 1000):
        for k in (2, 4, 8):
            times = [one_step(M, k, rng, seed) for seed in range(args.reps)]
            print(f"| {M} | {k} | {1e3 * statistics.median(times):.2f} | {1e3 * min(times):.2f} |")
    radio = LogDistance()
    print("\nBytes and airtime of one `nbp.belief` frame (envelope included) on the default log-distance radio "
          f"({radio.bitrate_bps / 1e6:g} Mbit/s):\n")
    print("| M | d | bytes | airtime ms |")
    print("|---|---|---|---|")
    for M, d in ((100, 2), (300, 2), (1000, 2), (300, 3), (1000, 3)):
        size = len(wire.encode(belief_of(np.zeros(d), M, rng, d), 1, 1))
        print(f"| {M} | {d} | {size} | {1e3 * radio.airtime_s(size):.2f} |")


if __name__ == "__main__":
    main()
