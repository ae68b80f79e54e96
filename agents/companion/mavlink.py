"""MAVLink adapter: the agent daemon's link to a PX4 or ArduPilot flight controller (FC).

`FlightController` reads the FC's own estimate and sensors (ODOMETRY or LOCAL_POSITION_NED,
ATTITUDE, GPS_RAW_INT, HIGHRES_IMU) into small dataclasses in swarmloc's frames, and sends the
swarm's estimate back (ODOMETRY or VISION_POSITION_ESTIMATE) for the autopilot to fuse as
external vision. pymavlink does the protocol; this module does frames, units, liveness and rate.

Frames: MAVLink's local frame is NED and its body frame FRD; swarmloc's are ENU and FLU
(docs/uas.md). NED <-> ENU swaps x and y and negates z; FRD <-> FLU negates y and z; each map is
its own inverse, so one matrix serves both directions.

Thread-free: `poll()` drains the non-blocking connection and returns what arrived. The daemon's
single loop calls it, so pymavlink's parser and send sequence, which are not thread-safe, have
one owner and need no lock; the kernel's socket buffer is the queue. The price is that the
daemon must call `poll()` often (20 ms; docs/deploy.md#mavlink says why).
"""

from __future__ import annotations

import enum
import logging
import math
import os
import time
from collections import Counter
from dataclasses import dataclass

import numpy as np

os.environ["MAVLINK20"] = "1"  # before pymavlink is imported: it picks the wire version then
from pymavlink import mavutil  # noqa: E402

from swarmloc.models import ins  # noqa: E402

mavutil.set_dialect("common")  # PX4 and ArduPilot both speak it; ardupilotmega would be pymavlink's default
mavlink = mavutil.mavlink
log = logging.getLogger("swarmloc.mavlink")

HEARTBEAT_TIMEOUT = 3.0
"""s without a HEARTBEAT after which the FC counts as lost."""

_MAX_READS = 1000
"""Reads (datagrams, or up to 4 KiB of a stream) per poll(): far more than an FC sends between two polls."""

_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
_FLU_FRD = np.diag([1.0, -1.0, -1.0])
_NAN3 = np.full(3, math.nan)

_WGS84_A = 6_378_137.0
_WGS84_E2 = (1.0 / 298.257223563) * (2.0 - 1.0 / 298.257223563)


# --------------------------------------------------------------------------- frames


def enu_from_ned(v) -> np.ndarray:
    """A vector from NED to ENU, or back (the map is its own inverse)."""
    return _ENU_NED @ np.asarray(v, float)


def flu_from_frd(v) -> np.ndarray:
    """A body vector from FRD to FLU, or back."""
    return _FLU_FRD @ np.asarray(v, float)


def enu_flu_from_ned_frd(C: np.ndarray) -> np.ndarray:
    """The rotation matrix body -> ENU/FLU of one given body -> NED/FRD, or back."""
    return _ENU_NED @ C @ _FLU_FRD


def ned_from_enu_cov(P) -> np.ndarray:
    """A 3x3 covariance from ENU to NED, or back."""
    return _ENU_NED @ np.asarray(P, float) @ _ENU_NED


def quat_enu_from_ned(q_ned) -> np.ndarray:
    """MAVLink's attitude quaternion (FRD body -> NED, w x y z) as swarmloc's (FLU -> ENU)."""
    return ins.dcm_to_quat(enu_flu_from_ned_frd(ins.quat_to_dcm(ins.quat_normalize(q_ned))))


def yaw_enu_from_ned(yaw: float) -> float:
    """Heading clockwise from north (MAVLink) as yaw counter-clockwise from east, or back."""
    return math.remainder(math.pi / 2 - yaw, 2 * math.pi)


def urt(M: np.ndarray) -> list[float]:
    """The 21-element upper-right triangle of a 6x6 covariance, row by row (MAVLink's layout)."""
    return [float(x) for x in np.asarray(M)[np.triu_indices(6)]]


class LocalFrame:
    """ENU metres on the tangent plane at a WGS 84 origin, exact through ECEF."""

    def __init__(self, lat: float, lon: float, alt: float):
        self.origin = (lat, lon, alt)
        self._o = _ecef(lat, lon, alt)
        sa, ca = math.sin(math.radians(lat)), math.cos(math.radians(lat))
        so, co = math.sin(math.radians(lon)), math.cos(math.radians(lon))
        self._R = np.array([[-so, co, 0.0], [-sa * co, -sa * so, ca], [ca * co, ca * so, sa]])

    def enu(self, lat: float, lon: float, alt: float) -> np.ndarray:
        return self._R @ (_ecef(lat, lon, alt) - self._o)


def _ecef(lat: float, lon: float, h: float) -> np.ndarray:
    la, lo = math.radians(lat), math.radians(lon)
    N = _WGS84_A / math.sqrt(1.0 - _WGS84_E2 * math.sin(la) ** 2)
    return np.array([(N + h) * math.cos(la) * math.cos(lo), (N + h) * math.cos(la) * math.sin(lo),
                     (N * (1.0 - _WGS84_E2) + h) * math.sin(la)])


# --------------------------------------------------------------------------- samples
# t is the FC's clock in seconds, as it stamps the message (time_boot_ms or time_usec).


@dataclass(frozen=True)
class Odometry:
    """The FC's own estimate. From LOCAL_POSITION_NED, q and rate are None."""
    t: float
    position: np.ndarray  # ENU, m, from the FC's local origin
    velocity: np.ndarray  # ENU, m/s; NaN when sent in the body frame without an attitude
    q: np.ndarray | None  # FLU -> ENU, w x y z
    rate: np.ndarray | None  # FLU, rad/s
    source: str  # "ODOMETRY" or "LOCAL_POSITION_NED"


@dataclass(frozen=True)
class Attitude:
    t: float
    q: np.ndarray  # FLU -> ENU, w x y z
    rate: np.ndarray  # FLU, rad/s


@dataclass(frozen=True)
class Imu:
    t: float
    rate: np.ndarray  # FLU, rad/s
    specific_force: np.ndarray  # FLU, m/s^2: +9.81 on z level at rest


@dataclass(frozen=True)
class GnssFix:
    t: float
    fix_type: int  # GPS_FIX_TYPE: 3 is 3D, 4 DGPS, 5 and 6 RTK
    lat: float  # deg
    lon: float  # deg
    alt: float  # m above mean sea level
    position: np.ndarray | None  # ENU, m, from the reference origin; None below a 3D fix
    h_acc: float  # m, 1-sigma horizontal; NaN unknown
    v_acc: float  # m, 1-sigma vertical; NaN unknown
    hdop: float  # unitless (GPS_RAW_INT's eph is HDOP x 100, not metres); NaN unknown
    vdop: float
    satellites: int


class Link(str, enum.Enum):
    WAITING = "waiting"  # no HEARTBEAT from an autopilot yet, timeout not reached
    ALIVE = "alive"
    LOST = "lost"


class OutputRate:
    """Lets at most `hz` calls a second through, evenly: the caller offers every estimate and
    the link carries the configured rate."""

    def __init__(self, hz: float):
        if not hz > 0:
            raise ValueError(f"output rate must be positive, got {hz}")
        self.period = 1.0 / hz
        self._next = -math.inf
        self._last = -math.inf

    def ready(self, now: float | None = None) -> bool:
        now = time.monotonic() if now is None else now
        # Never two within half a period: a late call catches the schedule up, but not with a
        # pair back to back, which an autopilot drops (PX4 keeps one sample per filter period).
        if now < self._next or now - self._last < self.period / 2:
            return False
        # Step the schedule instead of restarting it at `now`, so the caller's jitter does not
        # lower the rate; after a long gap restart it, so there is no burst to catch up.
        self._next = self._next + self.period if now - self._next < self.period else now + self.period
        self._last = now
        return True

    def due_in(self, now: float) -> float:
        """s until the next call would be let through (0: now)."""
        return max(0.0, self._next - now, self._last + self.period / 2 - now)


# --------------------------------------------------------------------------- the adapter


class FlightController:
    """A MAVLink connection to one flight controller.

    url: what pymavlink opens: "udpin:0.0.0.0:14540" (listen), "udpout:HOST:PORT" (send first),
    "tcp:HOST:PORT", or a serial device "/dev/ttyACM0" at `baud`.
    We speak as (source_system, source_component): a companion shares the FC's system id, as
    component MAV_COMP_ID_ONBOARD_COMPUTER.
    origin: (lat, lon, alt MSL) of the ENU frame for GNSS fixes; None takes the first 3D fix.
    output: "odometry" or "vision_position_estimate", at most `output_hz` a second.
    frame_id: ODOMETRY's pose frame. MAV_FRAME_LOCAL_NED for PX4; ArduPilot accepts only
    MAV_FRAME_LOCAL_FRD (our ENU is north-aligned either way, so the numbers are the same).
    """

    def __init__(self, url: str, *, source_system: int = 1,
                 source_component: int = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER, baud: int = 921600,
                 origin: tuple[float, float, float] | None = None, output: str = "odometry",
                 output_hz: float = 30.0, frame_id: int = mavlink.MAV_FRAME_LOCAL_NED,
                 heartbeat_timeout: float = HEARTBEAT_TIMEOUT):
        if output not in ("odometry", "vision_position_estimate"):
            raise ValueError(f"output must be odometry or vision_position_estimate, got {output!r}")
        self.url, self.output, self.frame_id = url, output, frame_id
        self.heartbeat_timeout = heartbeat_timeout
        self.output_rate = OutputRate(output_hz)
        self.local = LocalFrame(*origin) if origin is not None else None
        self.conn = mavutil.mavlink_connection(url, baud=baud, source_system=source_system,
                                               source_component=source_component, dialect="common",
                                               robust_parsing=True)
        self._datagrams = isinstance(self.conn, (mavutil.mavudp, mavutil.mavmcast))
        self.fc: tuple[int, int] | None = None  # (system, component) of the autopilot
        self.autopilot: int | None = None  # MAV_AUTOPILOT of its HEARTBEAT
        self.received: Counter[str] = Counter()  # accepted messages by type
        self.dropped: Counter[str] = Counter()  # by reason
        self.attitude: np.ndarray | None = None  # latest FC attitude, FLU -> ENU
        self._have_odometry = False
        self._opened = time.monotonic()
        self._last_heartbeat: float | None = None
        self._state = Link.WAITING
        self._next_heartbeat = 0.0

    # ---------------------------------------------------------------- liveness

    @property
    def state(self) -> Link:
        """Whether the FC is heard, judged now (so it is right even between polls)."""
        since = self._opened if self._last_heartbeat is None else self._last_heartbeat
        if time.monotonic() - since > self.heartbeat_timeout:
            return Link.LOST
        return Link.WAITING if self._last_heartbeat is None else Link.ALIVE

    @property
    def alive(self) -> bool:
        return self.state is Link.ALIVE

    def _update_state(self) -> None:
        state = self.state
        if state is self._state:
            return
        if state is Link.LOST:
            log.warning("no heartbeat from the flight controller at %s for %g s", self.url, self.heartbeat_timeout)
        elif state is Link.ALIVE:
            log.info("flight controller at %s: system %d component %d, autopilot %d, heartbeat %s",
                     self.url, *self.fc, self.autopilot, "back" if self._state is Link.LOST else "received")
        self._state = state

    # ---------------------------------------------------------------- reading

    def poll(self) -> list[Odometry | Attitude | Imu | GnssFix]:
        """Everything that arrived since the last call, oldest first; never blocks, never raises
        on what the link brings (bad data is counted in `dropped`). Sends our HEARTBEAT at 1 Hz."""
        now = time.monotonic()
        if now >= self._next_heartbeat:
            self._next_heartbeat = now + 1.0
            self._send(self.conn.mav.heartbeat_encode(mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                                                      mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
                                                      mavlink.MAV_STATE_ACTIVE))
        out = []
        for _ in range(_MAX_READS):  # a flooded link must not hold the daemon's loop here
            try:
                data = self.conn.recv(4096)
            except OSError as e:  # TCP reset, serial unplugged: the heartbeat timeout reports it
                self.dropped["link-error"] += 1
                log.debug("read from %s failed: %s", self.url, e)
                break
            if not data:
                break
            try:
                msgs = self.conn.mav.parse_buffer(data) or []
            except Exception as e:  # robust parsing turns bad frames into BAD_DATA; this is the rest
                self.dropped["parse-error"] += 1
                log.debug("unparsable data from %s: %s", self.url, e)
                self._reset_parser()
                continue
            if self._datagrams and self.conn.mav.buf_len():
                # A datagram holds whole frames, so bytes left over are a truncated or corrupt
                # frame. Kept, a length byte of garbage would make the parser swallow up to
                # 280 bytes of the good datagrams that follow.
                self.dropped["bad-data"] += 1
                self._reset_parser()
            for msg in msgs:
                try:
                    sample = self._handle(msg)
                except Exception as e:  # a decodable but nonsensical message (NaN, bad enum)
                    self.dropped["bad-value"] += 1
                    log.debug("dropped %s from %s: %s", msg.get_type(), self.url, e)
                    continue
                if sample is not None:
                    out.append(sample)
        self._update_state()
        return out

    def _reset_parser(self) -> None:
        mav = self.conn.mav
        mav.buf, mav.buf_index, mav.expected_length = bytearray(), 0, mavlink.HEADER_LEN_V1 + 2

    def _handle(self, msg):
        kind = msg.get_type()
        if kind == "BAD_DATA":
            self.dropped["bad-data"] += 1
            return None
        self.conn.post_message(msg)  # pymavlink's own bookkeeping: per-system loss counts
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if kind == "HEARTBEAT":
            if msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID and self.fc in (None, src):
                self.fc, self.autopilot = src, msg.autopilot
                self._last_heartbeat = time.monotonic()
            return None
        # Telemetry only from the autopilot: on a shared link a VIO companion's ODOMETRY to the
        # FC, or our own, must not read as the FC's.
        if src != self.fc:
            return None
        handler = _HANDLERS.get(kind)
        if handler is None:
            return None
        sample = handler(self, msg)
        if sample is not None:
            self.received[kind] += 1
        return sample

    def _odometry(self, m) -> Odometry | None:
        if m.frame_id != mavlink.MAV_FRAME_LOCAL_NED:
            self.dropped["unsupported-frame"] += 1
            return None
        self._have_odometry = True
        # NaN is MAVLink's "no attitude"; a zero quaternion is no attitude either.
        q = quat_enu_from_ned(m.q) if np.all(np.isfinite(m.q)) and np.linalg.norm(m.q) > 0.5 else None
        v = np.array([m.vx, m.vy, m.vz], float)
        if m.child_frame_id == mavlink.MAV_FRAME_LOCAL_NED:
            v = enu_from_ned(v)
        elif m.child_frame_id == mavlink.MAV_FRAME_BODY_FRD:  # what PX4 sends
            v = ins.quat_to_dcm(q) @ flu_from_frd(v) if q is not None else _NAN3
        else:
            v = _NAN3
        if q is not None:
            self.attitude = q
        return Odometry(m.time_usec * 1e-6, enu_from_ned([m.x, m.y, m.z]), v, q,
                        flu_from_frd([m.rollspeed, m.pitchspeed, m.yawspeed]), "ODOMETRY")

    def _local_position(self, m) -> Odometry | None:
        if self._have_odometry:  # the same estimate twice would be fused twice
            return None
        return Odometry(m.time_boot_ms * 1e-3, enu_from_ned([m.x, m.y, m.z]),
                        enu_from_ned([m.vx, m.vy, m.vz]), None, None, "LOCAL_POSITION_NED")

    def _attitude(self, m) -> Attitude:
        # Same roll and pitch in both conventions (right wing down, nose up); only yaw changes.
        q = ins.quat_from_euler(m.roll, m.pitch, yaw_enu_from_ned(m.yaw))
        self.attitude = q
        return Attitude(m.time_boot_ms * 1e-3, q, flu_from_frd([m.rollspeed, m.pitchspeed, m.yawspeed]))

    def _gps(self, m) -> GnssFix:
        lat, lon, alt = m.lat * 1e-7, m.lon * 1e-7, m.alt * 1e-3
        position = None
        if m.fix_type >= mavlink.GPS_FIX_TYPE_3D_FIX:
            if self.local is None:
                self.local = LocalFrame(lat, lon, alt)
                log.info("GNSS origin from the first 3D fix: lat %.7f lon %.7f alt %.2f m", lat, lon, alt)
            position = self.local.enu(lat, lon, alt)
        return GnssFix(m.time_usec * 1e-6, m.fix_type, lat, lon, alt, position, _accuracy(m.h_acc),
                       _accuracy(m.v_acc), _dop(m.eph), _dop(m.epv), m.satellites_visible)

    def _imu(self, m) -> Imu:
        return Imu(m.time_usec * 1e-6, flu_from_frd([m.xgyro, m.ygyro, m.zgyro]),
                   flu_from_frd([m.xacc, m.yacc, m.zacc]))

    # ---------------------------------------------------------------- sending

    def send_estimate(self, t: float, position_enu, cov_position, velocity=None, cov_velocity=None,
                      yaw: float | None = None, yaw_var: float | None = None, reset_counter: int = 0) -> bool:
        """Offer an estimate to the autopilot; True if it went out, False if the output rate
        held it back. t: the estimate's time on the FC's clock (s); position (m) and velocity
        (m/s) in ENU with their 3x3 covariances; yaw counter-clockwise from east (rad);
        reset_counter (0-255): changed when the estimate jumped, so the autopilot resets to it
        instead of rejecting it (agents/companion/output.py decides when).

        The attitude sent is the FC's own roll and pitch with our yaw, or the FC's yaw when we
        have none; NaN (unknown) until the FC has reported an attitude. Velocity travels in
        the body frame (child_frame_id BODY_FRD, what ArduPilot requires), rotated with that
        attitude; VISION_POSITION_ESTIMATE carries no velocity."""
        if not self.output_rate.ready():
            return False
        pose_cov = np.zeros((6, 6))
        pose_cov[:3, :3] = ned_from_enu_cov(cov_position)
        pose_cov[3:, 3:] = np.diag([math.nan] * 3)  # roll and pitch are the FC's own: no news
        C = None  # body FRD -> NED of the attitude sent
        q, euler = [math.nan] * 4, [math.nan] * 3
        if self.attitude is not None:
            roll, pitch, fc_yaw = ins.euler_from_quat(self.attitude)
            if yaw is None:
                yaw = fc_yaw
            elif yaw_var is not None:
                pose_cov[5, 5] = yaw_var
            C = enu_flu_from_ned_frd(ins.quat_to_dcm(ins.quat_from_euler(roll, pitch, yaw)))
            q, euler = ins.dcm_to_quat(C).tolist(), [roll, pitch, yaw_enu_from_ned(yaw)]
        x, y, z = enu_from_ned(position_enu)
        usec = max(0, round(t * 1e6))
        mav = self.conn.mav
        if self.output == "vision_position_estimate":
            self._send(mav.vision_position_estimate_encode(usec, x, y, z, *euler, urt(pose_cov), reset_counter % 256))
            return True
        v, vel_cov = _NAN3, [math.nan] * 21
        if velocity is not None and C is not None:
            v = C.T @ enu_from_ned(velocity)
            if cov_velocity is not None:
                P = np.diag([math.nan] * 6)  # no body rates of ours
                P[:3, :3] = C.T @ ned_from_enu_cov(cov_velocity) @ C
                vel_cov = urt(P)
        self._send(mav.odometry_encode(usec, self.frame_id, mavlink.MAV_FRAME_BODY_FRD, x, y, z, q, *v,
                                       math.nan, math.nan, math.nan, urt(pose_cov), vel_cov, reset_counter % 256,
                                       estimator_type=mavlink.MAV_ESTIMATOR_TYPE_VISION))
        return True

    def send_position_target(self, t: float, type_mask: int, position_enu=None, velocity_enu=None, accel_enu=None,
                             yaw: float | None = None, yaw_rate: float | None = None) -> bool:
        """A SET_POSITION_TARGET_LOCAL_NED to the autopilot in MAV_FRAME_LOCAL_NED (the offset
        from its EKF origin, which PX4 offboard and ArduPilot guided both take), addressed to
        the FC of the heartbeat; False while there is none. t: FC time (s, as time_boot_ms);
        vectors in ENU (None: ignored, as type_mask must then say); yaw counter-clockwise from
        east (rad), yaw_rate about up (rad/s). Unused fields go out as 0."""
        if self.fc is None:
            return False
        p = enu_from_ned(position_enu) if position_enu is not None else np.zeros(3)
        v = enu_from_ned(velocity_enu) if velocity_enu is not None else np.zeros(3)
        a = enu_from_ned(accel_enu) if accel_enu is not None else np.zeros(3)
        heading = yaw_enu_from_ned(yaw) if yaw is not None else 0.0
        rate = -yaw_rate if yaw_rate is not None else 0.0  # about up -> about down
        ms = max(0, round(t * 1e3)) & 0xFFFFFFFF
        self._send(self.conn.mav.set_position_target_local_ned_encode(
            ms, *self.fc, mavlink.MAV_FRAME_LOCAL_NED, type_mask, *p, *v, *a, heading, rate))
        return True

    def _send(self, msg) -> None:
        try:
            self.conn.mav.send(msg)
        except OSError as e:  # a dead link is reported by the heartbeat timeout, not by sends
            self.dropped["send-error"] += 1
            log.debug("send to %s failed: %s", self.url, e)

    def close(self) -> None:
        self.conn.close()

    def __enter__(self) -> FlightController:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _accuracy(mm: int) -> float:
    # 0 is what a sender without these extension fields leaves in them.
    return mm * 1e-3 if mm else math.nan


def _dop(x: int) -> float:
    return x * 1e-2 if x != 0xFFFF else math.nan


_HANDLERS = {
    "ODOMETRY": FlightController._odometry,
    "LOCAL_POSITION_NED": FlightController._local_position,
    "ATTITUDE": FlightController._attitude,
    "GPS_RAW_INT": FlightController._gps,
    "HIGHRES_IMU": FlightController._imu,
}
