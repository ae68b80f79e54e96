"""A simulated flight controller on 127.0.0.1 for the MAVLink adapter's tests.

It flies a known circle and streams what PX4 streams to a companion: HEARTBEAT at 1 Hz,
ODOMETRY (or LOCAL_POSITION_NED), ATTITUDE and HIGHRES_IMU at 50 Hz, GPS_RAW_INT at 5 Hz, and
records every message it receives. Its conversions to NED, FRD and WGS 84 are written
independently of agents.mavlink (pymavlink's quaternion, a flat-earth offset), so a test that
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
            # Flat earth with WGS 84's radii of curvature: off by well under a millimetre at 20 m.
            e2 = (1 / 298.257223563) * (2 - 1 / 298.257223563)
            s2 = math.sin(math.radians(lat0)) ** 2
            r_north = 6378137.0 * (1 - e2) / (1 - e2 * s2) ** 1.5
            r_east = 6378137.0 / math.sqrt(1 - e2 * s2) * math.cos(math.radians(lat0))
            lat = lat0 + math.degrees(n / r_north)
            lon = lon0 + math.degrees(e / r_east)
            mav.gps_raw_int_send(us, mavlink.GPS_FIX_TYPE_3D_FIX, round(lat * 1e7), round(lon * 1e7),
                                 round((alt0 + u) * 1e3), 80, 120, round(5.0 * 100), 0, 12,
                                 h_acc=1500, v_acc=2500)
