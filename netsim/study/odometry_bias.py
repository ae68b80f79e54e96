"""The odometry bias states of ekf-ccl and ukf-ccl on a replay (docs/mrclam.md, "Odometry bias
states"): the sweep of their random-walk strengths, and the pick of one on a calibration span.

Why picked and not fitted: the two walk intensities say how fast a robot's speed scale and
turn-rate bias wander, which no single residual pins down (the calibration's residuals mix the
wander with the command table's errors and with Vicon's). So each setting of a small grid is
scored on the calibration span itself, the span its noise model was fitted on, and the one
with the smallest position RMSE among those whose mean NEES is at most `NEES_TARGET` is then
scored on data that neither the noise model nor the pick saw.
"""

from __future__ import annotations

import numpy as np

ESTIMATORS = ("ekf-ccl", "ukf-ccl")
SPEED_SCALE_WALKS = (1e-6, 1e-5, 1e-4)      # 1/s: the scale factor's variance gained per second
TURN_RATE_BIAS_WALKS = (1e-7, 1e-6, 1e-5)   # (rad/s)^2 per s
NEES_TARGET = 6.0  # twice the pose's dimension (issue 24's bound)
OFF = {"odometry_bias": False}


def grid() -> list[dict]:
    """The settings swept: no bias states, then every pair of walk intensities."""
    return [dict(OFF)] + [{"odometry_bias": True, "speed_scale_walk": sv, "turn_rate_bias_walk": sw}
                          for sv in SPEED_SCALE_WALKS for sw in TURN_RATE_BIAS_WALKS]


def label(params: dict) -> str:
    if not params["odometry_bias"]:
        return "off"
    return f"{params['speed_scale_walk']:g} / {params['turn_rate_bias_walk']:g}"


def score(sc, settings: list[dict], names=ESTIMATORS) -> list[tuple[str, dict, dict, float]]:
    """Each of `names` with each of `settings` on one replay of scenario sc (its frames computed
    once): [(name, params, metrics, share of robot-ticks whose NEES is under chi2(3)'s 97.5 %
    quantile)]."""
    import scipy.stats

    from netsim.sim import Simulation
    from swarmloc.estimators import REGISTRY
    from swarmloc.experiment.results import RunRecord, metrics, nees_series
    from swarmloc.experiment.runner import InProcessRunner

    record = InProcessRunner(Simulation(sc), {}).run(RunRecord.for_scenario(sc))
    out = []
    for params in settings:
        for name in names:
            record.est.pop(name, None), record._nis.pop(name, None)  # the previous setting's estimates
            ref = REGISTRY[name].make_reference(sc, record.ids, REGISTRY[name].settings(params))
            for frames in record.sensors:
                ref.step(frames)
                for a in record.ids:
                    record.add_estimate(name, a, ref.estimate(a))
            ne = nees_series(record, record.trace(name))
            ne = ne[np.isfinite(ne)]
            out.append((name, params, metrics(record, [name])["estimators"][name],
                        float(np.mean(ne <= scipy.stats.chi2.ppf(0.975, 3)))))
    return out


def pick(scored, names=ESTIMATORS) -> dict[str, dict]:
    """Per estimator, the setting of `scored` (score()'s rows on the calibration span) with the
    smallest position RMSE among the bias settings whose mean NEES is at most NEES_TARGET, else
    the one with the smallest NEES."""
    out = {}
    for name in names:
        cand = [(p, m) for n, p, m, _ in scored if n == name and p["odometry_bias"]]
        ok = [c for c in cand if c[1]["nees"]["mean"] <= NEES_TARGET]
        out[name] = (min(ok, key=lambda c: c[1]["rmse_m"]) if ok else min(cand, key=lambda c: c[1]["nees"]["mean"]))[0]
    return out


def pooled(ms: list[dict]) -> dict:
    """Metrics of several scored spans taken together: RMSEs and NEES averaged over every tick."""
    def counts(m):
        return sum(m["agents"][a]["nees"]["n"] for a in m["agents"] if m["agents"][a]["nees"])

    n = [counts(m) for m in ms]
    tot = sum(n)
    rmse = float(np.sqrt(sum(k * m["rmse_m"] ** 2 for k, m in zip(n, ms)) / tot))
    head = float(np.sqrt(sum(k * m["heading_rmse_rad"] ** 2 for k, m in zip(n, ms)) / tot))
    nees = sum(k * m["nees"]["mean"] for k, m in zip(n, ms)) / tot
    return {"rmse_m": rmse, "heading_rmse_rad": head, "nees": {"mean": nees}}
