"""CSL-CTL's covariance with and without the target ranges' noise in the unscented transform,
and with and without the heading in the agents' state.

The paper's U-transform (section 2.4) spans the agents' positions only (4N+1 sigma points);
`estimator.params.ut_noise: false` does the same. This runs the offline CSL-CTL reference on
wang2022 over seeds, both ways and for both readings of the paper's gyro noise, and prints the
target's NEES (2 dof; a consistent filter averages 2) and final error. Then the same seeds
with the agents on the position-only model of the 2019 paper (planar-speed-heading) against
planar-pose: the agents' own NEES under dead reckoning and the CSL-CTL target error.

    .venv/bin/python benchmarks/wang2022_ut_noise.py --seeds 6
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from netsim.sim import Simulation  # noqa: E402
from swarmloc.estimators.ctl.csl_ctl import JointCslCtl  # noqa: E402
from swarmloc.estimators.settings import CtlSettings  # noqa: E402
from swarmloc.experiment import scenario as S  # noqa: E402


def frames_and_truth(sc):
    sim = Simulation(sc)
    frames_of, truth = [], []
    for _ in range(sim.steps + 1):
        _, _, frames = sim.tick()
        frames_of.append(frames)
        truth.append((sim.truth(), sim.targets()[0]))
    return frames_of, truth


def run(sc, frames_of, truth, settings=None) -> tuple[float, float, float]:
    """Target NEES mean, final target error, agents' mean NEES per state dof of CSL-CTL."""
    joint = JointCslCtl.from_scenario(sc, sc.localized_ids, settings)
    nees, err, own = [], np.nan, []
    for frames, (states, o) in zip(frames_of, truth):
        joint.step(frames)
        for a in sc.localized_ids:
            b = joint.block(a)
            e = joint.model.error(states[a], joint.x[b])
            own.append(e @ np.linalg.solve(joint.P[b, b], e) / e.size)
        if joint.targets:
            b = joint.block(("target", 0))
            e = joint.x[b] - o
            nees.append(e @ np.linalg.solve(joint.P[b, b], e))
            err = np.linalg.norm(e)
    return float(np.mean(nees)), float(err), float(np.mean(own[len(sc.localized_ids):]))


def models(seeds: int) -> None:
    print("\n| agents' model | CSL-CTL agents' NEES / dof | target NEES | final target error (m) |")
    print("|---|---|---|---|")
    for model in ("planar-pose", "planar-speed-heading"):
        rows = []
        for seed in range(1, seeds + 1):
            data = S.load("wang2022").model_dump()
            data["seed"] = seed
            for a in data["world"]["agents"]:
                a["model"] = model
            sc = S.parse(data)
            rows.append(run(sc, *frames_and_truth(sc)))
        a = np.array(rows)
        print(f"| {model} | {a[:, 2].mean():.2f} | {a[:, 0].mean():.2f} | {a[:, 1].mean():.2f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=6)
    args = ap.parse_args()
    print("| gyro noise (rad/s) | ut_noise | target NEES, mean of seeds | per seed | final target error (m), mean |")
    print("|---|---|---|---|---|")
    for reading in (0.05, 0.0025):
        rows: dict[bool, list] = {True: [], False: []}
        for seed in range(1, args.seeds + 1):
            sc = S.load("wang2022").with_overrides(**{"seed": seed, "sensors.odometry.turn_rate_noise": reading})
            data = frames_and_truth(sc)
            for noise in (True, False):
                nees, err, _ = run(sc, *data, CtlSettings(ut_noise=noise))
                rows[noise].append((nees, err))
        for noise, r in rows.items():
            a = np.array(r)
            print(f"| {reading} | {str(noise).lower()} | {a[:, 0].mean():.2f} | {' '.join(f'{v:.2f}' for v in a[:, 0])} "
                  f"| {a[:, 1].mean():.2f} |")
    models(args.seeds)


if __name__ == "__main__":
    main()
