"""The MAVLink adapter against a simulated flight controller, over UDP on 127.0.0.1."""

import logging
import math
import socket
import time

import numpy as np
import pytest
from fake_fc import ORIGIN, FakeFlightController, G
from pymavlink.quaternion import QuaternionBase

from agents.companion.mavlink import (
    Attitude,
    FlightController,
    GnssFix,
    Imu,
    Link,
    Odometry,
    OutputRate,
    enu_from_ned,
    flu_from_frd,
    mavlink,
    quat_enu_from_ned,
    yaw_enu_from_ned,
)
from swarmloc.models import ins


def udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def poll_for(fc: FlightController, seconds: float, until=lambda: False) -> list:
    out, end = [], time.monotonic() + seconds
    while time.monotonic() < end and not until():
        out += fc.poll()
        time.sleep(0.005)
    return out


def truth_q(x) -> np.ndarray:
    return ins.quat_from_euler(x["roll"], x["pitch"], x["yaw"])


# --------------------------------------------------------------------------- frames, no network


def test_frame_conversions_by_hand():
    assert enu_from_ned([1.0, 2.0, 3.0]).tolist() == [2.0, 1.0, -3.0]  # north, east, down -> east, north, up
    assert flu_from_frd([1.0, 2.0, 3.0]).tolist() == [1.0, -2.0, -3.0]
    assert yaw_enu_from_ned(0.0) == pytest.approx(math.pi / 2)  # nose north
    assert yaw_enu_from_ned(math.pi / 2) == pytest.approx(0.0)  # nose east
    # Level, nose north: FRD forward is north, so FLU forward maps to ENU north.
    C = ins.quat_to_dcm(quat_enu_from_ned([1.0, 0.0, 0.0, 0.0]))
    np.testing.assert_allclose(C @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(C @ [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], atol=1e-12)
    # MAVLink's roll right wing down and pitch nose up are swarmloc's too (docs/uas.md).
    for roll, pitch, yaw in [(0.3, 0.0, 0.0), (0.0, 0.4, 1.0), (-0.2, 0.1, -2.5)]:
        q = quat_enu_from_ned(QuaternionBase([roll, pitch, yaw]).q)
        np.testing.assert_allclose(ins.euler_from_quat(q), [roll, pitch, yaw_enu_from_ned(yaw)], atol=1e-12)


def test_output_rate_holds_its_rate_under_jitter():
    rate, rng = OutputRate(10.0), np.random.default_rng(0)
    now, sent = 0.0, 0
    while now < 10.0:
        sent += rate.ready(now)
        now += 0.02 + rng.uniform(-0.004, 0.004)  # 50 Hz estimates with jitter
    assert 99 <= sent <= 101
    assert rate.ready(100.0) and not rate.ready(100.05)  # after a gap: one, not a burst
    # A call late by most of a period catches the schedule up, but not back to back (an
    # autopilot keeps one sample per filter period and drops the other).
    rate = OutputRate(30.0)
    assert rate.ready(0.0) and rate.ready(1 / 30 + 0.03)
    assert not rate.ready(2 / 30 + 0.001) and rate.due_in(2 / 30 + 0.001) > 0
    assert rate.ready(1 / 30 + 0.03 + 1 / 60 + 1e-9)


# --------------------------------------------------------------------------- over UDP


@pytest.fixture
def port():
    return udp_port()


def test_round_trip_matches_the_truth(port):
    with FlightController(f"udpin:127.0.0.1:{port}", origin=ORIGIN) as fc, FakeFlightController(port) as sim:
        samples = poll_for(fc, 1.0)
        assert fc.state is Link.ALIVE and fc.fc == (1, 1) and fc.autopilot == mavlink.MAV_AUTOPILOT_PX4
    kinds = {k: [s for s in samples if isinstance(s, k)] for k in (Odometry, Attitude, Imu, GnssFix)}
    assert len(kinds[Odometry]) >= 40 and len(kinds[Attitude]) >= 40 and len(kinds[Imu]) >= 40
    assert len(kinds[GnssFix]) >= 4
    assert not fc.dropped

    for s in kinds[Odometry]:
        x = sim.truth(s.t)
        assert s.source == "ODOMETRY"
        np.testing.assert_allclose(s.position, x["position"], atol=1e-4)
        np.testing.assert_allclose(s.velocity, x["velocity"], atol=1e-4)  # sent in body FRD
        assert np.linalg.norm(ins.attitude_error(truth_q(x), s.q)) < 1e-5
        # Turning counter-clockwise at omega: about ENU up, in whatever body axes that is.
        np.testing.assert_allclose(ins.quat_to_dcm(s.q) @ s.rate, [0, 0, sim.circle.omega], atol=1e-5)
    for s in kinds[Attitude]:
        x = sim.truth(s.t)
        assert np.linalg.norm(ins.attitude_error(truth_q(x), s.q)) < 1e-5
        roll, pitch, yaw = ins.euler_from_quat(s.q)
        assert roll < -0.1 and abs(pitch) < 1e-6  # banked left into a left turn
        assert math.remainder(yaw - x["yaw"], 2 * math.pi) == pytest.approx(0.0, abs=1e-6)
    for s in kinds[Imu]:
        x = sim.truth(s.t)
        C = ins.quat_to_dcm(truth_q(x))
        np.testing.assert_allclose(s.specific_force, C.T @ (x["accel"] + [0, 0, G]), atol=1e-4)
        assert s.specific_force[2] == pytest.approx(G / math.cos(sim.circle.bank), abs=1e-4)  # FLU: up is +
        np.testing.assert_allclose(C @ s.rate, [0, 0, sim.circle.omega], atol=1e-5)
    for s in kinds[GnssFix]:
        x = sim.truth(s.t)
        assert s.fix_type == 3 and s.satellites == 12
        assert np.linalg.norm(s.position - x["position"]) < 0.1
        assert (s.h_acc, s.v_acc, s.hdop, s.vdop) == pytest.approx((1.5, 2.5, 0.8, 1.2))


def test_local_position_fallback_and_first_fix_origin(port):
    with FlightController(f"udpin:127.0.0.1:{port}") as fc, FakeFlightController(port, odometry=False) as sim:
        samples = poll_for(fc, 0.6)
    odo = [s for s in samples if isinstance(s, Odometry)]
    fixes = [s for s in samples if isinstance(s, GnssFix)]
    assert odo and all(s.source == "LOCAL_POSITION_NED" and s.q is None for s in odo)
    for s in odo:
        np.testing.assert_allclose(s.position, sim.truth(s.t)["position"], atol=1e-4)
        np.testing.assert_allclose(s.velocity, sim.truth(s.t)["velocity"], atol=1e-4)
    assert len(fixes) >= 2 and fc.local.origin == pytest.approx((fixes[0].lat, fixes[0].lon, fixes[0].alt))
    first = sim.truth(fixes[0].t)["position"]
    for s in fixes:
        assert np.linalg.norm(s.position - (sim.truth(s.t)["position"] - first)) < 0.1


def test_send_estimate_reaches_the_fc_as_odometry(port):
    p_enu = np.array([12.5, -3.25, 7.0])
    v_enu = np.array([1.5, -0.5, 0.25])
    A = np.array([[0.5, 0.1, -0.2], [0.0, 0.4, 0.3], [0.1, 0.0, 0.9]])
    P = A @ A.T  # non-diagonal, so a transposed or misplaced element shows
    Pv = 0.01 * P
    yaw_enu, yaw_var = 0.7, 0.02
    with FlightController(f"udpin:127.0.0.1:{port}", output_hz=10) as fc, FakeFlightController(port) as sim:
        poll_for(fc, 2.0, until=lambda: fc.alive and fc.attitude is not None)
        sent, start = 0, time.monotonic()
        while time.monotonic() - start < 1.0:
            fc.poll()
            sent += fc.send_estimate(123.456, p_enu, P, v_enu, Pv, yaw=yaw_enu, yaw_var=yaw_var)
            time.sleep(0.005)
        fc.output = "vision_position_estimate"
        time.sleep(0.1)
        assert fc.send_estimate(123.5, p_enu, P)
        time.sleep(0.1)  # the fake's loop reads every 20 ms
        # Our HEARTBEAT goes at 1 Hz; the first may leave before udpin knows the fake's address,
        # so wait for the next (up to 3 s) rather than assume the 1.2 s above held two of them.
        ours = lambda: any(m.get_type() == "HEARTBEAT" and m.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER  # noqa: E731
                           for m in list(sim.received))
        deadline = time.monotonic() + 3.0
        while not ours() and time.monotonic() < deadline:
            fc.poll()
            time.sleep(0.02)
    odometry = [m for m in sim.received if m.get_type() == "ODOMETRY"]
    assert 10 <= sent <= 11 and len(odometry) == sent
    assert any(m.get_type() == "HEARTBEAT" and m.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER for m in sim.received)

    m = odometry[-1]
    assert (m.get_srcSystem(), m.get_srcComponent()) == (1, mavlink.MAV_COMP_ID_ONBOARD_COMPUTER)
    assert m.time_usec == 123_456_000
    assert (m.frame_id, m.child_frame_id) == (mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_BODY_FRD)
    assert m.estimator_type == mavlink.MAV_ESTIMATOR_TYPE_VISION
    assert [m.x, m.y, m.z] == np.float32([-3.25, 12.5, -7.0]).tolist()  # north, east, down

    # The 6x6 pose covariance in NED (x north, y east, z down; roll, pitch, yaw), built by hand.
    N, E, U = 1, 0, 2  # rows of P
    Pn = [[P[N, N], P[N, E], -P[N, U]], [P[E, N], P[E, E], -P[E, U]], [-P[U, N], -P[U, E], P[U, U]]]
    full = np.zeros((6, 6))
    full[:3, :3] = Pn
    full[3, 3] = full[4, 4] = math.nan  # roll and pitch: the FC's own
    full[5, 5] = yaw_var
    expect = [full[i, j] for i in range(6) for j in range(i, 6)]
    np.testing.assert_array_equal(m.pose_covariance, np.float32(expect))
    assert m.pose_covariance[1] == np.float32(P[N, E]) and m.pose_covariance[2] == np.float32(-P[N, U])
    assert m.pose_covariance[6] == np.float32(P[E, E]) and m.pose_covariance[11] == np.float32(P[U, U])
    assert m.pose_covariance[20] == np.float32(yaw_var)

    # Attitude: our yaw as heading from north, the FC's roll and pitch.
    roll, pitch, heading = QuaternionBase(list(m.q)).euler
    assert heading == pytest.approx(math.pi / 2 - yaw_enu, abs=1e-6)
    assert roll == pytest.approx(sim.circle.bank, abs=1e-6) and pitch == pytest.approx(0.0, abs=1e-6)
    # Velocity in body FRD: the message's own attitude turns it back into NED.
    R = QuaternionBase(list(m.q)).dcm
    np.testing.assert_allclose(R @ [m.vx, m.vy, m.vz], [-0.5, 1.5, -0.25], atol=1e-5)
    Pv_body = np.array(m.velocity_covariance)[[0, 1, 2, 6, 7, 11]]
    Pv_ned = R @ np.array([[Pv_body[0], Pv_body[1], Pv_body[2]], [Pv_body[1], Pv_body[3], Pv_body[4]],
                           [Pv_body[2], Pv_body[4], Pv_body[5]]]) @ R.T
    np.testing.assert_allclose(Pv_ned, 0.01 * np.array(Pn), atol=1e-7)

    vpe = [m for m in sim.received if m.get_type() == "VISION_POSITION_ESTIMATE"]
    assert len(vpe) == 1 and [vpe[0].x, vpe[0].y, vpe[0].z] == np.float32([-3.25, 12.5, -7.0]).tolist()
    assert vpe[0].covariance[:3] == np.float32(expect[:3]).tolist() and math.isnan(vpe[0].covariance[20])


@pytest.mark.parametrize("kind", ["udpin", "udpout"])
def test_missing_flight_controller_is_reported_not_raised(port, kind, caplog):
    url = f"{kind}:127.0.0.1:{port}"  # udpout: our heartbeats meet a closed port (ICMP refused)
    with caplog.at_level(logging.INFO, logger="swarmloc.mavlink"), FlightController(url, heartbeat_timeout=0.5) as fc:
        assert fc.poll() == [] and fc.state is Link.WAITING
        assert poll_for(fc, 0.8) == []
        assert fc.state is Link.LOST and not fc.alive
        assert fc.send_estimate(1.0, [0, 0, 0], np.eye(3))  # no one to hear it, and no error
    lost = [r for r in caplog.records if "no heartbeat" in r.getMessage()]
    assert [r.getMessage() for r in lost] == [f"no heartbeat from the flight controller at {url} for 0.5 s"]
    assert lost[0].levelno == logging.WARNING


def test_garbage_is_counted_and_dropped(port):
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    heartbeat = mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0,
                                     mavlink.MAV_STATE_ACTIVE).pack(mav)
    bad_crc = bytearray(heartbeat)
    bad_crc[-1] ^= 0xFF
    rng = np.random.default_rng(1)
    junk = [rng.bytes(200), bytes(range(256)), b"\xfd\x09\x00", bytes(bad_crc), b"\xfe" * 40, heartbeat[:7]]
    with FlightController(f"udpin:127.0.0.1:{port}") as fc, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for chunk in junk:
            s.sendto(chunk, ("127.0.0.1", port))
        assert poll_for(fc, 0.2) == []
        assert fc.dropped["bad-data"] > 0 and fc.state is Link.WAITING
        # One good datagram right after the junk is enough: none of the junk lingers in the parser.
        s.sendto(heartbeat, ("127.0.0.1", port))
        poll_for(fc, 0.5, until=lambda: fc.alive)
        assert fc.alive and fc.fc == (1, 1)
