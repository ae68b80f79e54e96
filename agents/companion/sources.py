"""Sensor sources the agent daemon polls from its loop (docs/deploy.md#sensor-sources).

Each turns something outside swarmloc into the node's input: one `Sensors` frame per estimator
tick, stamped with the sensor's own time. A zenoh source needs no code here (ready frames
arrive on a key the daemon subscribes to); the two below are polled. `ready(now)` returns the
frames completed since the last call and never blocks; `wait(now)` says how long the loop may
sleep before calling again. Both run in the daemon's one thread: pymavlink's parser and the
node have a single owner.
"""

from __future__ import annotations

import functools
import logging
import math
import time
from collections import Counter, deque
from pathlib import Path

import numpy as np

from swarmloc.models import ins
from swarmloc.wire.messages import AlignMsg, GnssMsg, ImuMsg, OdometryMsg, Sensors, VehicleMsg

log = logging.getLogger("swarmloc.agent")

REOPEN_PERIOD = 2.0
"""s between two attempts to open a flight controller that could not be opened (a serial device
not plugged in yet, a TCP server not listening)."""

POLL_PERIOD = 0.02
"""s between two polls of a flight controller: a serial port's buffer holds ~45 ms at 921600 baud."""

# Tick 0 of a UAS: the alignment the FC's own estimate gives (EkfNode replaces its placeholder
# prior with it). Attitude and velocity from an FC's EKF are far better than these; bounding
# them this loosely keeps the first GNSS fixes in charge.
ALIGN_VELOCITY_STD = 0.5  # m/s
ALIGN_ATTITUDE_STD = 0.05  # rad


OFFSET_WINDOW = 10.0
"""s of samples over which a flight controller's clock offset is the smallest (arrival - stamp):
long enough to catch a sample that arrived at once, short enough to follow the FC crystal's
drift (tens of ppm: a millisecond in 30 s)."""


def monotonic_of(unix: float) -> float:
    """A UNIX time (the system clock, NTP- or GPS-disciplined) on the loop's monotonic clock."""
    return unix - time.time() + time.monotonic()


class ClockOffset:
    """Offset of a flight controller's clock to the system clock: the smallest `arrival - stamp`
    over the last OFFSET_WINDOW seconds (the sample that waited least in the link and in our
    polling tells the offset best). A monotonic deque keeps the minimum in O(1) per sample."""

    def __init__(self):
        self.window: deque[tuple[float, float]] = deque()  # (arrival, arrival - stamp), values rising

    def add(self, arrival: float, stamp: float) -> float:
        v = arrival - stamp
        while self.window and self.window[-1][1] >= v:
            self.window.pop()
        self.window.append((arrival, v))
        while self.window[0][0] < arrival - OFFSET_WINDOW:
            self.window.popleft()
        return self.window[0][1]

    def reset(self) -> None:
        self.window.clear()


class FilePlayer:
    """Agent `aid`'s frames of a run directory's sensors.npz, in order, each when its `t` is
    due (`speed` recorded seconds per wall second from the first call, or from the swarm clock's
    `epoch`), or one per call with speed None (as fast as the loop takes them). Then nothing,
    said once.

    With an epoch every agent of the swarm plays its part of the recording on the same
    schedule, however late it started: frames already more than a tick overdue when the
    player starts (a restart mid-replay) are skipped and counted, and the node inflates its
    covariance over them as over any missed tick."""

    def __init__(self, path: Path, aid: int, speed: float | None, epoch: float | None = None):
        from swarmloc.experiment.results import frames_from_arrays  # scipy: only an agent that replays pays for it

        with np.load(path, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
        if aid not in arrays["ids"].tolist():
            raise ValueError(f"{path} holds agents {arrays['ids'].tolist()}, not {aid}")
        self.path, self.aid, self.speed = path, aid, speed
        self.frames = [frames[aid] for frames in frames_from_arrays(arrays)]
        self.next = 0
        self.skipped = 0
        self.start: float | None = None  # monotonic time of the first frame
        if epoch is not None and speed is not None:
            self.start = monotonic_of(epoch)

    @property
    def name(self) -> str:
        return f"file {self.path}"

    def _due(self, i: int) -> float:
        return self.start + (self.frames[i].t - self.frames[0].t) / self.speed

    def ready(self, now: float) -> list[Sensors]:
        if self.next >= len(self.frames):
            return []
        if self.start is None:
            self.start = now
        if self.next == 0 and self.speed is not None and len(self.frames) > 1:
            tick = (self.frames[1].t - self.frames[0].t) / self.speed
            while self.next < len(self.frames) - 1 and self._due(self.next) < now - tick:
                self.next += 1
            if self.next:
                self.skipped = self.next
                log.warning("agent %s: %s: started %.1f s after the swarm clock's epoch; skipping %d overdue frames",
                            self.aid, self.path, now - self.start, self.next)
        if self.speed is None:
            stop = self.next + 1
        else:
            stop = self.next
            while stop < len(self.frames) and self._due(stop) <= now:
                stop += 1
        out, self.next = self.frames[self.next:stop], stop
        if out and self.next == len(self.frames):
            log.warning("agent %s: %s replayed (%d frames, tick %d); no more sensor frames from it, the agent "
                        "keeps running", self.aid, self.path, len(self.frames), self.frames[-1].k)
        return out

    def wait(self, now: float) -> float:
        if self.next >= len(self.frames):
            return math.inf
        if self.speed is None or self.start is None:
            return 0.0
        return max(0.0, self._due(self.next) - now)

    def stats(self) -> dict:
        return {"frames": self.next, "of": len(self.frames), "skipped": self.skipped}

    def close(self) -> None:
        pass


class FlightControllerTicks:
    """A flight controller's samples (agents.companion.mavlink.FlightController) cut into ticks.

    The ticks are the FC's clock: tick 0 is the first sample that drives the model (ODOMETRY or
    LOCAL_POSITION_NED for a planar model, HIGHRES_IMU for uas-ins) at t0, tick k ends at
    t0 + k * tick, and a driving sample belongs to the tick it falls in. Tick k's frame goes
    out, stamped t0 + k * tick, when the first sample of a later tick shows that it is
    complete; a tick without driving samples (the FC fell silent) has no frame, and the node
    inflates its covariance over it. ATTITUDE and GNSS fixes are kept as they come: the latest
    attitude serves the samples after it, the latest good fix rides in the next frame.

    The planar frame's odometry is the mean over the tick's samples: speed along the heading
    (sideways motion is not in the model), the heading (ENU yaw, a circular mean) and the ENU
    yaw rate as turn rate, with the configured stds. Tick 0 has dt = 0: no motion, as in a run.
    A uas-ins frame carries the tick's HIGHRES_IMU rows, dt their mean spacing; its tick 0
    carries the alignment from the FC's attitude, velocity and fix (or the prior's position).
    A vehicle's frame (quadrotor, ground robot) carries `VehicleMsg`: dt the tick (0 at tick 0),
    the command in force `u` (the daemon's last, agents/companion/output.py; hover until one
    comes), the FC's latest attitude (a quaternion FLU -> ENU, or the ENU yaw) with
    `attitude_std`; its `t` is the swarm's time k * tick, which its controller's reference runs
    on (every vehicle alike), not the FC's.

    With the swarm clock's `epoch` (a UNIX time) ticks are the swarm's instead: tick k ends at
    epoch + k * tick on the system clock, which is the FC's clock plus an offset (ClockOffset,
    followed as it drifts). The first frame is then the swarm tick the first driving sample
    falls in, `start`, with tick 0's content: the node starts there from its prior.
    """

    def __init__(self, open_fc, model: str, cfg, prior: tuple[np.ndarray, np.ndarray], aid: int,
                 epoch: float | None = None):
        # open_fc() -> agents.companion.mavlink.FlightController; until it succeeds the FC counts as lost.
        self.open_fc, self.fc, self.url = open_fc, None, cfg.url
        self.model, self.cfg, self.prior, self.aid = model, cfg, prior, aid
        self._next_open = -math.inf
        self._open_failures = 0
        self.epoch = epoch
        self.offset = ClockOffset()
        self.start: int | None = None  # the first frame's tick
        self.tick = cfg.tick
        from swarmloc.models.motion import VEHICLES

        self.vehicle = model in VEHICLES
        self.planar = model != "uas-ins" and not self.vehicle
        self.u = None  # vehicles: the command in force (set by the daemon's output); None: hover
        self.position = None  # latest FC position (ENU), for a hold
        self.yaw = None  # latest FC yaw (ENU)
        # Called with (t, row) for every sample that drives the model, after it is cut into its
        # tick: the output propagates the swarm's estimate with them between ticks.
        self.listeners: list = []
        self.base: float | None = None  # FC time of tick 0's end: tick k ends at base + k * tick
        self.k = 0  # the tick being gathered
        self.last_t = 0.0  # FC time of the latest driving sample
        self.rows: list = []  # the tick's driving samples, as the model reads them
        self.fix = None  # latest good fix not yet sent
        self.attitude = None  # latest Attitude
        self.velocity = np.zeros(3)  # latest finite FC velocity (ENU), for the alignment
        self.height = 0.0  # latest FC height (ENU up), sent back with a planar estimate
        self.imu_t = None  # FC time of the last IMU row already in a frame
        self.counts: Counter[str] = Counter()
        self._next_poll = -math.inf
        self._was = None  # the FC's link state at the last poll

    @property
    def name(self) -> str:
        return f"mavlink {self.url}"

    def _open(self, now: float) -> bool:
        """Open the FC link if it is not open; retried every REOPEN_PERIOD, said once."""
        if self.fc is not None:
            return True
        if now < self._next_open:
            return False
        self._next_open = now + REOPEN_PERIOD
        try:
            self.fc = self.open_fc()
        except Exception as exc:  # pymavlink raises what the OS says (serial, TCP), untyped
            self._open_failures += 1
            if self._open_failures == 1:
                log.warning("agent %s: cannot open the flight controller at %s: %s; retrying every %g s, the agent "
                            "runs on the radio meanwhile", self.aid, self.url, exc, REOPEN_PERIOD)
            return False
        if self._open_failures:
            log.warning("agent %s: the flight controller at %s is open after %d failed attempts; sensor frames "
                        "follow its heartbeat", self.aid, self.url, self._open_failures)
        return True

    def time_of(self, k: int) -> float:
        return self.base + k * self.tick

    # ---------------------------------------------------------------- polling

    def ready(self, now: float) -> list[Sensors]:
        if now < self._next_poll or not self._open(now):
            return []
        self._next_poll = now + POLL_PERIOD
        from agents.companion.mavlink import Attitude, GnssFix, Imu, Link, Odometry

        out = []
        arrival = time.time()
        for s in self.fc.poll():
            if isinstance(s, Attitude):
                self.attitude = s
            elif isinstance(s, GnssFix):
                if s.position is not None and math.isfinite(s.h_acc) and s.h_acc > 0:
                    self.fix = s
                else:
                    self.counts["fix-unusable"] += 1
            elif isinstance(s, Odometry):
                if np.all(np.isfinite(s.velocity)):
                    self.velocity = s.velocity
                self.height = float(s.position[2])
                self.position = s.position
                q = s.q if s.q is not None else (self.attitude.q if self.attitude is not None else None)
                if q is not None:
                    self.yaw = ins.euler_from_quat(q)[2]
                if self.planar:
                    out += self._driving(s.t, self._planar_row(s), arrival)
                elif self.vehicle:
                    out += self._driving(s.t, self._vehicle_row(q), arrival)
            elif isinstance(s, Imu) and not self.planar and not self.vehicle:
                out += self._driving(s.t, (s.t, [*s.rate, *s.specific_force]), arrival)
        state = self.fc.state
        if state is Link.LOST and self.fc.dropped["link-error"]:
            # Lost with read errors: the device or the TCP peer is gone (a serial adapter
            # unplugged). This connection will not come back by itself: open a new one.
            log.warning("agent %s: the flight controller's link at %s fails to read; reopening it", self.aid, self.url)
            self.fc.close()
            self.fc, self._open_failures = None, 0
            self._next_open = now + REOPEN_PERIOD
        elif state is Link.ALIVE and self._was is Link.LOST:
            # The FC logs the loss at WARNING and the return at INFO: the return is as much news.
            log.warning("agent %s: the flight controller at %s is back; sensor frames resume", self.aid, self.fc.url)
        self._was = state
        return out

    def wait(self, now: float) -> float:
        return max(0.0, (self._next_poll if self.fc is not None else self._next_open) - now)

    def stats(self) -> dict:
        if self.fc is None:
            return {"tick": self.k, "link": "unopened", "open_failures": self._open_failures}
        clock = {} if self.epoch is None or not self.offset.window else {"clock_offset_s": self.offset.window[0][1]}
        return {"tick": self.k, "link": self.fc.state.value, **clock, "received": dict(self.fc.received),
                "dropped": dict(self.fc.dropped), "unused": dict(self.counts)}

    def close(self) -> None:
        if self.fc is not None:
            self.fc.close()

    # ---------------------------------------------------------------- ticks

    def _planar_row(self, s):
        """(speed along the heading, cos, sin of the heading, ENU yaw rate), or None."""
        q = s.q if s.q is not None else (self.attitude.q if self.attitude is not None else None)
        if q is None or not np.all(np.isfinite(s.velocity)):
            self.counts["no-attitude" if q is None else "no-velocity"] += 1
            return None
        yaw = ins.euler_from_quat(q)[2]
        c, sn = math.cos(yaw), math.sin(yaw)
        rate = s.rate if s.rate is not None else (self.attitude.rate if self.attitude is not None else None)
        wz = float((ins.quat_to_dcm(q) @ rate)[2]) if rate is not None else math.nan
        return (float(s.velocity[0] * c + s.velocity[1] * sn), c, sn, wz)

    def _vehicle_row(self, q):
        """A vehicle's orientation as its filter reads it: the quaternion FLU -> ENU (scalar
        first, as swarmloc/models/vehicles.py's), or a ground robot's ENU yaw; None without one."""
        if q is None:
            self.counts["no-attitude"] += 1
            return None
        if self.model == "quadrotor":
            return np.asarray(q, float).copy()
        return np.array([ins.euler_from_quat(q)[2]])

    def _command(self) -> np.ndarray:
        from swarmloc.models.vehicles import MODELS

        return MODELS[self.model].hover_input() if self.u is None else np.asarray(self.u, float).copy()

    def _driving(self, t: float, row, arrival: float) -> list[Sensors]:
        if row is None:
            return []
        out = self._cut(t, row, arrival)
        if self.start is not None:
            for listener in self.listeners:
                listener(t, row)
        return out

    def _cut(self, t: float, row, arrival: float) -> list[Sensors]:
        rebooted = self.base is not None and t < self.last_t - self.tick
        if rebooted:
            self.offset.reset()  # the old clock's offsets say nothing of the new one
        if self.epoch is not None:
            # FC time of the swarm's tick 0: re-anchored at every sample, so the FC's drift
            # against the system clock never piles up into a tick.
            self.base = self.epoch - self.offset.add(arrival, t)
        if self.start is None:
            if not self.planar and not self.vehicle and self.attitude is None:
                return []  # tick 0 of a UAS is its alignment, which needs the FC's attitude
            if self.base is None:
                self.base = t
            first = math.ceil((t - self.base) / self.tick - 1e-9)
            if first < 0:
                # Before the swarm clock's tick 0 (an FC up before the epoch): no tick yet. A
                # frame now would start the node early and stamp its first estimate ahead.
                self.counts["before-epoch"] += 1
                return []
            self.start = first
            self.last_t, self.imu_t = t, t
            self.k = self.start + 1
            return [self._tick0(row)]
        if rebooted:
            # The FC's clock restarts at 0: ticks go on from here, on the new clock.
            log.warning("agent %s: the flight controller's clock went back from %.3f s to %.3f s; ticks continue "
                        "from %d", self.aid, self.last_t, t, self.k)
            if self.epoch is None:
                self.base = t - (self.k - 0.5) * self.tick
            self.imu_t, self.last_t = None, t
        self.last_t = max(self.last_t, t)
        k = max(self.k, math.ceil((t - self.base) / self.tick - 1e-9))
        out = []
        if k > self.k:
            if self.rows:
                out.append(self._frame())
            self.k, self.rows = k, []
        self.rows.append(row)
        return out

    def _gnss(self) -> GnssMsg | None:
        fix, self.fix = self.fix, None
        if fix is None:
            return None
        if self.planar:
            return GnssMsg(fix.position[:2].copy(), fix.h_acc)
        return GnssMsg(fix.position.copy(), fix.h_acc, fix.v_acc if math.isfinite(fix.v_acc) else None)

    def _frame(self) -> Sensors:
        k, t = self.k, self.time_of(self.k)
        if self.vehicle:
            msg = VehicleMsg(self.tick, self._command(), self.rows[-1], self.cfg.attitude_std)
            return Sensors(k, k * self.tick, None, [], self._gnss(), vehicle=msg)
        if self.planar:
            a = np.array(self.rows)
            wz = a[:, 3][np.isfinite(a[:, 3])]
            c = self.cfg
            odo = OdometryMsg(self.tick, float(a[:, 0].mean()), math.atan2(a[:, 2].mean(), a[:, 1].mean()),
                              c.speed_std, c.heading_std, float(wz.mean()) if wz.size else 0.0, c.turn_rate_std)
            return Sensors(k, t, odo, [], self._gnss())
        times = [r[0] for r in self.rows]
        start = self.imu_t if self.imu_t is not None and self.imu_t < times[0] else times[0] - self.tick / len(times)
        self.imu_t = times[-1]
        imu = ImuMsg((times[-1] - start) / len(times), np.array([r[1] for r in self.rows]))
        return Sensors(k, t, None, [], self._gnss(), imu)

    def _tick0(self, row) -> Sensors:
        k = self.start
        t = self.time_of(k)
        if self.vehicle:
            msg = VehicleMsg(0.0, self._command(), row, self.cfg.attitude_std)
            return Sensors(k, k * self.tick, None, [], self._gnss(), vehicle=msg)
        if self.planar:
            c = self.cfg
            _, cos, sin, wz = row
            odo = OdometryMsg(0.0, 0.0, math.atan2(sin, cos), c.speed_std, c.heading_std, 0.0, c.turn_rate_std)
            return Sensors(k, t, odo, [], self._gnss())
        x, P = self.prior[0].copy(), self.prior[1].copy()
        if self.fix is not None:
            x[0:3] = self.fix.position
            v = self.fix.v_acc if math.isfinite(self.fix.v_acc) else self.fix.h_acc
            P[0:3, 0:3] = np.diag([self.fix.h_acc**2, self.fix.h_acc**2, v**2])
        x[3:6] = self.velocity
        x[6:9] = ins.rotvec_from_quat(self.attitude.q)
        for sl, std in ((slice(3, 6), ALIGN_VELOCITY_STD), (slice(6, 9), ALIGN_ATTITUDE_STD)):
            P[sl, :] = 0.0
            P[:, sl] = 0.0
            P[sl, sl] = np.eye(3) * std**2
        return Sensors(k, t, None, [], self._gnss(), align=AlignMsg(x, P))


ROS2_SILENCE = 2.0
"""s without an odometry message after which a ROS 2 odometry topic counts as lost."""


class Ros2Odometry:
    """nav_msgs/msg/Odometry from a ROS 2 topic (rmw_zenoh's key, any type hash), as the samples a
    flight controller gives (agents.companion.mavlink.Odometry), so FlightControllerTicks cuts
    them into ticks exactly as it does a flight controller's ODOMETRY: ROS's pose is the body
    (child frame, x forward, z up) in an ENU world frame and its twist is in the body, which is
    the FC adapter's FLU and ENU. The subscriber only appends the payload; `poll` decodes in
    the daemon's loop, counting what it cannot use."""

    def __init__(self, session, key: str, distro: str):
        self.url, self.distro = key, distro
        self.received: Counter[str] = Counter()
        self.dropped: Counter[str] = Counter()
        self._inbox: deque = deque(maxlen=4096)  # a burst beyond it drops the oldest, counted below
        self._heard = -math.inf
        self._sub = session.declare_subscriber(key, self._put)

    def _put(self, sample) -> None:
        from swarmloc import wire

        if len(self._inbox) == self._inbox.maxlen:
            self.dropped["inbox-full"] += 1
        self._inbox.append(wire.bounded(sample.payload))

    @property
    def state(self):
        from agents.companion.mavlink import Link

        if self._heard == -math.inf:
            return Link.WAITING
        return Link.ALIVE if time.monotonic() - self._heard < ROS2_SILENCE else Link.LOST

    def poll(self) -> list:
        from agents.companion.mavlink import Odometry
        from swarmloc.wire import ros2

        out = []
        while self._inbox:
            data = self._inbox.popleft()
            if data is None:
                self.dropped["oversize"] += 1
                continue
            try:
                s = ros2.decode_odometry(data, self.distro)
            except ros2.Ros2Error:
                self.dropped["bad-data"] += 1
                continue
            self.received["ODOMETRY"] += 1
            self._heard = time.monotonic()
            C = ins.quat_to_dcm(s.q)
            out.append(Odometry(s.t, s.position, C @ s.linear, s.q, s.angular, "ROS2"))
        return out

    def close(self) -> None:
        self._sub.undeclare()


def build(node, specs, output=None, epoch: float | None = None, session=None, ros2=None) -> list:
    """The polled sources of the configuration's `sensors` entries (mavlink, file, ros2), in order;
    `output`: the configuration's outputs.mavlink, which the flight controller's link carries;
    `epoch`: the swarm clock's (UNIX time of tick 0), or None; `session` and `ros2` (a
    swarmloc.wire.ros2.Topics): the Zenoh session and ROS 2 domain a ros2 source listens in."""
    out = []
    for spec in specs:
        if spec.kind == "ros2":
            from swarmloc.wire.ros2 import odometry_key

            link = Ros2Odometry(session, odometry_key(ros2, spec.topic), ros2.distro)
            e = node.estimate()
            out.append(FlightControllerTicks(lambda link=link: link, node.model.name, spec, (e.mean, e.cov), node.id,
                                             epoch))
            out[-1]._open(-math.inf)
            continue
        if spec.kind == "file":
            out.append(FilePlayer(spec.path, node.id, None if spec.speed == "as_fast_as_possible" else spec.speed,
                                  epoch))
        elif spec.kind == "mavlink":
            from agents.companion.mavlink import FlightController, mavlink

            e = node.estimate()
            opener = functools.partial(FlightController, spec.url, baud=spec.baud or 921600,
                                       origin=tuple(spec.origin) if spec.origin else None, **_output_args(output, mavlink))
            ticks = FlightControllerTicks(opener, node.model.name, spec, (e.mean, e.cov), node.id, epoch)
            ticks._open(-math.inf)  # at once: a link that opens is polled from the first turn
            out.append(ticks)
    return out


def _output_args(output, mavlink) -> dict:
    if output is None:
        return {}
    frame = mavlink.MAV_FRAME_LOCAL_FRD if output.frame == "local_frd" else mavlink.MAV_FRAME_LOCAL_NED
    return {"output": output.message, "output_hz": output.rate_hz, "frame_id": frame}
