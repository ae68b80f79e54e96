"""Motion and measurement models.

A model owns its state dimension: nothing else in swarmloc assumes a platform's state is a
2-vector. Later vehicle models (heading, velocity, 3D) register here under their own name.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np


@dataclass(frozen=True)
class Odometry:
    """Proprioceptive input for one step: measured speed and heading, with their noise.

    The standard deviations travel with the reading because the driver (or netsim's sensor
    model) is the one that knows them; the filter needs them for the process noise.
    """

    dt: float
    speed: float
    heading: float
    speed_std: float
    heading_std: float


class MotionModel:
    """Per-platform motion model: x_{k+1} = f(x_k, u_k) with Jacobian F and process noise Q."""

    name: ClassVar[str]
    state_dim: ClassVar[int]
    position_dim: ClassVar[int]
    # True when F is the identity: cross-covariances P_ij are then untouched by a time
    # update, which is what lets each node predict alone (UKF-DCL eq. 3-4).
    identity_transition: ClassVar[bool]

    def predict(self, x: np.ndarray, u: Odometry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        raise NotImplementedError

    def position(self, x: np.ndarray) -> np.ndarray:
        return x[..., : self.position_dim]


class PlanarSpeedHeading(MotionModel):
    """UKF-DCL eq. (1): planar position driven by measured speed and heading.

    x_{k+1} = x_k + dt * v_m * [cos(phi_m), sin(phi_m)]. Speed and heading errors enter
    through G = d f / d(v, phi), so Q = G diag(speed_std^2, heading_std^2) G^T.
    """

    name = "planar-speed-heading"
    state_dim = 2
    position_dim = 2
    identity_transition = True

    def predict(self, x, u):
        c, s = np.cos(u.heading), np.sin(u.heading)
        x_new = x + u.dt * u.speed * np.array([c, s])
        G = u.dt * np.array([[c, -u.speed * s], [s, u.speed * c]])
        Q = G @ np.diag([u.speed_std**2, u.heading_std**2]) @ G.T
        return x_new, np.eye(2), Q


MOTION_MODELS: dict[str, MotionModel] = {m.name: m for m in (PlanarSpeedHeading(),)}


class RelativeMeasurement:
    """z = h(x_a, x_b) + noise between two platforms; vectorised over leading axes."""

    name: ClassVar[str]
    dim: ClassVar[int]

    def __init__(self, model: MotionModel):
        self.model = model

    def h(self, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def h_joint(self, x_pair: np.ndarray) -> np.ndarray:
        """h on stacked [x_a; x_b] (last axis), the form the unscented transform wants."""
        d = self.model.state_dim
        return self.h(x_pair[..., :d], x_pair[..., d : 2 * d])


class Range(RelativeMeasurement):
    """UKF-DCL eq. (2) with a distance sensor: z = ||p_a - p_b|| + n, n ~ N(0, R)."""

    name = "range"
    dim = 1

    def h(self, xa, xb):
        diff = self.model.position(xa) - self.model.position(xb)
        return np.linalg.norm(diff, axis=-1, keepdims=True)
