"""UKF-CCL: the centralized UKF over the joint state of the whole swarm, the gold standard.

It sees every platform's odometry and every relative measurement, processes the measurements
of a tick in the same key order as the distributed chains (`swarmloc.node.keyed_measurements`:
measurer, kind, target, index), factors P with the measuring and measured platform first
(eq. 17), and gates them with the same chi-square gate, keyed (measurer, kind, target).
"""

from __future__ import annotations

import numpy as np

from swarmloc.filters import fusion, kalman, plausibility
from swarmloc.models.measurements import RangeBearing, StateLayout, wrap_angle
from swarmloc.models.motion import MOTION_MODELS, PlanarPoseBias, Range, reported_dim
from swarmloc.node import LANDMARK, RANGE, RANGE_BEARING, Estimate, keyed_measurements, odometry_of
from swarmloc.wire.messages import Sensors


class Observations:
    """What each kind of measurement is, shared by UKF-DCL and UKF-CCL: h on the stacked states
    of the platforms it reads (the measurer's, then the measured agent's, none for a landmark),
    its angle components, and (z, R) from a message. Range-bearing needs the heading in the
    state (planar-pose); a landmark must be on the map."""

    def __init__(self, model, landmarks=None):
        self.model = model
        self.landmarks = {int(i): np.asarray(p, float) for i, p in dict(landmarks or {}).items()}
        self.range = Range(model)
        lay = model.layout
        pose = lay.attitude is not None and lay.pos_dim == 2
        # std is R, which comes with each message: these models are used for h only.
        self.rb = RangeBearing(lay, std=1.0, other=lay, body_frame=True) if pose else None
        self.mark = RangeBearing(lay, std=1.0, other=StateLayout.planar(), body_frame=True) if pose else None

    @staticmethod
    def measured(key) -> int:
        """The platform a measurement involves besides its measurer (the measurer itself for a landmark)."""
        return key[0] if key[1] == LANDMARK else key[2]

    @staticmethod
    def dim(kind: int) -> int:
        return 1 if kind == RANGE else 2

    def usable(self, key) -> bool:
        kind, target = key[1], key[2]
        if kind == RANGE:
            return target != key[0]
        if self.rb is None:
            return False
        return target != key[0] if kind == RANGE_BEARING else target in self.landmarks

    def h(self, key):
        """(h on stacked platform states, angle components of z)."""
        if key[1] == RANGE:
            return self.range.h_joint, ()
        if key[1] == RANGE_BEARING:
            d = self.model.state_dim
            return (lambda X: self.rb.h(X[..., :d], X[..., d:2 * d])), self.rb.angles
        mark = self.landmarks[key[2]]
        return (lambda X: self.mark.h(X, mark)), self.mark.angles

    def z(self, kind: int, msg) -> tuple[np.ndarray, np.ndarray]:
        if kind == RANGE:
            return np.array([msg.range]), np.array([[msg.std**2]])
        return np.array([msg.range, msg.bearing]), np.diag([msg.range_std**2, msg.bearing_std**2])

    @staticmethod
    def innovation(z: np.ndarray, z_bar: np.ndarray, angles) -> np.ndarray:
        nu = z - z_bar
        if angles:
            nu[list(angles)] = wrap_angle(nu[list(angles)])
        return nu


class CentralizedUKF:
    algorithm = "ukf-ccl"

    def __init__(self, x0: dict[int, np.ndarray], P0: np.ndarray, model="planar-speed-heading", spread: float | None = None,
                 landmarks: dict | None = None, gate: kalman.Gate | None = None):
        self.model = MOTION_MODELS[model] if isinstance(model, str) else model
        self.ids = sorted(x0)
        self.d = self.model.state_dim
        # Where each block starts in the joint state: the platforms', then any a subclass adds.
        self.offset = {a: i * self.d for i, a in enumerate(self.ids)}
        self.size = {a: self.d for a in self.ids}
        self.x = np.concatenate([np.asarray(x0[a], float) for a in self.ids])
        self.P = kalman.block_diag([np.asarray(P0, float)] * len(self.ids))
        self.ut = kalman.UnscentedTransform.for_pair(self.model.state_dim, spread)
        self.obs = Observations(self.model, landmarks)
        self.gate = gate if gate is not None else kalman.Gate()
        self.k = -1
        self.nis: dict[int, list[tuple[float, int]]] = {}
        self.gated = 0
        # Measurements refused as implausible (issue 26, finding 7), and who is told of each:
        # a replica's node counts them in its drops (CslCtlNode).
        self.refused: dict[str, int] = {}
        self.on_refused = None

    @classmethod
    def from_scenario(cls, scenario, ids, settings=None):
        est = scenario.estimation
        x0 = {a: scenario.prior(a)[0] for a in ids}
        P0, model = scenario.prior(ids[0])[1], scenario.agent(ids[0]).model
        bias = PlanarPoseBias.from_settings(settings) if model == "planar-pose" else None
        if bias is not None:  # the pose with its odometry's bias states (docs/mrclam.md)
            x0 = {a: bias.augment(x, P0)[0] for a, x in x0.items()}
            P0, model = bias.augment(x0[ids[0]], P0)[1], bias
        return cls(x0, P0, model, est.spread,
                   {m.id: m.position for m in scenario.world.landmarks}, kalman.Gate(est.gate, est.gate_open_after))

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
        if self.model.identity_transition:
            self.P = self.P + kalman.block_diag(Qs)  # F P F^T with F = I, without two n^3 products
        else:
            self.x, self.P = kalman.predict(self.x, self.P, kalman.block_diag(Fs), kalman.block_diag(Qs))
        self.k = frames[self.ids[0]].k
        self.nis = {a: [] for a in self.ids}
        for key, z, R in self.observations(frames):
            nis = self.update(key[0], self.obs.measured(key), z, R, key)
            if nis is not None:
                self.nis[key[0]].append(nis)

    def observations(self, frames: dict[int, Sensors]):
        """(key, z, R) of every usable measurement of the tick, in key order."""
        keyed = [(key, r) for m, s in frames.items() for key, r in keyed_measurements(m, s) if self.obs.usable(key)]
        for key, r in sorted(keyed, key=lambda t: t[0]):
            yield (key, *self.obs.z(key[1], r))

    @staticmethod
    def measurements(frames: dict[int, Sensors]):
        """(m, n, z, R) of the tick's ranges among platforms, in key order."""
        keyed = [(key, r) for m, s in frames.items() for key, r in keyed_measurements(m, s)
                 if key[1] == RANGE and r.target != m]
        for (m, _, n, _), r in sorted(keyed, key=lambda t: t[0]):
            yield m, n, np.array([r.range]), np.array([[r.std**2]])

    def update(self, m: int, n: int, z: np.ndarray, R: np.ndarray, key=None) -> tuple[float, int] | None:
        """Measurement `key` (a range m -> n when None) through the gate; (NIS, dof), or None if gated."""
        key = (m, RANGE, n, 0) if key is None else key
        idx = np.r_[self.block(m)] if key[1] == LANDMARK else np.r_[self.block(m), self.block(n)]
        # The sigma points of the measured platforms' columns of the eq. 17 factor only: the
        # factor's other columns are zero in those rows, so their sigma points read h at the
        # mean and fold into the centre weight (kalman.UnscentedTransform). Those columns are
        # S_k = P[:, idx] L^-T with L the lower factor of P[idx, idx]: O(n k) per measurement
        # instead of a Cholesky factor of all of P (O(n^3)), the same filter (equal to the
        # whole factor's to rounding, tests/test_ukf_ccl.py); what makes it run at 256 platforms.
        L = np.linalg.cholesky(self.P[np.ix_(idx, idx)])
        h, angles = self.obs.h(key)
        z_bar, Pzz, Y = self.ut.measurement_moments(self.x[idx], L, h, angles)
        nu = self.obs.innovation(z, z_bar, angles)
        # A member's measurement (in a replica, CSL-CTL: another agent's share; issue 26,
        # finding 7) past the innovation bound, or claiming more information than its innovation
        # covariance allows, is refused before the gate, which stands open after a streak.
        reason = plausibility.update(nu, Pzz + R, Y)
        if reason is not None:
            self.refused[reason] = self.refused.get(reason, 0) + 1
            if self.on_refused is not None:
                self.on_refused(reason, f"measurement {tuple(key)}")
            return None
        nis = fusion.nis(nu, Pzz + R)
        if not self.gate.admit(tuple(key[:3]), nis, len(z)):
            self.gated += 1
            return None
        Pxz = kalman.solve_lower(L, self.P[idx]).T @ Y
        self.x, self.P, _ = kalman.update(self.x, self.P, Pxz, Pzz + R, nu)
        return nis, len(z)

    def estimate(self, a: int) -> Estimate:
        """Platform a's marginal (of its reported part: an augmented state's pose), with the NIS of
        the measurements a took this tick."""
        b = slice(self.offset[a], self.offset[a] + min(self.size[a], reported_dim(self.model)))
        return Estimate(self.k, self.x[b].copy(), self.P[b, b].copy(), tuple(self.nis.get(a, ())))
