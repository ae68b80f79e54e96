"""UKF-CCL: the centralized UKF over the joint state of the whole swarm, the gold standard.

It sees every platform's odometry and every relative measurement, processes the measurements
of a tick in the same key order (measurer, measured, index) as the distributed chains, and
factors P with the measuring and measured platform first (eq. 17).
"""

from __future__ import annotations

import numpy as np

from swarmloc import fusion, kalman
from swarmloc.messages import Sensors
from swarmloc.models import MOTION_MODELS, Range
from swarmloc.node import Estimate, keyed_ranges, odometry_of


class CentralizedUKF:
    algorithm = "ukf-ccl"

    def __init__(self, x0: dict[int, np.ndarray], P0: np.ndarray, model="planar-speed-heading", spread: float | None = None):
        self.model = MOTION_MODELS[model] if isinstance(model, str) else model
        self.ids = sorted(x0)
        self.d = self.model.state_dim
        # Where each block starts in the joint state: the platforms', then any a subclass adds.
        self.offset = {a: i * self.d for i, a in enumerate(self.ids)}
        self.size = {a: self.d for a in self.ids}
        self.x = np.concatenate([np.asarray(x0[a], float) for a in self.ids])
        self.P = kalman.block_diag([np.asarray(P0, float)] * len(self.ids))
        self.ut = kalman.UnscentedTransform.for_pair(self.model.state_dim, spread)
        self.meas = Range(self.model)
        self.k = -1
        self.nis: dict[int, list[tuple[float, int]]] = {}

    @classmethod
    def from_scenario(cls, scenario, ids, settings=None):
        x0 = {a: scenario.prior(a)[0] for a in ids}
        return cls(x0, scenario.prior(ids[0])[1], scenario.agent(ids[0]).model, scenario.estimation.spread)

    def block(self, a) -> slice:
        return slice(self.offset[a], self.offset[a] + self.size[a])

    def step(self, frames: dict[int, Sensors]) -> None:
        """One tick: every platform's time update, then the tick's measurements in key order."""
        Fs, Qs = [], []
        for a in self.ids:
            x, F, Q = self.model.predict(self.x[self.block(a)], odometry_of(frames[a]))
            self.x[self.block(a)] = x
            Fs.append(F)
            Qs.append(Q)
        self.x, self.P = kalman.predict(self.x, self.P, kalman.block_diag(Fs), kalman.block_diag(Qs))
        self.k = frames[self.ids[0]].k
        self.nis = {a: [] for a in self.ids}
        for m, n, z, R in self.measurements(frames):
            self.nis[m].append(self.update(m, n, z, R))

    @staticmethod
    def measurements(frames: dict[int, Sensors]):
        keyed = [(key, r) for m, s in frames.items() for key, r in keyed_ranges(m, s) if r.target != m]
        for (m, n, _), r in sorted(keyed, key=lambda t: t[0]):
            yield m, n, np.array([r.range]), np.array([[r.std**2]])

    def update(self, m: int, n: int, z: np.ndarray, R: np.ndarray) -> tuple[float, int]:
        idx = np.r_[self.block(m), self.block(n)]
        S = kalman.cholesky_first(self.P, idx)
        z_bar, Pzz, Y = self.ut.measurement_moments(self.x, S, lambda X: self.meas.h_joint(X[..., idx]))
        self.x, self.P, _ = kalman.update(self.x, self.P, S @ Y, Pzz + R, z - z_bar)
        return fusion.nis(z - z_bar, Pzz + R), len(z)

    def estimate(self, a: int) -> Estimate:
        """Platform a's marginal, with the NIS of the measurements a took this tick."""
        b = self.block(a)
        return Estimate(self.k, self.x[b].copy(), self.P[b, b].copy(), tuple(self.nis.get(a, ())))
