"""A jammer: a transmitter of noise at a (possibly moving) position, in a time window."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from netsim.channel.physics import FloatArray


def pos3(p: ArrayLike) -> FloatArray:
    a = np.asarray(p, dtype=float).reshape(-1)
    if a.shape == (2,):
        return np.array([a[0], a[1], 0.0])
    if a.shape == (3,):
        return a.copy()
    raise ValueError(f"position must be 2D or 3D, got shape {np.shape(p)}")


@dataclass(frozen=True)
class Jammer:
    """An emitter of noise-like power, active on the half-open interval [t_start, t_end).

    ``power_dbm`` is the EIRP. With ``band_hz`` wider than the receiver
    bandwidth only the fraction B / band_hz falls in band; ``None`` puts all of
    the power in band. Received power uses the model's path loss without shadowing.
    """

    position: tuple[float, ...]
    power_dbm: float
    t_start: float
    t_end: float
    band_hz: float | None = None

    def __post_init__(self) -> None:
        # Stored as a tuple so the dataclass stays hashable and comparable.
        object.__setattr__(self, "position", tuple(float(v) for v in pos3(self.position)))
        if self.t_end < self.t_start:
            raise ValueError("jammer t_end must be >= t_start")
        if self.band_hz is not None and self.band_hz <= 0:
            raise ValueError("jammer band_hz must be > 0")

    def active_during(self, t0: float, t1: float) -> bool:
        """Whether [t_start, t_end) intersects the half-open interval [t0, t1)."""
        return self.t_start < t1 and self.t_end > t0
