"""The scenario `swarmloc replay` runs: an MR.CLAM recording replayed through the agents, with
the span it scores and the part of the recording its noise model is fitted on.

A scenario file can name a recording itself (`world: {source: mrclam, ...}`); filling in what
such a file leaves out (agents, landmarks, duration) is part of parsing it, in scenario.py.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

from swarmloc.datasets.calibrate import NoiseModel
from swarmloc.experiment.scenario import SCENARIO_VERSION, Scenario, ScenarioError, parse, recording

REPLAY_REFERENCES = ("il", "ekf", "ekf-ccl", "ukf-ccl")
BIAS_ESTIMATORS = ("ukf-dcl", "ekf-ccl", "ukf-ccl")
"""Estimators with per-robot odometry bias states (OdometryBiasSettings): UKF-DCL and its references."""
CALIBRATIONS = ("held-out", "scored", "none")


def replay_spans(rec, duration: float | None, offset: float | None, calibration: str, noise=None,
                 min_calibration: float | None = None) -> tuple[float, float | None, list[tuple[float, float]] | None]:
    """(offset, duration, calibration windows) of a replay: what it scores and what its noise is
    fitted on, in seconds from the recording's start (windows None: nothing to fit here).

    Given a span (offset and/or duration), it is scored. Otherwise: with a noise model of the
    same recording, the longest part outside the model's windows (all of it if none is left);
    with calibration "held-out", the second half, the first calibrating it. "held-out" fits on
    what the scored span leaves (at least min_calibration s of it, default two horizons per
    cross-validation block); "scored" on the scored span."""
    from swarmloc.datasets import calibrate

    if min_calibration is None:
        min_calibration = 2 * calibrate.FOLDS * calibrate.HORIZON
    total = rec.duration
    if offset is None and duration is None:
        if noise is not None:
            if noise.recording == rec.source.name:
                gaps = [(a, b) for a, b in _outside(noise.windows, total) if b - a >= calibrate.MIN_WINDOW]
                if gaps:
                    offset, end = max(gaps, key=lambda g: g[1] - g[0])
                    duration = end - offset
        elif calibration == "held-out":
            (lo, hi), (offset, end) = calibrate.held_out_split(total)
            return offset, end - offset, [(lo, hi)]
    offset = 0.0 if offset is None else float(offset)
    end = total if duration is None else offset + float(duration)
    if offset >= total or end > total + 1e-9:
        return offset, duration, None  # the scenario says what is wrong with the span
    if noise is not None or calibration == "none":
        return offset, duration, None
    if calibration == "scored":
        return offset, duration, [(offset, min(end, total))]
    windows = calibrate.complement(total, offset, min(end, total))
    left = sum(b - a for a, b in windows)
    if left < min_calibration:
        raise ScenarioError(f"only {left:.1f} s of the recording lies outside the scored {offset:g}-{end:g} s: too "
                            f"little to calibrate on (at least {min_calibration:g} s); pass a noise model (--noise) or "
                            "fit on the scored data (--fit-on-scored)")
    return offset, duration, windows


def _outside(windows, total: float) -> list[tuple[float, float]]:
    out, at = [], 0.0
    for a, b in sorted(windows):
        if a > at:
            out.append((at, a))
        at = max(at, b)
    if at < total:
        out.append((at, total))
    return out


def replay_scenario(path, *, estimator: str = "ukf-dcl", dt: float = 0.1, duration: float | None = None,
                    offset: float | None = None, robots: list[int] | None = None, landmarks: bool = True,
                    observations: bool = True, gate: float | None = 0.999, mode: str = "lockstep",
                    speed: float = 1.0, seed: int = 0, noise=None, calibration: str = "held-out",
                    horizon: float | None = None, odometry_horizon: float | None = None,
                    odometry_bias: bool = False) -> Scenario:
    """The scenario `swarmloc replay` runs: the recording at `path` replayed at ticks of dt, the
    agents running `estimator` and the offline references beside it, its noise model
    (swarmloc.datasets.calibrate) fitted on a part of the recording it does not score (calibration
    "held-out", the default: replay_spans says which), on the scored part ("scored"), or given
    (`noise`, a NoiseModel). The scenario's description says which (`replay_label`).

    calibration "none", a swarmloc.datasets.mrclam.NoiseFit as `noise`, or an `odometry_horizon`: the
    model before calibration, white noise pooled over the robots and fitted on the whole
    recording (mrclam.fit_noise, odometry tick by tick or over odometry_horizon s).

    `odometry_bias`: the references ekf-ccl and ukf-ccl, and the agents' ukf-dcl, with their
    per-robot odometry bias states at their default walks (OdometryBiasSettings, docs/mrclam.md)."""
    from swarmloc.datasets import calibrate, mrclam
    from swarmloc.estimators import REGISTRY

    if calibration not in CALIBRATIONS:
        raise ScenarioError(f"calibration {calibration!r}: one of {CALIBRATIONS}")
    legacy = isinstance(noise, mrclam.NoiseFit) or odometry_horizon is not None or calibration == "none"
    p = Path(path).expanduser().resolve()
    try:
        rec = recording(str(p))
    except mrclam.MrclamError as exc:
        raise ScenarioError(str(exc)) from None
    model = noise if isinstance(noise, NoiseModel) else None
    offset, duration, windows = replay_spans(rec, duration, offset, "none" if legacy else calibration, model)
    # Robots the recording lacks: no calibration, the scenario's check below names them.
    if model is None and not legacy and windows is not None and not set(robots or ()) - set(rec.robots):
        try:
            model = calibrate.calibrate(rec, windows, dt, calibrate.HORIZON if horizon is None else horizon,
                                        robots=robots)
        except calibrate.CalibrationError as exc:
            raise ScenarioError(f"{p}: calibration: {exc}") from None
    fit = None
    if legacy:
        fit = noise if isinstance(noise, mrclam.NoiseFit) else mrclam.fit_noise(rec, dt, horizon=odometry_horizon)
    end = rec.duration if duration is None else offset + duration
    clock = {"mode": mode, "dt": dt, "speed": speed, **({"duration": duration} if duration is not None else {})}
    world = {"source": "mrclam", "path": str(p), "offset": offset, **({"robots": robots} if robots else {}),
             "noise": model}
    if isinstance(noise, mrclam.NoiseFit):
        what = f"noise: white, pooled over the robots (given, uncalibrated); scored on {offset:.1f}-{end:.1f} s"
    elif legacy:
        what = (f"noise fitted on the scored data: white, pooled over the robots against the whole recording's Vicon "
                f"(uncalibrated); scored on {offset:.1f}-{end:.1f} s")
    else:
        what = calibrate.label(model, p.name, offset, end)
    sensors = {"range_bearing": {"robots": observations, "landmarks": landmarks}}
    if fit is not None:
        sensors["odometry"] = {"speed_noise": fit.speed, "turn_rate_noise": fit.turn_rate}
        sensors["range_bearing"].update(range_noise=fit.range, bearing_noise=fit.bearing)
    data = {
        "version": SCENARIO_VERSION, "name": re.sub(r"[^A-Za-z0-9_.-]", "_", f"replay-{p.name}"),
        "description": f"MR.CLAM recording {p.name} replayed (Leung et al., IJRR 2011); {what}", "seed": seed,
        "clock": clock, "world": world, "sensors": sensors,
        "radio": {"model": "unit-disk", "range_m": math.inf},
        "estimation": {"initial_std": 0.02, "initial_heading_std": 0.02, "gate": gate},
        "estimator": {"name": estimator},
        "references": [r for r in REPLAY_REFERENCES if r != estimator and "planar-pose" in REGISTRY[r].models],
    }
    if odometry_bias:
        data["reference_params"] = {r: {"odometry_bias": True} for r in BIAS_ESTIMATORS if r in data["references"]}
        if estimator in BIAS_ESTIMATORS:  # the agents' filter with the model of its references
            data["estimator"]["params"] = {"odometry_bias": True}
    return parse(data, f"replay of {p}")


def replay_label(scenario: Scenario) -> str:
    """What a replay's noise was fitted on and what it scores (one line, for its output)."""
    from swarmloc.datasets import calibrate

    w = scenario.world
    if w.source != "mrclam":
        return ""
    end = w.offset + scenario.clock.duration
    biased = [r for r, params in scenario.reference_params.items() if params.get("odometry_bias")]
    if scenario.estimator.params.get("odometry_bias"):
        biased.insert(0, scenario.estimator.name)
    names = ", ".join(biased[:-1]) + (" and " if len(biased) > 1 else "") + (biased[-1] if biased else "")
    extra = f"; {names} with odometry bias states" if biased else ""
    if w.noise is None:
        _, sep, what = scenario.description.partition("; noise")
        return (("noise" + what) if sep else calibrate.label(None, Path(w.path).name, w.offset, end)) + extra
    return calibrate.label(w.noise, Path(w.path).name, w.offset, end) + extra
