"""Noise models of a recording, fitted against its own ground truth (`swarmloc calibrate`).

A recorded robot's sensors are not the white-noise sensors an estimator assumes (docs/replay.md,
"Noise, calibrated against Vicon"): on MR.CLAM the robot turns and drives other than commanded
in a way that depends on the command, the recorded range is close to the distance along the
camera's axis rather than to the target, and what is left over is correlated in time. A
`NoiseModel` describes, per robot,

- its odometry: the lags by which the forward and the angular velocity commands lead the motion,
  a table of corrections added to each command (the median difference between the motion and
  the command in a cell of (command speed, command turn rate)), and the std of what is left;
- its camera, for landmarks and for robots apart: the range error as a function of the
  measured range r and bearing b, a0 + a1 r + a2 r b + a3 r b^2, the bearing error as
  c0 + c1 b + c2 b^2, and the std of what is left (the range's in proportion to the range).

netsim's replay world (netsim/world/recorded.py) plays a recording through such a model: it corrects
each reading and states each std in the frame, as a calibrated sensor driver would; the
estimators are unchanged.

How each number is fitted (`calibrate`), all against the recording's Vicon truth, on the given
windows only:

- lags: `mrclam.estimate_odometry_lag` on the speed and on the turn rate, over the windows
  (the turn rate's own only where it fits significantly better: `turn_rate_lag`);
- the command table: per cell of 0.01 m/s x 0.05 rad/s with at least MIN_CELL ticks, the
  median of (truth - command); a command in no such cell is left as it is (a speed-only
  fallback for those shrinks the stds and does not keep Dataset6 consistent: docs/replay.md);
- the bias coefficients: least squares, iterated with the residuals beyond GATE_Z robust
  stds left out (those the replay's 0.999 gate rejects are not the Gaussian core);
- which of them: among nested models (the range's: none, a0, a0 + a1 r, all four terms; the
  bearing's: none, c0, c0 + c1 b, all three; the odometry's: no table or the table), the
  one whose cross-validated residuals (below) imply the smallest white-equivalent std. A
  short window seen from a narrow spread of ranges and bearings keeps a simple model;
- the stds, white-equivalent at `horizon` seconds: the residuals of each channel (a tick's
  speed and turn rate; an observation's relative range error and bearing error) are summed
  over consecutive batches of `horizon` seconds, and std^2 = sum of the squared batch sums /
  the number of residuals summed (batches overlapping, one starting every tick). For white residuals that is their variance; for residuals
  correlated over less than the horizon it is their long-run variance (the spectral density at
  zero frequency: the batch-means estimator of simulation output analysis), the variance of
  the white noise that drifts over the horizon as the residuals do. A dead-reckoning gap
  between landmarks, or the ticks over which a filter averages one landmark's observations,
  then spread as the filter assumes;
- out of sample: the residuals behind each std are cross-validated. Each window is cut into
  `folds` consecutive blocks, and the residuals of a block are those of the corrections
  fitted on the other blocks: the spread the corrections leave on data they were not fitted
  to, which is larger than on their own (the corrections written out are fitted on all).

`NoiseModel.save` writes the documented YAML (`noise.yaml`); `load` reads and checks it.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal, Sequence

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from swarmloc.datasets import mrclam

FORMAT = "swarmloc-noise/1"
HORIZON = 10.0   # s, the default white-equivalence horizon (docs/replay.md: why)
FOLDS = 2
MIN_CELL = 20    # ticks a command cell needs before its median is used (its std error is then ~0.28 std)
GATE_Z = 3.29    # the two-sided 0.999 quantile of the normal, the replay gate's probability
SPEED_STEP, TURN_RATE_STEP = 0.01, 0.05   # the command table's cells (MR.CLAM logs speeds to 0.01 m/s)
MIN_WINDOW = 10.0  # s: less than this is no calibration window
KINDS = ("landmarks", "robots")


class CalibrationError(ValueError):
    """A noise model that cannot be fitted or read; the message is one line."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ObservationNoise(_Strict):
    """One robot's camera observing landmarks (or robots)."""

    range_bias: tuple[float, float, float, float] = Field(description="range error (m) = a0 + a1 r + a2 r b + "
                                                          "a3 r b^2 in the measured range r and bearing b; the "
                                                          "replay subtracts it")
    bearing_bias: tuple[float, float, float] = Field(description="bearing error (rad) = c0 + c1 b + c2 b^2")
    range_std_per_m: float = Field(gt=0, description="std of the corrected range, per metre of range")
    bearing_std: float = Field(gt=0, description="std of the corrected bearing (rad)")
    samples: int = Field(ge=0, description="observations the fit used")

    def correct(self, r, b) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Corrected ranges and bearings and their stds, for measured ranges r and bearings b."""
        r, b = np.asarray(r, float), np.asarray(b, float)
        a0, a1, a2, a3 = self.range_bias
        c0, c1, c2 = self.bearing_bias
        rc = r - (a0 + r * (a1 + b * (a2 + a3 * b)))
        bc = mrclam.wrap(b - (c0 + b * (c1 + c2 * b)))
        return rc, bc, self.range_std_per_m * np.abs(rc), np.full(bc.shape, self.bearing_std)


class OdometryNoise(_Strict):
    """One robot's odometry."""

    speed_lag: float = Field(description="s by which the speed command leads the motion")
    turn_rate_lag: float = Field(description="s by which the turn-rate command leads the turn")
    speed_step: float = Field(SPEED_STEP, gt=0, description="the table's cell size in commanded speed (m/s)")
    turn_rate_step: float = Field(TURN_RATE_STEP, gt=0, description="... in commanded turn rate (rad/s)")
    table: list[tuple[int, int, float, float, int]] = Field(
        default_factory=list, description="rows [i, j, dv, dw, n]: a tick whose mean command is within half a "
        "cell of (i speed_step, j turn_rate_step) moved at (v + dv, w + dw); n ticks measured it")
    speed_std: float = Field(gt=0, description="std of a tick's corrected mean speed (m/s), white-equivalent")
    turn_rate_std: float = Field(gt=0, description="... of its corrected mean turn rate (rad/s)")
    samples: int = Field(ge=0, description="ticks the fit used")

    def correct(self, v, w) -> tuple[np.ndarray, np.ndarray]:
        """Corrected mean speeds and turn rates of ticks whose mean commands are v, w."""
        v, w = np.asarray(v, float), np.asarray(w, float)
        if not self.table:
            return v.copy(), w.copy()
        i, j = _cells(v, w, self.speed_step, self.turn_rate_step)
        cells = {(a, b): (dv, dw) for a, b, dv, dw, _ in self.table}
        corr = np.array([cells.get(key, (0.0, 0.0)) for key in zip(i.ravel().tolist(), j.ravel().tolist())]).reshape(
            v.shape + (2,))
        return v + corr[..., 0], w + corr[..., 1]


class RobotNoise(_Strict):
    odometry: OdometryNoise
    landmarks: ObservationNoise | None = Field(None, description="its observations of landmarks; null: none seen")
    robots: ObservationNoise | None = Field(None, description="its observations of other robots; null: none seen")


class NoiseModel(_Strict):
    """The noise of each robot of one recording (module docstring); the YAML of noise.yaml."""

    format: Literal["swarmloc-noise/1"] = FORMAT
    recording: str = Field(description="the recording's directory name (e.g. MRCLAM_Dataset6)")
    windows: list[tuple[float, float]] = Field(description="the spans fitted on, seconds from the recording's start")
    dt: float = Field(gt=0, description="the tick (s) the odometry was fitted at")
    horizon: float = Field(gt=0, description="s over which the stds are white-equivalent")
    folds: int = Field(ge=1, description="cross-validation blocks per window behind the stds (1: in sample)")
    robots: dict[int, RobotNoise]

    @field_validator("windows")
    @classmethod
    def _spans(cls, v):
        if not v or any(not (math.isfinite(a) and math.isfinite(b) and b > a) for a, b in v):
            raise ValueError("windows must be [from, to] pairs with to > from")
        return v

    def covered(self) -> float:
        return float(sum(b - a for a, b in self.windows))

    def overlap(self, lo: float, hi: float) -> float:
        """Seconds of [lo, hi] (from the recording's start) inside the windows fitted on."""
        return float(sum(max(0.0, min(b, hi) - max(a, lo)) for a, b in self.windows))

    def to_yaml(self) -> str:
        data = self.model_dump(mode="python")
        data["windows"] = [list(w) for w in self.windows]
        for r in data["robots"].values():
            r["odometry"]["table"] = [list(row) for row in r["odometry"]["table"]]
            for k in KINDS:
                if r[k] is not None:
                    r[k]["range_bias"], r[k]["bearing_bias"] = list(r[k]["range_bias"]), list(r[k]["bearing_bias"])
        return HEADER + yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=110)

    def save(self, path) -> Path:
        path = Path(path)
        path.write_text(self.to_yaml())
        return path

    @classmethod
    def parse(cls, data, source: str = "<noise model>") -> "NoiseModel":
        if not isinstance(data, dict):
            raise CalibrationError(f"{source}: a noise model is a YAML mapping, got {type(data).__name__}")
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            err = exc.errors()[0]
            loc = ".".join(str(p) for p in err["loc"])
            raise CalibrationError(f"{source}: {loc or '(top level)'}: {err['msg']}") from None

    @classmethod
    def load(cls, path) -> "NoiseModel":
        path = Path(path)
        try:
            data = yaml.safe_load(path.read_text())
        except OSError as exc:
            raise CalibrationError(f"{path}: cannot read: {exc.strerror or exc}") from None
        except yaml.YAMLError as exc:
            raise CalibrationError(f"{path}: not valid YAML: {str(exc).splitlines()[0]}") from None
        return cls.parse(data, str(path))


HEADER = """\
# swarmloc noise model (swarmloc calibrate; docs/replay.md). Per robot:
#   odometry: speed_lag, turn_rate_lag (s the commands lead the motion); table rows [i, j, dv, dw, n]:
#     a tick commanded (v, w) within half a cell of (i speed_step, j turn_rate_step) moved at (v + dv, w + dw);
#     speed_std, turn_rate_std: std of what is left, white-equivalent over `horizon` s.
#   landmarks, robots: the camera's range error a0 + a1 r + a2 r b + a3 r b^2 (range_bias) and bearing
#     error c0 + c1 b + c2 b^2 (bearing_bias) in the measured range r (m) and bearing b (rad); range_std_per_m
#     (the range's std is this times the range), bearing_std (rad) of what is left.
# windows: the spans fitted on (s from the recording's start); the stds are cross-validated over `folds`
# blocks of each window.
"""


# ---------------------------------------------------------------------------------------------
# Fitting


def _cells(v, w, sv: float, sw: float) -> tuple[np.ndarray, np.ndarray]:
    return np.round(np.asarray(v) / sv).astype(np.int64), np.round(np.asarray(w) / sw).astype(np.int64)


def _truth_motion(truth: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Per tick, the truth's mean forward speed (displacement along the mid heading) and turn rate."""
    a, b = truth[:-1], truth[1:]
    mid = np.angle(np.exp(1j * a[:, 2]) + np.exp(1j * b[:, 2]))
    vt = ((b[:, 0] - a[:, 0]) * np.cos(mid) + (b[:, 1] - a[:, 1]) * np.sin(mid)) / dt
    return vt, mrclam.wrap(b[:, 2] - a[:, 2]) / dt


def fit_table(v, w, vt, wt, speed_step: float = SPEED_STEP, turn_rate_step: float = TURN_RATE_STEP,
              min_cell: int = MIN_CELL) -> list[tuple[int, int, float, float, int]]:
    """The command table (module docstring) of ticks with mean commands v, w and truth vt, wt."""
    ok = np.isfinite(vt) & np.isfinite(wt) & np.isfinite(v) & np.isfinite(w)
    if not ok.any():
        return []
    i, j = _cells(v[ok], w[ok], speed_step, turn_rate_step)
    dv, dw = (vt - v)[ok], (wt - w)[ok]
    keys, inverse, counts = np.unique(np.column_stack([i, j]), axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    return [(int(key[0]), int(key[1]), float(np.median(dv[inverse == c])), float(np.median(dw[inverse == c])), int(n))
            for c, (key, n) in enumerate(zip(keys, counts)) if n >= min_cell]


def _trimmed_lstsq(X: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least squares, iterated with the rows whose residual exceeds GATE_Z robust stds left out."""
    keep = np.isfinite(y) & np.isfinite(X).all(axis=1)
    if keep.sum() < 2 * X.shape[1]:
        return np.zeros(X.shape[1])
    coef = np.linalg.lstsq(X[keep], y[keep], rcond=None)[0]
    for _ in range(10):
        res = y - X @ coef
        s = mrclam.robust_std(res[keep])
        new = np.isfinite(y) & np.isfinite(X).all(axis=1) & (np.abs(res) <= GATE_Z * s)
        if new.sum() < 2 * X.shape[1] or np.array_equal(new, keep):
            break
        keep = new
        coef = np.linalg.lstsq(X[keep], y[keep], rcond=None)[0]
    return coef


def range_features(r, b) -> np.ndarray:
    r, b = np.asarray(r, float), np.asarray(b, float)
    return np.column_stack([np.ones_like(r), r, r * b, r * b * b])


def bearing_features(b) -> np.ndarray:
    b = np.asarray(b, float)
    return np.column_stack([np.ones_like(b), b, b * b])


def batch_std(residual, t, horizon: float, segment=None, step: float = 0.1) -> float:
    """sqrt(sum over batches of (sum of the batch's residuals)^2 / the residuals summed): the
    white-equivalent std at `horizon` seconds (module docstring), over overlapping batches
    (Meketon and Schmeiser's overlapping batch means: one batch starting at every `step`, which
    halves the estimate's variance against disjoint batches). t: each residual's time (s);
    batches lie within one `segment` (an id per residual: a calibration window), never across
    two; a segment shorter than the horizon is one batch. horizon <= 0: the root mean square."""
    e, t = np.asarray(residual, float), np.asarray(t, float)
    seg = np.zeros(e.shape, np.int64) if segment is None else np.asarray(segment, np.int64)
    ok = np.isfinite(e) & np.isfinite(t)
    e, t, seg = e[ok], t[ok], seg[ok]
    if e.size == 0:
        return math.nan
    if horizon <= 0:
        return float(np.sqrt(np.mean(e**2)))
    width = max(1, int(round(horizon / step)))
    num = den = 0.0
    for sid in np.unique(seg):
        m = seg == sid
        cell = np.round((t[m] - t[m].min()) / step).astype(np.int64)
        sums = np.bincount(cell, weights=e[m])
        counts = np.bincount(cell).astype(float)
        cs, cn = np.r_[0.0, np.cumsum(sums)], np.r_[0.0, np.cumsum(counts)]
        w = min(width, sums.size)
        S, N = cs[w:] - cs[:-w], cn[w:] - cn[:-w]
        num += np.sum(S**2)
        den += np.sum(N)
    return float(math.sqrt(num / den)) if den > 0 else math.nan


def _inliers(e: np.ndarray) -> np.ndarray:
    s = mrclam.robust_std(e)
    return np.isfinite(e) & (np.abs(e) <= GATE_Z * s) if math.isfinite(s) and s > 0 else np.isfinite(e)


class _Samples:
    """One robot's ticks and observations in the calibration windows, against truth."""

    def __init__(self, rec: mrclam.Recording, robot: int, windows, dt: float, lag: float, turn_lag: float):
        v, w, vt, wt, tt, seg = [], [], [], [], [], []
        obs = {k: {"r": [], "b": [], "tr": [], "tb": [], "t": [], "seg": []} for k in KINDS}
        for n, (lo, hi) in enumerate(windows):
            start, steps = rec.t0 + lo, int(math.floor((hi - lo) / dt + 1e-9))
            tk = mrclam.ticked(rec, robot, start, dt, steps, lag, turn_lag)
            mv, mw = _truth_motion(tk.truth, dt)
            # A tick that begins before the first (shifted) command has no command for its start.
            known = start + dt * np.arange(steps) >= rec.odometry[robot].t[0] + max(lag, turn_lag)
            mv, mw = np.where(known, mv, np.nan), np.where(known, mw, np.nan)
            v.append(tk.v[1:]), w.append(tk.w[1:]), vt.append(mv), wt.append(mw)
            tt.append(lo + dt * np.arange(1, steps + 1)), seg.append(np.full(steps, n))
            at = tk.truth[tk.tick]
            t_obs = start + dt * tk.tick
            other = np.full((tk.tick.size, 2), np.nan)
            is_robot = np.isin(tk.subject, rec.robots)
            for s in np.unique(tk.subject):
                sel = tk.subject == s
                if s in rec.robots:
                    other[sel] = rec.truth_at(int(s), t_obs[sel])[:, :2]
                elif s in rec.landmarks:
                    other[sel] = rec.landmarks[int(s)].xy
            d = other - at[:, :2]
            true_r = np.hypot(d[:, 0], d[:, 1])
            true_b = mrclam.wrap(np.arctan2(d[:, 1], d[:, 0]) - at[:, 2])
            for kind, sel in (("landmarks", ~is_robot), ("robots", is_robot)):
                o = obs[kind]
                o["r"].append(tk.range[sel]), o["b"].append(tk.bearing[sel]), o["tr"].append(true_r[sel])
                o["tb"].append(true_b[sel]), o["t"].append(lo + dt * tk.tick[sel]), o["seg"].append(np.full(sel.sum(), n))
        cat = np.concatenate
        self.v, self.w, self.vt, self.wt, self.t, self.seg = cat(v), cat(w), cat(vt), cat(wt), cat(tt), cat(seg)
        self.obs = {k: {name: cat(x) for name, x in o.items()} for k, o in obs.items()}


def _folds(t: np.ndarray, seg: np.ndarray, windows, folds: int) -> np.ndarray:
    """Each sample's cross-validation block: the window cut into `folds` consecutive pieces."""
    out = np.zeros(t.shape, np.int64)
    for n, (lo, hi) in enumerate(windows):
        m = seg == n
        out[m] = np.minimum(np.floor((t[m] - lo) / ((hi - lo) / folds)), folds - 1)
    return out


RANGE_TERMS = (0, 1, 2, 4)    # nested range bias models: none, a0, a0 + a1 r, the whole of range_features
BEARING_TERMS = (0, 1, 2, 3)  # none, c0, c0 + c1 b, c0 + c1 b + c2 b^2


def _cross_validated(X: np.ndarray, y: np.ndarray, usable: np.ndarray, fold: np.ndarray, folds: int,
                     terms: int) -> np.ndarray:
    """Out-of-fold residuals of the bias model with the first `terms` columns of X (NaN where
    unusable): each fold's from the coefficients fitted on the others (folds 1: on all)."""
    res = np.full(y.shape, np.nan)
    for f in range(folds):
        test = usable & (fold == f)
        train = usable & (fold != f) if folds > 1 else usable
        if not test.any():
            continue
        coef = _trimmed_lstsq(X[train][:, :terms], y[train]) if terms else np.zeros(0)
        res[test] = y[test] - X[test][:, :terms] @ coef
    return res


def _select(X: np.ndarray, y: np.ndarray, usable: np.ndarray, fold: np.ndarray, folds: int, choices, score,
            wrap: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The bias model among the nested `choices` (numbers of columns of X) whose out-of-fold
    residuals score lowest (`score`: the white-equivalent std they imply), the simpler one on a
    tie: (its coefficients fitted on everything, padded with zeros; its out-of-fold residuals).
    A richer model wins only where the data pin it down: with few observations from a narrow
    spread of ranges and bearings its extrapolation loses on the blocks it did not see."""
    best = None
    for terms in choices:
        res = _cross_validated(X, y, usable, fold, folds, terms)
        if wrap:
            res = mrclam.wrap(res)
        value = score(res)
        if math.isfinite(value) and (best is None or value < best[0] * (1 - 1e-9)):
            best = (value, terms, res)
    if best is None:
        return np.zeros(X.shape[1]), np.full(y.shape, np.nan)
    _, terms, res = best
    coef = np.zeros(X.shape[1])
    coef[:terms] = _trimmed_lstsq(X[usable][:, :terms], y[usable]) if terms else []
    return coef, res


def _fit_observations(o: dict, fold: np.ndarray, folds: int, horizon: float) -> ObservationNoise | None:
    r, b, tr, tb = o["r"], o["b"], o["tr"], o["tb"]
    er, eb = r - tr, mrclam.wrap(b - tb)
    usable = np.isfinite(er) & np.isfinite(eb) & (r > 0)
    if usable.sum() < 20:
        return None
    t, seg = o["t"], o["seg"]

    def white(res):  # the white-equivalent std of a channel's inliers
        k = _inliers(res)
        return batch_std(res[k], t[k], horizon, seg[k]) if k.any() else math.nan

    # The range's std is in proportion to it: the model is scored on the relative error.
    cr, res_r = _select(range_features(r, b), er, usable, fold, folds, RANGE_TERMS,
                        lambda res: white(res / np.maximum(r - (er - res), 1e-3)))
    cb, res_b = _select(bearing_features(b), eb, usable, fold, folds, BEARING_TERMS, white, wrap=True)
    rel = res_r / np.maximum(r - (er - res_r), 1e-3)  # the corrected range is r - (er - res)
    sr, sb = white(rel), white(res_b)
    if not (math.isfinite(sr) and math.isfinite(sb)):
        return None
    return ObservationNoise(range_bias=tuple(map(float, cr)), bearing_bias=tuple(map(float, cb)),
                            range_std_per_m=max(sr, 1e-6), bearing_std=max(sb, 1e-6), samples=int(usable.sum()))


def _fit_odometry(s: _Samples, fold: np.ndarray, folds: int, horizon: float, lag: float,
                  turn_lag: float) -> OdometryNoise:
    """The command table if its out-of-fold residuals drift less than the raw commands' (speed
    and turn rate together, each relative to its raw spread), else none."""
    ok = np.isfinite(s.vt) & np.isfinite(s.wt)
    dv, dw = np.full(s.v.shape, np.nan), np.full(s.v.shape, np.nan)
    for f in range(folds):
        test = ok & (fold == f)
        train = ok & (fold != f) if folds > 1 else ok
        if not test.any():
            continue
        table = fit_table(s.v[train], s.w[train], s.vt[train], s.wt[train])
        probe = OdometryNoise(speed_lag=lag, turn_rate_lag=turn_lag, table=table, speed_std=1, turn_rate_std=1, samples=0)
        pv, pw = probe.correct(s.v[test], s.w[test])
        dv[test], dw[test] = s.vt[test] - pv, s.wt[test] - pw
    # Every residual counts: a wheel that slips moves the robot (Vicon's own noise cancels in the sums).
    sv, sw = batch_std(dv, s.t, horizon, s.seg), batch_std(dw, s.t, horizon, s.seg)
    rv, rw = batch_std(s.vt - s.v, s.t, horizon, s.seg), batch_std(s.wt - s.w, s.t, horizon, s.seg)
    if not (math.isfinite(sv) and math.isfinite(sw)):
        raise CalibrationError("no tick of the windows has ground truth at both ends")
    table = fit_table(s.v[ok], s.w[ok], s.vt[ok], s.wt[ok])
    if (sv / rv) ** 2 + (sw / rw) ** 2 >= 2.0:
        table, sv, sw = [], rv, rw
    return OdometryNoise(speed_lag=lag, turn_rate_lag=turn_lag, table=table, speed_std=max(sv, 1e-6),
                         turn_rate_std=max(sw, 1e-6), samples=int(ok.sum()))


def turn_rate_lag(rec: mrclam.Recording, robot: int, spans, speed_lag: float, step: float = 0.01,
                  block: float = 5.0) -> float:
    """The turn rate's own lag (estimate_odometry_lag on the turn rate) if it fits the truth's turn
    rate better than the speed's lag does beyond doubt, else the speed's lag: the paired squared
    differences at the two lags, summed over blocks of `block` s (the differences are correlated
    over seconds), must differ by more than 1.96 standard errors. A robot that turns little, or
    always in proportion to its speed, leaves the turn rate's lag undetermined."""
    lag = mrclam.estimate_odometry_lag(rec, robot, channel="turn_rate", spans=spans)
    o = rec.odometry[robot]
    diff = []
    for s0, s1 in spans:
        grid = np.arange(max(s0, o.t[0]), min(s1, o.t[-1]), step)
        held = mrclam.odometry_hold(o, grid, "turn_rate")
        d = [(held - mrclam.truth_turn_rate(rec, robot, grid + x)) ** 2 for x in (speed_lag, lag)]
        ok = np.isfinite(d[0]) & np.isfinite(d[1])
        cells = np.floor((grid[ok] - grid[0]) / block).astype(np.int64)
        diff.append(np.bincount(cells, weights=d[0][ok] - d[1][ok]))
    diff = np.concatenate(diff) if diff else np.zeros(0)
    if diff.size < 10:
        return speed_lag
    return lag if diff.mean() > 1.96 * diff.std(ddof=1) / math.sqrt(diff.size) else speed_lag


def check_windows(rec: mrclam.Recording, windows) -> list[tuple[float, float]]:
    """The windows (s from the recording's start) as sorted pairs inside it; CalibrationError if not."""
    out = []
    for w in windows:
        lo, hi = (float(x) for x in w)
        if not (0 <= lo < hi <= rec.duration + 1e-9):
            raise CalibrationError(f"window {lo:g}:{hi:g} s is not inside the recording's 0:{rec.duration:.3f} s")
        if hi - lo < MIN_WINDOW:
            raise CalibrationError(f"window {lo:g}:{hi:g} s is shorter than {MIN_WINDOW:g} s")
        out.append((lo, min(hi, rec.duration)))
    out.sort()
    if any(b[0] < a[1] for a, b in zip(out, out[1:])):
        raise CalibrationError(f"windows overlap: {out}")
    return out


def calibrate(rec: mrclam.Recording, windows: Sequence[tuple[float, float]] | None = None, dt: float = 0.1,
              horizon: float = HORIZON, folds: int = FOLDS, robots: Sequence[int] | None = None) -> NoiseModel:
    """Fit every robot's NoiseModel on `windows` of `rec` (seconds from its start; default the
    whole recording), at ticks of dt, stds white-equivalent over `horizon` s and cross-validated
    over `folds` blocks per window (module docstring). CalibrationError if it cannot."""
    if not dt > 0 or not horizon > 0 or folds < 1:
        raise CalibrationError(f"dt and horizon must be > 0 and folds >= 1, got {dt}, {horizon}, {folds}")
    windows = check_windows(rec, windows if windows is not None else [(0.0, rec.duration)])
    spans = [(rec.t0 + lo, rec.t0 + hi) for lo, hi in windows]
    out = {}
    unknown = sorted(set(robots or ()) - set(rec.robots))
    if unknown:
        raise CalibrationError(f"the recording has robots {list(rec.robots)}, not {unknown[0]}")
    for r in (robots if robots is not None else rec.robots):
        try:
            lag = mrclam.estimate_odometry_lag(rec, r, spans=spans)
            turn_lag = turn_rate_lag(rec, r, spans, lag)
        except ValueError as exc:
            raise CalibrationError(f"Robot{r}: {exc}") from None
        s = _Samples(rec, r, windows, dt, lag, turn_lag)
        try:
            odometry = _fit_odometry(s, _folds(s.t, s.seg, windows, folds), folds, horizon, lag, turn_lag)
        except CalibrationError as exc:
            raise CalibrationError(f"Robot{r}: {exc}") from None
        kinds = {k: _fit_observations(o, _folds(o["t"], o["seg"], windows, folds), folds, horizon)
                 for k, o in s.obs.items()}
        out[int(r)] = RobotNoise(odometry=odometry, **kinds)
    model = NoiseModel(recording=rec.source.name, windows=windows, dt=dt, horizon=horizon, folds=folds, robots=out)
    return NoiseModel.model_validate(_rounded(model.model_dump()))  # what noise.yaml holds, exactly


def _rounded(x):
    """Floats to 6 significant digits (far below any fitted number's own uncertainty), so a
    model and its noise.yaml are the same model."""
    if isinstance(x, float):
        return float(f"{x:.6g}")
    if isinstance(x, dict):
        return {k: _rounded(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return type(x)(_rounded(v) for v in x)
    return x


def parse_windows(text: str) -> list[tuple[float, float]]:
    """'0:442' or '0:200,400:600' (seconds from the recording's start) as [(0, 442)]; ValueError if not."""
    out = []
    for part in text.split(","):
        bits = part.strip().split(":")
        if len(bits) != 2:
            raise ValueError(f"{part.strip()!r} is not FROM:TO")
        try:
            out.append((float(bits[0]), float(bits[1])))
        except ValueError:
            raise ValueError(f"{part.strip()!r} is not FROM:TO in seconds") from None
    return out


def complement(duration: float, lo: float, hi: float, min_length: float = MIN_WINDOW) -> list[tuple[float, float]]:
    """The parts of [0, duration] outside [lo, hi] at least min_length long."""
    return [(a, b) for a, b in ((0.0, lo), (hi, duration)) if b - a >= min_length]


def held_out_split(duration: float) -> tuple[tuple[float, float], tuple[float, float]]:
    """The default replay's (calibration window, scored span): the first half and the second."""
    half = duration / 2
    return (0.0, half), (half, duration)


def label(model: NoiseModel | None, recording: str, lo: float, hi: float) -> str:
    """One line saying what the noise of a replay scored on [lo, hi] s of `recording` was fitted on."""
    if model is None:
        return "noise: not calibrated (the scenario's white noise)"
    spans = ", ".join(f"{a:.1f}-{b:.1f} s" for a, b in model.windows)
    if model.recording != recording:
        return f"noise calibrated on another recording ({model.recording}, {spans}); scored on {lo:.1f}-{hi:.1f} s"
    shared = model.overlap(lo, hi)
    if shared >= model.dt / 2:  # less than half a tick in common: the windows' rounding, no scored tick
        return (f"noise fitted on the scored data: calibrated on {spans} of {recording}, which covers {shared:.1f} s "
                f"of the scored {lo:.1f}-{hi:.1f} s")
    return f"noise calibrated on {spans} of {recording}, held out: scored on {lo:.1f}-{hi:.1f} s"
