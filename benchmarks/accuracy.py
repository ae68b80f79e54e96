"""Accuracy figures quoted in docs/ukf-dcl.md (not timings): UKF-DCL against UKF-CCL and IL.

Usage: python benchmarks/accuracy.py     (about a minute; in-process runner, no Zenoh)
"""

from __future__ import annotations

from swarmloc.process import pin_blas

pin_blas()  # before numpy loads

import numpy as np  # noqa: E402

from netsim.sim import Simulation  # noqa: E402
from swarmloc.experiment import scenario as S  # noqa: E402
from swarmloc.experiment.results import compute_references, metrics  # noqa: E402
from swarmloc.experiment.runner import InProcessRunner, make_nodes  # noqa: E402

ALGS = ["il", "ukf-dcl", "ukf-ccl"]


def run(sc):
    nodes = make_nodes("ukf-dcl", sc)
    record = InProcessRunner(Simulation(sc), nodes).run()
    compute_references(sc, record)
    return metrics(record, ALGS), nodes, record


def main() -> None:
    m, _, rec = run(S.load("wang2019"))
    a, b = rec.trace("ukf-dcl"), rec.trace("ukf-ccl")
    print("wang2019 mean error (m):", {k: round(v["mean_error_m"], 2) for k, v in m["estimators"].items()})
    print("  per agent UKF-DCL:", {k: round(v["mean_error_m"], 2) for k, v in m["estimators"]["ukf-dcl"]["agents"].items()})
    print(f"  |UKF-DCL - UKF-CCL| max: mean {np.abs(a.mean - b.mean).max():.1e}, cov {np.abs(a.cov - b.cov).max():.1e}")
    print("Fig. 7 trend, 5 seeds: p, UKF-DCL error, IL error, UKF-DCL mean NEES")
    base = S.load("wang2019")
    for p in (0.05, 0.1, 0.2, 0.5, 1.0):
        runs = [run(base.with_overrides(**{"sensors.range.probability": p, "seed": s}))[0]["estimators"] for s in range(1, 6)]
        dcl = np.mean([r["ukf-dcl"]["mean_error_m"] for r in runs])
        il = np.mean([r["il"]["mean_error_m"] for r in runs])
        nees = np.mean([np.mean([x["mean_nees"] for x in r["ukf-dcl"]["agents"].values()]) for r in runs])
        print(f"  {p:<5} {dcl:.2f} {il:.2f} {nees:.2f}")
    nees, err = {k: [] for k in ALGS}, {k: [] for k in ALGS}
    for seed in range(1, 11):
        m, _, _ = run(S.load("random7").with_overrides(**{"radio.range_m": 60.0, "seed": seed}))
        for k in ALGS:
            nees[k] += [v["mean_nees"] for v in m["estimators"][k]["agents"].values()]
            err[k].append(m["estimators"][k]["mean_error_m"])
    print("random7, 60 m radio, 10 seeds:", {k: f"error {np.mean(err[k]):.2f} m, NEES {np.mean(nees[k]):.2f}" for k in ALGS})
    m, nodes, _ = run(S.load("wang2019").with_overrides(**{"clock.duration": 2400.0, "radio.range_m": 150.0}))
    print("wang2019, 2400 s, 150 m radio:", {k: round(v["mean_error_m"], 2) for k, v in m["estimators"].items()},
          "NEES", [round(v["mean_nees"], 2) for v in m["estimators"]["ukf-dcl"]["agents"].values()],
          "outsider commits", sum(n.stats["outsider_commits"] for n in nodes.values()),
          "orphaned", sum(n.stats["orphaned"] for n in nodes.values()))


if __name__ == "__main__":
    main()
