"""Motion and measurement models.

A model owns its state dimension: nothing else in swarmloc assumes a platform's state is a
2-vector. Later vehicle models (heading, velocity, 3D) register here under their own name.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from swarmloc.models import ins
from swarmloc.models.measurements import StateLayout


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
    turn_rate: float = 0.0  # measured over the step (rad/s): what a model with heading in its state reads
    turn_rate_std: float = 0.0


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

    def error(self, x_true: np.ndarray, x_est: np.ndarray) -> np.ndarray:
        """The estimation error in the coordinates of the estimate's covariance (for NEES)."""
        return np.asarray(x_true, float) - np.asarray(x_est, float)

    @property
    def layout(self):
        """Where measurement models find position (and attitude, clock) in the state."""
        return StateLayout.planar()


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


class PlanarPose(MotionModel):
    """A unicycle: planar position and heading, driven by measured speed and turn rate.

    x_{k+1} = x_k + dt v cos(theta_k), y_{k+1} = y_k + dt v sin(theta_k),
    theta_{k+1} = theta_k + dt w, with Q = G diag(speed_std^2, turn_rate_std^2) G^T,
    G = d f / d(v, w). With the heading in the state, a gyro's drift is a state error that
    persists from step to step, as it does in the world; eq. (1)'s position-only model can only
    treat it as fresh noise each step, and is overconfident when the gyro is poor."""

    name = "planar-pose"
    state_dim = 3
    position_dim = 2
    identity_transition = False

    def predict(self, x, u):
        c, s = np.cos(x[2]), np.sin(x[2])
        x_new = x + np.array([u.dt * u.speed * c, u.dt * u.speed * s, u.dt * u.turn_rate])
        F = np.array([[1.0, 0.0, -u.dt * u.speed * s], [0.0, 1.0, u.dt * u.speed * c], [0.0, 0.0, 1.0]])
        G = np.array([[u.dt * c, 0.0], [u.dt * s, 0.0], [0.0, u.dt]])
        Q = G @ np.diag([u.speed_std**2, u.turn_rate_std**2]) @ G.T
        return x_new, F, Q

    def error(self, x_true, x_est):
        e = np.asarray(x_true, float) - np.asarray(x_est, float)
        e[..., 2] = (e[..., 2] + np.pi) % (2 * np.pi) - np.pi
        return e

    @property
    def layout(self):
        return StateLayout.planar_pose()


class PlanarPoseBias(PlanarPose):
    """A unicycle whose odometry is biased: the planar pose [x, y, heading] augmented with a
    scale factor s on the measured speed and a bias b on the measured turn rate, each a random
    walk. The robot moves at v (1 + s) and turns at w + b:

        x_{k+1} = x_k + dt v (1 + s) cos(theta_k), y likewise with sin,
        theta_{k+1} = theta_k + dt (w + b),  s_{k+1} = s_k + n_s,  b_{k+1} = b_k + n_b,

    with Var(n_s) = speed_scale_walk dt and Var(n_b) = turn_rate_bias_walk dt. A wheel radius
    off by a per cent, or a drive that turns a little on a straight command, is an error that
    lasts for minutes: white noise can only spread it as fresh noise each tick, which makes the
    filter either overconfident over minutes or too timid over seconds (docs/mrclam.md). Not a
    platform model (nothing records its truth): an estimator's augmented state, reported as the
    pose block alone (`reported_dim`)."""

    name = "planar-pose-bias"
    state_dim = 5
    reported_dim = 3
    platform = "planar-pose"  # the model of what the estimates report (platform_model)

    def __init__(self, speed_scale_walk: float, turn_rate_bias_walk: float, speed_scale_std: float,
                 turn_rate_bias_std: float):
        self.walk = np.array([speed_scale_walk, turn_rate_bias_walk], float)
        self.prior_std = np.array([speed_scale_std, turn_rate_bias_std], float)

    @classmethod
    def from_settings(cls, settings) -> "PlanarPoseBias | None":
        """The model an estimator's settings ask for (odometry_bias and its four numbers), or None."""
        if not getattr(settings, "odometry_bias", False):
            return None
        return cls(settings.speed_scale_walk, settings.turn_rate_bias_walk, settings.speed_scale_std,
                   settings.turn_rate_bias_std)

    def args(self) -> list[float]:
        """The constructor's arguments, in order, as plain numbers (what a NodeSpec carries)."""
        return [float(self.walk[0]), float(self.walk[1]), float(self.prior_std[0]), float(self.prior_std[1])]

    def augment(self, x0: np.ndarray, P0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A pose prior with the biases appended: zero, independent of the pose, prior_std each."""
        x = np.concatenate([np.asarray(x0, float)[:3], [0.0, 0.0]])
        P = np.zeros((5, 5))
        P[:3, :3] = np.asarray(P0, float)[:3, :3]
        P[3:, 3:] = np.diag(self.prior_std**2)
        return x, P

    def predict(self, x, u):
        c, s = np.cos(x[2]), np.sin(x[2])
        v, w = u.speed * (1.0 + x[3]), u.turn_rate + x[4]
        x_new = x + np.array([u.dt * v * c, u.dt * v * s, u.dt * w, 0.0, 0.0])
        F = np.eye(5)
        F[0, 2], F[1, 2] = -u.dt * v * s, u.dt * v * c
        F[0, 3], F[1, 3], F[2, 4] = u.dt * u.speed * c, u.dt * u.speed * s, u.dt
        G = np.array([[u.dt * c, 0.0], [u.dt * s, 0.0], [0.0, u.dt], [0.0, 0.0], [0.0, 0.0]])
        Q = G @ np.diag([u.speed_std**2, u.turn_rate_std**2]) @ G.T
        Q[3:, 3:] += np.diag(self.walk * u.dt)
        return x_new, F, Q

    @property
    def layout(self):
        return StateLayout(5, slice(0, 2), slice(2, 3))


def platform_model(model: MotionModel) -> MotionModel:
    """The platform's model behind an estimator's augmented one (what its estimates report and
    the truth is of); the model itself otherwise."""
    platform = getattr(model, "platform", None)
    return MOTION_MODELS[platform] if platform else model


def reported_dim(model: MotionModel) -> int:
    """The leading components of a state an estimate reports (an augmented state's platform part)."""
    return getattr(model, "reported_dim", model.state_dim)


class UasIns(MotionModel):
    """A UAS with a strapdown INS (swarmloc/models/ins.py): the 16-state error model of the EKF-CI paper.

    The state vector an estimate reports (and truth records) is
    [position (3, ENU m), velocity (3, m/s), attitude (3, the rotation vector of the body FLU to
    ENU rotation), gyro bias (3, rad/s), accelerometer bias (3, m/s^2), clock bias (1, m)], and
    its covariance is that of the error state dx of swarmloc/models/ins.py, in the same order: the
    attitude error is a small ENU-frame rotation, not a difference of rotation vectors. `error`
    computes that dx, which is what NEES needs. The filter is driven by IMU samples, not by
    `predict`, and F is not the identity.
    """

    name = "uas-ins"
    state_dim = 16
    position_dim = 3
    identity_transition = False

    @staticmethod
    def pack(state) -> np.ndarray:
        return np.concatenate([state.position, state.velocity, ins.rotvec_from_quat(state.quaternion),
                               state.gyro_bias, state.accel_bias, [state.clock_bias]])

    @staticmethod
    def unpack(x: np.ndarray, clock_drift: float = 0.0):
        x = np.asarray(x, float)
        return ins.InsState(x[0:3], x[3:6], ins.quat_from_rotvec(x[6:9]), x[9:12], x[12:15], float(x[15]), clock_drift)

    def error(self, x_true: np.ndarray, x_est: np.ndarray) -> np.ndarray:
        return ins.state_error(self.unpack(x_true), self.unpack(x_est))

    def predict(self, x, u):
        raise TypeError("uas-ins is propagated by IMU mechanization (swarmloc/models/ins.py), not by odometry")

    @property
    def layout(self):
        return StateLayout.uas16("rotation-vector")


class GroundStation(MotionModel):
    """A fixed radio participant that is not localized (a fusion centre's ground station):
    no state, no sensors; its position (scenario `start`) only matters to the radio."""

    name = "ground-station"
    state_dim = 0
    position_dim = 3
    identity_transition = True

    def predict(self, x, u):
        return x, np.zeros((0, 0)), np.zeros((0, 0))


class Vehicle(MotionModel):
    """A vehicle of Oliveros & Ashrafiuon 2023 driven by its actuator inputs (swarmloc/models/vehicles.py
    holds the dynamics): a quadrotor's 13 states [position, quaternion (scalar first), body velocity,
    body rates] or a ground robot's 7 [position, yaw, surge speed, climb rate, yaw rate]. Its
    filters (swarmloc/estimators/vehicles/filters.py) propagate with the command in force, not with
    odometry."""

    position_dim = 3
    identity_transition = False

    def __init__(self, name: str, state_dim: int):
        self.name, self.state_dim = name, state_dim

    @property
    def dynamics(self):
        from swarmloc.models.vehicles import MODELS

        return MODELS[self.name]

    def predict(self, x, u):
        raise TypeError(f"{self.name} is propagated with its actuator command (swarmloc/models/vehicles.py), not odometry")

    def error(self, x_true, x_est):
        e = np.asarray(x_true, float) - np.asarray(x_est, float)
        if self.name == "ground-robot":
            e[..., 3] = (e[..., 3] + np.pi) % (2 * np.pi) - np.pi
        return e

    @property
    def layout(self):
        return StateLayout(self.state_dim, slice(0, 3))


QUADROTOR = Vehicle("quadrotor", 13)
GROUND_ROBOT = Vehicle("ground-robot", 7)
VEHICLES = (QUADROTOR.name, GROUND_ROBOT.name)

MOTION_MODELS: dict[str, MotionModel] = {m.name: m for m in (PlanarSpeedHeading(), PlanarPose(), UasIns(), GroundStation(),
                                                             QUADROTOR, GROUND_ROBOT)}


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
