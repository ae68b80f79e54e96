"""A simulated flight controller on 127.0.0.1 for the MAVLink adapter's tests.

It flies a known circle and streams what PX4 streams to a companion: HEARTBEAT at 1 Hz,
ODOMETRY (or LOCAL_POSITION_NED), ATTITUDE and HIGHRES_IMU at 50 Hz, GPS_RAW_INT at 5 Hz, and
records every message it receives. Its conversions to NED, FRD and WGS 84 are written
independently of agents.companion.mavlink (pymavlink's quaternion, a flat-earth offset), so a test that
compares the adapter's output with `truth` checks the adapter's conversions, not a copy of them.
"""

from __future__ import annotations

import math
import os
import threading
import time

import numpy as np

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402
from pymavlink.quaternion import QuaternionBase  # noqa: E402

mavutil.set_dialect("common")
mavlink = mavutil.mavlink

G = 9.80665
ORIGIN = (47.397742, 8.545594, 488.0)  # PX4 SITL's home, Zurich: lat, lon (deg), alt MSL (m)



def metres_per_radian(lat0: float) -> tuple[float, float]:
    """North and east metres per radian of latitude and longitude at lat0: a flat earth with
    WGS 84's radii of curvature, off by well under a millimetre at 20 m."""
    e2 = (1 / 298.257223563) * (2 - 1 / 298.257223563)
    s2 = math.sin(math.radians(lat0)) ** 2
    return (6378137.0 * (1 - e2) / (1 - e2 * s2) ** 1.5,
            6378137.0 / math.sqrt(1 - e2 * s2) * math.cos(math.radians(lat0)))


class Circle:
    """Counter-clockwise (seen from above) at constant height and speed, nose along the track,
    banked for the turn: the truth in swarmloc's ENU/FLU."""

    def __init__(self, radius=20.0, speed=5.0, height=10.0):
        self.radius, self.speed, self.height = radius, speed, height
        self.omega = speed / radius
        self.bank = -math.atan(speed**2 / (radius * G))  # left wing down: negative roll

    def truth(self, t: float) -> dict:
        a = self.omega * t
        yaw = a + math.pi / 2  # ENU, counter-clockwise from east
        p = np.array([self.radius * math.cos(a), self.radius * math.sin(a), self.height])
        v = self.speed * np.array([-math.sin(a), math.cos(a), 0.0])
        acc = -self.omega**2 * (p - [0.0, 0.0, self.height])
        return {"t": t, "position": p, "velocity": v, "yaw": yaw, "roll": self.bank, "pitch": 0.0,
                "accel": acc}


class FakeFlightController:
    """Streams to the adapter at `port` (udpout, as mavlink-router does) from its own thread."""

    def __init__(self, port: int, circle: Circle | None = None, odometry: bool = True,
                 rate_hz: float = 50.0, system: int = 1):
        self.circle = circle or Circle()
        self.odometry, self.period = odometry, 1.0 / rate_hz
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=system,
                                               source_component=mavlink.MAV_COMP_ID_AUTOPILOT1,
                                               dialect="common")
        self.received: list = []
        self.boot = time.monotonic()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.conn.close()

    def truth(self, t: float) -> dict:
        return self.circle.truth(t)

    def _run(self):
        k = 0
        while not self._stop.is_set():
            t = k * self.period
            delay = self.boot + t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            if k % round(1.0 / self.period) == 0:
                self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                                             mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 0,
                                             mavlink.MAV_STATE_ACTIVE)
            self._stream(self.truth(t), gps=k % round(0.2 / self.period) == 0)
            while (m := self.conn.recv_match(blocking=False)) is not None:
                if m.get_type() != "BAD_DATA":
                    self.received.append(m)
            k += 1

    def _stream(self, x: dict, gps: bool):
        mav, t = self.conn.mav, x["t"]
        e, n, u = x["position"]
        ve, vn, vu = x["velocity"]
        roll, pitch, yaw_ned = x["roll"], x["pitch"], math.pi / 2 - x["yaw"]
        q = QuaternionBase([roll, pitch, yaw_ned])  # FRD -> NED, aerospace 3-2-1
        R = np.array(q.dcm)  # FRD -> NED
        omega_ned = np.array([0.0, 0.0, -self.circle.omega])  # counter-clockwise from above: about -down
        w_frd = R.T @ omega_ned
        v_frd = R.T @ np.array([vn, ve, -vu])
        a_ned = np.array([x["accel"][1], x["accel"][0], -x["accel"][2]])
        f_frd = R.T @ (a_ned - [0.0, 0.0, G])  # an accelerometer reads specific force
        us, ms = int(t * 1e6), int(t * 1e3)
        if self.odometry:  # as PX4: pose in LOCAL_NED, velocity in BODY_FRD
            nan21 = [math.nan] * 21
            mav.odometry_send(us, mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_BODY_FRD, n, e, -u,
                              list(q.q), *v_frd, *w_frd, nan21, nan21,
                              estimator_type=mavlink.MAV_ESTIMATOR_TYPE_AUTOPILOT)
        else:
            mav.local_position_ned_send(ms, n, e, -u, vn, ve, -vu)
        mav.attitude_send(ms, roll, pitch, yaw_ned, *w_frd)
        mav.highres_imu_send(us, *f_frd, *w_frd, 0, 0, 0, 1013.0, 0, 0, 20.0, 0x3F)
        if gps:
            lat0, lon0, alt0 = ORIGIN
            r_north, r_east = metres_per_radian(lat0)
            lat = lat0 + math.degrees(n / r_north)
            lon = lon0 + math.degrees(e / r_east)
            mav.gps_raw_int_send(us, mavlink.GPS_FIX_TYPE_3D_FIX, round(lat * 1e7), round(lon * 1e7),
                                 round((alt0 + u) * 1e3), 80, 120, round(5.0 * 100), 0, 12,
                                 h_acc=1500, v_acc=2500)


# --------------------------------------------------------------------------- an autopilot's interface
#
# `SimulatedAutopilot` is the simulated FC grown into one that behaves, at its MAVLink
# interface, like an autopilot: its estimator consumes the companion's external odometry and
# says whether it would fuse each message (`Ekf2ExternalVision`, PX4 EKF2's rules), and it flies
# the companion's setpoints in offboard mode through a simple vehicle model, its position
# controller closing the loop on its own estimate. Written from PX4's documentation and source
# (named in each class), not from agents/companion: a test comparing the two checks the
# companion against the autopilot's rules, not against a copy of its own.

EV_MAX_INTERVAL = 0.2
"""s: PX4 EKF2's EV_MAX_INTERVAL (ekf2/EKF/common.h): external vision starts only while samples
come at most this far apart, and fusion stops after twice this without one
(aid_sources/external_vision/ev_control.cpp)."""

COM_OF_LOSS_T = 1.0
"""s: PX4's default offboard-loss timeout: setpoints absent this long make the vehicle fail safe."""


class Ekf2ExternalVision:
    """PX4 EKF2's handling of external vision position, message by message.

    - Routing and frames (mavlink_receiver, EKF2.cpp UpdateExtVisionSample): ODOMETRY with
      frame_id LOCAL_NED or LOCAL_FRD and estimator_type VISION or VIO, or VISION_POSITION_ESTIMATE;
      the position must be finite.
    - Time: PX4 maps a companion's stamp to its own clock only through a converged TIMESYNC,
      and otherwise takes the arrival time (Timesync::sync_stamp); we answer no TIMESYNC, so the
      sample's time is arrival - EKF2_EV_DELAY - half the filter period (setExtVisionData). A
      sample closer than the filter period to the last one is dropped ("EV data too fast"); one
      whose true age (arrival - the stamp, both our clock here) exceeds EKF2_DELAY_MAX, the
      fusion horizon, is fused at the wrong time: counted `beyond-horizon`, not fused.
    - Covariance (EKF2_EV_NOISE_MD 0): each axis's variance is the message's if finite, at least
      EKF2_EVP_NOISE^2; the parameter's when the message has none.
    - Starting (ev_control.cpp): the interval to the previous sample below EV_MAX_INTERVAL; at
      the start the position resets to the vision one. A changed reset_counter resets it again.
    - Fusing: innovation against the estimate at the sample's time; rejected when
      innov^2 / (gate^2 (P + R)) > 1 on a horizontal axis (EKF2_EVP_GATE, 5 SD).
    - Stopping: no sample for 2 EV_MAX_INTERVAL ("vision data stopped").

    The estimator behind it is deliberately small: per axis a position dead-reckoned on a
    velocity with a slowly wandering bias (IMU and flow without GPS), with variance growing by
    `drift_q` a second, corrected by the fused samples. Without external vision it drifts; that
    is what the companion's estimate is for."""

    def __init__(self, ev_delay: float = 0.0, delay_max: float = 0.2, evp_noise: float = 0.1, evp_gate: float = 5.0,
                 predict: float = 0.01, drift_q: float = 0.02, bias_rw: float = 0.01, seed: int = 0):
        self.ev_delay, self.delay_max, self.evp_noise, self.evp_gate = ev_delay, delay_max, evp_noise, evp_gate
        self.predict, self.drift_q, self.bias_rw = predict, drift_q, bias_rw
        self.rng = np.random.default_rng(seed)
        self.p = None  # estimated position (ENU), set at the first step
        self.P = np.full(3, 1.0)  # its variance per axis
        self.bias = np.zeros(3)  # the velocity error it dead-reckons with
        self.history: list[tuple[float, np.ndarray]] = []  # (time, p) over the fusion horizon
        self.active = False
        self.last_sample_t = -math.inf  # sample time of the last sample taken into the buffer
        self.last_pushed = -math.inf  # arrival of the last sample taken
        self.reset_counter = None
        self.events: list[tuple[float, str]] = []  # (FC time, what happened)
        self.now = 0.0
        self.arrivals: list[float] = []  # of every vision message
        self.ages: list[float] = []  # arrival - stamp
        self.positions: list[tuple[float, np.ndarray]] = []  # (stamp, position ENU) of every vision message
        self.covariance: dict[str, int] = {"own": 0, "floored": 0, "missing": 0}
        self.fused_t: list[float] = []

    def _count(self, what: str) -> str:
        self.events.append((self.now, what))
        return what

    @property
    def counts(self) -> dict[str, int]:
        return self.counts_since(-math.inf)

    def counts_since(self, since: float) -> dict[str, int]:
        out: dict[str, int] = {}
        for t, what in self.events:
            if t >= since:
                out[what] = out.get(what, 0) + 1
        return out

    def step(self, now: float, dt: float, v_true: np.ndarray, p_true: np.ndarray) -> None:
        """The estimator's prediction over dt, on the true velocity plus its bias."""
        self.now = now
        if self.p is None:
            self.p = np.array(p_true, float)
        self.bias += self.bias_rw * math.sqrt(dt) * self.rng.standard_normal(3)
        self.bias[2] = 0.0  # height is the barometer's: not drifting here
        self.p = self.p + (v_true + self.bias) * dt
        self.P = self.P + self.drift_q * dt
        self.history.append((now, self.p.copy()))
        while self.history and self.history[0][0] < now - 2 * self.delay_max - 0.1:
            self.history.pop(0)
        if self.active and now - self.last_pushed > 2 * EV_MAX_INTERVAL:
            self.active = False
            self._count("stopped")

    def _p_at(self, t: float) -> np.ndarray:
        for ht, hp in reversed(self.history):
            if ht <= t:
                return hp
        return self.history[0][1] if self.history else self.p

    def offer(self, now: float, msg) -> str:
        """A vision message arriving at `now` (FC time): what EKF2 would do with it."""
        self.now = now
        kind = msg.get_type()
        if kind == "ODOMETRY":
            if msg.frame_id not in (mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_FRD):
                return self._count("unsupported-frame")
            if msg.estimator_type not in (mavlink.MAV_ESTIMATOR_TYPE_VISION, mavlink.MAV_ESTIMATOR_TYPE_VIO):
                return self._count("not-vision")
            stamp, cov, reset = msg.time_usec * 1e-6, list(msg.pose_covariance), msg.reset_counter
        else:
            stamp, cov, reset = msg.usec * 1e-6, list(msg.covariance), msg.reset_counter
        z_ned = np.array([msg.x, msg.y, msg.z], float)
        if not np.all(np.isfinite(z_ned)):
            return self._count("no-position")
        self.arrivals.append(now)
        self.ages.append(now - stamp)
        z = np.array([z_ned[1], z_ned[0], -z_ned[2]])  # NED -> ENU
        self.positions.append((stamp, z))
        var_ned = np.array([cov[0], cov[6], cov[11]], float)
        floor = self.evp_noise**2
        if np.all(np.isfinite(var_ned)):
            self.covariance["own" if np.all(var_ned >= floor) else "floored"] += 1
            R = np.maximum(var_ned[[1, 0, 2]], floor)
        else:
            self.covariance["missing"] += 1
            R = np.full(3, floor)
        t_sample = now - self.ev_delay - self.predict / 2
        if t_sample < self.last_sample_t + self.predict:
            return self._count("too-fast")
        interval = t_sample - self.last_sample_t
        self.last_sample_t, self.last_pushed = t_sample, now
        if now - stamp > self.delay_max:
            return self._count("beyond-horizon")
        reset_changed = self.reset_counter is not None and reset != self.reset_counter
        self.reset_counter = reset
        if not self.active:
            if interval >= EV_MAX_INTERVAL:
                return self._count("not-started")  # starting needs two samples within EV_MAX_INTERVAL
            self.active = True
            self._correct(z - self.p, R)
            return self._count("started")
        if reset_changed:
            self._correct(z - self.p, R)
            return self._count("reset")
        innov = z - self._p_at(t_sample)
        S = self.P + R
        ratio = innov**2 / (self.evp_gate**2 * S)
        if max(ratio[0], ratio[1]) > 1.0:
            return self._count("gated")
        K = self.P / S
        self._correct(K * innov, (1 - K) * self.P)
        return self._count("fused")

    def _correct(self, dp: np.ndarray, P: np.ndarray) -> None:
        """Move the estimate by dp, the past ones kept for the fusion horizon too (as EKF2's
        output predictor carries a correction at the delayed horizon forward to now)."""
        self.p, self.P = self.p + dp, np.array(P, float)
        self.history = [(t, hp + dp) for t, hp in self.history]
        self.fused_t.append(self.last_pushed)

    def report(self, since: float = -math.inf) -> dict:
        """What a test or the docs read: counts, rate and intervals of the vision messages, their
        true age at arrival, how their covariance was used, and the longest gap between fusions
        after `since`."""
        arr = np.array([a for a in self.arrivals if a >= since])
        gaps = np.diff(arr) if arr.size > 1 else np.zeros(0)
        ages = np.array(self.ages[-len(arr):]) if arr.size else np.zeros(0)
        fused = np.array([t for t in self.fused_t if t >= since])
        # The longest stretch without a fusion, from `since` to the last message.
        edges = np.concatenate([[arr[0]] if arr.size else [], fused, [arr[-1]] if arr.size else []])
        out = {"counts": self.counts_since(since), "covariance": dict(self.covariance), "messages": int(arr.size)}
        if gaps.size:
            out.update(rate_hz=float((arr.size - 1) / (arr[-1] - arr[0])), interval_ms_p50=float(np.median(gaps) * 1e3),
                       interval_ms_p99=float(np.quantile(gaps, 0.99) * 1e3), interval_ms_max=float(gaps.max() * 1e3),
                       jitter_ms=float(gaps.std() * 1e3), age_ms_p50=float(np.median(ages) * 1e3),
                       age_ms_p99=float(np.quantile(ages, 0.99) * 1e3), age_ms_max=float(ages.max() * 1e3),
                       fusion_gap_ms_max=float(np.diff(np.sort(edges)).max() * 1e3) if edges.size > 1 else None)
        return out


class SimulatedAutopilot(FakeFlightController):
    """A PX4-like flight controller on 127.0.0.1 (udpout to the companion, as FakeFlightController):

    - vehicle "rover": a differential-drive robot whose origin is `d` ahead of its axle (the
      ground robot of swarmloc's vehicle models, written here independently): its speed and yaw
      rate follow their targets through first-order loops (k_v, k_w); the targets come from a
      velocity setpoint by inverting the origin's kinematics, or from a position setpoint
      through a P gain on its own estimate. "copter": a point mass whose acceleration is PX4's
      cascade in one line, kp (p_sp - p_est) + kv (v_sp - v_est) + a_ff, bounded; yaw follows
      the setpoint's first-order.
    - offboard (PX4 flight_modes/offboard): entered once setpoints have streamed above 2 Hz for
      more than a second (`auto_offboard`: the operator switches as soon as PX4 allows);
      SET_POSITION_TARGET_LOCAL_NED in MAV_FRAME_LOCAL_NED with a supported type_mask only
      (copter: position, velocity, acceleration, position + velocity, position + velocity +
      acceleration; rover: position or velocity); no setpoint for COM_OF_LOSS_T: failsafe,
      hold (the operator re-engages when the stream is back).
    - its estimator is Ekf2ExternalVision: the ODOMETRY it streams is its own estimate, which
      the companion's external vision corrects; GPS_RAW_INT (5 Hz) only with `gps`, from the
      truth with `gps_std` noise.
    It streams HEARTBEAT (1 Hz), ODOMETRY, ATTITUDE and HIGHRES_IMU at `rate_hz`."""

    def __init__(self, port: int, vehicle: str = "rover", start=(0.0, 0.0, 0.0, 0.0), gps: bool = True,
                 gps_std: float = 0.05, rate_hz: float = 50.0, physics_hz: float = 100.0, ev: Ekf2ExternalVision | None = None,
                 auto_offboard: bool = True, d: float = 0.05, drive: tuple[float, float] | None = None,
                 system: int = 1, seed: int = 0):
        self.vehicle, self.gps, self.gps_std = vehicle, gps, gps_std
        self.ev = ev or Ekf2ExternalVision(seed=seed)
        self.auto_offboard, self.d = auto_offboard, d
        self.drive = drive  # rover outside offboard: (speed, yaw rate) its pilot drives at; None: stopped
        self.rng = np.random.default_rng([seed, 1])
        self.physics_dt = 1.0 / physics_hz
        x, y, z, yaw = start
        self.p, self.yaw = np.array([x, y, z], float), float(yaw)
        self.v_body, self.w = 0.0, 0.0  # rover: speed along the heading, yaw rate
        self.v = np.zeros(3)  # copter: ENU velocity
        self.a = np.zeros(3)
        self.setpoint = None  # (time, type_mask, p, v, a, yaw)
        self.stream_start = None  # FC time the current setpoint stream began (no gap above 0.5 s)
        self.offboard = False
        self.offboard_time = 0.0
        self.failsafes = 0
        self.failsafe_t: list[float] = []
        self.offboard_since = None  # FC time offboard was last entered
        self.setpoints = {"received": 0, "rejected": 0}
        self.truth_log: list[tuple] = []
        self.truth_listeners: list = []
        super().__init__(port, rate_hz=rate_hz, system=system)

    # ---------------------------------------------------------------- the loop

    def _run(self):
        k = 0
        per_stream = max(1, round(self.period / self.physics_dt))  # physics steps per streamed sample
        self.boot = time.monotonic()  # boots when it starts, not when it was made: no burst to catch up
        while not self._stop.is_set():
            t = k * self.physics_dt
            delay = self.boot + t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            now = time.monotonic() - self.boot  # the FC's clock: seconds since boot
            while (m := self.conn.recv_match(blocking=False)) is not None:
                if m.get_type() != "BAD_DATA":
                    self.received.append(m)
                    self._receive(now, m)
            self._physics(now, self.physics_dt)
            if k % per_stream == 0:
                n = k // per_stream
                if n % round(1.0 / self.period) == 0:
                    kind = mavlink.MAV_TYPE_GROUND_ROVER if self.vehicle == "rover" else mavlink.MAV_TYPE_QUADROTOR
                    self.conn.mav.heartbeat_send(kind, mavlink.MAV_AUTOPILOT_PX4,
                                                 mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 0, mavlink.MAV_STATE_ACTIVE)
                self._stream_estimate(now, gps=self.gps and n % round(0.2 / self.period) == 0)
                if n % 5 == 0:
                    row = (now, *self.p.tolist(), self.yaw, self.offboard)
                    self.truth_log.append(row)
                    for listener in self.truth_listeners:
                        listener(row)
            k += 1

    def _receive(self, now: float, m) -> None:
        kind = m.get_type()
        if kind in ("ODOMETRY", "VISION_POSITION_ESTIMATE"):
            self.ev.offer(now, m)
        elif kind == "SET_POSITION_TARGET_LOCAL_NED":
            self._setpoint(now, m)

    def _setpoint(self, now: float, m) -> None:
        self.setpoints["received"] += 1
        groups = [(m.type_mask >> b) & 7 for b in (0, 3, 6)]  # position, velocity, acceleration: 0 used, 7 ignored
        used = tuple(g == 0 for g in groups)
        copter = {(True, False, False), (False, True, False), (False, False, True), (True, True, False),
                  (True, True, True)}
        # A rover's velocity may leave vz out (ArduPilot Rover's "use velocity" mask ignores it).
        rover_velocity = groups[0] == 7 and groups[1] in (0, 4) and groups[2] == 7
        ok_mask = (used in copter and all(g in (0, 7) for g in groups)) if self.vehicle == "copter" else \
            (used == (True, False, False) or rover_velocity)
        if (m.target_system != self.conn.mav.srcSystem or m.coordinate_frame != mavlink.MAV_FRAME_LOCAL_NED
                or not ok_mask):
            self.setpoints["rejected"] += 1
            return
        enu = lambda x, y, z: np.array([y, x, -z], float)
        p = enu(m.x, m.y, m.z) if groups[0] == 0 else None
        v = enu(m.vx, m.vy, m.vz) if groups[1] != 7 else None
        a = enu(m.afx, m.afy, m.afz) if groups[2] == 0 else None
        yaw = (math.pi / 2 - m.yaw) if not m.type_mask & 1024 else None
        if self.setpoint is None or now - self.setpoint[0] > 0.5:  # a stream at > 2 Hz has no longer gap
            self.stream_start = now
        if self.setpoint is not None and now - self.setpoint[0] > self.setpoints.get("gap_s", 0.0):
            self.setpoints["gap_s"], self.setpoints["gap_at"] = now - self.setpoint[0], now
        self.setpoint = (now, m.type_mask, p, v, a, yaw)

    def _mode(self, now: float) -> None:
        if self.offboard and now - self.setpoint[0] > COM_OF_LOSS_T:
            self.offboard = False
            self.failsafes += 1
            self.failsafe_t.append(now)
        elif (not self.offboard and self.auto_offboard and self.setpoint is not None
              and now - self.setpoint[0] <= 0.5 and now - self.stream_start > 1.0):
            self.offboard = True  # PX4 allows the switch after more than a second of > 2 Hz setpoints
            self.offboard_since = now

    # ---------------------------------------------------------------- the vehicle

    def _physics(self, now: float, dt: float) -> None:
        self._mode(now)
        p_est = self.ev.p if self.ev.p is not None else self.p
        sp = self.setpoint if self.offboard else None
        if self.offboard:
            self.offboard_time += dt
        if self.vehicle == "rover":
            vel = np.zeros(2)  # hold: stop
            if sp is None and self.drive is not None:  # driven by its pilot
                v_star, w_star = self.drive
            if sp is not None:
                _, _, p_sp, v_sp, _, _ = sp
                if v_sp is not None:
                    vel = v_sp[:2]
                elif p_sp is not None:
                    vel = 1.0 * (p_sp[:2] - p_est[:2])
                    n = np.linalg.norm(vel)
                    vel = vel * min(1.0, 2.0 / n) if n > 0 else vel
            c, s = math.cos(self.yaw), math.sin(self.yaw)
            if sp is not None or self.drive is None:
                v_star = c * vel[0] + s * vel[1]
                w_star = float(np.clip((-s * vel[0] + c * vel[1]) / self.d, -4.0, 4.0))
            self.v_body += 5.0 * (v_star - self.v_body) * dt + 0.002 * math.sqrt(dt) * self.rng.standard_normal()
            self.w += 10.0 * (w_star - self.w) * dt + 0.002 * math.sqrt(dt) * self.rng.standard_normal()
            v_enu = np.array([self.v_body * c - self.d * self.w * s, self.v_body * s + self.d * self.w * c, 0.0])
            self.a = (v_enu - self.v) / dt
            self.v = v_enu
            self.yaw = math.remainder(self.yaw + self.w * dt, 2 * math.pi)
        else:
            a = np.zeros(3)
            yaw_sp = self.yaw
            v_est = self.v + self.ev.bias
            if sp is not None:
                _, _, p_sp, v_sp, a_ff, ysp = sp
                if p_sp is not None:
                    a += 1.0 * (p_sp - p_est)
                a += 2.0 * ((v_sp if v_sp is not None else np.zeros(3)) - v_est)
                if a_ff is not None:
                    a += a_ff
                yaw_sp = ysp if ysp is not None else self.yaw
            else:
                a += -2.0 * v_est  # hold: brake
            n = np.linalg.norm(a)
            self.a = a * min(1.0, 5.0 / n) if n > 0 else a
            self.v = self.v + self.a * dt
            self.w = 2.0 * math.remainder(yaw_sp - self.yaw, 2 * math.pi)
            self.yaw = math.remainder(self.yaw + self.w * dt, 2 * math.pi)
        self.p = self.p + self.v * dt
        self.ev.step(now, dt, self.v, self.p)

    def _stream_estimate(self, t: float, gps: bool) -> None:
        mav = self.conn.mav
        p_est = self.ev.p if self.ev.p is not None else self.p
        e, n, u = p_est
        v_est = self.v + self.ev.bias
        # Level but for a copter's tilt into its acceleration (thrust along a + g up).
        if self.vehicle == "copter":
            f = self.a + np.array([0.0, 0.0, G])
            c, s = math.cos(self.yaw), math.sin(self.yaw)
            fx, fy = c * f[0] + s * f[1], -s * f[0] + c * f[1]  # in the yaw frame (FLU)
            pitch, roll = math.atan2(fx, f[2]), math.atan2(-fy, math.hypot(fx, f[2]))
        else:
            roll = pitch = 0.0
        yaw_ned = math.pi / 2 - self.yaw
        q = QuaternionBase([roll, pitch, yaw_ned])
        R = np.array(q.dcm)
        w_frd = R.T @ np.array([0.0, 0.0, -self.w])
        v_frd = R.T @ np.array([v_est[1], v_est[0], -v_est[2]])
        us, ms = int(t * 1e6), int(t * 1e3)
        nan21 = [math.nan] * 21
        mav.odometry_send(us, mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_BODY_FRD, n, e, -u, list(q.q), *v_frd,
                          *w_frd, nan21, nan21, estimator_type=mavlink.MAV_ESTIMATOR_TYPE_AUTOPILOT)
        mav.attitude_send(ms, roll, pitch, yaw_ned, *w_frd)
        a_ned = np.array([self.a[1], self.a[0], -self.a[2]])
        f_frd = R.T @ (a_ned - [0.0, 0.0, G])
        mav.highres_imu_send(us, *f_frd, *w_frd, 0, 0, 0, 1013.0, 0, 0, 20.0, 0x3F)
        if gps:
            lat0, lon0, alt0 = ORIGIN
            r_north, r_east = metres_per_radian(lat0)
            te, tn, tu = self.p + self.gps_std * self.rng.standard_normal(3) * [1, 1, 0]
            mav.gps_raw_int_send(us, mavlink.GPS_FIX_TYPE_RTK_FIXED, round((lat0 + math.degrees(tn / r_north)) * 1e7),
                                 round((lon0 + math.degrees(te / r_east)) * 1e7), round((alt0 + tu) * 1e3), 80, 120,
                                 0, 0, 16, h_acc=max(1, round(self.gps_std * 1e3)), v_acc=max(1, round(self.gps_std * 2e3)))

    def report(self, since: float = -math.inf) -> dict:
        """The estimator's report and the setpoints' (offboard now, and since when; failsafes), all
        over what came after `since` (FC time)."""
        return {"ev": self.ev.report(since), "setpoints": dict(self.setpoints), "offboard": self.offboard,
                "offboard_since": self.offboard_since, "offboard_s": self.offboard_time,
                "failsafes": sum(t >= since for t in self.failsafe_t)}


def main(argv=None) -> int:
    """`python tests/fake_fc.py --port P ...`: a SimulatedAutopilot as a process (the
    flight-controller-in-the-loop test runs one in each host's network namespace). Its truth
    goes to --truth as JSON lines (t, east, north, up, yaw, offboard) at a fifth of the stream
    rate with the UNIX time each row was taken, its report to --report when SIGTERM ends it
    (over what came after --epoch, a UNIX time, when given)."""
    import argparse
    import json
    import signal

    p = argparse.ArgumentParser()
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--vehicle", choices=["rover", "copter"], default="rover")
    p.add_argument("--start", type=float, nargs=4, default=[0.0, 0.0, 0.0, 0.0], help="east north up yaw")
    p.add_argument("--gps", action="store_true")
    p.add_argument("--drive", type=float, nargs=2, default=None, help="rover outside offboard: speed, yaw rate")
    p.add_argument("--gps-std", type=float, default=0.05)
    p.add_argument("--ev-delay", type=float, default=0.0, help="EKF2_EV_DELAY (s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--truth", required=True)
    p.add_argument("--report", required=True)
    p.add_argument("--epoch", type=float, default=None, help="UNIX time the report starts at")
    a = p.parse_args(argv)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    truth = open(a.truth, "w", buffering=1)
    sim = SimulatedAutopilot(a.port, a.vehicle, tuple(a.start), gps=a.gps, gps_std=a.gps_std, drive=a.drive,
                             ev=Ekf2ExternalVision(ev_delay=a.ev_delay, seed=a.seed), seed=a.seed)
    sim.truth_listeners.append(lambda row: truth.write(json.dumps([*row, time.time()]) + "\n"))
    with sim:
        print("fake-fc up", flush=True)
        while not stop.wait(0.2):
            pass
    truth.close()
    boot_unix = time.time() - (time.monotonic() - sim.boot)
    with open(a.report, "w") as f:
        json.dump(sim.report(-math.inf if a.epoch is None else a.epoch - boot_unix), f)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
