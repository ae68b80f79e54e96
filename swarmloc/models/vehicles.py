"""Vehicle dynamics, relative-position measurement model and tracking controllers.

This is the one place the vehicle maths lives: netsim integrates these models as world truth,
the estimators use them as their process and measurement models, and agents use the
controllers. Two platforms, after Oliveros & Ashrafiuon 2023 (sections 2-4, 6.1):

* ``Quadrotor``: x = [r (3, inertial ENU, z up), q (4, unit, scalar first), v (3, body-frame
  velocity), w (3, body angular rate)], u = [thrust along body z, tau_x, tau_y, tau_z].
* ``GroundRobot``: x = [x, y, z, phi (yaw), v_x (body surge speed), z_dot, w_z],
  u = [surge force F_x, yaw moment tau_z].

Both are control-affine, xdot = f(x) + g(x) u, with analytic Jacobians d xdot / d x.
Body axes are FLU (x forward, y left, z up); R_0v maps body coordinates to inertial ones.

Pure numpy: no I/O, no threads, no middleware imports.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

GRAVITY = 9.81
_E3 = np.array([0.0, 0.0, 1.0])


# ---------------------------------------------------------------------------------------------
# small rotation helpers


def _cross(a, b) -> np.ndarray:
    # np.cross on two 3-vectors costs ~15 us of axis handling; this is most of a dynamics call.
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def skew(a) -> np.ndarray:
    """S(a), with S(a) b = a x b."""
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def quat_rotation(q) -> np.ndarray:
    """R_0v(q) = (2 q0^2 - 1) I + 2 (q q^T + q0 S(q)) (Oliveros & Ashrafiuon 2023, eq. 2).

    Kept in this unnormalised form everywhere (dynamics, Jacobians, measurements) so that the
    analytic derivatives are those of the very function evaluated, and finite differences on q
    without renormalising agree with them."""
    q0, qv = q[0], q[1:4]
    return (2.0 * q0 * q0 - 1.0) * np.eye(3) + 2.0 * (np.outer(qv, qv) + q0 * skew(qv))


def quat_G(q) -> np.ndarray:
    """G(q) (4x3) in qdot = 1/2 G(q) w for a body-frame rate w: G = [-q^T; q0 I + S(q)].

    This is q (x) [0, w] for scalar-first Hamilton quaternions, the convention in which
    quat_rotation maps body to inertial coordinates (tested by integrating a constant rate)."""
    q0, qv = q[0], q[1:4]
    return np.vstack([-qv[None, :], q0 * np.eye(3) + skew(qv)])


def _d_rot_times(q, a) -> np.ndarray:
    """d (R(q) a) / d q (3x4), eq. 12-13: [4 q0 a + 2 S(q) a | 2 q a^T + 2 (q.a) I - 2 q0 S(a)]."""
    q0, qv = q[0], q[1:4]
    d0 = 4.0 * q0 * a + 2.0 * _cross(qv, a)
    dv = 2.0 * np.outer(qv, a) + 2.0 * (qv @ a) * np.eye(3) - 2.0 * q0 * skew(a)
    return np.column_stack([d0, dv])


def _d_rotT_times(q, a) -> np.ndarray:
    """d (R(q)^T a) / d q (3x4): transposing R flips the sign of every S(q) term."""
    q0, qv = q[0], q[1:4]
    d0 = 4.0 * q0 * a - 2.0 * _cross(qv, a)
    dv = 2.0 * np.outer(qv, a) + 2.0 * (qv @ a) * np.eye(3) + 2.0 * q0 * skew(a)
    return np.column_stack([d0, dv])


def rot_z(phi: float) -> np.ndarray:
    c, s = math.cos(phi), math.sin(phi)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def wrap_yaw(a: float) -> float:
    """Angle a (a float) to [-pi, pi), in Python arithmetic: the scalar form for per-step code
    (the vehicles' controllers and EKFs); measurements.wrap_angle is the numpy form for arrays."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


# ---------------------------------------------------------------------------------------------
# parameters


@dataclass(frozen=True)
class QuadrotorParams:
    """Quadrotor mass and geometry; defaults are the paper's section 6.1 airframe.

    mass: kg. inertia: principal moments (Ixx, Iyy, Izz), kg m^2, body axes principal.
    arm: rotor arm length, m. c_t: rotor thrust coefficient (thrust = c_t Omega^2).
    c_q: rotor drag-torque coefficient (torque = c_q Omega^2)."""

    mass: float = 1.01
    inertia: tuple[float, float, float] = (0.0066, 0.0065, 0.0109)
    arm: float = 0.226
    c_t: float = 7e-6
    c_q: float = 2.6e-7


@dataclass(frozen=True)
class GroundParams:
    """Wheeled (differential-drive) robot; defaults are the paper's section 6.1 robot.

    mass: kg. izz: yaw moment of inertia, kg m^2. d: distance from the rear axle forward to
    the vehicle origin, m (the origin's lateral body velocity is d w_z)."""

    mass: float = 1.748
    izz: float = 0.0126
    d: float = 0.05


# ---------------------------------------------------------------------------------------------
# models


class VehicleModel:
    """A control-affine vehicle model xdot = f(x) + g(x) u, with the EKF's discretisation."""

    name: str
    state_dim: int
    input_dim: int
    position_dim = 3
    orientation_dim: int
    # where the orientation coordinates sit in the state (relpos Jacobian columns)
    _orientation_slice: slice

    def f(self, x) -> np.ndarray:
        raise NotImplementedError

    def g(self, x) -> np.ndarray:
        raise NotImplementedError

    def xdot(self, x, u) -> np.ndarray:
        x = np.asarray(x, float)
        return self.f(x) + self.g(x) @ np.asarray(u, float)

    def jacobian(self, x, u=None) -> np.ndarray:
        """d xdot / d x. g is state-independent for both platforms, so u does not enter."""
        raise NotImplementedError

    def _normalise(self, x: np.ndarray) -> np.ndarray:
        return x

    def step(self, x, u, dt, substeps=1) -> np.ndarray:
        """RK4 over dt with u held (zero-order hold), in `substeps` equal sub-steps."""
        x = np.array(x, float)
        u = np.asarray(u, float)
        h = float(dt) / int(substeps)
        for _ in range(int(substeps)):
            k1 = self.xdot(x, u)
            k2 = self.xdot(x + 0.5 * h * k1, u)
            k3 = self.xdot(x + 0.5 * h * k2, u)
            k4 = self.xdot(x + h * k3, u)
            x = self._normalise(x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4))
        return x

    def transition(self, x, u, dt) -> tuple[np.ndarray, np.ndarray]:
        """The EKF's discrete model: (next state, F = I + dt J(x, u)).

        The propagated state is the accurate RK4 one; F is the first-order transition matrix of
        the linearisation (paper eq. 43 uses J at the sample)."""
        x = np.asarray(x, float)
        return self.step(x, u, dt), np.eye(self.state_dim) + float(dt) * self.jacobian(x, u)

    def noise_input(self, x) -> np.ndarray:
        """Gamma (n x m): actuator noise enters exactly where the input does, so Gamma = g(x).
        A continuous input-noise density Q_u gives the discrete Q_d ~ dt Gamma Q_u Gamma^T; a
        per-step input perturbation held over dt gives (dt Gamma) Q_u (dt Gamma)^T."""
        return self.g(x)

    def position(self, x) -> np.ndarray:
        return np.asarray(x, float)[:3]

    def rotation(self, x) -> np.ndarray:
        raise NotImplementedError

    def orientation(self, x) -> np.ndarray:
        raise NotImplementedError

    def orientation_jacobian(self, x) -> np.ndarray:
        raise NotImplementedError

    def yaw(self, x) -> float:
        raise NotImplementedError

    def hover_input(self, x=None) -> np.ndarray:
        raise NotImplementedError

    def initial_state(self, position, yaw=0.0) -> np.ndarray:
        raise NotImplementedError

    def _rotT_jacobian(self, x, a) -> np.ndarray:
        """d (R(x)^T a) / d (orientation coordinates), (3, orientation_dim)."""
        raise NotImplementedError

    def rot_jacobian(self, x, a) -> np.ndarray:
        """d (R(x) a) / d (orientation coordinates), (3, orientation_dim): how a body-frame
        vector taken to the world moves with the orientation."""
        raise NotImplementedError


class Quadrotor(VehicleModel):
    """Rigid-body quadrotor (Oliveros & Ashrafiuon 2023, eq. 6-14) with gravity.

    r' = R v, q' = 1/2 G(q) w, v' = -w x v + [0, 0, f]/m - R^T [0, 0, g],
    w' = I^-1 (-w x I w) + I^-1 tau. The extracted eq. 6 shows no gravity; the control
    section's m r'' = R [0, 0, f] - [0, 0, m g] has it, and written in body-frame velocity that
    is the R^T g term above."""

    name = "quadrotor"
    state_dim = 13
    input_dim = 4
    orientation_dim = 4
    _orientation_slice = slice(3, 7)

    def __init__(self, params: QuadrotorParams = QuadrotorParams()):
        self.params = params
        self.inertia = np.asarray(params.inertia, float)
        self._B = np.zeros((13, 4))
        self._B[9, 0] = 1.0 / params.mass
        self._B[10:13, 1:4] = np.diag(1.0 / self.inertia)

    def f(self, x):
        x = np.asarray(x, float)
        q, v, w = x[3:7], x[7:10], x[10:13]
        R = quat_rotation(q)
        I = self.inertia
        return np.concatenate([
            R @ v,
            0.5 * quat_G(q) @ w,
            -_cross(w, v) - GRAVITY * (R.T @ _E3),
            -_cross(w, I * w) / I,
        ])

    def g(self, x=None):
        return self._B.copy()

    def jacobian(self, x, u=None):
        """Eq. 11 with gravity: blocks dr'/dq (eq. 12-13), dr'/dv = R, dq'/dq (eq. 14),
        dq'/dw = G/2, dv'/dq = -g d(R^T e3)/dq, dv'/dv = -S(w), dv'/dw = S(v),
        dw'/dw = I^-1 (S(I w) - S(w) I)."""
        x = np.asarray(x, float)
        q, v, w = x[3:7], x[7:10], x[10:13]
        I = self.inertia
        J = np.zeros((13, 13))
        J[0:3, 3:7] = _d_rot_times(q, v)
        J[0:3, 7:10] = quat_rotation(q)
        J[3, 4:7] = -0.5 * w
        J[4:7, 3] = 0.5 * w
        J[4:7, 4:7] = -0.5 * skew(w)
        J[3:7, 10:13] = 0.5 * quat_G(q)
        J[7:10, 3:7] = -GRAVITY * _d_rotT_times(q, _E3)
        J[7:10, 7:10] = -skew(w)
        J[7:10, 10:13] = skew(v)
        J[10:13, 10:13] = (skew(I * w) - skew(w) @ np.diag(I)) / I[:, None]
        return J

    def _normalise(self, x):
        n = np.linalg.norm(x[3:7])
        if n > 0.0:
            x[3:7] /= n
        return x

    def rotation(self, x):
        return quat_rotation(np.asarray(x, float)[3:7])

    def orientation(self, x):
        return np.array(x[3:7], float)

    def orientation_jacobian(self, x):
        H = np.zeros((4, 13))
        H[:, 3:7] = np.eye(4)
        return H

    def yaw(self, x):
        R = self.rotation(x)
        return math.atan2(R[1, 0], R[0, 0])  # ZYX (yaw-pitch-roll) yaw

    def hover_input(self, x=None):
        return np.array([self.params.mass * GRAVITY, 0.0, 0.0, 0.0])

    def initial_state(self, position, yaw=0.0):
        x = np.zeros(13)
        x[:3] = position
        x[3] = math.cos(0.5 * yaw)
        x[6] = math.sin(0.5 * yaw)
        return x

    def _rotT_jacobian(self, x, a):
        return _d_rotT_times(np.asarray(x, float)[3:7], a)

    def rot_jacobian(self, x, a):
        return _d_rot_times(np.asarray(x, float)[3:7], np.asarray(a, float))


class GroundRobot(VehicleModel):
    """Wheeled robot with its origin d ahead of the rear axle (Oliveros & Ashrafiuon 2023,
    eq. 15-16): r' = [v cos phi - d w sin phi, v sin phi + d w cos phi, z'], phi' = w,
    v' = d w^2 + F/m, z'' = 0, w' = -(m d / Izz) w v + tau / Izz."""

    name = "ground-robot"
    state_dim = 7
    input_dim = 2
    orientation_dim = 1
    _orientation_slice = slice(3, 4)

    def __init__(self, params: GroundParams = GroundParams()):
        self.params = params
        self._B = np.zeros((7, 2))
        self._B[4, 0] = 1.0 / params.mass
        self._B[6, 1] = 1.0 / params.izz

    def f(self, x):
        x = np.asarray(x, float)
        p = self.params
        phi, v, zd, w = x[3], x[4], x[5], x[6]
        c, s = math.cos(phi), math.sin(phi)
        return np.array([
            v * c - p.d * w * s,
            v * s + p.d * w * c,
            zd,
            w,
            p.d * w * w,
            0.0,
            -(p.mass * p.d / p.izz) * w * v,
        ])

    def g(self, x=None):
        return self._B.copy()

    def jacobian(self, x, u=None):
        x = np.asarray(x, float)
        p = self.params
        phi, v, w = x[3], x[4], x[6]
        c, s = math.cos(phi), math.sin(phi)
        k = p.mass * p.d / p.izz
        J = np.zeros((7, 7))
        J[0, 3], J[0, 4], J[0, 6] = -v * s - p.d * w * c, c, -p.d * s
        J[1, 3], J[1, 4], J[1, 6] = v * c - p.d * w * s, s, p.d * c
        J[2, 5] = 1.0
        J[3, 6] = 1.0
        J[4, 6] = 2.0 * p.d * w
        J[6, 4], J[6, 6] = -k * w, -k * v
        return J

    def rotation(self, x):
        return rot_z(float(x[3]))

    def orientation(self, x):
        return np.array([x[3]], float)

    def orientation_jacobian(self, x):
        H = np.zeros((1, 7))
        H[0, 3] = 1.0
        return H

    def yaw(self, x):
        return float(x[3])

    def hover_input(self, x=None):
        return np.zeros(2)

    def initial_state(self, position, yaw=0.0):
        x = np.zeros(7)
        x[:3] = position
        x[3] = yaw
        return x

    def _rotT_jacobian(self, x, a):
        c, s = math.cos(x[3]), math.sin(x[3])
        dRT = np.array([[-s, c, 0.0], [-c, -s, 0.0], [0.0, 0.0, 0.0]])  # d Rz(phi)^T / d phi
        return (dRT @ a)[:, None]

    def rot_jacobian(self, x, a):
        c, s = math.cos(x[3]), math.sin(x[3])
        dR = np.array([[-s, -c, 0.0], [c, -s, 0.0], [0.0, 0.0, 0.0]])  # d Rz(phi) / d phi
        return (dR @ np.asarray(a, float))[:, None]


MODELS: dict[str, VehicleModel] = {"quadrotor": Quadrotor(), "ground-robot": GroundRobot()}


# ---------------------------------------------------------------------------------------------
# relative position measurement (section 4)


def relpos(base: VehicleModel, xb, target: VehicleModel, xt) -> np.ndarray:
    """The target's position in the base's body frame, z = R_0b^T (r_t - r_b) (eq. 34).

    The transpose is lost in the extracted text; R_0b maps body to inertial, so expressing an
    inertial vector in the body frame needs R_0b^T."""
    return base.rotation(xb).T @ (target.position(xt) - base.position(xb))


def relpos_jacobian(base: VehicleModel, xb, target: VehicleModel, xt) -> tuple[np.ndarray, np.ndarray]:
    """(H_b (3, n_b), H_t (3, n_t)): d relpos / d x_b and d relpos / d x_t (eq. 35-41), for any
    pairing of quadrotor and ground-robot base and target."""
    xb = np.asarray(xb, float)
    r0 = target.position(xt) - base.position(xb)
    RT = base.rotation(xb).T
    Hb = np.zeros((3, base.state_dim))
    Hb[:, :3] = -RT
    Hb[:, base._orientation_slice] = base._rotT_jacobian(xb, r0)
    Ht = np.zeros((3, target.state_dim))
    Ht[:, :3] = RT
    return Hb, Ht


# ---------------------------------------------------------------------------------------------
# reference trajectory


@dataclass(frozen=True)
class CircleReference:
    """A horizontal circle flown (or driven) at constant speed.

    center: circle centre (m); its z is the flight height (a ground robot's z).
    radius: m (0: a fixed point). period: seconds per lap, positive anticlockwise seen from
    above, negative clockwise. phase: polar angle of the reference at t = 0 (rad).
    yaw: None makes the yaw follow the direction of travel (constant 0 when radius is 0,
    where no direction exists); a number holds that yaw."""

    center: tuple[float, float, float]
    radius: float
    period: float
    phase: float = 0.0
    yaw: float | None = None

    def __post_init__(self):
        if self.radius < 0.0 or self.period == 0.0 or not math.isfinite(self.period):
            raise ValueError("CircleReference needs radius >= 0 and a finite, nonzero period")

    @property
    def rate(self) -> float:
        return 2.0 * math.pi / self.period

    def derivatives(self, t: float, order: int = 4) -> list[np.ndarray]:
        """[r, r', ..., r^(order)] at t, each (3,): r^(k) = rho w^k [cos, sin](theta + k pi/2)."""
        w = self.rate
        theta = self.phase + w * t
        out = [np.asarray(self.center, float) + self.radius * np.array([math.cos(theta), math.sin(theta), 0.0])]
        for k in range(1, order + 1):
            a = theta + k * 0.5 * math.pi
            out.append(self.radius * w**k * np.array([math.cos(a), math.sin(a), 0.0]))
        return out

    def yaw_derivatives(self, t: float) -> tuple[float, float, float]:
        """(psi, psi', psi'') of the reference yaw at t."""
        if self.yaw is not None:
            return float(self.yaw), 0.0, 0.0
        if self.radius == 0.0:
            return 0.0, 0.0, 0.0
        w = self.rate
        psi = self.phase + w * t + math.copysign(0.5 * math.pi, w)
        return wrap_yaw(psi), w, 0.0

    def start_state(self, model: VehicleModel) -> np.ndarray:
        """The vehicle at the reference's t = 0 point and yaw, level and at rest (a hovering
        quadrotor is at rest: its hover thrust is hover_input)."""
        return model.initial_state(self.derivatives(0.0, 0)[0], self.yaw_derivatives(0.0)[0])


# ---------------------------------------------------------------------------------------------
# controllers


class QuadrotorController:
    """Nonlinear tracking controller of Oliveros & Ashrafiuon 2023, section 3 (eq. 18-31),
    rederived on the quaternion state.

    Position: the thrust is given a dynamic extension f_hat (f_hat'' is the virtual input), so
    r'''' is affine in (w_x', w_y', f_hat''): with b = body z axis,
    m r'' = f_hat b - m g e3, m r''' = R (w x e3 f_hat + e3 f_hat'),
    m r'''' = R (e3 f_hat'' + 2 w x e3 f_hat' + (w' x + w x w x) e3 f_hat)   (eq. 18-20).
    Each inertial axis i is given the error dynamics
    e'''' + 5 l e''' + 10 l^2 e'' + 10 l^3 e' + 5 l^4 e + l^5 int e = 0 (all roots at -l, eq. 21)
    with l = lam for x, y and l = lam_z for z; r', r'', r''' in the errors come from the model
    (r' = R v and the two lines above), so only the reference needs higher derivatives. The
    body-frame rows of the snap equation give w_x', w_y' (hence tau_x, tau_y, eq. 25-26) and
    f_hat'' (eq. 27's role).

    Thrust: the applied thrust is f_hat itself. The paper also states a separate thrust law
    (eq. 28, second order in z); applying it while the roll/pitch law assumes f = f_hat would
    make the x-y snap computation wrong whenever the two differ. Applying f_hat keeps the
    feedback linearisation exact, and z still gets its own eigenvalue lam_z through the third
    row. f_hat, f_hat' are integrated exactly for f_hat'' held over each interval, from
    f_hat = m g, f_hat' = 0.

    Yaw: psi = atan2(R21, R11) (ZYX yaw), whose rate is psi' = (w_z R33 + w_y R32)/(R11^2 + R21^2)
    (differentiating R' = R S(w)); differentiating once more and asking
    e_psi'' + 3 l e_psi' + 3 l^2 e_psi + l^3 int e_psi = 0 (l = lam_psi, eq. 29) gives w_z',
    the quaternion counterpart of eq. 30-31.

    Moments are tau = I w' + w x I w. Bounds (documented limits, not part of the design):
    thrust in [0, 4 m g] (each of four rotors at most m g); |tau_x|, |tau_y| <= arm m g (one
    rotor at full thrust against an idle one); |tau_z| <= 2 (c_q / c_t) m g; f_hat kept in
    [0.05 m g, 4 m g] and divisions by f_hat, R33 and cos^2(pitch) protected, so a poor
    estimate gives a bounded command rather than NaN. The position-error integral is clipped
    to +-int_limit (m s) against wind-up while the estimate is poor."""

    def __init__(self, params: QuadrotorParams, reference: CircleReference, lam: float = 2.5,
                 lam_z: float = 2.0, lam_psi: float = 2.0, int_limit: float = 1.0):
        self.params = params
        self.reference = reference
        self.lam, self.lam_z, self.lam_psi = float(lam), float(lam_z), float(lam_psi)
        self.int_limit = float(int_limit)
        m, g = params.mass, GRAVITY
        self.inertia = np.asarray(params.inertia, float)
        self.f_max = 4.0 * m * g
        self.tau_max = np.array([params.arm * m * g, params.arm * m * g, 2.0 * params.c_q / params.c_t * m * g])
        self._f, self._fd, self._fdd = m * g, 0.0, 0.0
        self._int_e = np.zeros(3)
        self._int_psi = 0.0

    def command(self, x, t: float, dt: float) -> np.ndarray:
        """u = [f, tau_x, tau_y, tau_z] from the state estimate x at time t; dt is the time since
        the previous call (it advances f_hat and the error integrals)."""
        p = self.params
        m, I = p.mass, self.inertia
        dt = max(float(dt), 0.0)

        # f_hat'' was held since the previous call: advance the extension exactly
        self._f += self._fd * dt + 0.5 * self._fdd * dt * dt
        self._fd += self._fdd * dt
        self._f = float(np.clip(self._f, 0.05 * m * GRAVITY, self.f_max))
        self._fd = float(np.clip(self._fd, -50.0 * m * GRAVITY, 50.0 * m * GRAVITY))
        f, fd = self._f, self._fd

        x = np.asarray(x, float)
        q = x[3:7]
        nq = np.linalg.norm(q)
        q = q / nq if nq > 1e-9 else np.array([1.0, 0.0, 0.0, 0.0])
        r, v, w = x[0:3], x[7:10], x[10:13]
        R = quat_rotation(q)

        ref = self.reference.derivatives(t, 4)
        r1 = R @ v
        r2 = R[:, 2] * (f / m) - GRAVITY * _E3
        r3 = R @ (_cross(w, _E3) * f + _E3 * fd) / m
        e0, e1, e2, e3 = r - ref[0], r1 - ref[1], r2 - ref[2], r3 - ref[3]
        self._int_e = np.clip(self._int_e + e0 * dt, -self.int_limit, self.int_limit)
        lam = np.array([self.lam, self.lam, self.lam_z])
        snap = (ref[4] - 5.0 * lam * e3 - 10.0 * lam**2 * e2 - 10.0 * lam**3 * e1
                - 5.0 * lam**4 * e0 - lam**5 * self._int_e)
        sb = m * (R.T @ snap)  # body rows of eq. 20: what (w', f_hat'') must produce
        wx, wy, wz = w
        fdiv = max(f, 0.05 * m * GRAVITY)
        wdy = (sb[0] - 2.0 * wy * fd - f * wx * wz) / fdiv
        wdx = (-sb[1] - 2.0 * wx * fd + f * wy * wz) / fdiv
        fdd = sb[2] + (wx * wx + wy * wy) * f

        # yaw
        psi_r, psid_r, psidd_r = self.reference.yaw_derivatives(t)
        D = max(R[0, 0] ** 2 + R[1, 0] ** 2, 1e-3)  # cos^2(pitch): protected near +-90 deg
        psi = math.atan2(R[1, 0], R[0, 0])
        psid = (wz * R[2, 2] + wy * R[2, 1]) / D
        e_psi = wrap_yaw(psi - psi_r)
        self._int_psi = float(np.clip(self._int_psi + e_psi * dt, -1.0, 1.0))
        lp = self.lam_psi
        psidd = psidd_r - 3.0 * lp * (psid - psid_r) - 3.0 * lp**2 * e_psi - lp**3 * self._int_psi
        R00d = R[0, 1] * wz - R[0, 2] * wy
        R10d = R[1, 1] * wz - R[1, 2] * wy
        Dd = 2.0 * (R[0, 0] * R00d + R[1, 0] * R10d)
        R22d = R[2, 0] * wy - R[2, 1] * wx
        R21d = -R[2, 0] * wz + R[2, 2] * wx
        r22 = R[2, 2] if abs(R[2, 2]) > 0.2 else math.copysign(0.2, R[2, 2])
        wdz = (psidd * D + psid * Dd - wdy * R[2, 1] - wz * R22d - wy * R21d) / r22

        wdot = np.array([wdx, wdy, wdz])
        tau = I * wdot + _cross(w, I * w)
        u = np.concatenate([[f], np.clip(tau, -self.tau_max, self.tau_max)])
        if not np.all(np.isfinite(u)) or not math.isfinite(fdd):
            # only an absurd estimate overflows: hold thrust, no moments, freeze f_hat
            self._fdd = 0.0
            return np.array([f, 0.0, 0.0, 0.0])
        self._fdd = float(fdd)
        return u


class GroundController:
    """Tracking controller for the wheeled robot (the paper leaves it to the literature).

    The vehicle origin sits d ahead of the rear axle, so its inertial planar velocity
    Rz(phi) [v, d w] is invertible in (v, w) whenever d != 0: the origin is steered like a
    point. The desired origin velocity r_ref' + k_p (r_ref - r) (magnitude capped at v_max)
    is inverted for (v*, w*) (w* capped at w_max), and the surge force and yaw moment cancel
    the model's coupling terms and close first-order loops on v and w:
    F = m (k_v (v* - v) - d w^2), tau = Izz k_w (w* - w) + m d w v.
    On a circle (v*, w*) are constant in steady state, so the inner loops leave no lag. The
    heading is not controlled: it follows the path (the zero dynamics are stable moving
    forward with d > 0). z is not actuated."""

    def __init__(self, params: GroundParams, reference: CircleReference, k_p: float = 1.0,
                 k_v: float = 5.0, k_w: float = 10.0, v_max: float = 1.0, w_max: float = 4.0):
        if params.d == 0.0:
            raise ValueError("GroundController needs d != 0 (the origin ahead of the axle)")
        self.params = params
        self.reference = reference
        self.k_p, self.k_v, self.k_w = float(k_p), float(k_v), float(k_w)
        self.v_max, self.w_max = float(v_max), float(w_max)

    def command(self, x, t: float, dt: float) -> np.ndarray:
        """u = [F_x, tau_z] from the state estimate x at time t (dt unused: no integrators)."""
        p = self.params
        x = np.asarray(x, float)
        ref = self.reference.derivatives(t, 1)
        vel = ref[1][:2] + self.k_p * (ref[0][:2] - x[:2])
        n = float(np.hypot(vel[0], vel[1]))
        if n > self.v_max:
            vel = vel * (self.v_max / n)
        c, s = math.cos(x[3]), math.sin(x[3])
        v_star = c * vel[0] + s * vel[1]
        w_star = float(np.clip((-s * vel[0] + c * vel[1]) / p.d, -self.w_max, self.w_max))
        v, w = x[4], x[6]
        F = p.mass * (self.k_v * (v_star - v) - p.d * w * w)
        tau = p.izz * self.k_w * (w_star - w) + p.mass * p.d * w * v
        u = np.array([F, tau])
        return u if np.all(np.isfinite(u)) else np.zeros(2)


def controller_for(model: VehicleModel, reference: CircleReference, **gains):
    """The tracking controller for `model` (a Quadrotor or GroundRobot) on `reference`."""
    if isinstance(model, Quadrotor):
        return QuadrotorController(model.params, reference, **gains)
    if isinstance(model, GroundRobot):
        return GroundController(model.params, reference, **gains)
    raise TypeError(f"no controller for vehicle model {type(model).__name__}")


def actuator_std(model: VehicleModel, force: float, moment: float) -> np.ndarray:
    """The std of the world's noise on each of a vehicle's inputs: the force (thrust or surge)
    first, then the moments (scenario `sensors.vehicle.force_noise`, `moment_noise`)."""
    return np.r_[float(force), np.full(model.input_dim - 1, float(moment))]
