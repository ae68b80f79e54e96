"""Loader of one UTIAS MR.CLAM dataset directory (real robots, real sensors, Vicon truth).

K. Y. K. Leung, Y. Halpern, T. D. Barfoot, H. H. T. Liu, "The UTIAS Multi-Robot Cooperative
Localization and Mapping Dataset", International Journal of Robotics Research 30(8):969-974,
2011. Datasets 1-9 share one format, which this module reads unchanged; see docs/mrclam.md for
the format, the quirks and how each is handled.

numpy only. Times stay absolute seconds in float64 (about 1.25e9 s; float64 resolves about
0.24 us there); `Recording.t0` and `Recording.relative` give times from the common start.
"""

from __future__ import annotations

import math
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple, Sequence

import numpy as np

MAX_GAP = 0.5  # s: truth_at reports NaN inside ground-truth gaps longer than this
KINDS = ("Odometry", "Measurement", "Groundtruth")
COLUMNS = {"Barcodes.dat": 2, "Landmark_Groundtruth.dat": 5, "Odometry": 3, "Measurement": 4, "Groundtruth": 4}
ROBOT_FILE = re.compile(r"^Robot(\d+)_(Odometry|Measurement|Groundtruth)\.dat$")
UNKNOWN_BARCODE = "unknown barcode"
SELF_MEASUREMENT = "self measurement"


class MrclamError(ValueError):
    """A directory that is not a readable MR.CLAM dataset; the message is one line naming it."""


class Landmark(NamedTuple):
    x: float
    y: float
    x_std: float
    y_std: float

    @property
    def xy(self) -> tuple[float, float]:
        return (self.x, self.y)

    @property
    def std(self) -> tuple[float, float]:
        return (self.x_std, self.y_std)


def _frozen(*arrays: np.ndarray) -> None:
    for a in arrays:
        a.flags.writeable = False


@dataclass(frozen=True)
class Odometry:
    """Commanded forward velocity v [m/s] and angular velocity w [rad/s] from time t [s] on."""
    t: np.ndarray
    v: np.ndarray
    w: np.ndarray

    def __post_init__(self):
        _frozen(self.t, self.v, self.w)

    def __len__(self) -> int:
        return self.t.size


@dataclass(frozen=True)
class Measurements:
    """Range [m] and bearing [rad] to `subject` (subject id: robots 1-5, landmarks 6-20)."""
    t: np.ndarray
    subject: np.ndarray
    range: np.ndarray
    bearing: np.ndarray

    def __post_init__(self):
        _frozen(self.t, self.subject, self.range, self.bearing)

    def __len__(self) -> int:
        return self.t.size


@dataclass(frozen=True)
class Groundtruth:
    """Vicon pose: x, y [m], heading [rad] at time t [s]."""
    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray

    def __post_init__(self):
        _frozen(self.t, self.x, self.y, self.heading)

    def __len__(self) -> int:
        return self.t.size


def wrap(a):
    """Angle(s) wrapped to (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(a, dtype=float), 2 * np.pi)


@dataclass(frozen=True)
class Recording:
    """One MR.CLAM dataset directory, loaded. Per-robot dicts are keyed by robot subject id."""
    source: Path
    robots: tuple[int, ...]
    barcodes: dict[int, int]            # subject id -> barcode
    subject_of_barcode: dict[int, int]  # barcode -> subject id
    landmarks: dict[int, Landmark]
    odometry: dict[int, Odometry]
    measurements: dict[int, Measurements]
    groundtruth: dict[int, Groundtruth]
    t0: float     # the common span: every robot has odometry in [t0, t_end]
    t_end: float
    dropped: dict[str, int] = field(default_factory=dict)                     # reason -> rows
    dropped_by_robot: dict[int, dict[str, int]] = field(default_factory=dict)  # robot -> reason -> rows

    @property
    def duration(self) -> float:
        return self.t_end - self.t0

    def relative(self, t):
        """Seconds since t0 (negative before it: ground truth starts ~12 s before odometry)."""
        return np.asarray(t, dtype=float) - self.t0

    def truth_span(self, robot: int) -> tuple[float, float]:
        """First and last ground-truth times of `robot`; truth_at is NaN outside."""
        g = self.groundtruth[robot]
        if len(g) == 0:
            return (math.nan, math.nan)
        return (float(g.t[0]), float(g.t[-1]))

    def truth_valid(self, robot: int, t, max_gap: float = MAX_GAP) -> np.ndarray:
        """True where truth_at(robot, t) is a number: inside the truth span and not inside a
        ground-truth gap longer than max_gap (a sample time itself is always valid)."""
        g = self.groundtruth[robot]
        t = np.asarray(t, dtype=float)
        if len(g) == 0:
            return np.zeros(t.shape, dtype=bool)
        tg = g.t
        i = np.clip(np.searchsorted(tg, t, side="right") - 1, 0, tg.size - 1)
        j = np.minimum(i + 1, tg.size - 1)
        inside = (t >= tg[0]) & (t <= tg[-1])
        return inside & ((tg[i] == t) | (tg[j] - tg[i] <= max_gap))

    def truth_at(self, robot: int, t, max_gap: float = MAX_GAP) -> np.ndarray:
        """Ground-truth pose (x, y, heading) at time(s) t: shape t.shape + (3,).

        x, y are linear between the bracketing Vicon samples; heading is unwrapped, interpolated
        and wrapped back to (-pi, pi] (the short way round). NaN outside truth_span (no
        extrapolation) and inside gaps longer than max_gap."""
        g = self.groundtruth[robot]
        t = np.asarray(t, dtype=float)
        out = np.full(t.shape + (3,), np.nan)
        ok = self.truth_valid(robot, t, max_gap)
        if ok.any():
            tv = t[ok]
            out[ok, 0] = np.interp(tv, g.t, g.x)
            out[ok, 1] = np.interp(tv, g.t, g.y)
            out[ok, 2] = wrap(np.interp(tv, g.t, np.unwrap(g.heading)))
        return out

    def odometry_shifted(self, robot: int, lag: float) -> Odometry:
        """The robot's odometry with lag seconds added to its times (lag > 0 delays it: use
        estimate_odometry_lag to line commands up with the motion they cause)."""
        o = self.odometry[robot]
        return Odometry(o.t + lag, o.v.copy(), o.w.copy())

    def summary(self) -> str:
        lines = [f"{self.source}: robots {list(self.robots)}, {len(self.landmarks)} landmarks, "
                 f"{self.duration:.3f} s common span from t0={self.t0:.3f}"]
        for r in self.robots:
            a, b = self.truth_span(r)
            lines.append(f"  Robot{r}: {len(self.odometry[r])} odometry, {len(self.measurements[r])} measurements, "
                         f"{len(self.groundtruth[r])} truth [{self.relative(a):.3f}, {self.relative(b):.3f}] s")
        lines.append(f"  dropped: {self.dropped}")
        return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# Parsing


def _scan_for_error(path: Path, ncols: int) -> str | None:
    """The first line of `path` that is not `ncols` numbers, as 'file:line: what'."""
    with open(path, "r", errors="replace") as f:
        for n, line in enumerate(f, 1):
            body = line.split("#", 1)[0].split()
            if not body:
                continue
            if len(body) != ncols:
                return f"{path}:{n}: expected {ncols} columns, found {len(body)}"
            for tok in body:
                try:
                    float(tok)
                except ValueError:
                    return f"{path}:{n}: cannot parse {tok[:20]!r} as a number"
    return None


def _table(path: Path, ncols: int) -> np.ndarray:
    """The numeric rows of an MR.CLAM file ('#' comments), shape (n, ncols), float64."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data": an empty table is fine
            a = np.loadtxt(path, comments="#", dtype=np.float64, ndmin=2)
    except ValueError as e:
        raise MrclamError(_scan_for_error(path, ncols) or f"{path}: does not parse: {str(e).splitlines()[0]}") from None
    except OSError as e:
        raise MrclamError(f"{path}: cannot read: {e.strerror or e}") from None
    if a.size == 0:
        return np.zeros((0, ncols))
    if a.shape[1] != ncols:
        raise MrclamError(_scan_for_error(path, ncols) or f"{path}: expected {ncols} columns, found {a.shape[1]}")
    if not np.isfinite(a).all():
        row = int(np.nonzero(~np.isfinite(a).all(axis=1))[0][0])
        raise MrclamError(f"{path}: data row {row + 1} holds a non-finite value")
    return a


def _by_time(a: np.ndarray) -> np.ndarray:
    """Rows in time order (stable: the files are already non-decreasing, this is a guard)."""
    if a.shape[0] > 1 and (np.diff(a[:, 0]) < 0).any():
        a = a[np.argsort(a[:, 0], kind="stable")]
    return a


def _integer_column(a: np.ndarray, col: int, path: Path) -> np.ndarray:
    c = a[:, col]
    bad = np.nonzero(c != np.round(c))[0]
    if bad.size:
        raise MrclamError(f"{path}: data row {bad[0] + 1}, column {col + 1} is {c[bad[0]]!r}, not an integer id")
    return c.astype(np.int64)


def robot_files(path: Path) -> dict[int, dict[str, Path]]:
    found: dict[int, dict[str, Path]] = {}
    for p in path.iterdir():
        m = ROBOT_FILE.match(p.name)
        if m:
            found.setdefault(int(m.group(1)), {})[m.group(2)] = p
    return found


def load(path) -> Recording:
    """Load one MR.CLAM dataset directory (e.g. MRCLAM_Dataset6). Raises MrclamError."""
    path = Path(path)
    if not path.is_dir():
        raise MrclamError(f"{path}: no such directory" if not path.exists() else f"{path}: not a directory")
    for name in ("Barcodes.dat", "Landmark_Groundtruth.dat"):
        if not (path / name).is_file():
            raise MrclamError(f"{path}: not an MR.CLAM dataset: {name} is missing")
    files = robot_files(path)
    if not files:
        raise MrclamError(f"{path}: not an MR.CLAM dataset: no RobotN_Odometry/Measurement/Groundtruth.dat files")
    for r, kinds in sorted(files.items()):
        missing = [k for k in KINDS if k not in kinds]
        if missing:
            raise MrclamError(f"{path}: Robot{r}_{missing[0]}.dat is missing (Robot{r} has "
                              f"{', '.join(f'Robot{r}_{k}.dat' for k in KINDS if k in kinds)})")

    bpath = path / "Barcodes.dat"
    b = _table(bpath, 2)
    subj, code = _integer_column(b, 0, bpath), _integer_column(b, 1, bpath)
    barcodes = {int(s): int(c) for s, c in zip(subj, code)}
    subject_of_barcode = {c: s for s, c in barcodes.items()}
    if len(barcodes) != len(subj) or len(subject_of_barcode) != len(barcodes):
        raise MrclamError(f"{bpath}: subjects and barcodes are not one-to-one")

    lpath = path / "Landmark_Groundtruth.dat"
    lm = _table(lpath, 5)
    landmarks = {int(s): Landmark(float(x), float(y), float(sx), float(sy))
                 for s, x, y, sx, sy in zip(_integer_column(lm, 0, lpath), *lm[:, 1:].T)}

    robots = tuple(sorted(files))
    for r in robots:
        if r not in barcodes:
            raise MrclamError(f"{bpath}: Robot{r} has files but no barcode")

    known = np.array(sorted(subject_of_barcode), dtype=np.int64)
    subject_lut = np.array([subject_of_barcode[c] for c in known], dtype=np.int64)
    odometry, measurements, groundtruth = {}, {}, {}
    dropped: dict[str, int] = {UNKNOWN_BARCODE: 0, SELF_MEASUREMENT: 0}
    dropped_by_robot: dict[int, dict[str, int]] = {}
    for r in robots:
        o = _by_time(_table(files[r]["Odometry"], 3))
        odometry[r] = Odometry(o[:, 0].copy(), o[:, 1].copy(), o[:, 2].copy())

        g = _by_time(_table(files[r]["Groundtruth"], 4))
        groundtruth[r] = Groundtruth(g[:, 0].copy(), g[:, 1].copy(), g[:, 2].copy(), g[:, 3].copy())

        mpath = files[r]["Measurement"]
        m = _by_time(_table(mpath, 4))
        bc = _integer_column(m, 1, mpath)
        pos = np.clip(np.searchsorted(known, bc), 0, max(known.size - 1, 0))
        is_known = known[pos] == bc if known.size else np.zeros(bc.size, dtype=bool)
        subject = np.where(is_known, subject_lut[pos] if known.size else 0, 0)
        is_self = is_known & (subject == r)
        keep = is_known & ~is_self
        counts = {UNKNOWN_BARCODE: int((~is_known).sum()), SELF_MEASUREMENT: int(is_self.sum())}
        dropped_by_robot[r] = counts
        for k, v in counts.items():
            dropped[k] += v
        measurements[r] = Measurements(m[keep, 0].copy(), subject[keep].copy(), m[keep, 2].copy(), m[keep, 3].copy())

    starts = [odometry[r].t[0] for r in robots if len(odometry[r])]
    ends = [odometry[r].t[-1] for r in robots if len(odometry[r])]
    if not starts:
        raise MrclamError(f"{path}: every RobotN_Odometry.dat is empty")
    return Recording(source=path, robots=robots, barcodes=barcodes, subject_of_barcode=subject_of_barcode,
                     landmarks=landmarks, odometry=odometry, measurements=measurements, groundtruth=groundtruth,
                     t0=float(max(starts)), t_end=float(min(ends)), dropped=dropped, dropped_by_robot=dropped_by_robot)


# ---------------------------------------------------------------------------------------------
# Odometry lag


def truth_speed(rec: Recording, robot: int, t, half_window: float = 0.1, max_gap: float = MAX_GAP) -> np.ndarray:
    """Signed forward speed [m/s] from ground truth by central difference over +-half_window,
    projected on the mid heading; NaN where either end is not valid truth."""
    t = np.asarray(t, dtype=float)
    a = rec.truth_at(robot, t - half_window, max_gap)
    b = rec.truth_at(robot, t + half_window, max_gap)
    h = np.angle(np.exp(1j * a[..., 2]) + np.exp(1j * b[..., 2]))
    return ((b[..., 0] - a[..., 0]) * np.cos(h) + (b[..., 1] - a[..., 1]) * np.sin(h)) / (2 * half_window)


def truth_turn_rate(rec: Recording, robot: int, t, half_window: float = 0.1, max_gap: float = MAX_GAP) -> np.ndarray:
    """Turn rate [rad/s] from ground truth by central difference of the heading over
    +-half_window; NaN where either end is not valid truth."""
    t = np.asarray(t, dtype=float)
    a = rec.truth_at(robot, t - half_window, max_gap)
    b = rec.truth_at(robot, t + half_window, max_gap)
    return wrap(b[..., 2] - a[..., 2]) / (2 * half_window)


def odometry_hold(o: Odometry, t, channel: str = "speed") -> np.ndarray:
    """Odometry forward velocity (channel "speed") or angular velocity ("turn_rate") held from
    each row to the next (zero-order hold); NaN outside."""
    t = np.asarray(t, dtype=float)
    if len(o) == 0:
        return np.full(t.shape, np.nan)
    i = np.searchsorted(o.t, t, side="right") - 1
    v = (o.v if channel == "speed" else o.w)[np.clip(i, 0, len(o) - 1)]
    return np.where((i >= 0) & (t <= o.t[-1]), v, np.nan)


CHANNELS = ("speed", "turn_rate")


def lag_cost(rec: Recording, robot: int, max_lag: float = 1.0, step: float = 0.01,
             min_lag: float | None = None, half_window: float = 0.1, channel: str = "speed",
             spans: Sequence[tuple[float, float]] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Mean squared difference between the odometry's forward speed (or, channel "turn_rate",
    its angular velocity) at t and the ground truth's at t + lag, for lags min_lag..max_lag
    (default -max_lag) by step. spans: the absolute time spans to compare over (default: the
    whole overlap of odometry and ground truth)."""
    if channel not in CHANNELS:
        raise ValueError(f"channel {channel!r}: one of {CHANNELS}")
    o = rec.odometry[robot]
    a, b = rec.truth_span(robot)
    lo = -max_lag if min_lag is None else min_lag
    if len(o) == 0 or not math.isfinite(a):
        raise ValueError(f"Robot{robot}: no odometry or no ground truth")
    k_lo, k_hi = int(math.floor(lo / step + 1e-9)), int(math.ceil(max_lag / step - 1e-9))
    truth = truth_speed if channel == "speed" else truth_turn_rate
    lags = step * np.arange(k_lo, k_hi + 1)
    sq, count = np.zeros(lags.size), np.zeros(lags.size)
    for s0, s1 in (spans if spans is not None else [(-math.inf, math.inf)]):
        t_start, t_stop = max(o.t[0], a, s0), min(o.t[-1], b, s1)
        n = int((t_stop - t_start) / step) + 1 if t_stop > t_start else 0
        if n < 10:
            continue
        grid = t_start + step * np.arange(n)
        vo = odometry_hold(o, grid, channel)
        vt = truth(rec, robot, t_start + step * np.arange(k_lo, n + k_hi), half_window)  # vt[j - k_lo] at grid[0]+j*step
        for i, k in enumerate(range(k_lo, k_hi + 1)):
            d = vo - vt[k - k_lo: k - k_lo + n]
            ok = np.isfinite(d)
            sq[i] += np.sum(d[ok] ** 2)
            count[i] += ok.sum()
    if not count.any():
        raise ValueError(f"Robot{robot}: odometry and ground truth barely overlap")
    with np.errstate(invalid="ignore", divide="ignore"):
        cost = np.where(count >= 10, sq / np.maximum(count, 1), np.nan)
    return lags, cost


def estimate_odometry_lag(rec: Recording, robot: int, max_lag: float = 1.0, step: float = 0.01,
                          min_lag: float | None = None, half_window: float = 0.1, channel: str = "speed",
                          spans: Sequence[tuple[float, float]] | None = None) -> float:
    """Seconds by which `robot`'s odometry leads its true motion (> 0: the command at t shows in
    the ground-truth speed at t + lag). Least squares over candidate shifts on a `step` grid
    (lag_cost), refined by a parabola through the best three. Ground truth is used only where
    truth_at is valid (not in gaps, not after it ends). channel "turn_rate": the same for the
    angular velocity (on Dataset6 the turns show 0.16-0.20 s after they are logged, the forward
    speed 0.22-0.25 s). spans: only these absolute time spans (a calibration window)."""
    lags, cost = lag_cost(rec, robot, max_lag, step, min_lag, half_window, channel, spans)
    if not np.isfinite(cost).any():
        raise ValueError(f"Robot{robot}: no overlap of odometry and valid ground truth")
    i = int(np.nanargmin(cost))
    best = float(lags[i])
    if 0 < i < lags.size - 1 and np.isfinite(cost[i - 1]) and np.isfinite(cost[i + 1]):
        c0, c1, c2 = cost[i - 1], cost[i], cost[i + 1]
        den = c0 - 2 * c1 + c2
        if den > 0:
            best += float(step * 0.5 * (c0 - c2) / den)
    return best


# ---------------------------------------------------------------------------------------------
# Excerpts


def _windows(t_from, t_to) -> list[tuple[float, float]]:
    lo = np.atleast_1d(np.asarray(t_from, dtype=float))
    hi = np.atleast_1d(np.asarray(t_to, dtype=float))
    if lo.shape != hi.shape or lo.ndim != 1:
        raise ValueError("t_from and t_to must be two numbers or two sequences of the same length")
    if (hi < lo).any():
        raise ValueError("every window needs t_from <= t_to")
    return list(zip(lo.tolist(), hi.tolist()))


def write_excerpt(rec_or_path, out_dir, t_from, t_to, robots: Sequence[int] | None = None) -> Path:
    """Copy the rows of an MR.CLAM directory whose time lies in [t_from, t_to] (absolute seconds;
    pass sequences for a union of windows) to out_dir, in the same format: the raw lines are
    copied, so the 4 comment lines, the columns, the number formatting and the rows the loader
    drops (unknown barcodes) are all kept. Barcodes.dat and Landmark_Groundtruth.dat are copied
    whole. `robots` (default all) limits which RobotN_*.dat files are written. Returns out_dir."""
    src = rec_or_path.source if isinstance(rec_or_path, Recording) else Path(rec_or_path)
    if not isinstance(rec_or_path, Recording):
        load(src)  # the source must be a readable dataset
    windows = _windows(t_from, t_to)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for name in ("Barcodes.dat", "Landmark_Groundtruth.dat"):
        (out / name).write_bytes((src / name).read_bytes())
    for r, kinds in sorted(robot_files(src).items()):
        if robots is not None and r not in robots:
            continue
        for kind, p in kinds.items():
            kept = []
            with open(p, "r") as f:
                for line in f:
                    body = line.split("#", 1)[0].split()
                    if not body:
                        kept.append(line)  # comments (the 4 header lines)
                        continue
                    t = float(body[0])
                    if any(a <= t <= b for a, b in windows):
                        kept.append(line)
            (out / p.name).write_text("".join(kept))
    return out


# ---------------------------------------------------------------------------------------------
# Ticks: the recording as a fixed-rate sensor stream (what netsim's replay delivers)


@dataclass(frozen=True)
class Ticked:
    """One robot's recording resampled to ticks k = 0..steps at times start + k dt.

    v, w: the mean forward and angular velocity commanded over tick k, (t_{k-1}, t_k] (index 0
    is the start: zero), from the odometry shifted by its lag (w by the turn-rate lag, if given). truth: (steps + 1, 3) pose at
    t_k, NaN where truth_at is. Measurements taken in (t_{k-1}, t_k] belong to tick k (`tick`),
    and their bearing is carried to t_k: the observer turned by the integral of its commanded
    w from t_m to t_k (up to 0.57 rad/s x dt), and a body-frame bearing turns the other way. The
    observer's and subject's translation over that interval (at most 0.09 m/s x dt) is left."""
    v: np.ndarray
    w: np.ndarray
    truth: np.ndarray
    tick: np.ndarray
    subject: np.ndarray
    range: np.ndarray
    bearing: np.ndarray


def _integral(t_rows: np.ndarray, values: np.ndarray, t) -> np.ndarray:
    """Integral from the first row to t of a zero-order hold of values (0 before the first row)."""
    if t_rows.size == 0:
        return np.zeros(np.shape(t))
    cum = np.r_[0.0, np.cumsum(values[:-1] * np.diff(t_rows))]
    i = np.searchsorted(t_rows, t, side="right") - 1
    ic = np.clip(i, 0, t_rows.size - 1)
    return np.where(i >= 0, cum[ic] + values[ic] * (np.asarray(t) - t_rows[ic]), 0.0)


def ticked(rec: Recording, robot: int, start: float, dt: float, steps: int, lag: float,
           turn_lag: float | None = None) -> Ticked:
    """`robot`'s recording from absolute time `start` as ticks of dt (see Ticked); turn_lag
    (default lag): the lag of the angular velocity, which also carries the bearings."""
    o = rec.odometry_shifted(robot, lag)
    if turn_lag is not None and turn_lag != lag:
        ow = rec.odometry_shifted(robot, turn_lag)
    else:
        ow = o
    t = start + dt * np.arange(steps + 1)
    iv, iw = _integral(o.t, o.v, t), _integral(ow.t, ow.w, t)
    v, w = np.r_[0.0, np.diff(iv) / dt], np.r_[0.0, np.diff(iw) / dt]
    m = rec.measurements[robot]
    k = np.ceil((m.t - start) / dt - 1e-9).astype(np.int64)
    keep = (k >= 1) & (k <= steps)
    k, tm = k[keep], m.t[keep]
    turned = _integral(ow.t, ow.w, start + dt * k) - _integral(ow.t, ow.w, tm)
    return Ticked(v, w, rec.truth_at(robot, t), k, m.subject[keep].copy(), m.range[keep].copy(),
                  wrap(m.bearing[keep] - turned))


def odometry_lags(rec: Recording) -> dict[int, float]:
    """estimate_odometry_lag of every robot (0.22-0.25 s on Dataset6)."""
    return {r: estimate_odometry_lag(rec, r) for r in rec.robots}


def robust_std(x: np.ndarray) -> float:
    """1.4826 x the median absolute deviation from the median: the std of the Gaussian core,
    unmoved by the few gross errors the data have (misread barcodes, Vicon glitches)."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if x.size else math.nan


@dataclass(frozen=True)
class NoiseFit:
    """Sensor noise of a recording measured against its ground truth at a tick rate."""
    speed: float        # m/s: white noise on a tick's mean forward velocity
    turn_rate: float    # rad/s
    range: float        # m
    bearing: float      # rad
    samples: dict       # what each figure was computed from (counts)
    plain: dict         # the plain standard deviations of the same residuals, for comparison
    per_tick: dict = field(default_factory=dict)  # speed, turn_rate fitted tick by tick (horizon dt)


def _horizon_std(residual: np.ndarray, n: int) -> float:
    """robust_std of the sums of n consecutive residuals, over sqrt(n): the white noise whose
    integral over n ticks spreads as the residuals' does."""
    m = residual.size // n
    sums = residual[: m * n].reshape(m, n)
    whole = np.isfinite(sums).all(axis=1)
    return robust_std(sums[whole].sum(axis=1)) / math.sqrt(n)


def fit_noise(rec: Recording, dt: float, lags: dict[int, float] | None = None, horizon: float | None = None) -> NoiseFit:
    """The noise the estimators should assume, from the residuals of each sensor against Vicon.

    Odometry: per tick, the truth's displacement along its mid heading and its heading change
    over the tick, against the tick's mean command. Its errors are correlated in time (wheel
    slip, scale, the turn-rate error of a wheel-odometry heading), so white noise fitted tick by
    tick understates how dead reckoning drifts. With `horizon` (s) the std is fitted instead to
    the spread of the errors summed over that many seconds, divided by the square root of the
    ticks summed: on Dataset6 at dt 0.1 s and a 10 s horizon, 0.058 m/s and 0.075 rad/s against
    0.011 and 0.053 tick by tick (`per_tick`). docs/replay.md shows what each does to accuracy and
    NEES; None (the default): tick by tick.
    Range and bearing: every measurement against the truth at its tick (robots and landmarks
    pooled). Robust std (robust_std) throughout."""
    lags = odometry_lags(rec) if lags is None else lags
    steps = int(math.floor(rec.duration / dt))
    n = 1 if horizon is None else max(1, int(round(horizon / dt)))
    dv, dw, dr, db = [], [], [], []
    ticks = {r: ticked(rec, r, rec.t0, dt, steps, lags[r]) for r in rec.robots}
    for r, tk in ticks.items():
        a, b = tk.truth[:-1], tk.truth[1:]
        mid = np.angle(np.exp(1j * a[:, 2]) + np.exp(1j * b[:, 2]))
        dv.append(((b[:, 0] - a[:, 0]) * np.cos(mid) + (b[:, 1] - a[:, 1]) * np.sin(mid)) / dt - tk.v[1:])
        dw.append(wrap(b[:, 2] - a[:, 2]) / dt - tk.w[1:])
        at = tk.truth[tk.tick]
        other = np.full((tk.tick.size, 2), np.nan)
        for s in np.unique(tk.subject):
            sel = tk.subject == s
            if s in ticks:
                other[sel] = ticks[s].truth[tk.tick[sel], :2]
            elif s in rec.landmarks:
                other[sel] = rec.landmarks[s].xy
        d = other - at[:, :2]
        dr.append(tk.range - np.hypot(d[:, 0], d[:, 1]))
        db.append(wrap(tk.bearing - (np.arctan2(d[:, 1], d[:, 0]) - at[:, 2])))
    res = {name: np.concatenate(x) for name, x in (("speed", dv), ("turn_rate", dw), ("range", dr), ("bearing", db))}
    over = {name: np.concatenate([_horizon_std(x, n) * np.ones(1) for x in xs]) for name, xs in
            (("speed", dv), ("turn_rate", dw))}
    return NoiseFit(speed=float(np.median(over["speed"])), turn_rate=float(np.median(over["turn_rate"])),
                    range=robust_std(res["range"]), bearing=robust_std(res["bearing"]),
                    samples={k: int(np.isfinite(v).sum()) for k, v in res.items()},
                    plain={k: float(np.nanstd(v)) for k, v in res.items()},
                    per_tick={k: robust_std(res[k]) for k in ("speed", "turn_rate")})
