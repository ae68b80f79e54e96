"""What the agent daemon sends its flight controller (FC), driven from the daemon's one loop
(docs/deploy.md#outputs, #setpoints).

- `EstimateStream` (`outputs.mavlink`): the swarm's estimate at the autopilot's rate. The node
  estimates once a tick; an autopilot's EKF wants external vision at 30-50 Hz. Between ticks
  the latest estimate is propagated with the FC's own high-rate samples (the ones the ticks
  are cut from: ODOMETRY for planar models and vehicles, HIGHRES_IMU for uas-ins) through the
  estimator's time update, covariance included, and the propagated state goes out at
  `rate_hz`, stamped with the FC time of the last sample it has absorbed. A new swarm
  estimate restarts the propagation from its own tick's time (re-applying the samples since),
  so what goes out is always "the latest swarm estimate, moved forward by the FC's motion".
  When that restart moves the estimate by more than `reset_gate` standard deviations (of the
  difference: old and new covariances added, as the autopilot's innovation test adds its own
  and the message's) from where propagation had it (a rejoin, a first fix after an outage), the
  message's reset counter changes: the autopilot then resets to it instead of gating it out.
- `SetpointStream` (`outputs.setpoints`, closed-loop vehicles, off unless `enabled`): each
  command of the node becomes the state the command drives the vehicle's model to in one tick,
  sent as SET_POSITION_TARGET_LOCAL_NED (a quadrotor: position, velocity and acceleration with
  yaw; a ground robot: velocity), streamed at `rate_hz`. Estimates older than `stale_after`
  (or a lost FC link) turn it into a hold: the FC's own position at zero velocity (a
  quadrotor), zero velocity (a ground robot).

`FcOutputs` holds both; the daemon calls `estimate`, `command`, `poll` and `wait` and nothing
else (agents/daemon.py, `_fc_*` methods).
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter, deque

import numpy as np

from swarmloc.models import ins
from swarmloc.models.motion import MOTION_MODELS, VEHICLES, Odometry

log = logging.getLogger("swarmloc.agent")

PLANAR_HEIGHT_STD = 100.0
"""m: a planar estimate says nothing about height, so the flight controller gets its own height
back with a std no autopilot fuses."""

SAMPLES_KEPT = 2000
"""FC samples kept to re-propagate a new estimate from its tick's time: seconds of them at any
rate an FC streams, far more than the tick or two an estimate lags the samples."""

# SET_POSITION_TARGET_LOCAL_NED type_mask bits (POSITION_TARGET_TYPEMASK): a set bit ignores the field.
IGNORE_POSITION = 1 | 2 | 4
IGNORE_VELOCITY = 8 | 16 | 32
IGNORE_VZ = 32
IGNORE_ACCEL = 64 | 128 | 256
IGNORE_YAW = 1024
IGNORE_YAW_RATE = 2048
COPTER_TRACK = IGNORE_YAW_RATE  # position, velocity and acceleration feed-forward, yaw: PX4 offboard and ArduPilot guided
COPTER_HOLD = IGNORE_ACCEL | IGNORE_YAW_RATE  # position, zero velocity, yaw
ROVER_VELOCITY = IGNORE_POSITION | IGNORE_VZ | IGNORE_ACCEL | IGNORE_YAW | IGNORE_YAW_RATE  # 3559: ArduPilot Rover's "use velocity"


# --------------------------------------------------------------------------- propagation


class Propagator:
    """The estimator's time update over one FC sample: `advance(mean, cov, dt, row)`.

    A tick-level filter adds its process noise once a tick, Q(tick); propagated over a part dt
    of a tick it adds Q(tick) dt / tick, so the covariance grows linearly in time at the node's
    own rate and a whole tick of samples adds what the node's step adds (the planar models'
    and the vehicles' Q scale with dt^2 per step, which would otherwise shrink with the sample
    rate). The INS is a continuous-time model already: its Q is exact for any dt."""

    def __init__(self, node, source_cfg):
        self.name = node.model.name
        self.position_dim = 2 if self.name in ("planar-speed-heading", "planar-pose") else 3
        self.tick = float(source_cfg.tick)
        self.cfg = source_cfg
        if self.name in VEHICLES:
            from swarmloc.estimators.vehicles.filters import process_noise
            from swarmloc.models.vehicles import MODELS

            self.dyn, self._noise = MODELS[self.name], process_noise
            self.actuator_std = np.asarray(node.actuator_std, float)
            self.u = self.dyn.hover_input()
        elif self.name == "uas-ins":
            from swarmloc.estimators.ekf.local import InsEkf

            self._ins, self.imu = InsEkf, getattr(getattr(node, "filter", None), "imu", ins.ImuSpec())
        else:
            self.model = MOTION_MODELS[self.name]

    def advance(self, mean: np.ndarray, cov: np.ndarray, dt: float, row) -> tuple[np.ndarray, np.ndarray]:
        if dt <= 0.0:
            return mean, cov
        if self.name in VEHICLES:
            x = np.asarray(mean, float)
            x_new, F = self.dyn.transition(x, self.u, dt)
            Q = self._noise(self.dyn, x, dt, self.actuator_std) * (self.tick / dt)
            return x_new, F @ cov @ F.T + Q
        if self.name == "uas-ins":
            from swarmloc.wire.messages import ImuMsg

            f = self._ins(mean, cov, self.imu)
            f.predict(ImuMsg(dt, np.asarray([row[1]], float)))
            return f.vector(), f.P
        speed, c, s, wz = row
        c_ = self.cfg
        u = Odometry(dt, speed, math.atan2(s, c), c_.speed_std, c_.heading_std, wz if math.isfinite(wz) else 0.0,
                     c_.turn_rate_std)
        x, F, Q = self.model.predict(np.asarray(mean, float), u)
        return x, F @ cov @ F.T + Q * (self.tick / dt)

    def position(self, mean, cov) -> tuple[np.ndarray, np.ndarray]:
        n = self.position_dim
        return np.asarray(mean)[:n], np.asarray(cov)[:n, :n]


class EstimateStream:
    """The swarm's estimate to the FC at `rate_hz` (module docstring). `ticks` is the
    FlightControllerTicks source: its FC link, its samples (as a listener) and tick times."""

    def __init__(self, node, ticks, cfg):
        self.ticks, self.cfg = ticks, cfg
        self.prop = Propagator(node, ticks.cfg)
        self.samples: deque = deque(maxlen=SAMPLES_KEPT)  # (FC time, row)
        self.chain: tuple[np.ndarray, np.ndarray, float] | None = None  # mean, cov, FC time
        self.reset_counter = 0
        self.resets = 0
        self.sent = 0
        self.last_sent_t = -math.inf
        self.sent_wall: deque = deque(maxlen=512)
        self.counts: Counter[str] = Counter()
        ticks.listeners.append(self.sample)

    # ---------------------------------------------------------------- inputs

    def sample(self, t: float, row) -> None:
        """An FC sample that drives the model: kept, and the current chain moved up to it."""
        if self.samples and t <= self.samples[-1][0]:
            if t < self.samples[-1][0] - 1.0:  # the FC's clock went back: a reboot
                self.samples.clear()
                self.chain = None
            return
        self.samples.append((t, row))
        if self.chain is not None:
            mean, cov, t0 = self.chain
            self.chain = (*self._advance(mean, cov, t0, t, row), t)

    def _advance(self, mean, cov, t0, t, row):
        try:
            x, P = self.prop.advance(mean, cov, t - t0, row)
        except (ValueError, FloatingPointError, np.linalg.LinAlgError):
            self.counts["propagation-error"] += 1
            return mean, cov
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(P))):
            self.counts["propagation-error"] += 1
            return mean, cov
        return x, 0.5 * (P + P.T)

    def estimate(self, mean: np.ndarray, cov: np.ndarray, t: float) -> None:
        """A new swarm estimate at FC time t: the chain restarts from it, through the samples
        after t; a jump past `reset_gate` from the old chain changes the reset counter."""
        chain = (np.asarray(mean, float), np.asarray(cov, float), float(t))
        for ts, row in self.samples:
            if ts > chain[2]:
                chain = (*self._advance(*chain, ts, row), ts)
        old, self.chain = self.chain, chain
        if old is not None and self._jumped(old, chain):
            self.reset_counter = (self.reset_counter + 1) % 256
            self.resets += 1
            if self.resets <= 10 or self.resets % 100 == 0:
                log.warning("agent output: the swarm's estimate jumped past %g std; reset counter %d (%d resets)",
                            self.cfg.reset_gate, self.reset_counter, self.resets)

    def _jumped(self, old, new) -> bool:
        # As the autopilot's innovation test sees it: its own estimate about where our stream
        # had it (P_old), the new message's variance P_new.
        p_old, P_old = self.prop.position(old[0], old[1])
        p_new, P_new = self.prop.position(new[0], new[1])
        d = p_new - p_old
        try:
            m2 = float(d @ np.linalg.solve(P_old + P_new, d))
        except np.linalg.LinAlgError:
            return True
        return not m2 <= self.cfg.reset_gate**2

    def set_command(self, u) -> None:
        if hasattr(self.prop, "u"):
            self.prop.u = np.asarray(u, float)

    # ---------------------------------------------------------------- output

    def poll(self, now: float) -> None:
        if self.chain is None or self.ticks.fc is None or self.chain[2] <= self.last_sent_t:
            return  # nothing new: the same stamp twice is one sample to an autopilot
        mean, cov, t = self.chain
        if send(self.ticks, self.prop.name, mean, cov, t, self.reset_counter):
            self.last_sent_t = t
            self.sent += 1
            self.sent_wall.append(now)

    def wait(self, now: float) -> float:
        if self.chain is None or self.ticks.fc is None or self.chain[2] <= self.last_sent_t:
            return math.inf  # the next sample wakes the loop (the source's own wait)
        return self.ticks.fc.output_rate.due_in(now)

    def stats(self) -> dict:
        gaps = np.diff(self.sent_wall) if len(self.sent_wall) > 2 else np.zeros(0)
        out = {"sent": self.sent, "reset_counter": self.reset_counter, "resets": self.resets}
        if gaps.size:
            out.update({"rate_hz": float(1.0 / gaps.mean()), "interval_ms_p50": float(np.median(gaps) * 1e3),
                        "interval_ms_p99": float(np.quantile(gaps, 0.99) * 1e3),
                        "jitter_ms": float(gaps.std() * 1e3)})
        return {**out, **({"errors": dict(self.counts)} if self.counts else {})}


def send(ticks, model_name: str, mean: np.ndarray, cov: np.ndarray, t: float, reset_counter: int = 0) -> bool:
    """Offer an estimate to the FC (agents/companion/mavlink.py converts ENU to NED): position with
    its covariance; a planar model's height is the FC's own (PLANAR_HEIGHT_STD), planar-pose adds
    its heading, uas-ins its velocity and yaw, a vehicle its inertial velocity and yaw. True if
    it went out."""
    fc = ticks.fc
    if fc is None:
        return False
    if model_name == "uas-ins":
        yaw = ins.euler_from_quat(ins.quat_from_rotvec(mean[6:9]))[2]
        return fc.send_estimate(t, mean[0:3], cov[0:3, 0:3], mean[3:6], cov[3:6, 3:6], yaw, float(cov[8, 8]),
                                reset_counter=reset_counter)
    if model_name in VEHICLES:
        from swarmloc.models.vehicles import MODELS

        dyn = MODELS[model_name]
        # Inertial velocity r' = f(x)[:3] (the input does not enter it); its covariance through
        # the same map's Jacobian rows, J[:3].
        J = dyn.jacobian(mean)[:3]
        velocity, cov_v = dyn.f(mean)[:3], J @ cov @ J.T
        yaw_var = float(cov[3, 3]) if model_name == "ground-robot" else None  # a quaternion's yaw: not sent
        return fc.send_estimate(t, mean[0:3], cov[0:3, 0:3], velocity, cov_v, dyn.yaw(mean), yaw_var,
                                reset_counter=reset_counter)
    P = np.zeros((3, 3))
    P[:2, :2] = cov[:2, :2]
    P[2, 2] = PLANAR_HEIGHT_STD**2
    position = np.array([mean[0], mean[1], ticks.height])
    if model_name == "planar-pose":
        return fc.send_estimate(t, position, P, yaw=float(mean[2]), yaw_var=float(cov[2, 2]),
                                reset_counter=reset_counter)
    return fc.send_estimate(t, position, P, reset_counter=reset_counter)


# --------------------------------------------------------------------------- setpoints


class SetpointStream:
    """A closed-loop vehicle's commands as setpoints (module docstring)."""

    def __init__(self, node, ticks, cfg):
        from agents.companion.mavlink import OutputRate
        from swarmloc.models.vehicles import MODELS

        self.ticks, self.cfg = ticks, cfg
        self.name = node.model.name
        self.dyn = MODELS[self.name]
        self.tick = float(ticks.cfg.tick)
        self.rate = OutputRate(cfg.rate_hz)
        self.target = None  # (type_mask, position, velocity, accel, yaw, yaw_rate), from the last command
        self.made = -math.inf  # monotonic time of the estimate the target was made from
        self.holding = True
        self.counts: Counter[str] = Counter()

    def command(self, u, mean, now: float) -> None:
        """The node's command from its estimate `mean` (made now): where the model goes under it."""
        try:
            x = self.dyn.step(np.asarray(mean, float), np.asarray(u, float), self.tick)
        except (ValueError, FloatingPointError):
            self.counts["bad-command"] += 1
            return
        velocity = self.dyn.f(x)[:3]  # inertial: r' = R v (quadrotor), Rz(phi) [v, d w] (ground robot)
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(velocity))):
            self.counts["bad-command"] += 1
            return
        if self.name == "quadrotor":
            from swarmloc.models.vehicles import GRAVITY

            R = self.dyn.rotation(x)
            accel = R[:, 2] * (float(u[0]) / self.dyn.params.mass) - np.array([0.0, 0.0, GRAVITY])
            self.target = (COPTER_TRACK, x[:3].copy(), velocity, accel, self.dyn.yaw(x), None)
        else:
            self.target = (ROVER_VELOCITY, None, velocity, None, None, None)
        self.made = now

    def _hold(self):
        if self.name == "quadrotor":
            if self.ticks.position is None:
                return None
            return (COPTER_HOLD, np.asarray(self.ticks.position, float), np.zeros(3), None, self.ticks.yaw or 0.0,
                    None)
        return (ROVER_VELOCITY, None, np.zeros(3), None, None, None)

    def fresh(self, now: float) -> bool:
        """Whether the last command is one to fly: made from an estimate at most stale_after
        old, with the FC's heartbeat there."""
        from agents.companion.mavlink import Link

        fc = self.ticks.fc
        return (self.target is not None and now - self.made <= self.cfg.stale_after and fc is not None
                and fc.state is Link.ALIVE)

    def poll(self, now: float) -> None:
        fc = self.ticks.fc
        if fc is None or not self.rate.ready(now):
            return
        fresh = self.fresh(now)
        if fresh != (not self.holding):
            if fresh:
                log.warning("agent setpoints: tracking the swarm's commands")
            elif self.target is not None:
                log.warning("agent setpoints: no fresh estimate for %g s (or the FC link is lost): holding",
                            self.cfg.stale_after)
            self.holding = not fresh
        target = self.target if fresh else self._hold()
        if target is None:
            self.counts["hold-without-position"] += 1
            return
        mask, p, v, a, yaw, rate = target
        t = self.ticks.last_t
        if fc.send_position_target(t, mask, p, v, a, yaw, rate):
            self.counts["hold" if not fresh else "track"] += 1

    def wait(self, now: float) -> float:
        return self.rate.due_in(now) if self.ticks.fc is not None else math.inf

    def stats(self) -> dict:
        return {"holding": self.holding, **dict(self.counts)}


# --------------------------------------------------------------------------- both


class FcOutputs:
    """The daemon's flight-controller outputs: the estimate stream and, when enabled, setpoints."""

    def __init__(self, node, ticks, estimate_cfg=None, setpoint_cfg=None):
        self.node, self.ticks = node, ticks
        self.estimates = EstimateStream(node, ticks, estimate_cfg) if estimate_cfg is not None else None
        enabled = setpoint_cfg is not None and setpoint_cfg.enabled
        self.setpoints = SetpointStream(node, ticks, setpoint_cfg) if enabled else None
        # Covariance intersection imports scipy on its first fusion (swarmloc.filters.fusion):
        # under load that is a pause of a second in the loop, and an autopilot stops fusing
        # external vision after 0.4 s of silence and leaves offboard after 1 s. Paid here.
        import scipy.optimize  # noqa: F401

    def estimate(self, k: int, mean, cov, from_fc: bool) -> None:
        """The node's estimate of tick k; `from_fc`: its frame came from this FC (else the FC
        time is its latest sample's: a frame from another source is on another clock)."""
        if self.estimates is None:
            return
        # Never later than the latest sample: on the swarm clock a first sample before the epoch
        # starts the node at tick 0, whose end is the epoch, still ahead.
        t = self.ticks.last_t
        if from_fc and self.ticks.base is not None:
            t = min(self.ticks.time_of(k), t)
        self.estimates.estimate(mean, cov, t)

    def command(self, u, mean) -> None:
        self.ticks.u = np.asarray(u, float)  # the next frame's command in force
        if self.estimates is not None:
            self.estimates.set_command(u)
        if self.setpoints is not None:
            self.setpoints.command(u, mean, time.monotonic())

    def poll(self, now: float) -> None:
        for out in (self.estimates, self.setpoints):
            if out is not None:
                out.poll(now)
        if self.setpoints is not None and self.ticks.u is not None and not self.setpoints.fresh(now):
            # The FC holds: the last command is not what the vehicle does any more. Until the
            # next one, frames and propagation carry the model's hover input (no force).
            self.ticks.u = None
            if self.estimates is not None:
                self.estimates.set_command(self.setpoints.dyn.hover_input())

    def wait(self, now: float) -> float:
        return min([math.inf, *(o.wait(now) for o in (self.estimates, self.setpoints) if o is not None)])

    def stats(self) -> dict:
        return {**({"estimates": self.estimates.stats()} if self.estimates is not None else {}),
                **({"setpoints": self.setpoints.stats()} if self.setpoints is not None else {})}
