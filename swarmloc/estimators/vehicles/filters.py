"""EKFs for the quadrotors and ground robots of Oliveros & Ashrafiuon 2023 (sections 4-5).

Two filters on the vehicle models of swarmloc/models/vehicles.py (x' = f(x) + g(x) u, propagated with
the actuator command in force):

* `VehicleEkf`: one vehicle's own EKF. Propagation with its command, the IMU's orientation,
  GPS fixes, and, for cooperative localization *without* CL (the paper's "without CL" runs), a
  relative position to a target whose estimate is taken as given (`update_relpos_anchor`).
* `JointVehicleEkf`: the paper's centralized EKF-CL over every member's stacked state, members
  of mixed state sizes (13 for a quadrotor, 7 for a ground robot). Propagation is eq. 44
  (P_ij <- F_i P_ij F_j^T, block-diagonal F); a relative position of target t measured in base
  b's body frame (section 4, eq. 34-41) is fused with eq. 45-47: the joint H is zero except in
  the base's and target's columns, and the gain K = P H^T S^-1 is computed for *all* members,
  so the cross-covariances built up by earlier relative measurements carry the information to
  vehicles not involved in this one.

Noise model. The world perturbs each actuator input by white noise held over the tick
(std `actuator_std`, one per input); it reaches the state only through g, so over a tick of
length dt the state is perturbed by dt g(x) eta, giving Q = dt^2 g diag(std^2) g^T
(`process_noise`). That Q is rank m < n (the inputs never reach the position directly, nor a
ground robot's z), so a tiny floor `Q_FLOOR` I is added to keep P positive definite.

Covariance update. Every update uses the Joseph form P+ = (I - K H) P (I - K H)^T + K R K^T
with the optimal gain K = P H^T S^-1. Algebraically that is eq. 47's P - K S K^T (the tests
check the two agree to 1e-12); numerically the Joseph form is a sum of positive semi-definite
terms, whereas P - K S K^T subtracts two nearly equal matrices when a precise measurement
(5 mm GPS or relative position) meets a loose prior, and rounding can then leave P with
negative eigenvalues. The cost (a few (N x N) products, N <= ~100) is irrelevant here.
After every update P is symmetrised ((P + P^T) / 2) and each quaternion renormalised.

Quaternion covariance. Renormalising q -> q/|q| is part of the estimator, so by default P is
mapped through its Jacobian as well (`_project_quaternion`), leaving a Q_FLOOR variance along q.
The plain additive form (P untouched) lets the relative-position measurement, which sees |q|
through the unnormalised R(q), gain information along a direction the renormalisation discards;
that made the filter overconfident (tests' two-quadrotor hover, 5 seeds: vehicle 2's mean
position NEES 3.8, 4.3, 16, 90 and 3.5e6 instead of 3; with the projection 2.5..4.3). `project_quaternion=False` gives the plain form of eq. 47, which the tests compare
against term by term.

Errors: wrong shapes, non-finite inputs and non-positive stds raise ValueError; an innovation
covariance that is not positive definite (singular) raises numpy.linalg.LinAlgError, which
callers count. Every update returns its NIS, e^T S^-1 e.

Pure numpy: no I/O, no middleware imports.
"""

from __future__ import annotations

import math

import numpy as np

from swarmloc.estimators.ekf.common import RejectedInput, checked
from swarmloc.filters import plausibility
from swarmloc.models.vehicles import VehicleModel, relpos, relpos_jacobian, wrap_yaw

# Added to the process noise on every predict with dt > 0 (state units squared, per tick).
# 1e-10 is a 1e-5 (m, rad, m/s ...) standard deviation per tick: far below anything the
# actuator noise or the sensors resolve, so it does not bias the filter, yet it keeps the
# directions the inputs do not reach (position, a ground robot's z and z_dot) from collapsing
# to exactly zero variance after repeated precise updates.
Q_FLOOR = 1e-10


# ---------------------------------------------------------------------------------------------
# checks


def _vector(a, n: int, what: str) -> np.ndarray:
    return checked(a, (n,), what)


def _matrix(a, n: int, what: str) -> np.ndarray:
    return checked(a, (n, n), what)


def _stds(std, m: int, what: str) -> np.ndarray:
    """A scalar std (every component) or one per component, all finite and > 0."""
    s = np.asarray(std, dtype=float)
    if s.ndim == 0:
        s = np.full(m, float(s))
    if s.shape != (m,):
        raise ValueError(f"{what}: expected a scalar or shape ({m},), got {s.shape}")
    if not (np.isfinite(s).all() and (s > 0.0).all()):
        raise ValueError(f"{what}: standard deviations must be finite and > 0, got {s}")
    return s


def _actuator_std(model: VehicleModel, actuator_std) -> np.ndarray:
    s = np.asarray(actuator_std, dtype=float)
    if s.shape != (model.input_dim,):
        raise ValueError(f"actuator_std: expected shape ({model.input_dim},) for a {model.name}, got {s.shape}")
    if not (np.isfinite(s).all() and (s >= 0.0).all()):
        raise ValueError(f"actuator_std: must be finite and >= 0, got {s}")
    return s


def _dt(dt) -> float:
    dt = float(dt)
    if not (math.isfinite(dt) and dt >= 0.0):
        raise ValueError(f"dt must be finite and >= 0, got {dt}")
    return dt


# ---------------------------------------------------------------------------------------------
# shared maths


def process_noise(model: VehicleModel, x, dt, actuator_std, q: float | None = None) -> np.ndarray:
    """Q (n, n) for one tick of length dt: actuator noise eta ~ N(0, diag(actuator_std^2)) held
    over the tick enters as dt g(x) eta, so Q = dt^2 g diag(std^2) g^T, plus Q_FLOOR I (dt > 0)
    so P stays positive definite where the inputs do not reach. dt = 0 gives Q = 0.

    q: instead, the constant Q = q I per tick of Oliveros & Ashrafiuon (section 6.1: "diagonal,
    with 0.1 values"), which does not follow the world's noise."""
    dt = _dt(dt)
    std = _actuator_std(model, actuator_std)
    n = model.state_dim
    if dt == 0.0:
        return np.zeros((n, n))
    if q is not None:
        if not (math.isfinite(q) and q > 0.0):
            raise ValueError(f"process noise q must be finite and > 0, got {q}")
        return float(q) * np.eye(n)
    G = np.asarray(model.g(x), dtype=float)
    if G.shape != (n, model.input_dim):
        raise ValueError(f"{model.name}.g: expected shape ({n}, {model.input_dim}), got {G.shape}")
    Gs = G * std  # g diag(std): columns scaled
    return dt * dt * (Gs @ Gs.T) + Q_FLOOR * np.eye(n)


def _predict_one(model: VehicleModel, x, u, dt, actuator_std, q: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x_next, F, Q) of one member's tick. dt = 0 leaves the state as it is (F = I, Q = 0)."""
    n = model.state_dim
    u = _vector(u, model.input_dim, f"{model.name} input u")
    dt = _dt(dt)
    if dt == 0.0:
        return np.array(x, dtype=float), np.eye(n), np.zeros((n, n))
    x_next, F = model.transition(x, u, dt)
    return np.asarray(x_next, dtype=float), np.asarray(F, dtype=float), process_noise(model, x, dt, actuator_std, q)


def _kalman_update(x: np.ndarray, P: np.ndarray, H: np.ndarray, e: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(x+, P+, NIS) for innovation e = z - h(x) with Jacobian H (m, N) and noise R (m, m).

    Joseph form (module docstring: why), symmetrised. S must be positive definite: a singular
    (or indefinite, or non-finite) S raises numpy.linalg.LinAlgError."""
    PHt = P @ H.T
    S = H @ PHt + R
    S = 0.5 * (S + S.T)
    if not np.isfinite(S).all():
        raise np.linalg.LinAlgError("innovation covariance is not finite")
    # Cholesky both tests positive definiteness (raises LinAlgError otherwise) and gives a
    # stable solve for K and the NIS.
    L = np.linalg.cholesky(S)
    # K = P H^T S^-1 = (S^-1 H P)^T, S symmetric; solve through L L^T.
    Y = np.linalg.solve(L, PHt.T)
    K = np.linalg.solve(L.T, Y).T
    w = np.linalg.solve(L, e)
    nis = float(w @ w)
    x_new = x + K @ e
    A = np.eye(x.size) - K @ H
    P_new = A @ P @ A.T + K @ R @ K.T
    P_new = 0.5 * (P_new + P_new.T)
    return x_new, P_new, nis


def _plausible(P: np.ndarray, H: np.ndarray, e: np.ndarray, R: np.ndarray, what: str) -> None:
    """A member's datum (issue 26, finding 7): its innovation within plausibility's bound
    against S = H P H^T + R, whatever a gate would say; RejectedInput (the filter unchanged)
    otherwise. With S so formed by the receiver, the update moves the state by at most
    dx^T P^-1 dx <= nis_limit (plausibility.step_bound)."""
    S = H @ P @ H.T + R
    why = plausibility.innovation(e, 0.5 * (S + S.T))
    if why is not None:
        raise RejectedInput(why, f"{what}: innovation {np.linalg.norm(e):.3g} past the bound")


def _quaternion_slice(model: VehicleModel) -> slice | None:
    """Where a quadrotor's quaternion sits in its state (None: no quaternion, e.g. a yaw angle)."""
    return slice(3, 7) if model.orientation_dim == 4 else None


def _normalise(model: VehicleModel, x: np.ndarray) -> tuple[np.ndarray | None, float]:
    """Renormalise x's quaternion in place; (the unit quaternion, the norm it had), or (None, 1)."""
    qs = _quaternion_slice(model)
    if qs is None:
        return None, 1.0
    n = float(np.linalg.norm(x[qs]))
    if not (n > 0.0 and math.isfinite(n)):
        raise np.linalg.LinAlgError(f"{model.name}: quaternion of norm {n} after the update")
    x[qs] = x[qs] / n
    return x[qs].copy(), n


def _project_quaternion(P: np.ndarray, start: int, q: np.ndarray, norm: float) -> None:
    """P <- N P N^T (in place) for a quaternion at P[start:start+4] renormalised from norm `norm`
    to unit q, then Q_FLOOR q q^T added back.

    Why: renormalising is a nonlinear function of the state, q -> q/|q|, with Jacobian
    N = (I - q q^T)/|q|; an EKF that applies it to x must apply N to P as well. Without it, P
    keeps a variance along q (the radial direction, which is not an attitude) that the
    relative-position measurement *does* see: the unnormalised R(q) of swarmloc/models/vehicles.py
    scales with |q|^2, so d(R^T a)/d(radial) = 2 (R^T + I) a. A 5 mm relative position at a
    few metres then explains part of every position residual by a change of |q| that the
    renormalisation throws away, while P records it as information gained (module docstring:
    the NEES it costs). The Q_FLOOR q q^T keeps P positive definite (the radial direction is
    otherwise exactly singular), as Q_FLOOR does elsewhere."""
    sl = slice(start, start + 4)
    N = (np.eye(4) - np.outer(q, q)) / norm
    P[sl, :] = N @ P[sl, :]
    P[:, sl] = P[:, sl] @ N.T
    P[sl, sl] += Q_FLOOR * np.outer(q, q)


def _attitude_innovation(model: VehicleModel, x: np.ndarray, z) -> np.ndarray:
    """z - h(x) for the IMU's orientation: a quaternion's sign is chosen to agree with the estimate
    (q and -q are the same attitude); a yaw innovation is wrapped to [-pi, pi)."""
    z = _vector(z, model.orientation_dim, f"{model.name} attitude z")
    h = np.asarray(model.orientation(x), dtype=float)
    if model.orientation_dim == 4:
        if float(z @ h) < 0.0:
            z = -z
        return z - h
    if model.orientation_dim == 1:
        return np.array([wrap_yaw(float(z[0] - h[0]))])
    return z - h


def _gps_cov(std, std_vertical) -> np.ndarray:
    s = _stds(std, 3, "gps std")
    if std_vertical is not None:
        s = s.copy()
        s[2] = _stds(std_vertical, 1, "gps std_vertical")[0]
    return np.diag(s * s)


# ---------------------------------------------------------------------------------------------
# one vehicle


class VehicleEkf:
    """One vehicle's own EKF. `x` (n,) and `P` (n, n) are plain attributes (callers may save and
    restore them).

    project_quaternion (default True): wherever the quaternion is renormalised (x0 and after
    every update) P is mapped through the normalisation's Jacobian (`_project_quaternion`: why).
    False gives the plain additive EKF of the paper (x renormalised, P left as it is)."""

    def __init__(self, model: VehicleModel, x0, P0, actuator_std, *, project_quaternion: bool = True,
                 q: float | None = None):
        self.model = model
        self.q = None if q is None else float(q)  # a constant Q = q I per tick (process_noise)
        self.project_quaternion = bool(project_quaternion)
        n = model.state_dim
        x = _vector(x0, n, f"{model.name} x0").copy()
        P0 = _matrix(P0, n, f"{model.name} P0")
        self.actuator_std = _actuator_std(model, actuator_std)
        self.x, self.P = self._normalised(x, 0.5 * (P0 + P0.T))

    def _normalised(self, x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q, norm = _normalise(self.model, x)
        if q is not None and self.project_quaternion:
            P = P.copy()
            _project_quaternion(P, _quaternion_slice(self.model).start, q, norm)
            P = 0.5 * (P + P.T)
        return x, P

    def predict(self, u, dt) -> None:
        """x = model.step(x, u, dt) (RK4); P = F P F^T + Q, F = I + dt J(x, u) at the prior."""
        x, F, Q = _predict_one(self.model, self.x, u, dt, self.actuator_std, self.q)
        P = F @ self.P @ F.T + Q
        self.x, self.P = x, 0.5 * (P + P.T)

    def _apply(self, H, e, R) -> float:
        x, P, nis = _kalman_update(self.x, self.P, H, e, R)
        self.x, self.P = self._normalised(x, P)
        return nis

    def update_gps(self, z, std, std_vertical=None) -> float:
        """Absolute position z (3,), std scalar or (3,); std_vertical, if given, replaces z's std."""
        z = _vector(z, 3, "gps z")
        H = np.zeros((3, self.model.state_dim))
        H[:, :3] = np.eye(3)
        return self._apply(H, z - self.model.position(self.x), _gps_cov(std, std_vertical))

    def update_attitude(self, z, std) -> float:
        """The IMU's orientation (quaternion (4,) or yaw (1,)); std scalar or per component."""
        m = self.model
        e = _attitude_innovation(m, self.x, z)
        s = _stds(std, m.orientation_dim, "attitude std")
        return self._apply(np.asarray(m.orientation_jacobian(self.x), dtype=float), e, np.diag(s * s))

    def update_relpos_anchor(self, z, std, target_model: VehicleModel, xt, Pt=None) -> float:
        """Relative position z (3,) of a target in this vehicle's body frame, against the target's
        estimate xt taken as given ("no CL"). Pt, if given, adds H_t Pt H_t^T to the innovation
        covariance (the cross-covariance between the two estimates is ignored, as it is unknown
        to a vehicle alone); only this vehicle's state is updated."""
        z = _vector(z, 3, "relpos z")
        s = _stds(std, 3, "relpos std")
        xt = _vector(xt, target_model.state_dim, f"{target_model.name} target xt")
        Hb, Ht = relpos_jacobian(self.model, self.x, target_model, xt)
        R = np.diag(s * s)
        if Pt is not None:
            Pt = _matrix(Pt, target_model.state_dim, f"{target_model.name} target Pt")
            R = R + Ht @ Pt @ Ht.T
        e = z - relpos(self.model, self.x, target_model, xt)
        # No plausibility bound here: "no CL" ignores the correlation between the two estimates
        # and its honest innovations pass 100 sigma (oliveros3: 4,860 in 120 s); it is the
        # paper's baseline, not a defence (issue 26, finding 7: not checked).
        return self._apply(np.asarray(Hb, dtype=float), e, R)


    def update_relpos_ci(self, z, std, target_model: VehicleModel, xt, Pt, criterion: str = "det") -> tuple[float, float]:
        """As update_relpos_anchor, but fused by covariance intersection: the target's estimate
        may be correlated with this one in any way (each may already hold the other's earlier
        estimates), so the update is made with both covariances inflated, P / w and
        (R + H_t Pt H_t^T) / (1 - w) (swarmloc.filters.fusion.ci_partial's form, linearised at x), which
        bounds every cross-covariance. The update inflates the states H does not see by 1 / w,
        so w must weigh them too: "det" (the default, unit-free) minimises log det P+, "trace"
        the trace of all of P+. (Minimising the position block's trace alone let the unseen
        states' covariance grow by 1 / w at every fusion: in the closed-loop caravan it passed
        1e9 within 8 s of losing GPS.) Returns (NIS at the chosen w, w); w = 1 is no update."""
        from swarmloc.filters.fusion import best_omega, objective

        z = _vector(z, 3, "relpos z")
        s = _stds(std, 3, "relpos std")
        xt = _vector(xt, target_model.state_dim, f"{target_model.name} target xt")
        Pt = _matrix(Pt, target_model.state_dim, f"{target_model.name} target Pt")
        Hb, Ht = relpos_jacobian(self.model, self.x, target_model, xt)
        Hb = np.asarray(Hb, dtype=float)
        R = np.diag(s * s) + Ht @ Pt @ Ht.T
        e = z - relpos(self.model, self.x, target_model, xt)
        _plausible(self.P, Hb, e, R, "relpos")

        def fuse(w: float):
            return _kalman_update(self.x, self.P / w, Hb, e, R / (1.0 - w))

        f = objective(criterion)

        def cost(w: float) -> float:
            if w <= 0.0:
                return math.inf  # H sees 3 of n states: w = 0 would discard the rest of the prior
            return f(self.P) if w >= 1.0 else f(fuse(w)[1])

        w = best_omega(cost)
        if w >= 1.0:
            return 0.0, 1.0
        x, P, nis = fuse(w)
        # Nor a fusion that moves the relative position further than the bound in S's metric
        # (a small w takes nearly all of the innovation).
        S = Hb @ self.P @ Hb.T + R
        why = plausibility.shift(Hb @ (x - self.x), 0.5 * (S + S.T))
        if why is not None:
            raise RejectedInput(why, "relpos: the fusion moves the estimate past the bound")
        self.x, self.P = self._normalised(x, P)
        return nis, w

# ---------------------------------------------------------------------------------------------
# the centralized joint filter


class JointVehicleEkf:
    """The paper's centralized EKF-CL (section 5) over members of mixed state sizes.

    `x` (N,) is every member's state stacked in `members` order, `P` (N, N) the joint covariance
    with its cross-covariance blocks; `slice(aid)` locates a member in both.

    project_quaternion: as for VehicleEkf, applied to every quadrotor member (on `add` and after
    every update)."""

    def __init__(self, *, project_quaternion: bool = True):
        self.project_quaternion = bool(project_quaternion)
        self._ids: list[int] = []
        self._models: dict[int, VehicleModel] = {}
        self._noise: dict[int, np.ndarray] = {}
        self._q: dict[int, float | None] = {}
        self._start: dict[int, int] = {}
        self.x = np.zeros(0)
        self.P = np.zeros((0, 0))

    @property
    def members(self) -> list[int]:
        return list(self._ids)

    def model(self, aid) -> VehicleModel:
        return self._models[self._known(aid)]

    def _known(self, aid):
        if aid not in self._models:
            raise ValueError(f"agent {aid} is not a member (members: {self._ids})")
        return aid

    def slice(self, aid) -> slice:
        aid = self._known(aid)
        s = self._start[aid]
        return slice(s, s + self._models[aid].state_dim)

    def _reindex(self) -> None:
        s = 0
        self._start = {}
        for a in self._ids:
            self._start[a] = s
            s += self._models[a].state_dim

    def add(self, aid, model: VehicleModel, x, P, actuator_std, q: float | None = None) -> None:
        """Append a member with its own estimate, uncorrelated with the others (zero cross-blocks);
        q: a constant process noise q I per tick instead of the actuator noise's (process_noise)."""
        if aid in self._models:
            raise ValueError(f"agent {aid} is already a member")
        n = model.state_dim
        x = _vector(x, n, f"agent {aid} x").copy()
        P = _matrix(P, n, f"agent {aid} P")
        std = _actuator_std(model, actuator_std)
        P = 0.5 * (P + P.T)
        quat, norm = _normalise(model, x)
        if quat is not None and self.project_quaternion:
            P = P.copy()
            _project_quaternion(P, _quaternion_slice(model).start, quat, norm)
            P = 0.5 * (P + P.T)
        N = self.x.size
        Pj = np.zeros((N + n, N + n))
        Pj[:N, :N] = self.P
        Pj[N:, N:] = P
        self.x = np.concatenate([self.x, x])
        self.P = Pj
        self._ids.append(aid)
        self._models[aid] = model
        self._noise[aid] = std
        self._q[aid] = None if q is None else float(q)
        self._reindex()

    def remove(self, aid) -> None:
        """Marginalise a member out: drop its rows and columns (a Gaussian's marginal)."""
        sl = self.slice(aid)
        keep = np.r_[0:sl.start, sl.stop:self.x.size]
        self.x = self.x[keep]
        self.P = self.P[np.ix_(keep, keep)]
        self._ids.remove(aid)
        del self._models[aid], self._noise[aid], self._q[aid]
        self._reindex()

    def marginal(self, aid) -> tuple[np.ndarray, np.ndarray]:
        sl = self.slice(aid)
        return self.x[sl].copy(), self.P[sl, sl].copy()

    def predict(self, inputs: dict) -> None:
        """Propagate every member with its (u, dt): eq. 44, block-diagonal F, P_ij <- F_i P_ij F_j^T,
        P_ii <- F_i P_ii F_i^T + Q_i. Every member needs an entry (ValueError otherwise: a member
        cannot be propagated without its command); ids that are not members are refused too."""
        missing = [a for a in self._ids if a not in inputs]
        if missing:
            raise ValueError(f"predict: no (u, dt) for members {missing}")
        extra = [a for a in inputs if a not in self._models]
        if extra:
            raise ValueError(f"predict: inputs for non-members {extra}")
        # Everything computed (and checked) before anything changes: a bad input leaves the
        # filter as it was.
        steps = {}
        for a in self._ids:
            try:
                u, dt = inputs[a]
            except (TypeError, ValueError):
                raise ValueError(f"predict: inputs[{a}] must be a (u, dt) pair") from None
            sl = self.slice(a)
            steps[a] = (sl,) + _predict_one(self._models[a], self.x[sl], u, dt, self._noise[a], self._q[a])
        x = self.x.copy()
        P = self.P.copy()
        # F P F^T with F block-diagonal, a block row then a block column at a time: O(N^2 n)
        # instead of forming the (N x N) F.
        for sl, xn, F, _ in steps.values():
            x[sl] = xn
            P[sl, :] = F @ P[sl, :]
        for sl, _, F, _ in steps.values():
            P[:, sl] = P[:, sl] @ F.T
        for sl, _, _, Q in steps.values():
            P[sl, sl] += Q
        self.x, self.P = x, 0.5 * (P + P.T)

    def _apply(self, H, e, R) -> float:
        # Every datum the centre takes is a member's (issue 26, finding 7).
        _plausible(self.P, H, e, R, "datum")
        x, P, nis = _kalman_update(self.x, self.P, H, e, R)
        projected = False
        for a in self._ids:
            sl = self.slice(a)
            xa = x[sl].copy()
            q, norm = _normalise(self._models[a], xa)
            x[sl] = xa
            if q is not None and self.project_quaternion:
                _project_quaternion(P, sl.start + _quaternion_slice(self._models[a]).start, q, norm)
                projected = True
        if projected:
            P = 0.5 * (P + P.T)
        self.x, self.P = x, P
        return nis

    def update_gps(self, aid, z, std, std_vertical=None) -> float:
        """Member aid's absolute position z (3,); the gain reaches every correlated member."""
        sl = self.slice(aid)
        z = _vector(z, 3, "gps z")
        H = np.zeros((3, self.x.size))
        H[:, sl.start:sl.start + 3] = np.eye(3)
        return self._apply(H, z - self._models[aid].position(self.x[sl]), _gps_cov(std, std_vertical))

    def update_attitude(self, aid, z, std) -> float:
        """Member aid's IMU orientation (quaternion or yaw), as VehicleEkf.update_attitude."""
        sl = self.slice(aid)
        m = self._models[aid]
        xa = self.x[sl]
        e = _attitude_innovation(m, xa, z)
        s = _stds(std, m.orientation_dim, "attitude std")
        H = np.zeros((m.orientation_dim, self.x.size))
        H[:, sl] = m.orientation_jacobian(xa)
        return self._apply(H, e, np.diag(s * s))

    def update_relpos(self, base, target, z, std) -> float:
        """Target's position z (3,) in base's body frame (eq. 34), fused with eq. 45-47: joint
        H = [.. H_b .. H_t ..], S = H P H^T + R (which expands to eq. 46 with its cross terms),
        K = P H^T S^-1 for all members."""
        if base == target:
            raise ValueError(f"update_relpos: base and target are the same agent {base}")
        sb, st = self.slice(base), self.slice(target)
        z = _vector(z, 3, "relpos z")
        s = _stds(std, 3, "relpos std")
        mb, mt = self._models[base], self._models[target]
        xb, xt = self.x[sb], self.x[st]
        Hb, Ht = relpos_jacobian(mb, xb, mt, xt)
        H = np.zeros((3, self.x.size))
        H[:, sb] = Hb
        H[:, st] = Ht
        e = z - relpos(mb, xb, mt, xt)
        return self._apply(H, e, np.diag(s * s))
