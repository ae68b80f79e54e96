"""The simulated autopilot's rules (tests/fake_fc.py), message by message, without sockets: the
flight-controller-in-the-loop tests lean on it to say whether PX4 would fuse what the
companion sends and fly what it commands."""

import math
import os

import numpy as np
import pytest

os.environ["MAVLINK20"] = "1"
from fake_fc import EV_MAX_INTERVAL, Ekf2ExternalVision, SimulatedAutopilot, mavlink  # noqa: E402

MAV = mavlink.MAVLink(None, srcSystem=1, srcComponent=mavlink.MAV_COMP_ID_ONBOARD_COMPUTER)


def odometry(stamp: float, east: float = 0.0, var: float = 0.04, reset: int = 0, frame=mavlink.MAV_FRAME_LOCAL_NED,
             estimator=mavlink.MAV_ESTIMATOR_TYPE_VISION):
    cov = [0.0] * 21
    cov[0] = cov[6] = cov[11] = var
    return MAV.odometry_encode(round(stamp * 1e6), frame, mavlink.MAV_FRAME_BODY_FRD, 0.0, east, 0.0,
                               [math.nan] * 4, math.nan, math.nan, math.nan, math.nan, math.nan, math.nan, cov,
                               [math.nan] * 21, reset, estimator_type=estimator)


def ekf() -> Ekf2ExternalVision:
    ev = Ekf2ExternalVision(evp_noise=0.1, seed=1)
    ev.step(0.0, 0.01, np.zeros(3), np.zeros(3))
    return ev


def feed(ev, times, **kw):
    out = []
    for t in times:
        ev.step(t, 0.01, np.zeros(3), np.zeros(3))
        out.append(ev.offer(t, odometry(t - 0.02, **kw)))
    return out


def test_vision_starts_on_its_second_sample_and_fuses_at_30_hz():
    ev = ekf()
    verdicts = feed(ev, np.arange(1, 31) / 30)
    assert verdicts[:2] == ["not-started", "started"] and set(verdicts[2:]) == {"fused"}
    r = ev.report()
    assert r["rate_hz"] == pytest.approx(30.0) and r["age_ms_p50"] == pytest.approx(20.0, abs=1e-3)
    assert r["covariance"] == {"own": 30, "floored": 0, "missing": 0}


def test_too_slow_never_starts_and_a_pause_stops_it():
    ev = ekf()
    assert set(feed(ev, np.arange(1, 11) * (EV_MAX_INTERVAL + 0.01))) == {"not-started"}  # below 5 Hz
    ev = ekf()
    feed(ev, np.arange(1, 11) / 30)
    assert ev.active
    for t in np.arange(0.35, 0.9, 0.01):  # silence
        ev.step(t, 0.01, np.zeros(3), np.zeros(3))
    assert not ev.active and ev.counts["stopped"] == 1


def test_what_px4_drops_or_refuses():
    ev = ekf()
    feed(ev, np.arange(1, 11) / 30)
    t = 11 / 30
    assert ev.offer(t, odometry(t - 0.02)) == "fused"
    assert ev.offer(t + 0.001, odometry(t - 0.019)) == "too-fast"  # within one filter period
    assert ev.offer(t + 0.04, odometry(t - 0.3)) == "beyond-horizon"  # older than EKF2_DELAY_MAX
    assert ev.offer(t + 0.08, odometry(t + 0.06, east=3.0, var=0.01)) == "gated"  # 3 m off at 0.1 m std
    assert ev.offer(t + 0.12, odometry(t + 0.10, east=3.0, var=0.01, reset=1)) == "reset"  # unless it says so
    assert ev.p[0] == pytest.approx(3.0)
    assert ev.offer(t + 0.16, odometry(t + 0.14, frame=mavlink.MAV_FRAME_BODY_FRD)) == "unsupported-frame"
    assert ev.offer(t + 0.2, odometry(t + 0.18, estimator=mavlink.MAV_ESTIMATOR_TYPE_AUTOPILOT)) == "not-vision"
    before = dict(ev.covariance)
    assert ev.offer(t + 0.24, odometry(t + 0.22, east=3.0, var=math.nan, reset=1)) == "fused"
    assert ev.covariance["missing"] == before["missing"] + 1  # fused with EKF2_EVP_NOISE instead
    assert ev.offer(t + 0.28, odometry(t + 0.26, east=3.0, var=1e-4, reset=1)) == "fused"
    assert ev.covariance["floored"] == before["floored"] + 1  # below EKF2_EVP_NOISE: its floor is used


def setpoint(mask: int, frame=mavlink.MAV_FRAME_LOCAL_NED, target: int = 1, vx: float = 1.0):
    return MAV.set_position_target_local_ned_encode(0, target, 1, frame, mask, 1.0, 2.0, -3.0, vx, 0.0, 0.0,
                                                    0.0, 0.0, 0.0, 0.0, 0.0)


@pytest.mark.parametrize("vehicle, mask, ok", [
    ("copter", 2048, True),  # position, velocity, acceleration, yaw
    ("copter", 2048 | 64 | 128 | 256, True),  # position, velocity, yaw
    ("copter", 2048 | 1 | 2 | 4 | 8 | 16 | 32, True),  # acceleration alone
    ("copter", 2048 | 1 | 2 | 4 | 64 | 128, False),  # velocity with half an acceleration
    ("copter", 2048 | 1 | 2 | 4 | 64 | 128 | 256 | 8, False),  # vy, vz only
    ("rover", 3559, True),  # ArduPilot Rover's "use velocity"
    ("rover", 2048 | 1024 | 8 | 16 | 32 | 64 | 128 | 256, True),  # position
    ("rover", 2048, False),  # a rover takes no acceleration
])
def test_only_setpoints_px4_supports_are_flown(vehicle, mask, ok):
    sim = SimulatedAutopilot(0, vehicle)  # never started: its sockets are not used
    try:
        sim._setpoint(1.0, setpoint(mask))
        assert (sim.setpoints["rejected"] == 0) == ok
        sim._setpoint(1.1, setpoint(3559 if vehicle == "rover" else 2048, frame=mavlink.MAV_FRAME_BODY_FRD))
        sim._setpoint(1.2, setpoint(3559 if vehicle == "rover" else 2048, target=7))
        assert sim.setpoints["rejected"] == (0 if ok else 1) + 2
    finally:
        sim.conn.close()


def test_offboard_after_a_second_of_setpoints_and_a_failsafe_when_they_stop():
    sim = SimulatedAutopilot(0, "rover", start=(0.0, 0.0, 0.0, math.pi / 2))  # nose north, as the setpoint
    try:
        for i in range(25):  # 20 Hz for 1.2 s
            sim._setpoint(i * 0.05, setpoint(3559))
            sim._physics(i * 0.05, 0.01)
        assert sim.offboard
        speed = sim.v_body
        for i in range(200):  # setpoints stop: 2 s of physics
            sim._physics(1.25 + i * 0.01, 0.01)
        assert not sim.offboard and sim.failsafes == 1 and abs(sim.v_body) < 0.05 < speed  # it stopped
    finally:
        sim.conn.close()
