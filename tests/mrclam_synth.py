"""A synthetic recording in the MR.CLAM file format, for "any other MR.CLAM dataset directory".

Robots with other ids and barcodes than Dataset6's, another landmark map, other rates, a
field-of-view-limited camera with noise of a known size, an odometry that leads the motion by
a known lag, and a Vicon with a gap: what the replay must take unchanged.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

HEADER = "# synthetic MR.CLAM-format recording (swarmloc tests)\n#\n# columns as in MR.CLAM\n#\n"
T0 = 1_300_000_000.0


def write(out: Path, robots=(1, 2, 3), duration: float = 60.0, seed: int = 0, lag: float = 0.2,
          range_std: float = 0.05, bearing_std: float = 0.01, speed_std: float = 0.005, rate_std: float = 0.02) -> Path:
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
        x, y, h = np.empty_like(t), np.empty_like(t), np.empty_like(t)
        x[0], y[0], h[0] = -1.5 + 1.5 * i, -1.0 + 0.8 * i, 0.3 * i
        for k in range(1, t.size):
            x[k] = x[k - 1] + dt * v[k - 1] * np.cos(h[k - 1])
            y[k] = y[k - 1] + dt * v[k - 1] * np.sin(h[k - 1])
            h[k] = h[k - 1] + dt * w[k - 1]
        poses[r] = (x, y, h)
        odo_t = np.arange(0.0, duration, 1 / 40)
        idx = np.searchsorted(t, odo_t + lag)
        _save(out / f"Robot{r}_Odometry.dat", np.column_stack([T0 + odo_t, v[idx] + speed_std * rng.standard_normal(odo_t.size),
                                                               w[idx] + rate_std * rng.standard_normal(odo_t.size)]), "%.6f")
        vicon = np.arange(-2.0, duration, 1 / 100)
        vicon = vicon[(vicon < 20.0) | (vicon > 21.5)] if r == robots[-1] else vicon  # a 1.5 s Vicon gap
        j = np.clip(np.searchsorted(t, vicon), 0, t.size - 1)
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
                    rows.append([T0 + tm, barcodes[s], rr + range_std * rng.standard_normal(),
                                 b + bearing_std * rng.standard_normal()])
        rows.append([T0 + duration / 2, 999, 1.0, 0.0])  # an unknown barcode
        rows.sort(key=lambda row: row[0])
        _save(out / f"Robot{r}_Measurement.dat", rows, "%.6f")
    return out


def _save(path: Path, rows, fmt: str) -> None:
    with open(path, "w") as f:
        f.write(HEADER)
        np.savetxt(f, np.asarray(rows, float), fmt=fmt, delimiter="\t")
