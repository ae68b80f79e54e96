"""The posterior Cramér-Rao bound (PCRB) of a run's estimation problem, from truth and the models.

Tichavský, Muravchik and Nehorai (IEEE TSP 46(5), 1998) give the Bayesian information matrix J_k
of the whole state at tick k recursively. For x_{k+1} = f(x_k) + w, w ~ N(0, Q), and
z = h(x) + v, v ~ N(0, R):

    J_{k+1} = D22 - D21 (J_k + D11)^-1 D12,
    D11 = F^T Q^-1 F,  D12 = D21^T = -F^T Q^-1,  D22 = Q^-1 + E[H^T R^-1 H],

F and H the Jacobians of f and h. By the matrix inversion lemma the prediction part is
(F J_k^-1 F^T + Q)^-1, the covariance form. Neither form survives what our problems have: a
singular Q (a vehicle's actuator noise reaches 2 or 4 of its 7 or 13 states; a target does not
move) and a singular J (a target nobody has ranged yet carries no information). With
M = F^-T J_k F^-1 (F is invertible for every model here) the same matrix is

    (M^-1 + Q)^-1 = M (I + Q M)^-1 = M - M C (I + C^T M C)^-1 C^T M,  Q = C C^T,

C (n x r) from each block's eigenvectors, only the directions Q reaches: it needs neither Q nor
J to be invertible (I + C^T M C has every eigenvalue >= 1, so one Cholesky factor does), and
costs O(n^2 r). Then the measurements of the tick add their H^T R^-1 H, and each position bound
comes from the Cholesky factor of J and the columns of its inverse that it needs.
`InformationRecursion` is this recursion; tests/test_bounds.py checks it against the D-form and
against a Kalman filter's covariance.

What is bounded. The state is the swarm's joint state, every localized agent in its estimators'
coordinates (planar position; planar pose; the 16-state INS error state of a UAS; a vehicle's
state, a quadrotor's attitude as a 3-vector rotation instead of 4 quaternion components) plus
each target's position. The expectation over the state in E[H^T R^-1 H] is replaced by its value
at the run's one true trajectory: every Jacobian is evaluated at the true state, the inputs the
motion models read (odometry, IMU samples, actuator commands) as recorded, and only the
measurements the recorded sensor stream holds count, each with the std its message states. The
prior's covariance is J_0^-1; targets have no prior. What comes out, inv(J_k), bounds the error
covariance of any estimator of x_k from the data up to tick k under these models (linearised
at truth: exact for linear models, first order otherwise). docs/estimators.md says which
assumptions each family adds.

Pure: no I/O. `pcrb(scenario, record)` computes the bound of a recorded run.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.linalg.lapack

from swarmloc.models import ins
from swarmloc.models.measurements import PositionFix, Pseudorange, Range, RangeBearing, RelativePosition, StateLayout
from swarmloc.models.motion import MOTION_MODELS
from swarmloc.models.vehicles import MODELS as VEHICLE_MODELS
from swarmloc.models.vehicles import actuator_std, quat_G, relpos_jacobian
from swarmloc.node import odometry_of

# --------------------------------------------------------------------------- the recursion


class InformationRecursion:
    """The information matrix J of a state made of blocks (name -> size), in block order."""

    def __init__(self, blocks: dict):
        self.names = list(blocks)
        self.start, at = {}, 0
        for name, size in blocks.items():
            self.start[name] = at
            at += int(size)
        self.size = {name: int(s) for name, s in blocks.items()}
        self.n = at
        self.J = np.zeros((at, at))

    def idx(self, name) -> np.ndarray:
        return np.arange(self.start[name], self.start[name] + self.size[name])

    def set_prior(self, name, P0: np.ndarray) -> None:
        """Block `name` starts with covariance P0, independent of the rest."""
        i = self.idx(name)
        self.J[np.ix_(i, i)] = _inverse(P0)

    def span(self, name) -> slice:
        return slice(self.start[name], self.start[name] + self.size[name])

    def predict(self, steps: dict) -> None:
        """Time update: name -> (F, Q) of that block (blocks not named keep F = I, Q = 0).

        M = G^T J G (G = F^-1, block-diagonal), then with Q = C C^T (C from each block's
        eigenvectors, only the directions Q reaches) Woodbury's (M^-1 + Q)^-1 =
        M - M C (I + C^T M C)^-1 C^T M = M - X^T X, X = L^-1 C^T M, L L^T = I + C^T M C: one
        Cholesky factor of a positive definite matrix (its eigenvalues are >= 1 whatever M's
        rank), about a third of the work of solving with I + Q M."""
        J = self.J
        for name, (F, _) in steps.items():
            if _is_eye(F):
                continue
            s, Gi = self.span(name), np.linalg.inv(F)
            J[:, s] = J[:, s] @ Gi
            J[s, :] = Gi.T @ J[s, :]
        factors = []
        for name, (_, Q) in steps.items():
            if not np.any(Q):
                continue
            C = _factor(Q)
            if C.shape[1]:
                factors.append((self.span(name), C))
        if factors:
            r = sum(C.shape[1] for _, C in factors)
            MC = np.empty((self.n, r))  # M C, C block-diagonal: one block column at a time
            at = 0
            for s, C in factors:
                MC[:, at:at + C.shape[1]] = J[:, s] @ C
                at += C.shape[1]
            A = np.eye(r)
            at = 0
            for s, C in factors:  # + C^T M C, one block row at a time
                A[at:at + C.shape[1], :] += C.T @ MC[s, :]
                at += C.shape[1]
            L = np.linalg.cholesky(0.5 * (A + A.T))
            X = _lower_solve(L, MC.T)
            J -= X.T @ X
        self.J = 0.5 * (J + J.T)

    def add(self, rows: list) -> list[int]:
        """Measurements z = h(blocks) + v, v ~ N(0, R), each row (names, [dh/d block], R): their
        information sum(H^T R^-1 H), added at once as Hw^T Hw, Hw the rows whitened by R^-1/2.
        Returns the indices of the rows left out: a Jacobian or std that is not finite, an R
        that is not positive definite."""
        if not rows:
            return []
        m = sum(R.shape[0] for _, _, R in rows)
        H = np.zeros((m, self.n))
        at, spans, bad = 0, [], []
        with np.errstate(invalid="ignore", divide="ignore"):
            for ri, (names, Hs, R) in enumerate(rows):
                d = R.shape[0]
                spans.append((at, at + d))
                if d == 1 or not np.any(R - np.diag(np.diag(R))):
                    W = (1.0 / np.sqrt(np.diag(R)))[:, None]
                else:
                    try:
                        W = np.linalg.inv(np.linalg.cholesky(0.5 * (R + R.T)))  # R^-1 = W^T W
                    except np.linalg.LinAlgError:
                        bad.append(ri)
                        at += d
                        continue
                for name, Hi in zip(names, Hs):
                    s = self.start[name]
                    H[at:at + d, s:s + Hi.shape[1]] += W * Hi if W.shape[1] == 1 else W @ Hi  # += : a block named twice sums
                at += d
        finite = np.isfinite(H).all(axis=1)
        if not finite.all():
            bad = sorted(set(bad) | {ri for ri, (a, b) in enumerate(spans) if not finite[a:b].all()})
        for ri in bad:
            H[spans[ri][0]:spans[ri][1]] = 0.0
        Y = H.T @ H
        self.J += 0.5 * (Y + Y.T)
        return bad

    def position_bounds(self, groups: list, flat: list = ()) -> np.ndarray:
        """sqrt(trace(inv(J)[g, g])) for each group g of indices: what `covariance` would give,
        from one Cholesky factor J = L L^T and the columns of L^-1 that the groups need
        (inv(J)_jj = |L^-1 e_j|^2), not the whole inverse. Blocks in `flat` without full
        information (NaN in `covariance`) take `covariance`'s way."""
        if flat:
            for name in flat:
                s = self.span(name)
                vals = np.linalg.eigvalsh(self.J[s, s])
                if not (vals > 1e-9 * max(float(vals.max(initial=0.0)), 1e-300)).all():
                    P = self.covariance(flat)
                    return np.array([math.sqrt(max(float(np.trace(P[np.ix_(g, g)])), 0.0))
                                     if np.isfinite(P[np.ix_(g, g)]).all() else math.nan for g in groups])
        L = np.linalg.cholesky(0.5 * (self.J + self.J.T))
        cols = np.concatenate(groups)
        E = np.zeros((self.n, cols.size))
        E[cols, np.arange(cols.size)] = 1.0
        V = _lower_solve(L, E)
        d = np.einsum("ij,ij->j", V, V)
        out, at = [], 0
        for g in groups:
            out.append(math.sqrt(float(d[at:at + len(g)].sum())))
            at += len(g)
        return np.array(out)

    def covariance(self, flat: list = ()) -> np.ndarray:
        """inv(J). Blocks in `flat` (targets) may carry no or partial information: their
        directions without information are left out of the inverse (they couple to nothing,
        see the module docstring) and come out NaN; every other block must be positive definite."""
        keep, basis = [], []
        for name in self.names:
            i = self.idx(name)
            if name not in flat:
                keep.append(i)
                continue
            vals, vecs = np.linalg.eigh(self.J[np.ix_(i, i)])
            good = vals > 1e-9 * max(float(vals.max(initial=0.0)), 1e-300)
            if good.all():
                keep.append(i)
            else:
                basis.append((i, vecs[:, good]))
        if not basis:
            return _inverse(self.J)
        # Coordinates: every kept component as it is, the informed directions of the others.
        cols = [np.eye(self.n)[:, i] for i in keep] + [np.eye(self.n)[:, i] @ V for i, V in basis]
        T = np.hstack(cols)
        P = np.full((self.n, self.n), np.nan)
        if T.shape[1] == 0:
            return P
        Pr = T @ _inverse(T.T @ self.J @ T) @ T.T
        full = np.concatenate(keep) if keep else np.zeros(0, int)
        P[np.ix_(full, full)] = Pr[np.ix_(full, full)]
        return P


def _factor(Q: np.ndarray) -> np.ndarray:
    """C with C C^T = Q, Q symmetric positive semi-definite: its Cholesky factor when it is
    definite, else its eigenvectors scaled, only the directions with positive eigenvalues
    (negative ones are rounding)."""
    Q = 0.5 * (Q + Q.T)
    try:
        return np.linalg.cholesky(Q)
    except np.linalg.LinAlgError:
        vals, vecs = np.linalg.eigh(Q)
        keep = vals > 0.0
        return vecs[:, keep] * np.sqrt(vals[keep])


def _lower_solve(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """L^-1 B for a lower triangular L: LAPACK's trtrs directly (scipy.linalg.solve_triangular's
    checks cost more than the solve at the sizes of a few agents)."""
    X, info = scipy.linalg.lapack.dtrtrs(L, B, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"triangular solve failed (LAPACK info {info})")
    return X


def _is_eye(F: np.ndarray) -> bool:
    return F.shape[0] == F.shape[1] and np.array_equal(F, np.eye(F.shape[0]))


def _inverse(A: np.ndarray) -> np.ndarray:
    """inv(A) of a symmetric positive definite A through its Cholesky factor (LinAlgError if not)."""
    A = 0.5 * (A + A.T)
    L = np.linalg.cholesky(A)
    Li = np.linalg.solve(L, np.eye(A.shape[0]))
    out = Li.T @ Li
    return 0.5 * (out + out.T)


# --------------------------------------------------------------------------- families


class Family:
    """One platform kind's part of the problem: its coordinates in the bound, its prior, its
    time step and the Jacobians of what it measures, all at its true state.

    to_bound(x): T with x = x_true + T dx for the bound's coordinates dx (identity but for a
    quadrotor). layout: where measurement models find position (and heading) in x."""

    name: str
    dim: int  # in the bound's coordinates
    position: tuple[int, ...]
    layout: StateLayout

    def to_bound(self, x: np.ndarray) -> np.ndarray | None:
        return None  # the identity

    def prior(self, scenario, aid: int, frame, x0: np.ndarray) -> np.ndarray:
        """The prior covariance in the bound's coordinates; x0 the true state of tick 0."""
        return scenario.prior(aid)[1]

    def step(self, x_prev: np.ndarray, x_now: np.ndarray, frame) -> tuple[np.ndarray, np.ndarray] | None:
        """(F, Q) from tick k-1 to k, or None when no time passes for the estimators."""
        raise NotImplementedError

    def H(self, x: np.ndarray, H: np.ndarray) -> np.ndarray:
        """A Jacobian w.r.t. the state, in the bound's coordinates."""
        T = self.to_bound(x)
        return H if T is None else H @ T


class Planar(Family):
    """planar-speed-heading and planar-pose: the models' own predict, F and Q at the true state
    with the recorded odometry (speed, heading or turn rate, and their stds)."""

    def __init__(self, model):
        self.model, self.name = model, model.name
        self.dim = model.state_dim
        self.position = (0, 1)
        self.layout = model.layout

    def step(self, x_prev, x_now, frame):
        if frame.odometry is None:
            return None
        _, F, Q = self.model.predict(x_prev, odometry_of(frame))
        return F, Q


class Uas(Family):
    """uas-ins: the 16-state error state of swarmloc/models/ins.py about the true nominal state. Over a
    tick, the product of the per-sample F of the error dynamics with the noise carried through
    them (`ins.propagate_rows`, the EKF's own time update), mechanized from the true state of the previous
    tick with the recorded IMU samples corrected by the true biases. (The truth is recorded once
    a tick; within it the attitude is the mechanized one, off the truth by what the IMU noise
    integrates to over a tick, a few 1e-5 rad.)"""

    name = "uas-ins"
    dim = 16
    position = (0, 1, 2)

    def __init__(self, scenario):
        self.model = MOTION_MODELS["uas-ins"]
        self.layout = self.model.layout
        self.imu, self.clock = scenario.sensors.imu.spec(), ins.ClockSpec()

    def prior(self, scenario, aid, frame, x0):
        if frame.align is None:
            raise ValueError(f"UAS {aid}: tick 0 has no alignment to start from")
        return np.asarray(frame.align.P, float)

    def step(self, x_prev, x_now, frame):
        imu = frame.imu
        if imu is None or len(imu.samples) == 0:
            return None
        rows = np.asarray(imu.samples, float)
        if not (np.isfinite(rows).all() and rows.ndim == 2 and rows.shape[1] == 6 and float(imu.dt) > 0):
            raise ValueError(f"unusable IMU samples at tick {frame.k}")
        # The EKF's own time update (InsEkf.predict), about the true state instead of its estimate.
        _, F, Qd = ins.propagate_rows(self.model.unpack(x_prev), rows, float(imu.dt), self.imu, self.clock)
        Phi, Q = np.eye(16), np.zeros((16, 16))
        for Fi, Qi in zip(F, Qd):
            Phi, Q = Fi @ Phi, Fi @ Q @ Fi.T + Qi
        return Phi, 0.5 * (Q + Q.T)


class Vehicle(Family):
    """quadrotor and ground-robot (swarmloc/models/vehicles.py): F = I + dt J(x_true, u) with the
    recorded command u, and the actuator noise the world draws, held over the tick:
    Q = dt^2 g diag(std^2) g^T (swarmloc/estimators/vehicles/filters.py process_noise without its Q_FLOOR, which the world
    does not have). A quadrotor's quaternion is unit: the bound's coordinates replace its 4
    components with the 3 of a body-frame rotation, q = q_true (x) [1, dtheta / 2], so
    T = d x / d dx has the block G(q) / 2 (vehicles.quat_G), whose columns are orthonormal to q;
    T^+ takes 2 G(q)^T. The unit-norm constraint is what the vehicle filters impose by
    renormalising (filters._project_quaternion)."""

    def __init__(self, scenario, model_name: str):
        self.model = VEHICLE_MODELS[model_name]
        self.name = model_name
        self.quad = self.model.orientation_dim == 4
        self.dim = self.model.state_dim - (1 if self.quad else 0)
        self.position = (0, 1, 2)
        self.layout = StateLayout(self.model.state_dim, slice(0, 3))
        v = scenario.sensors.vehicle
        self.std = actuator_std(self.model, v.force_noise, v.moment_noise)
        self._T: dict[bytes, np.ndarray] = {}

    def to_bound(self, x):
        if not self.quad:
            return None
        key = x[3:7].tobytes()
        T = self._T.get(key)
        if T is None:
            T = np.zeros((13, 12))
            T[0:3, 0:3] = np.eye(3)
            T[3:7, 3:6] = 0.5 * quat_G(x[3:7] / np.linalg.norm(x[3:7]))
            T[7:13, 6:12] = np.eye(6)
            if len(self._T) > 4:  # a tick reads two states at most: the previous and this one
                self._T.clear()
            self._T[key] = T
        return T

    def from_bound(self, x):
        """T^+ (12 x 13) of a quadrotor: T^+ T = I."""
        Tp = np.zeros((12, 13))
        Tp[0:3, 0:3] = np.eye(3)
        Tp[3:6, 3:7] = 2.0 * quat_G(x[3:7] / np.linalg.norm(x[3:7])).T
        Tp[6:12, 7:13] = np.eye(6)
        return Tp

    def prior(self, scenario, aid, frame, x0):
        P0 = scenario.prior(aid)[1]
        if not self.quad:
            return P0
        Tp = self.from_bound(x0)
        return Tp @ P0 @ Tp.T

    def step(self, x_prev, x_now, frame):
        v = frame.vehicle
        if v is None or not v.dt > 0:
            return None
        dt = float(v.dt)
        F = np.eye(self.model.state_dim) + dt * self.model.jacobian(x_prev, np.asarray(v.u, float))
        Gs = np.asarray(self.model.g(x_prev), float) * self.std
        Q = dt * dt * (Gs @ Gs.T)
        if self.quad:
            Tp = self.from_bound(x_now)
            F, Q = Tp @ F @ self.to_bound(x_prev), Tp @ Q @ Tp.T
        return F, 0.5 * (Q + Q.T)


def family_of(scenario, aid: int) -> Family:
    model = scenario.agent(aid).model
    if model in ("planar-speed-heading", "planar-pose"):
        return Planar(MOTION_MODELS[model])
    if model == "uas-ins":
        return Uas(scenario)
    if model in ("quadrotor", "ground-robot"):
        return Vehicle(scenario, model)
    raise ValueError(f"no bound for model {model!r}")


# --------------------------------------------------------------------------- a run's bound


@dataclass
class Bound:
    """The PCRB of one run, per tick: each agent's position bound sqrt(trace(P_pos)) (m) and
    each target's; NaN where the information is not full rank (a target not yet fixed).
    counts: measurements used per kind; skipped: what could not be used, by reason."""

    ids: list[int]
    position: np.ndarray  # (T, N)
    target_ids: list[int] = field(default_factory=list)
    target_position: np.ndarray | None = None  # (T, M)
    families: dict = field(default_factory=dict)
    counts: Counter = field(default_factory=Counter)
    skipped: Counter = field(default_factory=Counter)

    def summary(self) -> dict:
        """What metrics.json carries under "pcrb"."""
        def col(x):
            return [None if not math.isfinite(v) else float(v) for v in x]

        out = {"position_m": {str(a): col(self.position[:, i]) for i, a in enumerate(self.ids)},
               "families": {str(a): f for a, f in self.families.items()},
               "measurements": dict(sorted(self.counts.items())), "skipped": dict(sorted(self.skipped.items()))}
        if self.target_ids:
            out["targets_m"] = {str(o): col(self.target_position[:, i]) for i, o in enumerate(self.target_ids)}
        return out


def _finite_truth(truth: np.ndarray, dims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(truth with every NaN row (a Vicon gap, the end of a track) replaced by the nearest earlier
    finite one, or the first finite one before any; which (tick, agent) rows were real). A held
    row only carries an agent's time update through a gap: no measurement is linearised at it."""
    out = truth.copy()
    real = np.ones(truth.shape[:2], bool)
    for ci, n in enumerate(dims):
        x = out[:, ci, :n]
        ok = np.isfinite(x).all(axis=1)
        real[:, ci] = ok
        if ok.all() or not ok.any():
            continue
        idx = np.maximum.accumulate(np.where(ok, np.arange(len(ok)), -1))
        idx[idx < 0] = int(np.argmax(ok))
        out[:, ci, :n] = x[idx]
    return out, real


def pcrb(scenario, record) -> Bound:
    """The bound of a recorded run (`swarmloc.experiment.results.RunRecord`) of `scenario`."""
    ids = list(record.ids)
    fams = {a: family_of(scenario, a) for a in ids}
    truth, real = _finite_truth(record.truth_array(), record.dims)
    targets = list(record.target_ids)
    target_truth = np.stack(record.target_truth) if targets else None
    landmarks = {m.id: np.asarray(m.position, float) for m in scenario.world.landmarks}
    blocks = {a: fams[a].dim for a in ids} | {("target", o): 2 for o in targets}
    rec = InformationRecursion(blocks)
    bound = Bound(ids, np.full((len(record.k), len(ids)), np.nan), targets,
                  np.full((len(record.k), len(targets)), np.nan) if targets else None,
                  {a: fams[a].name for a in ids})
    col = {a: i for i, a in enumerate(ids)}
    flat = [("target", o) for o in targets]
    groups = [rec.start[a] + np.array(fams[a].position) for a in ids] + [rec.idx(n) for n in flat]

    def state(ti, a):
        return truth[ti, col[a], :record.dims[col[a]]]

    for ti, frames in enumerate(record.sensors):
        if ti == 0:
            for a in ids:
                rec.set_prior(a, fams[a].prior(scenario, a, frames[a], state(0, a)))
        else:
            steps = {}
            for a in ids:
                x0, x1 = state(ti - 1, a), state(ti, a)
                st = None if np.isnan(x0).any() or np.isnan(x1).any() else fams[a].step(x0, x1, frames[a])
                if st is None:
                    bound.skipped["ticks without a time update"] += 1
                else:
                    steps[a] = st
            rec.predict(steps)
        rows, kinds = [], []
        for names, Hs, R, kind in _measurements(frames, ids, fams, lambda a: state(ti, a), targets,
                                                 None if target_truth is None else target_truth[ti], landmarks,
                                                 bound.skipped):
            if not all(real[ti, col[n]] for n in names if n in col):
                bound.skipped[f"{kind} of an agent without truth"] += 1
                continue
            rows.append((names, Hs, R))
            kinds.append(kind)
        left_out = set(rec.add(rows))
        for ri, kind in enumerate(kinds):
            if ri in left_out:
                bound.skipped[f"{kind}: not finite or R not positive definite"] += 1
            else:
                bound.counts[kind] += 1
        values = rec.position_bounds(groups, flat)
        bound.position[ti] = np.where(real[ti], values[:len(ids)], math.nan)
        if targets:
            bound.target_position[ti] = values[len(ids):]
    return bound


def _measurements(frames, ids, fams, x, targets, target_truth, landmarks, skipped):
    """(blocks, Jacobians in the bound's coordinates, R, kind) of every measurement of a tick, at truth."""
    members = set(ids)
    tcol = {o: i for i, o in enumerate(targets)}
    for a in ids:
        s = frames.get(a)
        if s is None:
            continue
        fa, xa = fams[a], x(a)
        rows = []
        if s.gnss is not None:
            g = s.gnss
            p = fa.layout.pos_dim
            std = [g.std] * p
            if p == 3 and g.std_vertical is not None:
                std[2] = g.std_vertical
            rows.append(("gnss", lambda: ([a], [PositionFix(fa.layout, std=std).jacobians(xa)[0]],
                                          np.diag(np.square(std)))))
        if s.pseudoranges is not None and len(s.pseudoranges.rho):
            pr = s.pseudoranges

            def pseudo(pr=pr):
                m = Pseudorange(fa.layout, np.asarray(pr.sats, float), std=pr.std)
                return [a], [m.jacobians(xa)[0]], m.R
            rows.append(("pseudoranges", pseudo))
        for kind, items in (("range", s.ranges), ("relpos", s.relpos), ("range_bearing", s.rb)):
            for r in items:
                b = r.target
                if b not in members or b == a:
                    skipped[f"{kind} to no localized agent"] += 1
                    continue
                rows.append((kind, lambda r=r, b=b, kind=kind: _pair(kind, r, fa, xa, fams[b], x(b), a, b)))
        for r in s.targets:
            if r.target not in tcol:
                skipped["target range to no target"] += 1
                continue

            def target(r=r):
                m = Range(fa.layout, std=r.std, other=StateLayout.planar())
                Ha, Ht = m.jacobians(xa, target_truth[tcol[r.target]])
                return [a, ("target", r.target)], [Ha, Ht], m.R
            rows.append(("target_range", target))
        for r in s.landmarks:
            if r.target not in landmarks:
                skipped["landmark not on the map"] += 1
                continue

            def mark(r=r):
                m = RangeBearing(fa.layout, std=[r.range_std, r.bearing_std], other=StateLayout.planar(), body_frame=True)
                return [a], [m.jacobians(xa, landmarks[r.target])[0]], m.R
            rows.append(("landmark", mark))
        if s.vehicle is not None:
            rows.extend(_vehicle_rows(s.vehicle, a, fa, xa, fams, x, members, skipped))
        for kind, make in rows:
            try:
                names, Hs, R = make()
            except (ValueError, np.linalg.LinAlgError) as exc:  # a non-positive std, a model that cannot read it
                skipped[f"{kind}: {type(exc).__name__}"] += 1
                continue
            yield names, [fams[n].H(x(n), H) if n in fams else H for n, H in zip(names, Hs)], R, kind


def _pair(kind, r, fa, xa, fb, xb, a, b):
    if kind == "range":
        m = Range(fa.layout, std=r.std, other=fb.layout)
    elif kind == "relpos":
        m = RelativePosition(fa.layout, std=r.std, other=fb.layout)
    else:
        m = RangeBearing(fa.layout, std=[r.range_std, r.bearing_std], other=fb.layout, body_frame=True)
    Ha, Hb = m.jacobians(xa, xb)
    return [a, b], [Ha, Hb], m.R


def _vehicle_rows(v, a, fa, xa, fams, x, members, skipped):
    if not isinstance(fa, Vehicle):
        skipped["vehicle readings of no vehicle"] += 1
        return []
    rows = []
    model = fa.model

    def attitude():
        std = float(v.attitude_std)
        if not (std > 0 and math.isfinite(std)):
            raise ValueError("attitude std")
        return [a], [np.asarray(model.orientation_jacobian(xa), float)], np.eye(model.orientation_dim) * std**2
    rows.append(("attitude", attitude))
    for r in v.seen:
        b = r.target
        if b not in members or b == a or not isinstance(fams[b], Vehicle):
            skipped["vehicle relpos to no vehicle"] += 1
            continue

        def seen(r=r, b=b):
            std = float(r.std)
            if not (std > 0 and math.isfinite(std)):
                raise ValueError("relpos std")
            Hb, Ht = relpos_jacobian(model, xa, fams[b].model, x(b))
            return [a, b], [Hb, Ht], np.eye(3) * std**2
        rows.append(("vehicle_relpos", seen))
    return rows


__all__ = ["InformationRecursion", "Bound", "pcrb", "family_of"]
