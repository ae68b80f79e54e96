"""Measurement models for the EKF family: h, its analytic Jacobians, its noise, its residual.

A model does not know what a platform's state vector looks like; a `StateLayout` tells it
where position (and, when it needs them, attitude and receiver clock bias) sit. So the same
range model serves a 2-state planar robot, the 16-state UAS of the EKF-CI paper (position,
velocity, attitude, gyro bias, accelerometer bias, clock bias) and a pose state.

Conventions
-----------
* Every Jacobian is taken w.r.t. the whole platform state as laid out: shape
  (model.dim, layout.dim), zero outside the columns the model reads. For an error-state
  filter whose errors are additive in these components (position, clock; Euler angles as the
  paper's eq. 10-11 propagate them) the same matrices are the error-state Jacobians,
  evaluated at the nominal state; for a multiplicative attitude error see "rotation-vector".
* Two-platform models read (x_a, x_b) and measure b as seen from a: range ||p_b - p_a||,
  relative position p_b - p_a, bearing of b from a. Body-frame variants use a's attitude.
* Attitude (C rotates body vectors into the world frame; a body-frame vector is C^T v_world):
  - attitude_kind "euler" (default): a planar heading (one component, radians,
    counter-clockwise from the x axis), or 3D Euler angles [roll, pitch, yaw] in the ZYX
    convention, C = Rz(yaw) Ry(pitch) Rx(roll), the parameterisation behind the paper's
    R_alpha (eq. 4); additive, so the attitude columns are ordinary derivatives. With an ENU
    world and an FLU body (swarmloc/models/ins.py), this pitch is positive nose down.
  - attitude_kind "rotation-vector" (3D): the components hold phi, C = exp([phi x]), and the
    attitude columns are w.r.t. a world-frame small-angle perturbation, C <- exp([dtheta x]) C,
    not d/dphi. That is the attitude error of swarmloc/models/ins.py's error state
    (C_true = exp([dtheta x]) C_est): pack the nominal state with phi = log(C_nom) and the
    Jacobians are the error-state H.
* Receiver clock bias is range-equivalent (metres, c * dt), so it adds to a pseudorange.
* Angles returned by h are wrapped to [-pi, pi); `residual` wraps angular components, so an
  innovation never jumps by 2 pi across the branch cut.
* h is vectorised over leading axes (x[..., layout.dim]), as the unscented transform wants;
  Jacobians are for one point.
* Where a gradient does not exist (coincident platforms for range or bearing, a receiver at
  a satellite) the Jacobian row is zero: to first order the measurement then carries no
  information, and an EKF update makes no correction instead of producing NaN.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Sequence

import numpy as np


def wrap_angle(a):
    """Angle(s) mapped to [-pi, pi)."""
    return np.remainder(np.asarray(a, dtype=float) + np.pi, 2 * np.pi) - np.pi


ATTITUDE_KINDS = ("euler", "rotation-vector")


def _indices(s: slice, n: int) -> tuple[int, ...]:
    return tuple(range(n)[s])


@dataclass(frozen=True)
class StateLayout:
    """Where the quantities measurements read sit in one platform's state vector.

    position: 2 or 3 components. attitude (optional): 1 component (heading) with a 2D
    position, 3 with a 3D one, read as attitude_kind says ("euler" or "rotation-vector", see
    the module docstring). clock (optional): index of the receiver clock bias in metres.
    """

    dim: int
    position: slice
    attitude: slice | None = None
    clock: int | None = None
    attitude_kind: str = "euler"

    def __post_init__(self):
        pos = _indices(self.position, self.dim)
        if len(pos) not in (2, 3):
            raise ValueError(f"position must have 2 or 3 components within dim {self.dim}, got {pos}")
        used = list(pos)
        if self.attitude is not None:
            att = _indices(self.attitude, self.dim)
            want = 1 if len(pos) == 2 else 3
            if len(att) != want:
                raise ValueError(f"a {len(pos)}D position needs {want} attitude components, got {att}")
            used += att
        if self.attitude_kind not in ATTITUDE_KINDS:
            raise ValueError(f"attitude_kind is one of {ATTITUDE_KINDS}, got {self.attitude_kind!r}")
        if self.attitude_kind == "rotation-vector" and len(pos) != 3:
            raise ValueError("a rotation-vector attitude needs a 3D position")
        if self.clock is not None:
            if not 0 <= self.clock < self.dim:
                raise ValueError(f"clock index {self.clock} outside dim {self.dim}")
            used.append(self.clock)
        if len(set(used)) != len(used):
            raise ValueError("position, attitude and clock overlap")

    def __hash__(self):
        # The generated hash would hash the slices, which are unhashable before Python 3.12.
        return hash((self.dim, self.pos_idx, self.att_idx, self.clock, self.attitude_kind))

    @property
    def pos_idx(self) -> tuple[int, ...]:
        return _indices(self.position, self.dim)

    @property
    def att_idx(self) -> tuple[int, ...]:
        return () if self.attitude is None else _indices(self.attitude, self.dim)

    @property
    def pos_dim(self) -> int:
        return len(self.pos_idx)

    def position_of(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x)[..., self.pos_idx]

    def attitude_of(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x)[..., self.att_idx]

    def position_matrix(self) -> np.ndarray:
        """H selecting the position: the H of the paper's eq. 20 for this layout."""
        H = np.zeros((self.pos_dim, self.dim))
        H[np.arange(self.pos_dim), self.pos_idx] = 1.0
        return H

    @staticmethod
    def planar() -> "StateLayout":
        """[x, y]: the planar-speed-heading model's state."""
        return StateLayout(2, slice(0, 2))

    @staticmethod
    def planar_pose() -> "StateLayout":
        """[x, y, heading]."""
        return StateLayout(3, slice(0, 2), attitude=slice(2, 3))

    @staticmethod
    def pose3d(attitude_kind: str = "euler") -> "StateLayout":
        """[x, y, z, attitude (3)]."""
        return StateLayout(6, slice(0, 3), attitude=slice(3, 6), attitude_kind=attitude_kind)

    @staticmethod
    def uas16(attitude_kind: str = "euler") -> "StateLayout":
        """EKF-CI paper eq. 1: [r (3), v (3), alpha (3), b_g (3), b_a (3), c_b (1)].

        The same slots as swarmloc/models/ins.py's error state; use attitude_kind="rotation-vector"
        for its attitude error.
        """
        return StateLayout(16, slice(0, 3), attitude=slice(6, 9), clock=15, attitude_kind=attitude_kind)

    def rotation_of(self, x: np.ndarray) -> np.ndarray:
        """C of the platform's attitude (vectorised over leading axes)."""
        return rotation(self.attitude_of(x), self.attitude_kind)

    def d_rotate(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """d(C v)/d(attitude) for a fixed vector v: (pos_dim, n_att), one point."""
        att = self.attitude_of(x)
        if self.attitude_kind == "rotation-vector":
            # exp([d x]) C v = C v + d x (C v) = C v - [(C v) x] d
            return -skew(rotation(att, "rotation-vector") @ v)
        return np.column_stack([D @ v for D in _euler_derivatives(att)])

    def d_unrotate(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """d(C^T v)/d(attitude) for a fixed vector v: (pos_dim, n_att), one point."""
        att = self.attitude_of(x)
        if self.attitude_kind == "rotation-vector":
            # (exp([d x]) C)^T v = C^T (v - d x v) = C^T v + C^T [v x] d
            return rotation(att, "rotation-vector").T @ skew(v)
        return np.column_stack([D.T @ v for D in _euler_derivatives(att)])


def _elementary(axis: int, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation about one axis by a (vectorised) and its derivative w.r.t. a."""
    c, s = np.cos(a), np.sin(a)
    o, i = np.zeros_like(a), np.ones_like(a)
    if axis == 0:
        R = [[i, o, o], [o, c, -s], [o, s, c]]
        dR = [[o, o, o], [o, -s, -c], [o, c, -s]]
    elif axis == 1:
        R = [[c, o, s], [o, i, o], [-s, o, c]]
        dR = [[-s, o, c], [o, o, o], [-c, o, -s]]
    else:
        R = [[c, -s, o], [s, c, o], [o, o, i]]
        dR = [[-s, -c, o], [c, -s, o], [o, o, o]]
    to = lambda M: np.moveaxis(np.array(M, dtype=float), (0, 1), (-2, -1))
    return to(R), to(dR)


def skew(v: np.ndarray) -> np.ndarray:
    """[v x] (vectorised): skew(v) @ u == cross(v, u)."""
    v = np.asarray(v, dtype=float)
    o = np.zeros_like(v[..., 0])
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return np.moveaxis(np.array([[o, -z, y], [z, o, -x], [-y, x, o]]), (0, 1), (-2, -1))


def rotation(att: np.ndarray, kind: str = "euler") -> np.ndarray:
    """Body-to-world rotation C, vectorised over leading axes: shape (..., d, d).

    "euler": a heading (1 component) or ZYX Euler angles [roll, pitch, yaw] (3).
    "rotation-vector": C = exp([phi x]) (Rodrigues).
    """
    att = np.asarray(att, dtype=float)
    if kind == "rotation-vector":
        if att.shape[-1] != 3:
            raise ValueError("a rotation vector has 3 components")
        theta = np.linalg.norm(att, axis=-1)[..., None, None]
        K = skew(att)
        # sin(t)/t and (1 - cos t)/t^2 through sinc, exact at t = 0 without a branch.
        a = np.sinc(theta / np.pi)
        b = 0.5 * np.sinc(theta / (2 * np.pi)) ** 2
        return np.eye(3) + a * K + b * (K @ K)
    if kind != "euler":
        raise ValueError(f"attitude kind is one of {ATTITUDE_KINDS}, got {kind!r}")
    if att.shape[-1] == 1:
        c, s = np.cos(att[..., 0]), np.sin(att[..., 0])
        return np.moveaxis(np.array([[c, -s], [s, c]]), (0, 1), (-2, -1))
    if att.shape[-1] != 3:
        raise ValueError(f"Euler attitude has 1 (heading) or 3 (roll, pitch, yaw) components, got {att.shape[-1]}")
    Rx, _ = _elementary(0, att[..., 0])
    Ry, _ = _elementary(1, att[..., 1])
    Rz, _ = _elementary(2, att[..., 2])
    return Rz @ Ry @ Rx


def _euler_derivatives(att: np.ndarray) -> list[np.ndarray]:
    """dC/d att_k for Euler attitude (one point): one matrix per component."""
    if att.shape[-1] == 1:
        c, s = np.cos(att[0]), np.sin(att[0])
        return [np.array([[-s, -c], [c, -s]])]
    Rx, dRx = _elementary(0, att[0])
    Ry, dRy = _elementary(1, att[1])
    Rz, dRz = _elementary(2, att[2])
    return [Rz @ Ry @ dRx, Rz @ dRy @ Rx, dRz @ Ry @ Rx]


def _unit_rows(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(norms, d / norm) along the last axis, with a zero direction where the norm is zero."""
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    u = np.divide(d, n, out=np.zeros_like(d), where=n > 0)
    return n[..., 0], u


class MeasurementModel:
    """z = h(x_1, ..., x_platforms) + v, v ~ N(0, R).

    Noise is given either as `std` (a scalar, or one per component: R = diag(std^2)) or as
    a full `cov`. Subclasses set `name`, `platforms`, `angles` (indices of angular
    components of z) and implement `dim`, `h`, `jacobians`.
    """

    name: ClassVar[str]
    platforms: ClassVar[int]
    angles: ClassVar[tuple[int, ...]] = ()

    def __init__(self, layout: StateLayout, std=None, cov=None, other: StateLayout | None = None):
        if other is not None and self.platforms != 2:
            raise ValueError(f"{self.name} reads one platform; `other` is for two-platform models")
        self.layouts = (layout,) if self.platforms == 1 else (layout, other or layout)
        for lay in self.layouts:
            if not self.supports(lay):
                raise ValueError(f"{self.name} cannot read layout {lay}")
        if self.platforms == 2 and self.layouts[0].pos_dim != self.layouts[1].pos_dim:
            raise ValueError("both platforms need positions of the same dimension")
        self.R = self._noise(std, cov)

    @property
    def layout(self) -> StateLayout:
        return self.layouts[0]

    @property
    def dim(self) -> int:
        raise NotImplementedError

    @classmethod
    def supports(cls, layout: StateLayout) -> bool:
        """Whether this model can read a platform with this layout (before any options)."""
        return True

    def _noise(self, std, cov) -> np.ndarray:
        if (std is None) == (cov is None):
            raise ValueError("give exactly one of std and cov")
        if std is not None:
            std = np.broadcast_to(np.asarray(std, dtype=float), (self.dim,))
            if np.any(std <= 0):
                raise ValueError("std must be positive")
            return np.diag(std**2)
        R = np.array(cov, dtype=float)
        if R.shape != (self.dim, self.dim) or not np.allclose(R, R.T):
            raise ValueError(f"cov must be a symmetric {self.dim}x{self.dim} matrix")
        np.linalg.cholesky(R)  # raises LinAlgError if not positive definite
        return R

    def h(self, *xs: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def jacobians(self, *xs: np.ndarray) -> tuple[np.ndarray, ...]:
        """dh/dx_i for each platform argument, each of shape (dim, layout_i.dim)."""
        raise NotImplementedError

    def residual(self, z: np.ndarray, z_hat: np.ndarray) -> np.ndarray:
        """z - z_hat with angular components wrapped to [-pi, pi)."""
        nu = np.asarray(z, dtype=float) - np.asarray(z_hat, dtype=float)
        if self.angles:
            nu = nu.copy()
            nu[..., self.angles] = wrap_angle(nu[..., self.angles])
        return nu

    def joint(self, X: np.ndarray, starts: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """(h, H) on a stacked multi-platform state: platform i's block starts at starts[i].

        The form a centralized EKF needs: H has shape (dim, len(X)), zero outside the blocks.
        """
        if len(starts) != self.platforms:
            raise ValueError(f"{self.name} reads {self.platforms} platform(s), got {len(starts)} starts")
        X = np.asarray(X, dtype=float)
        for s, lay in zip(starts, self.layouts):
            if not 0 <= s <= X.shape[0] - lay.dim:
                raise ValueError(f"a block of {lay.dim} at {s} does not fit a state of {X.shape[0]}")
        xs = [X[s : s + lay.dim] for s, lay in zip(starts, self.layouts)]
        H = np.zeros((self.dim, X.shape[0]))
        # Added, not assigned: a block given twice (a platform measuring itself) sums.
        for s, lay, Hi in zip(starts, self.layouts, self.jacobians(*xs)):
            H[:, s : s + lay.dim] += Hi
        return self.h(*xs), H

    def _embed(self, layout: StateLayout, cols: tuple[int, ...], block: np.ndarray) -> np.ndarray:
        J = np.zeros((self.dim, layout.dim))
        J[:, cols] = block
        return J

    def __repr__(self) -> str:
        return f"{type(self).__name__}(dim={self.dim}, layouts={self.layouts})"


class Range(MeasurementModel):
    """Paper eq. 15: d = ||p_b - p_a|| + e."""

    name = "range"
    platforms = 2

    @property
    def dim(self) -> int:
        return 1

    def h(self, xa, xb):
        d = self.layouts[1].position_of(xb) - self.layouts[0].position_of(xa)
        return np.linalg.norm(d, axis=-1, keepdims=True)

    def jacobians(self, xa, xb):
        la, lb = self.layouts
        _, u = _unit_rows(lb.position_of(xb) - la.position_of(xa))
        return self._embed(la, la.pos_idx, -u[None]), self._embed(lb, lb.pos_idx, u[None])


    def second_order(self, xa, xb, P_rel: np.ndarray) -> tuple[float, float]:
        """The second-order terms of the range about the estimate: (mean bias, added variance)
        for a relative position p_b - p_a with covariance P_rel, from the Hessian
        (I - u u^T) / d of ||d||: bias = tr(Hs P_rel) / 2, variance = tr((Hs P_rel)^2) / 2.

        The range is curved across the line of sight: with a cross-track uncertainty s at a
        separation d it reads longer by about s^2 / (2 d), which at s = 3 m and d = 20 m is 22 cm,
        ten times a 2 cm ranging noise. A first-order EKF ignores that and grows overconfident;
        adding these terms to h and R (a second-order EKF) keeps it consistent."""
        la, lb = self.layouts
        dv = lb.position_of(xb) - la.position_of(xa)
        d = float(np.linalg.norm(dv))
        if d == 0.0:
            return 0.0, 0.0
        u = dv / d
        Hs = (np.eye(len(u)) - np.outer(u, u)) / d
        A = Hs @ P_rel
        return 0.5 * float(np.trace(A)), 0.5 * float(np.trace(A @ A))


class RelativePosition(MeasurementModel):
    """z = p_b - p_a in the world frame, or C(att_a)^T (p_b - p_a) in a's body frame.

    The relative information the paper's distributed filter fuses (section 4.1, eq. 19).
    """

    name = "relative-position"
    platforms = 2

    def __init__(self, layout, std=None, cov=None, other=None, body_frame: bool = False):
        self.body_frame = bool(body_frame)
        super().__init__(layout, std, cov, other)
        if self.body_frame and layout.attitude is None:
            raise ValueError("a body-frame relative position needs the observer's attitude in its layout")

    @property
    def dim(self) -> int:
        return self.layouts[0].pos_dim

    def h(self, xa, xb):
        la, lb = self.layouts
        d = lb.position_of(xb) - la.position_of(xa)
        if not self.body_frame:
            return d
        return np.einsum("...ji,...j->...i", la.rotation_of(xa), d)

    def jacobians(self, xa, xb):
        la, lb = self.layouts
        if not self.body_frame:
            eye = np.eye(self.dim)
            return self._embed(la, la.pos_idx, -eye), self._embed(lb, lb.pos_idx, eye)
        d = lb.position_of(xb) - la.position_of(xa)
        C = la.rotation_of(xa)
        Ha = self._embed(la, la.pos_idx, -C.T)
        Ha[:, la.att_idx] = la.d_unrotate(xa, d)
        return Ha, self._embed(lb, lb.pos_idx, C.T)

    def implied_position(self, x_known, P_known, z, known: str = "a"):
        """Position of the other platform implied by one platform's estimate and z.

        The paper's eq. 19 with its covariance: from a's estimate, p_b = p_a + C(att_a) z;
        from b's, p_a = p_b - z (world frame only: in a's body frame the rotation would need
        the unknown platform's own attitude). Returns (p, P_p) to first order,
        P_p = J P_known J^T + C R C^T, ready for fusion.ci_update with layout.position_matrix().
        """
        x_known = np.asarray(x_known, dtype=float)
        z = np.asarray(z, dtype=float)
        if known == "b":
            if self.body_frame:
                raise ValueError("a body-frame relative position locates b from a, not a from b")
            lb = self.layouts[1]
            J = lb.position_matrix()
            return lb.position_of(x_known) - z, J @ P_known @ J.T + self.R
        if known != "a":
            raise ValueError("known is 'a' or 'b'")
        la = self.layouts[0]
        J = la.position_matrix()
        if not self.body_frame:
            return la.position_of(x_known) + z, J @ P_known @ J.T + self.R
        C = la.rotation_of(x_known)
        J[:, la.att_idx] = la.d_rotate(x_known, z)
        return la.position_of(x_known) + C @ z, J @ P_known @ J.T + C @ self.R @ C.T


class Pseudorange(MeasurementModel):
    """Paper eq. 14: rho_k = ||s_k - r|| + c_b + e for satellites s_k (rows), one z per row.

    Satellite positions are in the frame of the state's position; no Sagnac or atmospheric
    terms: those belong to whoever forms the corrected pseudorange.
    """

    name = "pseudorange"
    platforms = 1

    def __init__(self, layout, satellites, std=None, cov=None):
        self.satellites = np.atleast_2d(np.asarray(satellites, dtype=float))
        if self.satellites.shape[-1] != layout.pos_dim:
            raise ValueError(f"satellite positions need {layout.pos_dim} components")
        super().__init__(layout, std, cov)

    @classmethod
    def supports(cls, layout):
        return layout.clock is not None

    @property
    def dim(self) -> int:
        return self.satellites.shape[0]

    def h(self, x):
        r = self.layout.position_of(x)[..., None, :]
        return np.linalg.norm(self.satellites - r, axis=-1) + np.asarray(x)[..., self.layout.clock, None]

    def jacobians(self, x):
        lay = self.layout
        _, u = _unit_rows(lay.position_of(x) - self.satellites)
        H = self._embed(lay, lay.pos_idx, u)
        H[:, lay.clock] = 1.0
        return (H,)


class PositionFix(MeasurementModel):
    """A GNSS (or any absolute) position fix: z = p + e."""

    name = "position-fix"
    platforms = 1

    @property
    def dim(self) -> int:
        return self.layout.pos_dim

    def h(self, x):
        return self.layout.position_of(x).copy()

    def jacobians(self, x):
        return (self.layout.position_matrix(),)


class _Planar2(MeasurementModel):
    """Shared by the planar angle models: 2D positions; heading needed in the body frame."""

    platforms = 2

    def __init__(self, layout, std=None, cov=None, other=None, body_frame: bool = False):
        self.body_frame = bool(body_frame)
        super().__init__(layout, std, cov, other)
        if self.body_frame and layout.attitude is None:
            raise ValueError(f"a body-frame {self.name} needs the observer's heading in its layout")

    @classmethod
    def supports(cls, layout):
        return layout.pos_dim == 2

    def _bearing(self, xa, xb):
        la, lb = self.layouts
        d = lb.position_of(xb) - la.position_of(xa)
        b = np.arctan2(d[..., 1], d[..., 0])
        if self.body_frame:
            b = b - la.attitude_of(xa)[..., 0]
        return d, wrap_angle(b)

    def _bearing_jacobians(self, xa, xb):
        """Rows d(bearing)/dx_a, d(bearing)/dx_b: +-[-dy, dx] / r^2, and -1 on a's heading."""
        la, lb = self.layouts
        d = lb.position_of(xb) - la.position_of(xa)
        r2 = d @ d
        g = np.array([-d[1], d[0]]) / r2 if r2 > 0 else np.zeros(2)
        ga, gb = np.zeros(la.dim), np.zeros(lb.dim)
        ga[list(la.pos_idx)] = -g
        gb[list(lb.pos_idx)] = g
        if self.body_frame:
            ga[la.att_idx[0]] = -1.0
        return ga, gb


class Bearing(_Planar2):
    """z = atan2(dy, dx) of p_b - p_a, minus a's heading in the body frame; in [-pi, pi)."""

    name = "bearing"
    angles = (0,)

    @property
    def dim(self) -> int:
        return 1

    def h(self, xa, xb):
        return self._bearing(xa, xb)[1][..., None]

    def jacobians(self, xa, xb):
        ga, gb = self._bearing_jacobians(xa, xb)
        return ga[None], gb[None]


class RangeBearing(_Planar2):
    """z = [range, bearing] of b from a (planar)."""

    name = "range-bearing"
    angles = (1,)

    @property
    def dim(self) -> int:
        return 2

    def h(self, xa, xb):
        d, b = self._bearing(xa, xb)
        return np.stack([np.linalg.norm(d, axis=-1), b], axis=-1)

    def jacobians(self, xa, xb):
        la, lb = self.layouts
        _, u = _unit_rows(lb.position_of(xb) - la.position_of(xa))
        Ha = self._embed(la, la.pos_idx, np.vstack([-u, np.zeros(2)]))
        Hb = self._embed(lb, lb.pos_idx, np.vstack([u, np.zeros(2)]))
        Ha[1], Hb[1] = self._bearing_jacobians(xa, xb)
        return Ha, Hb


MEASUREMENT_MODELS: dict[str, type[MeasurementModel]] = {
    m.name: m for m in (Range, RelativePosition, Pseudorange, PositionFix, Bearing, RangeBearing)
}
