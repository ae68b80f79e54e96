"""UAS world truth and sensors (netsim/world/uas_sensors.py): orbits, visibility, pseudoranges, IMU, paths."""

import math

import numpy as np
import pytest

from netsim.world import uas_sensors as uas
from swarmloc.models import ins

DAY = np.arange(0.0, 86400.0, 600.0)


def test_satellite_orbits_have_gps_radius_rate_and_inclination():
    c = uas.GnssConstellation()
    assert c.n == 30
    n_expected = math.sqrt(uas.MU_EARTH / uas.GPS_ORBIT_RADIUS**3)
    assert n_expected == pytest.approx(1.4586e-4, rel=1e-4)
    assert 2 * math.pi / n_expected == pytest.approx(43077, abs=1)  # 11 h 58 min
    for t in (0.0, 5000.0, 40000.0):
        r0, r1 = c.eci(t), c.eci(t + 60.0)
        np.testing.assert_allclose(np.linalg.norm(r0, axis=1), uas.GPS_ORBIT_RADIUS, rtol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(c.ecef(t), axis=1), uas.GPS_ORBIT_RADIUS, rtol=1e-12)
        cosang = np.sum(r0 * r1, axis=1) / uas.GPS_ORBIT_RADIUS**2
        np.testing.assert_allclose(np.arccos(cosang) / 60.0, n_expected, rtol=1e-6)
        h = np.cross(r0, r1)  # orbit normal
        np.testing.assert_allclose(np.degrees(np.arccos(h[:, 2] / np.linalg.norm(h, axis=1))), 55.0, atol=1e-9)
    # In ECEF the sky turns with the Earth: a polar-axis vector is unmoved, the rest turn by
    # OMEGA_EARTH t against inertial space.
    t = 3600.0
    eci, ecef = c.eci(t), c.ecef(t)
    np.testing.assert_allclose(ecef[:, 2], eci[:, 2])
    turn = np.arctan2(eci[:, 1], eci[:, 0]) - np.arctan2(ecef[:, 1], ecef[:, 0])
    np.testing.assert_allclose(np.mod(turn, 2 * math.pi), uas.OMEGA_EARTH * t, atol=1e-12)
    # Six planes 60 deg apart in right ascension, five satellites each.
    np.testing.assert_allclose(np.unique(np.round(np.degrees(c.raan), 9)), np.arange(0, 360, 60))


def test_site_frame_is_the_ellipsoid_tangent_plane():
    site = uas.Site()
    r = site.ecef()
    R = site.enu_rotation()
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)
    assert np.linalg.det(R) == pytest.approx(1.0)
    b2 = (uas.WGS84_A * (1 - uas.WGS84_F)) ** 2
    normal = np.array([r[0] / uas.WGS84_A**2, r[1] / uas.WGS84_A**2, r[2] / b2])
    np.testing.assert_allclose(R[2], normal / np.linalg.norm(normal), atol=1e-12)  # up is the ellipsoid normal
    assert R[1] @ [0.0, 0.0, 1.0] > 0  # north points to the north pole's side
    assert 6.369e6 < np.linalg.norm(r) < 6.372e6


@pytest.mark.parametrize("site", [uas.Site(), uas.Site(0.0, 0.0, 0.0), uas.Site(60.0, 10.0, 0.0), uas.Site(45.0, -100.0, 300.0)],
                         ids=["melbourne", "equator", "60N", "45N"])
def test_visible_satellites_are_above_the_mask_and_plentiful(site):
    c = uas.GnssConstellation(site=site)
    p = np.array([120.0, -40.0, 80.0])
    counts = []
    for t in DAY:
        ids, sats, el = c.visible(t, p)
        d = sats - p
        np.testing.assert_allclose(el, np.arcsin(d[:, 2] / np.linalg.norm(d, axis=1)))
        assert np.all(np.degrees(el) >= 10.0)
        # Slant range between zenith (a - |r_site|) and the 10 deg mask's 24 700 km.
        assert np.all((np.linalg.norm(d, axis=1) > 20.1e6) & (np.linalg.norm(d, axis=1) < 24.75e6))
        counts.append(len(ids))
        hidden = np.setdiff1d(c.ids, ids)
        dh = c.enu(t)[hidden] - p
        assert np.all(np.degrees(np.arcsin(dh[:, 2] / np.linalg.norm(dh, axis=1))) < 10.0)
    counts = np.array(counts)
    assert counts.min() >= 6 and counts.mean() >= 8, counts
    # A higher mask never shows more.
    assert all(len(c.visible(t, p, 30.0)[0]) <= len(c.visible(t, p, 10.0)[0]) for t in DAY[::12])


def test_pseudorange_minus_range_and_clock_has_the_configured_noise():
    """rho - |s - p| - clock bias over 1500 epochs (about 13 000 pseudoranges) from a flying
    UAS: the std of the residual is the configured 1.5 m within 3% (its sampling std is 0.6%)
    and its mean is zero within 4 standard errors."""
    c = uas.GnssConstellation(epoch=20000.0)
    rx = uas.GnssReceiver(c, rng=5, sigma=1.5)
    traj = uas.figure8()
    res, biases = [], []
    for t in np.arange(1500) * 1.0:
        p = traj.position(t)
        obs = rx.measure(t, p)
        assert obs.sigma == 1.5 and obs.t == t
        np.testing.assert_array_equal(obs.sat_positions, c.enu(t)[obs.sat_ids])
        res.append(obs.pseudoranges - np.linalg.norm(obs.sat_positions - p, axis=1) - rx.clock.bias)
        biases.append(rx.clock.bias)
    res = np.concatenate(res)
    assert len(res) > 10000
    assert np.std(res) == pytest.approx(1.5, rel=0.03)
    assert abs(np.mean(res)) < 4 * 1.5 / math.sqrt(len(res))
    assert np.ptp(biases) > 1.0  # the clock really wanders (and is not noise)


def test_receiver_clock_is_the_two_state_random_walk():
    quiet = uas.ReceiverClock(ins.ClockSpec(0.0, 0.0), bias=10.0, drift=2.0)
    assert quiet.advance(5.0) == pytest.approx(20.0)
    with pytest.raises(ValueError):
        quiet.advance(4.0)
    # 4000 clocks over T = 50 s: var(drift) = qd T, var(bias) = qb T + qd T^3/3 (8% bounds, 4.5 sigma).
    spec, T = ins.ClockSpec(), 50.0
    rng = np.random.default_rng(1)
    end = np.array([(lambda k: (k.advance(T), k.drift))(uas.ReceiverClock(spec, rng)) for _ in range(4000)])
    assert np.var(end[:, 1]) == pytest.approx(spec.drift_psd * T, rel=0.08)
    assert np.var(end[:, 0]) == pytest.approx(spec.bias_psd * T + spec.drift_psd * T**3 / 3, rel=0.08)


def test_level_hover_imu_reads_minus_gravity_on_body_z_plus_white_noise():
    """FLU body, ENU world: hovering level, the accelerometers read f = C^T(a - g) = -g, that
    is +9.80665 m/s^2 on the up axis; the gyros read zero. Noise: density / sqrt(dt)."""
    hover = uas.Hover((10.0, 20.0, 50.0), yaw=0.7)
    np.testing.assert_array_equal(hover.specific_force(3.0), [0.0, 0.0, ins.G0])
    spec = ins.ImuSpec(gyro_bias_rw=0.0, accel_bias_rw=0.0, gyro_bias_sigma0=0.0, accel_bias_sigma0=0.0)
    dt, n = 0.01, 20000
    rec = uas.ImuSimulator(hover, dt, spec, rng=3).run(n)
    sg, sa = spec.gyro_arw / math.sqrt(dt), spec.accel_vrw / math.sqrt(dt)
    np.testing.assert_allclose(rec.accel.mean(axis=0), [0.0, 0.0, ins.G0], atol=4 * sa / math.sqrt(n))
    np.testing.assert_allclose(rec.gyro.mean(axis=0), 0.0, atol=4 * sg / math.sqrt(n))
    np.testing.assert_allclose(rec.accel.std(axis=0), sa, rtol=0.03)
    np.testing.assert_allclose(rec.gyro.std(axis=0), sg, rtol=0.03)


def test_imu_biases_random_walk_and_gauss_markov():
    hover = uas.Hover()
    dt = 0.1
    rw = ins.ImuSpec(gyro_arw=0.0, accel_vrw=0.0)
    sim = uas.ImuSimulator(hover, dt, rw, rng=8)
    rec = sim.run(20000)
    # The output is the truth plus the bias in force; the bias steps with std rw sqrt(dt).
    np.testing.assert_allclose(rec.gyro, rec.gyro_bias, atol=1e-15)
    np.testing.assert_allclose(rec.accel - [0.0, 0.0, ins.G0], rec.accel_bias, atol=1e-14)
    assert np.std(np.diff(rec.gyro_bias, axis=0)) == pytest.approx(rw.gyro_bias_rw * math.sqrt(dt), rel=0.03)
    assert np.std(np.diff(rec.accel_bias, axis=0)) == pytest.approx(rw.accel_bias_rw * math.sqrt(dt), rel=0.03)
    # Gauss-Markov: b' = phi b + w with phi = exp(-dt/tau) (the regression slope tells it from a
    # random walk's 1 at 7 sigma) and var(w) = rw^2 tau/2 (1 - phi^2), the exact discretisation.
    tau = 20.0
    gm = ins.ImuSpec(gyro_arw=0.0, accel_vrw=0.0, bias_tau=tau, gyro_bias_rw=1e-3)
    b = uas.ImuSimulator(hover, dt, gm, rng=9, gyro_bias=[0.0, 0.0, 0.0]).run(20000).gyro_bias
    phi = math.exp(-dt / tau)
    slope = np.sum(b[1:] * b[:-1]) / np.sum(b[:-1] ** 2)
    assert slope == pytest.approx(phi, abs=2e-3)
    assert np.std(b[1:] - phi * b[:-1]) == pytest.approx(1e-3 * math.sqrt(tau / 2 * (1 - phi**2)), rel=0.02)
    # run(n) and n x step() draw the same numbers.
    a, b = uas.ImuSimulator(uas.figure8(), dt, rng=4), uas.ImuSimulator(uas.figure8(), dt, rng=4)
    rec = a.run(5)
    for k in range(5):
        s = b.step()
        np.testing.assert_allclose(s.gyro, rec.gyro[k], rtol=1e-15)
        np.testing.assert_allclose(s.accel, rec.accel[k], rtol=1e-15)


TRAJECTORIES = {
    "figure8": uas.figure8(climb=5.0),
    "circle": uas.circle(radius=60.0, speed=12.0, clockwise=True),
    "random": uas.random_smooth(7),
    "level-figure8": uas.figure8(heading=0.5, attitude="level"),
}


@pytest.mark.parametrize("name", TRAJECTORIES)
def test_trajectory_derivatives_are_consistent(name):
    """Central differences of position, velocity, acceleration and attitude reproduce velocity,
    acceleration, jerk and the body rate (h = 1e-3 s: truncation h^2/6 |p''''| < 1e-7)."""
    traj = TRAJECTORIES[name]
    t = np.linspace(0.0, 90.0, 37)
    h = 1e-3
    for lower, upper in [(0, 1), (1, 2), (2, 3)]:
        num = (traj.derivative(t + h, lower) - traj.derivative(t - h, lower)) / (2 * h)
        np.testing.assert_allclose(num, traj.derivative(t, upper), atol=1e-6)
    C, Cp, Cm = traj.dcm(t), traj.dcm(t + h), traj.dcm(t - h)
    Omega = np.einsum("kji,kjl->kil", C, (Cp - Cm) / (2 * h))  # C^T C' = [omega x]
    omega = traj.angular_rate(t)
    np.testing.assert_allclose(np.stack([Omega[:, 2, 1], Omega[:, 0, 2], Omega[:, 1, 0]], axis=1), omega, atol=1e-6)
    np.testing.assert_allclose(Omega + np.transpose(Omega, (0, 2, 1)), 0.0, atol=1e-6)
    # A proper rotation whose x axis is along the velocity.
    np.testing.assert_allclose(np.einsum("kji,kjl->kil", C, C), np.broadcast_to(np.eye(3), C.shape), atol=1e-14)
    v = traj.velocity(t)
    np.testing.assert_allclose(C[:, :, 0], v / np.linalg.norm(v, axis=1, keepdims=True), atol=1e-14)
    f = traj.specific_force(t)
    if traj.attitude_mode == "coordinated":
        np.testing.assert_allclose(f[:, 1], 0.0, atol=1e-12)  # no lateral force: coordinated
    else:
        assert np.allclose([ins.euler_from_quat(traj.quaternion(tk))[0] for tk in t], 0.0, atol=1e-12)


def test_coordinated_circle_banks_and_turns_at_the_textbook_rates():
    v, R = 12.0, 60.0
    traj = uas.circle(radius=R, speed=v)
    for t in (0.0, 7.0, 31.0):
        roll, pitch, yaw = ins.euler_from_quat(traj.quaternion(t))
        # Counter-clockwise is a left turn: left wing down, negative roll.
        assert roll == pytest.approx(-math.atan(v**2 / (R * ins.G0)), abs=1e-12)
        assert pitch == pytest.approx(0.0, abs=1e-12)
        p = traj.position(t)
        assert yaw == pytest.approx(math.atan2(p[0], -p[1]), abs=1e-12)  # tangent of a CCW circle
        # The turn rate v/R about the vertical is, in the banked body, split over y and z.
        np.testing.assert_allclose(traj.dcm(t) @ traj.angular_rate(t), [0.0, 0.0, v / R], atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(traj.specific_force(t)), math.hypot(ins.G0, v**2 / R), rtol=1e-12)


def test_truth_bundle_and_mean_imu():
    traj = uas.figure8()
    s = traj.truth(12.5)
    np.testing.assert_allclose(ins.quat_to_dcm(s.quaternion), traj.dcm(12.5), atol=1e-14)
    np.testing.assert_allclose(s.specific_force, traj.specific_force(12.5), atol=1e-14)
    # The IMU interval mean is the quadrature of the rate: for a short interval, the midpoint value.
    gyro, accel = uas.mean_imu(traj, 12.5, 1e-3)
    np.testing.assert_allclose(gyro, traj.angular_rate(12.5 + 5e-4), atol=1e-9)
    np.testing.assert_allclose(accel, traj.specific_force(12.5 + 5e-4), atol=1e-8)
    # Over a long interval it integrates: the mean of a circle's constant rate is that rate.
    c = uas.circle()
    np.testing.assert_allclose(uas.mean_imu(c, 0.0, 2.0)[0], c.angular_rate(1.0), atol=1e-12)


def test_random_trajectory_speed_stays_in_its_band():
    for seed in range(5):
        traj = uas.random_smooth(seed, speed=12.0, wander=0.4)
        speed = np.linalg.norm(traj.velocity(np.linspace(0.0, 600.0, 6001)), axis=1)
        assert speed.min() >= 0.6 * 12.0 - 1e-9 and speed.max() <= 1.4 * 12.0 + 1e-9
        assert np.linalg.norm(traj.position(np.linspace(0.0, 600.0, 601))[:, :2], axis=1).max() < 200.0


def test_relative_measurements():
    rng = np.random.default_rng(0)
    pi, pj = np.array([10.0, 0.0, 50.0]), np.array([0.0, 5.0, 45.0])
    rel = np.array([uas.relative_position(pi, pj, 0.05, rng) for _ in range(4000)])
    np.testing.assert_allclose(rel.mean(axis=0), pi - pj, atol=4 * 0.05 / math.sqrt(4000))  # i relative to j
    np.testing.assert_allclose(rel.std(axis=0), 0.05, rtol=0.05)
    assert uas.measure_range(pi, pj, 0.0, rng) == pytest.approx(math.sqrt(150.0))
    P = np.array([[0.0, 0.0, 50.0], [30.0, 0.0, 50.0], [0.0, 40.0, 50.0], [500.0, 0.0, 50.0]])
    exact = uas.inter_uav_ranges(P, 0.0, rng, max_range=100.0)
    assert exact == [(0, 1, 30.0), (0, 2, 40.0), (1, 2, 50.0)]
    noisy = np.array([d - 30.0 for _ in range(3000) for i, j, d in uas.inter_uav_ranges(P[:2], 0.02, rng)])
    assert np.std(noisy) == pytest.approx(0.02, rel=0.05)
