"""A synthetic recording in the MR.CLAM file format, for "any other MR.CLAM dataset directory".

Robots with other ids and barcodes than Dataset6's, another landmark map, other rates, a
field-of-view-limited camera with noise of a known size, an odometry that leads the motion by
a known lag, and a Vicon with a gap: what the replay must take unchanged.

Optionally the errors of a real robot, of known sizes (swarmloc calibrate must find them): a
speed the robot does not reach (speed_scale: the motion is speed_scale times the logged
command), a speed error correlated in time (an AR(1) process of std colour_std and time
constant colour_tau on the logged speed), a camera whose range is range_bias[0] +
range * (1 + range_bias[1] * bearing^2) and whose bearing is off by bearing_bias, with a range
noise in proportion to the range (range_rel_std) instead of a fixed one.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import scipy.signal

HEADER = "# synthetic MR.CLAM-format recording (swarmloc tests)\n#\n# columns as in MR.CLAM\n#\n"
T0 = 1_300_000_000.0


def write(out: Path, robots=(1, 2, 3), duration: float = 60.0, seed: int = 0, lag: float = 0.2,
          range_std: float = 0.05, bearing_std: float = 0.01, speed_std: float = 0.005, rate_std: float = 0.02,
          speed_scale: float = 1.0, colour_std: float = 0.0, colour_tau: float = 5.0, range_bias=(0.0, 0.0),
          bearing_bias: float = 0.0, range_rel_std: float | None = None) -> Path:
    rng = np.random.default_rng(seed)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    first_landmark = max(robots) + 1
    landmarks = {first_landmark + i: xy for i, xy in enumerate(
        [(-4.0, -3.0), (0.0, -3.5), (4.0, -3.0), (4.5, 0.0), (4.0, 3.0), (0.0, 3.5), (-4.0, 3.0), (-4.5, 0.0)])}
    subjects = list(robots) + list(landmarks)
    barcodes = {s: 100 + 7 * s for s in subjects}
    _save(out / "Barcodes.dat", [[s, barcodes[s]] for s in subjects], "%d")
    _save(out / "Landmark_Groundtruth.dat", [[s, x, y, 1e-4, 1e-4] for s, (x, y) in landmarks.items()], "%.6f")
    dt = 0.005  # the truth simulation's step
    t = np.arange(0.0, duration + 2 * lag + dt, dt)
    poses = {}
    for i, r in enumerate(robots):
        # Each robot circles a centre of its own, with a slowly varying speed: v and w are the
        # true commands, which reach the motion `lag` seconds after they are logged.
        v = 0.12 + 0.03 * np.sin(2 * np.pi * t / (20.0 + 5 * i))
        w = v / (1.5 + 0.5 * i) * (1 if i % 2 == 0 else -1)
        # Euler steps of dt: each pose the previous one plus dt times the previous commands.
        h = 0.3 * i + np.r_[0.0, np.cumsum(dt * w[:-1])]
        x = -1.5 + 1.5 * i + np.r_[0.0, np.cumsum(dt * v[:-1] * np.cos(h[:-1]))]
        y = -1.0 + 0.8 * i + np.r_[0.0, np.cumsum(dt * v[:-1] * np.sin(h[:-1]))]
        poses[r] = (x, y, h)
        odo_t = np.arange(0.0, duration, 1 / 40)
        idx = np.round((odo_t + lag) / dt).astype(int)  # the truth step at that time (searchsorted would jitter)
        colour = np.zeros(odo_t.size)
        if colour_std > 0:
            phi = np.exp(-(1 / 40) / colour_tau)
            shocks = colour_std * np.sqrt(1 - phi**2) * rng.standard_normal(odo_t.size)
            shocks[0] = colour_std * rng.standard_normal()  # the stationary start
            colour = scipy.signal.lfilter([1.0], [1.0, -phi], shocks)
        logged_v = v[idx] / speed_scale + colour + speed_std * rng.standard_normal(odo_t.size)
        _save(out / f"Robot{r}_Odometry.dat", np.column_stack([T0 + odo_t, logged_v,
                                                               w[idx] + rate_std * rng.standard_normal(odo_t.size)]), "%.6f")
        vicon = np.arange(-2.0, duration, 1 / 100)
        vicon = vicon[(vicon < 20.0) | (vicon > 21.5)] if r == robots[-1] else vicon  # a 1.5 s Vicon gap
        j = np.clip(np.round(vicon / dt).astype(int), 0, t.size - 1)
        _save(out / f"Robot{r}_Groundtruth.dat", np.column_stack([T0 + vicon, x[j], y[j], (h[j] + np.pi) % (2 * np.pi) - np.pi]),
              "%.6f")
    for r in robots:
        rows = []
        for tm in np.sort(rng.uniform(0.5, duration - 0.5, size=int(6 * duration))):
            k = np.searchsorted(t, tm)
            x, y, h = (a[k] for a in poses[r])
            for s in subjects:
                if s == r:
                    continue
                sx, sy = (poses[s][0][k], poses[s][1][k]) if s in poses else landmarks[s]
                rr, b = np.hypot(sx - x, sy - y), np.arctan2(sy - y, sx - x) - h
                b = (b + np.pi) % (2 * np.pi) - np.pi
                if rr < 5.0 and abs(b) < 0.6:
                    noise = range_std if range_rel_std is None else range_rel_std * rr
                    measured = range_bias[0] + rr * (1 + range_bias[1] * b * b)
                    rows.append([T0 + tm, barcodes[s], measured + noise * rng.standard_normal(),
                                 b + bearing_bias + bearing_std * rng.standard_normal()])
        rows.append([T0 + duration / 2, 999, 1.0, 0.0])  # an unknown barcode
        rows.sort(key=lambda row: row[0])
        _save(out / f"Robot{r}_Measurement.dat", rows, "%.6f")
    return out


def _save(path: Path, rows, fmt: str) -> None:
    with open(path, "w") as f:
        f.write(HEADER)
        np.savetxt(f, np.asarray(rows, float), fmt=fmt, delimiter="\t")
