"""Strapdown INS and its 16-state error model (Goel, Kealy, Lohani, eqs. 1-12), pure numpy.

The per-node state of the paper (eq. 1) is position, velocity, attitude, gyro bias,
accelerometer bias and receiver clock bias, 3+3+3+3+3+1 = 16. Here the nominal (total) state is
an `InsState` propagated by `mechanize`, and the EKF estimates the 16-vector *error* state
`dx = [dp, dv, dtheta, dbg, dba, dclk]` with `error_dynamics` (F, Q) and folds it back into the
nominal state with `inject`.

Frames and conventions (netsim/world/uas_sensors.py uses the same ones, so truth and filter agree):

* Navigation frame n: ENU (x east, y north, z up), a flat-earth local tangent plane at a
  reference point, metres. It does not rotate: no Earth rate, no transport rate, no Coriolis.
  Gravity is the constant vector ``GRAVITY = [0, 0, -9.80665]`` m/s^2 (it points down, -z).
  Why not the paper's ECEF (eqs. 2-4): a swarm flies within a few km for minutes, where the
  neglected terms are below MEMS sensor errors. Coriolis, 2 * 7.29e-5 rad/s * 15 m/s =
  2.2e-3 m/s^2, is under a tenth of the 3 mg turn-on accelerometer bias of the default `ImuSpec`; the
  Earth rate, 15 deg/h, is well under its 100 deg/h turn-on gyro bias, and the gravity
  direction turns by only 0.16 mrad per km travelled. netsim generates its truth in this same
  frame, so the model is exact for the simulated world; a tactical-grade IMU on real hardware
  would need the Earth-rate and Coriolis terms back.
* Body frame b: FLU (x forward, y left, z up), the ROS REP-103 pairing with ENU: a level
  vehicle with yaw 0 has its body axes on east, north, up.
* Quaternions: Hamilton, scalar first ``[w, x, y, z]``, unit norm, canonical ``w >= 0``. The
  attitude quaternion ``q`` rotates body vectors into ENU: ``v_n = C(q) v_b`` with
  ``C = quat_to_dcm(q)``; the body-rate increment composes on the right,
  ``q(t+dt) = q(t) (x) exp(omega_b dt)``.
* Euler angles (only for humans and tests): ``C = Rz(yaw) Ry(-pitch) Rx(roll)``; yaw is
  counter-clockwise from east about up, pitch positive nose up, roll positive right wing down.
* Accelerometers measure specific force ``f_b = C^T (a_n - GRAVITY)``: at rest and level they
  read ``+9.80665`` on body z (up), i.e. minus gravity.
* IMU samples (`ImuSample`) are the *mean* angular rate and specific force over the interval
  they cover (delta-theta / dt and delta-v / dt of an integrating IMU), not point samples.
* Clock bias and drift are in metres and metres per second (c times seconds), so the clock bias
  adds straight to a pseudorange (eq. 14).

Attitude error (the "phi angle"): ``C_true = exp([dtheta x]) C_est``, a small rotation in the
navigation frame that carries the estimate onto the truth (Titterton & Weston's
``C_est = (I - [phi x]) C_true`` to first order). In a non-rotating navigation frame the psi-
and phi-angle formulations coincide, since they differ only by the position error times the
transport rate, which is zero here. Every other error is truth minus estimate. A multiplicative
quaternion error replaces the paper's Euler-angle state (eq. 4): it has no singularity at
pitch +-90 deg and gives the simple F blocks below.

The continuous error dynamics, derived from mechanization with ``f = f_meas - ba``,
``w = w_meas - bg`` (n_a, n_g the sensor white noises, C the estimated attitude):

    dp'     = dv
    dv'     = -[(C f) x] dtheta - C dba - C n_a
    dtheta' = -C dbg - C n_g
    dbg'    = -dbg / tau + w_bg         (tau = inf: the random walk of eq. 5)
    dba'    = -dba / tau + w_ba         (eq. 6)
    dclk'   = w_clk                     (eq. 7)

Reading eq. 11 of the paper against this: as extracted, it puts -R dt in the velocity row under
the gyro-bias column and -R_alpha dt in the attitude row under the accelerometer-bias column.
Physically the accelerometer bias drives velocity and the gyro bias drives attitude, as above.
Its E = -d(R b_a)/d(alpha) corresponds to our -[(C f) x] once the measured specific force is
included.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from swarmloc.models.measurements import skew

G0 = 9.80665
"""Standard gravity, m/s^2."""
GRAVITY = np.array([0.0, 0.0, -G0])
"""Gravity in ENU, m/s^2: it points down."""

ERROR_DIM = 16
POS = slice(0, 3)
VEL = slice(3, 6)
ATT = slice(6, 9)
GYRO_BIAS = slice(9, 12)
ACCEL_BIAS = slice(12, 15)
CLOCK = 15
"""Index of the clock-bias error in the error state (an int, not a slice)."""

_DEG = math.pi / 180.0


# --------------------------------------------------------------------------- rotations


def quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product p (x) q, scalar first."""
    # Written out in scalars: np.cross on 3-vectors costs ten times the arithmetic, and the
    # product runs every mechanization step.
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return np.array([pw * qw - px * qx - py * qy - pz * qz,
                     pw * qx + px * qw + py * qz - pz * qy,
                     pw * qy - px * qz + py * qw + pz * qx,
                     pw * qz + px * qy - py * qx + pz * qw])


def quat_conj(q: np.ndarray) -> np.ndarray:
    return np.array([q[0], -q[1], -q[2], -q[3]])


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Unit norm and w >= 0 (q and -q are the same rotation; one representative keeps
    comparisons and differences well defined)."""
    q = np.asarray(q, float) / np.linalg.norm(q)
    return -q if q[0] < 0 else q


def quat_to_dcm(q: np.ndarray) -> np.ndarray:
    """Rotation matrix C with v_n = C v_b for the unit quaternion q = [w, x, y, z]."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def dcm_to_quat(C: np.ndarray) -> np.ndarray:
    """Unit quaternion (w >= 0) of a rotation matrix, Shepperd's method: dividing by the
    largest of the four candidates keeps it accurate for every rotation angle."""
    tr = C[0, 0] + C[1, 1] + C[2, 2]
    k = int(np.argmax([tr, C[0, 0], C[1, 1], C[2, 2]]))
    if k == 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = [0.25 * s, (C[2, 1] - C[1, 2]) / s, (C[0, 2] - C[2, 0]) / s, (C[1, 0] - C[0, 1]) / s]
    elif k == 1:
        s = 2.0 * math.sqrt(1.0 + C[0, 0] - C[1, 1] - C[2, 2])
        q = [(C[2, 1] - C[1, 2]) / s, 0.25 * s, (C[0, 1] + C[1, 0]) / s, (C[0, 2] + C[2, 0]) / s]
    elif k == 2:
        s = 2.0 * math.sqrt(1.0 - C[0, 0] + C[1, 1] - C[2, 2])
        q = [(C[0, 2] - C[2, 0]) / s, (C[0, 1] + C[1, 0]) / s, 0.25 * s, (C[1, 2] + C[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 - C[0, 0] - C[1, 1] + C[2, 2])
        q = [(C[1, 0] - C[0, 1]) / s, (C[0, 2] + C[2, 0]) / s, (C[1, 2] + C[2, 1]) / s, 0.25 * s]
    return quat_normalize(np.array(q))


def quat_from_rotvec(phi: np.ndarray) -> np.ndarray:
    """exp of a rotation vector (axis times angle, rad): exact for any angle."""
    phi = np.asarray(phi, float)
    angle = math.sqrt(phi @ phi)
    # np.sinc(x) = sin(pi x)/(pi x) is exact at 0, so the small-angle limit needs no branch.
    return np.concatenate(([math.cos(0.5 * angle)], 0.5 * np.sinc(angle / (2 * math.pi)) * phi))


def rotvec_from_quat(q: np.ndarray) -> np.ndarray:
    """log of a unit quaternion: the rotation vector of angle in [0, pi]."""
    q = quat_normalize(q)
    w, v = q[0], q[1:]
    n = math.sqrt(v @ v)
    if n < 1e-8:
        # atan2(n, w)/n = 1/w - n^2/(3 w^3) + O(n^4): the series avoids 0/0; what it drops is < 1e-32.
        return 2.0 * (1.0 / w - n * n / (3.0 * w**3)) * v
    return 2.0 * math.atan2(n, w) / n * v


def attitude_error(q_true: np.ndarray, q_est: np.ndarray) -> np.ndarray:
    """The nav-frame rotation vector dtheta with C_true = exp([dtheta x]) C_est."""
    return rotvec_from_quat(quat_mul(q_true, quat_conj(q_est)))


def quat_from_euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """q of C = Rz(yaw) Ry(-pitch) Rx(roll) (FLU body: pitch up is a negative turn about left)."""
    qz = np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])
    qy = np.array([math.cos(pitch / 2), 0.0, -math.sin(pitch / 2), 0.0])
    qx = np.array([math.cos(roll / 2), math.sin(roll / 2), 0.0, 0.0])
    return quat_normalize(quat_mul(quat_mul(qz, qy), qx))


def euler_from_quat(q: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in rad, the inverse of `quat_from_euler`; pitch in [-pi/2, pi/2]."""
    C = quat_to_dcm(q)
    pitch = math.asin(max(-1.0, min(1.0, C[2, 0])))
    return math.atan2(C[2, 1], C[2, 2]), pitch, math.atan2(C[1, 0], C[0, 0])


# --------------------------------------------------------------------------- sensor specs


@dataclass(frozen=True)
class ImuSpec:
    """IMU error model, SI units, the same on all three axes.

    The defaults are an industrial MEMS IMU (the class of the paper's "low cost" sensors):

    * ``gyro_arw``: angle random walk, the white-noise density of the rate, rad/s/sqrt(Hz)
      (= rad/sqrt(s)). 8.73e-5 is 0.3 deg/sqrt(h).
    * ``accel_vrw``: velocity random walk, m/s^2/sqrt(Hz) (= m/s/sqrt(s)). 1.0e-3 is
      0.06 m/s/sqrt(h), about 100 ug/sqrt(Hz).
    * ``gyro_bias_rw``: rate random walk, the density of the white noise driving the gyro bias,
      rad/s/sqrt(s). 8.08e-7 is 10 deg/h/sqrt(h).
    * ``accel_bias_rw``: accelerometer bias random walk, m/s^2/sqrt(s). 1.63e-5 is
      100 ug/sqrt(h).
    * ``bias_tau``: correlation time of both biases, s. ``inf`` (default) makes them the pure
      random walks of eqs. 5-6; a finite value makes them first-order Gauss-Markov,
      ``b' = -b/tau + w``, whose steady-state std is ``rw * sqrt(tau/2)`` (so a datasheet bias
      instability B with correlation time tau is ``rw = B * sqrt(2/tau)``).
    * ``gyro_bias_sigma0``, ``accel_bias_sigma0``: turn-on bias std (the world draws the initial
      bias from it, the filter starts its covariance with it). 4.85e-4 rad/s is 100 deg/h;
      2.94e-2 m/s^2 is 3 mg.

    A sample that averages white noise of density N over dt has std ``N / sqrt(dt)``.
    """

    gyro_arw: float = 0.3 * _DEG / 60.0
    accel_vrw: float = 0.06 / 60.0
    gyro_bias_rw: float = 10.0 * _DEG / 3600.0 / 60.0
    accel_bias_rw: float = 100e-6 * G0 / 60.0
    bias_tau: float = math.inf
    gyro_bias_sigma0: float = 100.0 * _DEG / 3600.0
    accel_bias_sigma0: float = 3e-3 * G0

    @classmethod
    def perfect(cls) -> "ImuSpec":
        """No noise, no bias: the IMU reports the truth."""
        return cls(0.0, 0.0, 0.0, 0.0, math.inf, 0.0, 0.0)

    @classmethod
    def from_datasheet(cls, arw_deg_rt_h: float, vrw_m_s_rt_h: float, rrw_deg_h_rt_h: float,
                       accel_rw_ug_rt_h: float, gyro_turn_on_deg_h: float, accel_turn_on_mg: float,
                       bias_tau: float = math.inf) -> "ImuSpec":
        """Build a spec from the units datasheets use (deg/sqrt(h), m/s/sqrt(h), deg/h/sqrt(h),
        ug/sqrt(h), deg/h, mg)."""
        return cls(
            gyro_arw=arw_deg_rt_h * _DEG / 60.0,
            accel_vrw=vrw_m_s_rt_h / 60.0,
            gyro_bias_rw=rrw_deg_h_rt_h * _DEG / 3600.0 / 60.0,
            accel_bias_rw=accel_rw_ug_rt_h * 1e-6 * G0 / 60.0,
            bias_tau=bias_tau,
            gyro_bias_sigma0=gyro_turn_on_deg_h * _DEG / 3600.0,
            accel_bias_sigma0=accel_turn_on_mg * 1e-3 * G0,
        )


@dataclass(frozen=True)
class ClockSpec:
    """Receiver clock, in metres: bias b (m) and drift d (m/s).

    The truth (netsim) is the standard two-state clock, ``b' = d + w_b``, ``d' = w_d``, with
    white-noise densities ``bias_psd`` (m^2/s) and ``drift_psd`` (m^2/s^3). The defaults are a
    TCXO with Allan coefficients h0 = 2e-19, h-2 = 2e-20 (Brown & Hwang):
    ``bias_psd = c^2 h0 / 2``, ``drift_psd = c^2 2 pi^2 h-2``.

    The 16-state filter of eq. 1 has no drift state: it keeps the drift in `InsState` as a
    known constant and models the clock-bias error as the random walk of eq. 7 with density
    ``filter_psd`` (m^2/s). That density must also absorb the unmodelled drift wander: after
    T s the drift has wandered by sqrt(drift_psd T), 1.9 m/s at T = 100 s, and a random walk
    keeps up over a 1 s GNSS epoch only if sqrt(filter_psd * 1 s) is at least that. Hence the
    default 4 m^2/s; pseudoranges from four or more satellites re-fix the bias every epoch.
    """

    bias_psd: float = 299_792_458.0**2 * 2e-19 / 2
    drift_psd: float = 299_792_458.0**2 * 2 * math.pi**2 * 2e-20
    filter_psd: float = 4.0


# --------------------------------------------------------------------------- nominal state


def _vec3(x) -> np.ndarray:
    a = np.array(x, float).reshape(3)
    return a


@dataclass
class ImuSample:
    """One IMU interval: mean body angular rate (rad/s) and mean specific force (m/s^2), body
    FLU, over the dt it covers."""

    gyro: np.ndarray
    accel: np.ndarray

    def __post_init__(self):
        self.gyro = _vec3(self.gyro)
        self.accel = _vec3(self.accel)


@dataclass
class InsState:
    """Nominal navigation state.

    position, velocity: ENU, m and m/s. quaternion: body FLU to ENU, [w, x, y, z]. gyro_bias
    (rad/s) and accel_bias (m/s^2): body axes, subtracted from the IMU output. clock_bias (m)
    and clock_drift (m/s): receiver clock; the drift is a known constant to the 16-state filter
    (see `ClockSpec`), 0 unless the caller knows better.
    """

    position: np.ndarray
    velocity: np.ndarray
    quaternion: np.ndarray
    gyro_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    accel_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    clock_bias: float = 0.0
    clock_drift: float = 0.0

    def __post_init__(self):
        self.position = _vec3(self.position)
        self.velocity = _vec3(self.velocity)
        self.quaternion = quat_normalize(np.array(self.quaternion, float).reshape(4))
        self.gyro_bias = _vec3(self.gyro_bias)
        self.accel_bias = _vec3(self.accel_bias)
        self.clock_bias = float(self.clock_bias)
        self.clock_drift = float(self.clock_drift)

    @property
    def dcm(self) -> np.ndarray:
        """C, body to ENU."""
        return quat_to_dcm(self.quaternion)

    def copy(self) -> "InsState":
        return InsState(self.position.copy(), self.velocity.copy(), self.quaternion.copy(),
                        self.gyro_bias.copy(), self.accel_bias.copy(), self.clock_bias, self.clock_drift)


def mechanize(state: InsState, imu: ImuSample, dt: float, bias_tau: float = math.inf) -> InsState:
    """One strapdown step of dt seconds; returns the new state (the input is not modified).

    1. Remove the estimated biases from the IMU means.
    2. Attitude: q1 = q0 (x) exp(w dt), exact for a body rate constant over the interval.
    3. Velocity: the body turns during the interval, so the held specific force is rotated with
       the mean of the start and end attitudes, (C0 + C1)/2 f, then gravity is added:
       v1 = v0 + ((C0 + C1)/2 f + g) dt. This is the trapezoidal rule on C(t) f and is second
       order: it captures the first-order rotation correction that using C0 alone would miss.
    4. Position: trapezoidal, p1 = p0 + (v0 + v1)/2 dt, exact for a constant acceleration.
    5. Clock: b1 = b0 + d dt with the known drift. Biases: the mean of their model, constant
       for random walks (bias_tau = inf, eqs. 5-6), decaying by exp(-dt/bias_tau) for
       Gauss-Markov biases. Pass the `ImuSpec.bias_tau` the error model uses, so the nominal and
       error-state bias models agree.

    Over a smooth trajectory with interval-mean IMU data, the global error of this scheme is
    O(dt^2) (tested in tests/test_ins.py).
    """
    w = imu.gyro - state.gyro_bias
    f = imu.accel - state.accel_bias
    C0 = quat_to_dcm(state.quaternion)
    q1 = quat_normalize(quat_mul(state.quaternion, quat_from_rotvec(w * dt)))
    C1 = quat_to_dcm(q1)
    v1 = state.velocity + (0.5 * (C0 + C1) @ f + GRAVITY) * dt
    p1 = state.position + 0.5 * (state.velocity + v1) * dt
    decay = math.exp(-dt / bias_tau)
    return InsState(p1, v1, q1, decay * state.gyro_bias, decay * state.accel_bias,
                    state.clock_bias + state.clock_drift * dt, state.clock_drift)


# --------------------------------------------------------------------------- error state


def inject(state: InsState, dx: np.ndarray) -> InsState:
    """Fold an error-state estimate dx (truth minus estimate, the 16-vector) into the nominal
    state: positions, velocities, biases and clock add; attitude is premultiplied by the small
    nav-frame rotation, q <- exp(dtheta) (x) q. Returns a new state."""
    dx = np.asarray(dx, float).reshape(ERROR_DIM)
    q = quat_normalize(quat_mul(quat_from_rotvec(dx[ATT]), state.quaternion))
    return InsState(state.position + dx[POS], state.velocity + dx[VEL], q,
                    state.gyro_bias + dx[GYRO_BIAS], state.accel_bias + dx[ACCEL_BIAS],
                    state.clock_bias + dx[CLOCK], state.clock_drift)


def state_error(true: InsState, est: InsState) -> np.ndarray:
    """The 16-vector error of `est` with respect to `true`: inject(est, state_error(true, est))
    reproduces `true` (up to its clock drift, which is not part of the error state)."""
    dx = np.empty(ERROR_DIM)
    dx[POS] = true.position - est.position
    dx[VEL] = true.velocity - est.velocity
    dx[ATT] = attitude_error(true.quaternion, est.quaternion)
    dx[GYRO_BIAS] = true.gyro_bias - est.gyro_bias
    dx[ACCEL_BIAS] = true.accel_bias - est.accel_bias
    dx[CLOCK] = true.clock_bias - est.clock_bias
    return dx


def error_jacobian(state: InsState, imu: ImuSample, spec: ImuSpec = ImuSpec()) -> np.ndarray:
    """A, the 16x16 continuous-time error dynamics dx' = A dx + G n (module docstring),
    evaluated at the nominal state at the start of the step."""
    C = quat_to_dcm(state.quaternion)
    f_n = C @ (imu.accel - state.accel_bias)
    A = np.zeros((ERROR_DIM, ERROR_DIM))
    A[POS, VEL] = np.eye(3)
    A[VEL, ATT] = -skew(f_n)
    A[VEL, ACCEL_BIAS] = -C
    A[ATT, GYRO_BIAS] = -C
    if math.isfinite(spec.bias_tau):
        A[GYRO_BIAS, GYRO_BIAS] = -np.eye(3) / spec.bias_tau
        A[ACCEL_BIAS, ACCEL_BIAS] = -np.eye(3) / spec.bias_tau
    return A


def noise_intensity(spec: ImuSpec = ImuSpec(), clock: ClockSpec = ClockSpec()) -> np.ndarray:
    """G Qc G^T, the 16x16 continuous noise intensity of the error state.

    Sensor white noise enters through -C n_a and -C n_g; the noise is isotropic, so
    C (s^2 I) C^T = s^2 I and the intensity is diagonal whatever the attitude."""
    d = np.zeros(ERROR_DIM)
    d[VEL] = spec.accel_vrw**2
    d[ATT] = spec.gyro_arw**2
    d[GYRO_BIAS] = spec.gyro_bias_rw**2
    d[ACCEL_BIAS] = spec.accel_bias_rw**2
    d[CLOCK] = clock.filter_psd
    return np.diag(d)


def error_dynamics(state: InsState, imu: ImuSample, dt: float, spec: ImuSpec = ImuSpec(),
                   clock: ClockSpec = ClockSpec()) -> tuple[np.ndarray, np.ndarray]:
    """Discrete error-state transition over one mechanization step: (F, Q), both 16x16.

    F = I + A dt (first order, as in eq. 10), A from `error_jacobian` at the start-of-step
    nominal state and IMU sample. Q is the exact noise covariance of that first-order
    transition, Q = int_0^dt (I + A s) W (I + A s)^T ds with W = `noise_intensity`:

        Q = W dt + (A W + W A^T) dt^2/2 + A W A^T dt^3/3

    It is positive semidefinite by construction, and its dt^2 and dt^3 terms carry the
    velocity noise into position (q_a dt^3/3) and the gyro noise into velocity, which the bare
    W dt would drop.
    """
    A = error_jacobian(state, imu, spec)
    W = noise_intensity(spec, clock)
    F = np.eye(ERROR_DIM) + A * dt
    AW = A @ W
    Q = W * dt + (AW + AW.T) * (dt**2 / 2) + A @ W @ A.T * (dt**3 / 3)
    return F, 0.5 * (Q + Q.T)


def propagate_rows(state: InsState, rows: np.ndarray, dt: float, spec: ImuSpec = ImuSpec(),
                   clock: ClockSpec = ClockSpec()) -> tuple[InsState, np.ndarray, np.ndarray]:
    """`mechanize` and `error_dynamics` over n IMU intervals of dt seconds each, rows (n, 6) of
    finite [gyro, accel] means: (the state after the last, F (n, 16, 16), Q (n, 16, 16)), each
    row's F and Q at the start of its interval. The same formulas, for all rows at once but the
    quaternion chain: the time update of InsEkf (swarmloc/estimators/ekf/local.py, which says what
    it saves; tests/test_ekf_nodes.py checks the two agree), and of swarmloc/experiment/bounds.py
    at the true state."""
    s, n = state, rows.shape[0]
    W = np.diag(noise_intensity(spec, clock))
    decay = 1.0 if math.isinf(spec.bias_tau) else math.exp(-dt / spec.bias_tau)
    # ins.mechanize decays the bias estimate after each interval: interval i uses decay^i b.
    powers = decay ** np.arange(n)[:, None]
    bg, ba = powers * s.gyro_bias, powers * s.accel_bias
    w, f = rows[:, :3] - bg, rows[:, 3:] - ba

    # Attitude: q_{i+1} = q_i (x) exp(w_i dt), ins.quat_from_rotvec's formula for all rows,
    # then the chain, which is the only serial part (plain floats: a numpy call per
    # quaternion product would cost more than the whole batch).
    phi = w * dt
    angle = np.sqrt(np.einsum("ij,ij->i", phi, phi))
    dq = np.column_stack([np.cos(0.5 * angle), 0.5 * np.sinc(angle / (2 * math.pi))[:, None] * phi]).tolist()
    pw, px, py, pz = s.quaternion.tolist()
    quats = [(pw, px, py, pz)]
    for qw, qx, qy, qz in dq:
        pw, px, py, pz = (pw * qw - px * qx - py * qy - pz * qz, pw * qx + px * qw + py * qz - pz * qy,
                          pw * qy - px * qz + py * qw + pz * qx, pw * qz + px * qy - py * qx + pz * qw)
        norm = math.sqrt(pw * pw + px * px + py * py + pz * pz)
        if pw < 0.0:
            norm = -norm  # ins.quat_normalize's canonical w >= 0
        pw, px, py, pz = pw / norm, px / norm, py / norm, pz / norm
        quats.append((pw, px, py, pz))
    Q = np.array(quats)
    C = np.moveaxis(quat_to_dcm(Q.T), -1, 0)  # (n+1, 3, 3); quat_to_dcm broadcasts over a trailing axis

    # Velocity and position as ins.mechanize: trapezoidal in the attitude and in velocity.
    a = 0.5 * np.einsum("nij,nj->ni", C[:-1] + C[1:], f) + GRAVITY
    v = np.vstack([s.velocity, s.velocity + np.cumsum(a * dt, axis=0)])
    p_end = s.position + 0.5 * dt * (v[:-1] + v[1:]).sum(axis=0)

    # Covariance: ins.error_jacobian and ins.error_dynamics for every row at once.
    C0 = C[:-1]
    A = np.zeros((n, ERROR_DIM, ERROR_DIM))
    A[:, POS, VEL] = np.eye(3)
    A[:, VEL, ATT] = -skew(np.einsum("nij,nj->ni", C0, f))
    A[:, VEL, ACCEL_BIAS] = -C0
    A[:, ATT, GYRO_BIAS] = -C0
    if not math.isinf(spec.bias_tau):
        idx = np.arange(9, 15)
        A[:, idx, idx] = -1.0 / spec.bias_tau
    F = np.eye(ERROR_DIM) + A * dt
    AW = A * W  # W diagonal: A @ diag(W)
    Qd = (np.diag(W) * dt + (AW + AW.transpose(0, 2, 1)) * (dt**2 / 2)
          + AW @ A.transpose(0, 2, 1) * (dt**3 / 3))
    Qd = 0.5 * (Qd + Qd.transpose(0, 2, 1))
    end = n * dt
    state = InsState(p_end, v[-1], Q[-1], decay**n * s.gyro_bias, decay**n * s.accel_bias,
                         s.clock_bias + s.clock_drift * end, s.clock_drift)
    return state, F, Qd
