"""UAS world truth and sensors: 3D trajectories, a strapdown IMU, a GNSS constellation with
pseudoranges, and inter-UAV relative measurements (Goel, Kealy, Lohani; eqs. 14-15, 19).
Pure numpy; no Zenoh.

Frames and units are those of swarmloc/models/ins.py, so the filter's model is exact for this world:
ENU local tangent plane at a reference site (metres, flat earth, constant gravity
``GRAVITY = [0, 0, -9.80665]`` m/s^2), body FLU (x forward, y left, z up), quaternions Hamilton
scalar-first body-to-ENU. Accelerometers measure specific force ``f_b = C^T (a - g)``: a level
hover reads ``+9.80665`` m/s^2 on body z. IMU samples are interval means (see `mean_imu`).

Randomness: every random component takes a seeded ``numpy.random.Generator`` (or an int seed)
of its own, so e.g. adding a satellite never changes the IMU noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from swarmloc.models.ins import GRAVITY, ClockSpec, ImuSample, ImuSpec, dcm_to_quat, quat_from_euler, quat_to_dcm

C_LIGHT = 299_792_458.0
"""Speed of light, m/s."""
MU_EARTH = 3.986004418e14
"""Earth's gravitational parameter (WGS 84), m^3/s^2."""
OMEGA_EARTH = 7.2921151467e-5
"""Earth rotation rate (WGS 84), rad/s."""
GPS_ORBIT_RADIUS = 26_559_700.0
"""Semi-major axis of the GPS orbits, m (period 43 077 s, about half a sidereal day)."""
WGS84_A = 6_378_137.0
WGS84_F = 1.0 / 298.257223563


def _rng(rng) -> np.random.Generator:
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.sum(a * b, axis=-1, keepdims=True)


def _unit_and_rate(w: np.ndarray, wd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """u = w/|w| and its time derivative (wd - (wd.u) u)/|w|."""
    n = np.linalg.norm(w, axis=-1, keepdims=True)
    u = w / n
    return u, (wd - _dot(wd, u) * u) / n


# --------------------------------------------------------------------------- trajectories


@dataclass
class UasTruth:
    """True kinematic state at time t: ENU position (m), velocity (m/s), acceleration (m/s^2),
    attitude quaternion (body FLU to ENU, [w, x, y, z]), body angular rate (rad/s) and body
    specific force (m/s^2)."""

    t: float
    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    quaternion: np.ndarray
    angular_rate: np.ndarray
    specific_force: np.ndarray


class Trajectory:
    """A smooth 3D flight path with attitude, evaluated analytically at any time.

    Every method takes a scalar or an array of times and returns arrays with the time shape in
    front: positions (..., 3), rotation matrices (..., 3, 3).

    Attitude (``attitude`` argument of the subclasses): the body x axis is along the velocity
    (yaw along track, pitch = flight-path angle, zero sideslip). Roll is either

    * ``"coordinated"`` (default): a coordinated turn, the fixed-wing way: body z is the part of
      the specific force a - g normal to the velocity, so the accelerometers see no lateral
      force (f_b[1] = 0) and the bank angle is atan(v^2 / (R g)) on a level circle; or
    * ``"level"``: zero roll: body z is the vertical's part normal to the velocity.

    The angular rate comes from the analytic derivative of the rotation matrix
    (C^T C' = [omega x]), which needs the jerk; subclasses give position derivatives up to
    order 3. Attitude is undefined where the speed is zero (or, coordinated, where a - g is
    along the velocity); the trajectories below keep the speed bounded away from zero.
    """

    attitude_mode: str = "coordinated"

    def derivative(self, t, order: int) -> np.ndarray:
        raise NotImplementedError

    def position(self, t) -> np.ndarray:
        return self.derivative(t, 0)

    def velocity(self, t) -> np.ndarray:
        return self.derivative(t, 1)

    def acceleration(self, t) -> np.ndarray:
        return self.derivative(t, 2)

    def jerk(self, t) -> np.ndarray:
        return self.derivative(t, 3)

    def _frame(self, t) -> tuple[np.ndarray, np.ndarray]:
        """C (body axes x, y, z in ENU as columns, (..., 3, 3)) and the body rate (..., 3)."""
        v, a, j = self.derivative(t, 1), self.derivative(t, 2), self.derivative(t, 3)
        x, xd = _unit_and_rate(v, a)
        if self.attitude_mode == "coordinated":
            f, fd = a - GRAVITY, j
            fx = _dot(f, x)
            w = f - fx * x
            wd = fd - (_dot(fd, x) + _dot(f, xd)) * x - fx * xd
        elif self.attitude_mode == "level":
            w = np.array([0.0, 0.0, 1.0]) - x[..., 2:3] * x
            wd = -xd[..., 2:3] * x - x[..., 2:3] * xd
        else:
            raise ValueError(f"unknown attitude mode {self.attitude_mode!r}")
        z, zd = _unit_and_rate(w, wd)
        y = np.cross(z, x)
        yd = np.cross(zd, x) + np.cross(z, xd)
        # C^T C' = [omega x]: omega_x = z.y', omega_y = x.z', omega_z = y.x'.
        omega = np.stack([_dot(z, yd)[..., 0], _dot(x, zd)[..., 0], _dot(y, xd)[..., 0]], axis=-1)
        return np.stack([x, y, z], axis=-1), omega

    def dcm(self, t) -> np.ndarray:
        """C(t), body to ENU, (..., 3, 3); its columns are the body axes in ENU."""
        return self._frame(t)[0]

    def angular_rate(self, t) -> np.ndarray:
        """Body angular rate omega_b (rad/s), (..., 3)."""
        return self._frame(t)[1]

    def specific_force(self, t) -> np.ndarray:
        """Body specific force C^T (a - g), m/s^2, (..., 3)."""
        C = self.dcm(t)
        return np.einsum("...ji,...j->...i", C, self.acceleration(t) - GRAVITY)

    def quaternion(self, t: float) -> np.ndarray:
        """Attitude quaternion [w, x, y, z] (body to ENU) at one time t."""
        return dcm_to_quat(self.dcm(float(t)))

    def truth(self, t: float) -> UasTruth:
        t = float(t)
        C, omega = self._frame(t)
        a = self.acceleration(t)
        return UasTruth(t, self.position(t), self.velocity(t), a, dcm_to_quat(C), omega, C.T @ (a - GRAVITY))


class SinusoidTrajectory(Trajectory):
    """p(t) = origin + velocity t + sum_k amplitude_k sin(freq_k t + phase_k).

    Sums of sinusoids have exact derivatives of every order, which makes the velocity,
    acceleration, jerk, attitude and body rate analytic. amplitudes (K, 3) m, freqs (K,) rad/s,
    phases (K,) rad, origin and velocity ENU m and m/s."""

    def __init__(self, amplitudes, freqs, phases, origin=(0.0, 0.0, 0.0), velocity=(0.0, 0.0, 0.0),
                 attitude: str = "coordinated"):
        self.amplitudes = np.asarray(amplitudes, float).reshape(-1, 3)
        self.freqs = np.asarray(freqs, float).reshape(-1)
        self.phases = np.asarray(phases, float).reshape(-1)
        if not (len(self.amplitudes) == len(self.freqs) == len(self.phases)):
            raise ValueError("amplitudes, freqs and phases must have the same length")
        self.origin = np.asarray(origin, float).reshape(3)
        self.drift = np.asarray(velocity, float).reshape(3)
        if attitude not in ("coordinated", "level"):
            raise ValueError(f"unknown attitude mode {attitude!r}: 'coordinated' or 'level'")
        self.attitude_mode = attitude

    def derivative(self, t, order: int) -> np.ndarray:
        t = np.asarray(t, float)
        arg = t[..., None] * self.freqs + self.phases + order * (math.pi / 2)
        out = (np.sin(arg) * self.freqs**order) @ self.amplitudes
        if order == 0:
            out = out + self.origin + t[..., None] * self.drift
        elif order == 1:
            out = out + self.drift
        return out


class Hover(Trajectory):
    """Holding position with a fixed yaw, level: zero velocity, zero rate."""

    def __init__(self, position=(0.0, 0.0, 50.0), yaw: float = 0.0):
        self.p = np.asarray(position, float).reshape(3)
        self.C = quat_to_dcm(quat_from_euler(0.0, 0.0, yaw))

    def derivative(self, t, order: int) -> np.ndarray:
        t = np.asarray(t, float)
        base = self.p if order == 0 else np.zeros(3)
        return np.broadcast_to(base, t.shape + (3,)).copy()

    def _frame(self, t):
        t = np.asarray(t, float)
        return np.broadcast_to(self.C, t.shape + (3, 3)).copy(), np.zeros(t.shape + (3,))


def _rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def figure8(center=(0.0, 0.0), altitude: float = 50.0, width: float = 200.0, height: float | None = None,
            period: float = 60.0, phase: float = 0.0, heading: float = 0.0, climb: float = 0.0,
            attitude: str = "coordinated") -> SinusoidTrajectory:
    """Figure-8 at altitude, a lemniscate of Gerono: along its axis (width/2) sin(w t), across
    (height/2) sin(2 w t), w = 2 pi/period; height defaults to width/2. heading (rad) turns the
    axis counter-clockwise from east; climb (m) adds an altitude wave climb sin(w t). The speed
    never drops below about 0.66 w width/2 (where cos^2(wt) = 3/8)."""
    height = width / 2 if height is None else height
    w = 2 * math.pi / period
    R = _rot_z(heading)
    amps = np.array([R @ [width / 2, 0.0, 0.0], R @ [0.0, height / 2, 0.0], [0.0, 0.0, climb]])
    return SinusoidTrajectory(amps, [w, 2 * w, w], [phase, 2 * phase, phase],
                              origin=(center[0], center[1], altitude), attitude=attitude)


def circle(center=(0.0, 0.0), altitude: float = 50.0, radius: float = 50.0, speed: float = 10.0,
           phase: float = 0.0, clockwise: bool = False, attitude: str = "coordinated") -> SinusoidTrajectory:
    """A level circle at altitude, constant speed (m/s); starts at angle `phase` (rad,
    counter-clockwise from east) around the center."""
    w = (-1.0 if clockwise else 1.0) * speed / radius
    amps = np.array([[radius, 0.0, 0.0], [0.0, radius, 0.0]])
    return SinusoidTrajectory(amps, [w, w], [phase + math.pi / 2, phase],
                              origin=(center[0], center[1], altitude), attitude=attitude)


def random_smooth(rng, center=(0.0, 0.0), altitude: float = 50.0, radius: float = 100.0,
                  speed: float = 12.0, n_terms: int = 4, wander: float = 0.4, vertical: float = 0.2,
                  attitude: str = "coordinated") -> SinusoidTrajectory:
    """A smooth random flight that stays near `center`: a loiter circle of `radius` at `speed`
    (random direction and phase) plus n_terms random quasi-periodic sinusoids with frequencies
    0.3 to 3 times the loiter's. Their velocity amplitudes sum to wander * speed, so the speed
    stays in [(1 - wander) speed, (1 + wander) speed] and the attitude is always defined;
    `vertical` scales the vertical part of each wander direction."""
    if not 0.0 <= wander < 1.0:
        raise ValueError("wander must be in [0, 1)")
    rng = _rng(rng)
    w0 = speed / radius * rng.choice([-1.0, 1.0])
    phase0 = rng.uniform(0, 2 * math.pi)
    freqs = abs(w0) * rng.uniform(0.3, 3.0, n_terms)
    dirs = rng.normal(size=(n_terms, 3)) * [1.0, 1.0, vertical]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    weights = rng.uniform(0.2, 1.0, n_terms)
    # Amplitude a_k = s weights_k / freq_k gives velocity amplitudes s weights_k summing to wander speed.
    speeds = wander * speed * weights / weights.sum()
    amps = np.vstack([[[radius, 0.0, 0.0], [0.0, radius, 0.0]], dirs * (speeds / freqs)[:, None]])
    all_freqs = np.concatenate([[w0, w0], freqs])
    phases = np.concatenate([[phase0 + math.pi / 2, phase0], rng.uniform(0, 2 * math.pi, n_terms)])
    return SinusoidTrajectory(amps, all_freqs, phases, origin=(center[0], center[1], altitude), attitude=attitude)


# --------------------------------------------------------------------------- IMU

_GL_NODES = np.array([-math.sqrt(0.6), 0.0, math.sqrt(0.6)])
_GL_WEIGHTS = np.array([5.0, 8.0, 5.0]) / 18.0  # Gauss-Legendre weights / 2: they sum to 1


def mean_imu(trajectory: Trajectory, t0, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free IMU output over [t0, t0 + dt]: the mean body rate and mean body specific force
    (what an integrating IMU's delta-theta/dt and delta-v/dt are), by 3-point Gauss-Legendre
    quadrature, exact for polynomials of degree 5 in t, so its error is O(dt^6) and negligible.
    t0 scalar or array; returns (gyro, accel), each (..., 3)."""
    t0 = np.asarray(t0, float)
    t = t0[..., None] + 0.5 * dt * (1.0 + _GL_NODES)
    gyro = np.einsum("...k,...ki->...i", np.broadcast_to(_GL_WEIGHTS, t.shape), trajectory.angular_rate(t))
    accel = np.einsum("...k,...ki->...i", np.broadcast_to(_GL_WEIGHTS, t.shape), trajectory.specific_force(t))
    return gyro, accel


@dataclass
class ImuRecord:
    """n consecutive IMU intervals: start times (n,), measured gyro and accel (n, 3), and the
    true biases that were in them (n, 3)."""

    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray

    def sample(self, k: int) -> ImuSample:
        return ImuSample(self.gyro[k], self.accel[k])


class ImuSimulator:
    """A strapdown IMU riding a trajectory.

    Each interval k covers [t_k, t_k + dt] and reports

        gyro  = mean omega_b + b_g,k + n_g,   n_g ~ N(0, gyro_arw^2 / dt)
        accel = mean f_b     + b_a,k + n_a,   n_a ~ N(0, accel_vrw^2 / dt)

    (white noise of density N averaged over dt has variance N^2/dt). The biases are held over
    an interval and then step as first-order Gauss-Markov processes, exactly discretised:
    b <- exp(-dt/tau) b + w, var(w) = rw^2 tau/2 (1 - exp(-2 dt/tau)), which is rw^2 dt, the
    random walk of eqs. 5-6, for tau = inf. Initial biases are drawn from the spec's turn-on
    sigmas unless given. The biases in force for the next interval are `gyro_bias` and
    `accel_bias`, the truth for the filter's bias states.
    """

    def __init__(self, trajectory: Trajectory, dt: float, spec: ImuSpec = ImuSpec(), rng=0,
                 t0: float = 0.0, gyro_bias=None, accel_bias=None):
        self.trajectory = trajectory
        self.dt = float(dt)
        self.spec = spec
        self.rng = _rng(rng)
        self.t = float(t0)
        init = self.rng.standard_normal(6)  # drawn even if given, so the noise stream is the same
        self.gyro_bias = init[:3] * spec.gyro_bias_sigma0 if gyro_bias is None else np.asarray(gyro_bias, float).copy()
        self.accel_bias = init[3:] * spec.accel_bias_sigma0 if accel_bias is None else np.asarray(accel_bias, float).copy()

    def _bias_step(self) -> tuple[float, float, float]:
        s, dt = self.spec, self.dt
        if math.isinf(s.bias_tau):
            return 1.0, s.gyro_bias_rw * math.sqrt(dt), s.accel_bias_rw * math.sqrt(dt)
        k = math.sqrt(s.bias_tau / 2 * -math.expm1(-2 * dt / s.bias_tau))
        return math.exp(-dt / s.bias_tau), s.gyro_bias_rw * k, s.accel_bias_rw * k

    def run(self, n: int) -> ImuRecord:
        """The next n intervals; n calls of `step` give the same numbers."""
        t = self.t + self.dt * np.arange(n)
        gyro, accel = mean_imu(self.trajectory, t, self.dt)
        z = self.rng.standard_normal((n, 12))
        decay, sg, sa = self._bias_step()
        bg, ba = np.empty((n, 3)), np.empty((n, 3))
        for k in range(n):
            bg[k], ba[k] = self.gyro_bias, self.accel_bias
            self.gyro_bias = decay * self.gyro_bias + sg * z[k, 6:9]
            self.accel_bias = decay * self.accel_bias + sa * z[k, 9:12]
        root_dt = math.sqrt(self.dt)
        gyro = gyro + bg + z[:, 0:3] * (self.spec.gyro_arw / root_dt)
        accel = accel + ba + z[:, 3:6] * (self.spec.accel_vrw / root_dt)
        self.t = float(self.t + n * self.dt)
        return ImuRecord(t, gyro, accel, bg, ba)

    def step(self) -> ImuSample:
        """The next interval [t, t + dt]; advances t."""
        return self.run(1).sample(0)


# --------------------------------------------------------------------------- GNSS


def geodetic_to_ecef(lat_deg: float, lon_deg: float, height_m: float) -> np.ndarray:
    """WGS 84 geodetic latitude, longitude (deg) and ellipsoidal height (m) to ECEF (m)."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    e2 = WGS84_F * (2 - WGS84_F)
    N = WGS84_A / math.sqrt(1 - e2 * math.sin(lat) ** 2)
    return np.array([(N + height_m) * math.cos(lat) * math.cos(lon),
                     (N + height_m) * math.cos(lat) * math.sin(lon),
                     (N * (1 - e2) + height_m) * math.sin(lat)])


def ecef_to_enu_rotation(lat_deg: float, lon_deg: float) -> np.ndarray:
    """R with v_enu = R v_ecef at the given geodetic latitude and longitude."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    sl, cl, sp, cp = math.sin(lon), math.cos(lon), math.sin(lat), math.cos(lat)
    return np.array([[-sl, cl, 0.0], [-sp * cl, -sp * sl, cp], [cp * cl, cp * sl, sp]])


@dataclass(frozen=True)
class Site:
    """The reference point whose tangent plane is the world's ENU frame (origin at its
    ellipsoid point at height_m). The default is Melbourne, home of two of the paper's
    authors."""

    lat_deg: float = -37.7983
    lon_deg: float = 144.9610
    height_m: float = 30.0

    def ecef(self) -> np.ndarray:
        return geodetic_to_ecef(self.lat_deg, self.lon_deg, self.height_m)

    def enu_rotation(self) -> np.ndarray:
        return ecef_to_enu_rotation(self.lat_deg, self.lon_deg)


class GnssConstellation:
    """A GPS-like Walker-delta constellation on circular orbits, seen from a `Site`.

    n_planes planes at `inclination_deg`, right ascensions of the ascending node 360/n_planes
    apart, sats_per_plane evenly spaced in argument of latitude, plane j shifted by
    j * phasing * 360/n_sats (Walker i: T/P/F). Defaults: 6 x 5 = 30 satellites at 55 deg and
    26 559.7 km, inside the 24-31 GPS has flown; mean motion sqrt(mu/a^3) = 1.4586e-4 rad/s.

    Satellite i at time t (s) in ECI has argument of latitude u_i + n (t + epoch) on its orbit;
    ECEF turns ECI by -OMEGA_EARTH (t + epoch) about z (Greenwich at angle 0 at epoch 0):
    Earth rotation is included, it costs nothing and moves the sky correctly. ENU is
    R_enu (r_ecef - r_site). `epoch` (s) picks the sky geometry at t = 0.

    Not modelled (the receiver's pseudorange noise stands for their residuals): light time and
    the Sagnac term (the satellite is taken at the reception time), satellite clocks,
    ionosphere, troposphere, multipath, eccentric and perturbed orbits.
    """

    def __init__(self, site: Site = Site(), n_planes: int = 6, sats_per_plane: int = 5,
                 inclination_deg: float = 55.0, radius: float = GPS_ORBIT_RADIUS, phasing: int = 1,
                 epoch: float = 0.0):
        self.site = site
        self.radius = float(radius)
        self.inclination = math.radians(inclination_deg)
        self.epoch = float(epoch)
        self.mean_motion = math.sqrt(MU_EARTH / self.radius**3)
        n = n_planes * sats_per_plane
        plane = np.repeat(np.arange(n_planes), sats_per_plane)
        slot = np.tile(np.arange(sats_per_plane), n_planes)
        self.raan = plane * (2 * math.pi / n_planes)
        self.arg_lat0 = slot * (2 * math.pi / sats_per_plane) + plane * phasing * (2 * math.pi / n)
        self.ids = np.arange(n)
        self._site_ecef = site.ecef()
        self._R_enu = site.enu_rotation()

    @property
    def n(self) -> int:
        return len(self.ids)

    def eci(self, t: float) -> np.ndarray:
        """Satellite positions (n, 3) in the Earth-centred inertial frame, m."""
        u = self.arg_lat0 + self.mean_motion * (t + self.epoch)
        cu, su = np.cos(u), np.sin(u)
        cO, sO = np.cos(self.raan), np.sin(self.raan)
        ci, si = math.cos(self.inclination), math.sin(self.inclination)
        return self.radius * np.stack([cu * cO - su * ci * sO, cu * sO + su * ci * cO, su * si], axis=-1)

    def ecef(self, t: float) -> np.ndarray:
        """Satellite positions (n, 3) in ECEF, m."""
        theta = OMEGA_EARTH * (t + self.epoch)
        return self.eci(t) @ _rot_z(-theta).T

    def enu(self, t: float) -> np.ndarray:
        """Satellite positions (n, 3) in the site's ENU frame, m."""
        return (self.ecef(t) - self._site_ecef) @ self._R_enu.T

    def visible(self, t: float, p=(0.0, 0.0, 0.0), mask_deg: float = 10.0):
        """Satellites above the elevation mask seen from ENU point p: (ids, ENU positions (m, 3),
        elevations (m,) rad). Elevation is against the ENU horizontal (flat earth)."""
        s = self.enu(t)
        d = s - np.asarray(p, float)
        el = np.arcsin(d[:, 2] / np.linalg.norm(d, axis=1))
        keep = el >= math.radians(mask_deg)
        return self.ids[keep], s[keep], el[keep]


class ReceiverClock:
    """Receiver clock error in metres: bias b and drift d, the two-state random walk of
    `ClockSpec` (b' = d + w_b, d' = w_d), stepped with its exact discretisation over any gap:
    [b, d] <- [[1, T], [0, 1]] [b, d] + w, cov(w) = [[qb T + qd T^3/3, qd T^2/2], [qd T^2/2, qd T]]."""

    def __init__(self, spec: ClockSpec = ClockSpec(), rng=0, bias: float = 0.0, drift: float = 0.0, t0: float = 0.0):
        self.spec = spec
        self.rng = _rng(rng)
        self.bias, self.drift, self.t = float(bias), float(drift), float(t0)

    def advance(self, t: float) -> float:
        """Move the clock to time t (not before the last one); return the bias (m)."""
        T = float(t) - self.t
        if T < 0:
            raise ValueError(f"clock cannot go back from {self.t} to {t}")
        qb, qd = self.spec.bias_psd, self.spec.drift_psd
        q11, q12, q22 = qb * T + qd * T**3 / 3, qd * T**2 / 2, qd * T
        z = self.rng.standard_normal(2)
        l11 = math.sqrt(q11)
        l21 = q12 / l11 if l11 > 0 else 0.0
        l22 = math.sqrt(max(q22 - l21 * l21, 0.0))
        self.bias += self.drift * T + l11 * z[0]
        self.drift += l21 * z[0] + l22 * z[1]
        self.t = float(t)
        return self.bias


@dataclass
class PseudorangeSet:
    """One epoch of pseudoranges (eq. 14): rho_i = |s_i - p| + clock bias + e_i, all in m, with
    the satellite positions s_i in ENU at the epoch."""

    t: float
    sat_ids: np.ndarray
    sat_positions: np.ndarray
    pseudoranges: np.ndarray
    sigma: float


class GnssReceiver:
    """A UAS's GNSS receiver: its own clock (`ReceiverClock`) and noise stream.

    sigma (m) is the pseudorange noise std: 1 m, a single-frequency code receiver after the
    broadcast corrections; the paper's 2 cm / 5 cm position accuracy implies carrier phase,
    which is out of scope here."""

    def __init__(self, constellation: GnssConstellation, rng=0, sigma: float = 1.0, mask_deg: float = 10.0,
                 clock: ReceiverClock | None = None):
        self.constellation = constellation
        self.rng = _rng(rng)
        self.sigma = float(sigma)
        self.mask_deg = float(mask_deg)
        self.clock = ReceiverClock(rng=self.rng.spawn(1)[0]) if clock is None else clock

    def measure(self, t: float, p) -> PseudorangeSet:
        """Pseudoranges at time t from ENU position p (m) to every satellite above the mask."""
        ids, sats, _ = self.constellation.visible(t, p, self.mask_deg)
        bias = self.clock.advance(t)
        geometric = np.linalg.norm(sats - np.asarray(p, float), axis=1)
        rho = geometric + bias + self.rng.normal(0.0, self.sigma, len(ids))
        return PseudorangeSet(float(t), ids, sats, rho, self.sigma)


# --------------------------------------------------------------------------- relative measurements


def relative_position(p_i, p_j, sigma: float, rng) -> np.ndarray:
    """Measured position of UAS i relative to UAS j, p_i - p_j + N(0, sigma^2 I), ENU m: the
    r_rel^ij of eq. 19, so that x_i = H x_j + r_rel^ij."""
    return np.asarray(p_i, float) - np.asarray(p_j, float) + _rng(rng).normal(0.0, sigma, 3)


def measure_range(p_i, p_j, sigma: float, rng) -> float:
    """Measured inter-UAV range |p_i - p_j| + N(0, sigma^2), m (eq. 15). Not clipped at zero:
    clipping would bias short ranges."""
    return float(np.linalg.norm(np.asarray(p_i, float) - np.asarray(p_j, float)) + _rng(rng).normal(0.0, sigma))


def inter_uav_ranges(positions, sigma: float, rng, max_range: float = math.inf) -> list[tuple[int, int, float]]:
    """Ranges between every pair i < j of the (N, 3) ENU positions whose true distance is at
    most max_range: a list of (i, j, measured range in m). One normal draw per pair within
    range, in (i, j) order."""
    rng = _rng(rng)
    P = np.asarray(positions, float)
    out = []
    for i in range(len(P)):
        for j in range(i + 1, len(P)):
            d = float(np.linalg.norm(P[i] - P[j]))
            if d <= max_range:
                out.append((i, j, d + float(rng.normal(0.0, sigma))))
    return out
