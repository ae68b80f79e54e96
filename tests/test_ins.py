"""Strapdown INS and its 16-state error model (swarmloc/models/ins.py)."""

import math

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from netsim.world import uas_sensors as uas
from swarmloc.models import ins


def level_hover_imu() -> ins.ImuSample:
    return ins.ImuSample([0.0, 0.0, 0.0], [0.0, 0.0, ins.G0])


def nominal() -> ins.InsState:
    """A generic state: off the origin, moving, banked and pitched, with biases and a clock."""
    return ins.InsState([100.0, -50.0, 30.0], [8.0, -3.0, 1.0], ins.quat_from_euler(0.2, -0.1, 1.0),
                        [1e-3, -2e-3, 5e-4], [0.05, -0.02, 0.03], 12.0, 0.5)


def manoeuvre_imu() -> ins.ImuSample:
    return ins.ImuSample([0.1, -0.2, 0.3], [1.0, -0.5, 10.5])


def test_rotation_helpers_agree_with_scipy():
    rng = np.random.default_rng(0)
    for rv in [*rng.normal(size=(20, 3)), np.zeros(3), [1e-12, 0.0, -2e-12], [0.0, 0.0, 3.1]]:
        rv = np.asarray(rv)
        ref = Rotation.from_rotvec(rv)
        q = ins.quat_from_rotvec(rv)
        x, y, z, w = ref.as_quat()  # scipy is scalar last
        np.testing.assert_allclose(ins.quat_normalize(q), ins.quat_normalize([w, x, y, z]), atol=1e-14)
        np.testing.assert_allclose(ins.quat_to_dcm(q), ref.as_matrix(), atol=1e-14)
        np.testing.assert_allclose(ins.dcm_to_quat(ref.as_matrix()), ins.quat_normalize(q), atol=1e-14)
        np.testing.assert_allclose(ins.rotvec_from_quat(q), ref.as_rotvec(), atol=1e-14)
    # Hamilton product: composing quaternions is multiplying their matrices.
    a, b = ins.quat_from_rotvec([0.3, -1.0, 0.2]), ins.quat_from_rotvec([-0.5, 0.1, 2.0])
    np.testing.assert_allclose(ins.quat_to_dcm(ins.quat_mul(a, b)), ins.quat_to_dcm(a) @ ins.quat_to_dcm(b), atol=1e-14)
    # Euler: C = Rz(yaw) Ry(-pitch) Rx(roll); pitch up raises the nose (body x gains +up).
    roll, pitch, yaw = 0.3, 0.2, -2.0
    q = ins.quat_from_euler(roll, pitch, yaw)
    np.testing.assert_allclose(ins.euler_from_quat(q), (roll, pitch, yaw), atol=1e-14)
    np.testing.assert_allclose(ins.quat_to_dcm(q), Rotation.from_euler("ZYX", [yaw, -pitch, roll]).as_matrix(), atol=1e-14)
    assert ins.quat_to_dcm(q)[2, 0] == pytest.approx(math.sin(pitch))


def test_stationary_level_imu_keeps_position_and_velocity_at_zero_for_60_s():
    """Level, at rest: the accelerometers read +g up (minus gravity), the gyros nothing. The
    rotated specific force cancels gravity exactly, so nothing moves, to the last bit."""
    s = ins.InsState(np.zeros(3), np.zeros(3), [1.0, 0.0, 0.0, 0.0])
    imu = level_hover_imu()
    for _ in range(6000):
        s = ins.mechanize(s, imu, 0.01)
    np.testing.assert_allclose(s.position, 0.0, atol=1e-12)
    np.testing.assert_allclose(s.velocity, 0.0, atol=1e-12)
    np.testing.assert_allclose(s.quaternion, [1.0, 0.0, 0.0, 0.0], atol=1e-15)


def test_stationary_tilted_imu_stays_put_to_rounding():
    """At rest but banked and pitched, f_b = C^T(-g) is irrational in every axis; rounding
    alone moves the vehicle, by nanometres over 60 s."""
    q = ins.quat_from_euler(0.4, -0.3, 2.0)
    imu = ins.ImuSample([0.0, 0.0, 0.0], ins.quat_to_dcm(q).T @ -ins.GRAVITY)
    s = ins.InsState(np.zeros(3), np.zeros(3), q)
    for _ in range(6000):
        s = ins.mechanize(s, imu, 0.01)
    assert np.linalg.norm(s.position) < 1e-9
    assert np.linalg.norm(s.velocity) < 1e-10


def test_constant_yaw_rate_gives_the_exact_yaw_and_no_drift():
    """0.5 rad/s about body z for 10 s is a 5 rad turn (past pi: the wrap is handled). The
    rotation-vector step is exact for a constant rate, so only rounding remains; a level turn
    keeps the specific force on the up axis, so position does not move at all."""
    s = ins.InsState(np.zeros(3), np.zeros(3), [1.0, 0.0, 0.0, 0.0])
    imu = ins.ImuSample([0.0, 0.0, 0.5], [0.0, 0.0, ins.G0])
    for _ in range(1000):
        s = ins.mechanize(s, imu, 0.01)
    roll, pitch, yaw = ins.euler_from_quat(s.quaternion)
    assert yaw == pytest.approx(5.0 - 2 * math.pi, abs=1e-12)
    assert roll == 0.0 and pitch == 0.0
    assert np.linalg.norm(ins.attitude_error(ins.quat_from_euler(0.0, 0.0, 5.0), s.quaternion)) < 1e-12
    np.testing.assert_allclose(s.position, 0.0, atol=1e-12)
    np.testing.assert_allclose(s.velocity, 0.0, atol=1e-12)


def _run_exact(traj, dt, T):
    n = int(round(T / dt))
    imu = uas.ImuSimulator(traj, dt, ins.ImuSpec.perfect(), rng=0).run(n)
    t0 = traj.truth(0.0)
    s = ins.InsState(t0.position, t0.velocity, t0.quaternion)
    perr = 0.0
    for k in range(n):
        s = ins.mechanize(s, imu.sample(k), dt)
        perr = max(perr, float(np.linalg.norm(s.position - traj.position((k + 1) * dt))))
    end = traj.truth(T)
    return perr, np.linalg.norm(s.velocity - end.velocity), np.linalg.norm(ins.attitude_error(end.quaternion, s.quaternion))


@pytest.mark.parametrize("traj", [uas.figure8(), uas.random_smooth(4)], ids=["figure8", "random"])
def test_exact_imu_of_a_trajectory_tracks_it_for_30_s(traj):
    """Perfect IMU at 100 Hz over a banking figure-8 (up to 13 deg of bank, 0.33 rad/s) or a
    random loiter: after 30 s the INS is within 2 mm, 0.1 mm/s and 0.1 urad of the truth.

    What is left is the integration scheme's own O(dt^2) error: the trapezoidal position rule
    (T dt^2/12 max|jerk| = 0.1 mm here), and the attitude step that takes the interval's mean
    rate as constant (3e-8 rad at 30 s), whose tilt error g dtheta integrates into velocity and
    twice into position (about 0.5 mm). The bound keeps a factor of 4 over what it measures."""
    perr, verr, aerr = _run_exact(traj, 0.01, 30.0)
    assert perr < 2e-3
    assert verr < 1e-4
    assert aerr < 1e-7


def test_mechanization_error_is_second_order():
    """Halving dt quarters the tracking error: the bound above is the scheme, not a bug."""
    traj = uas.figure8()
    coarse = _run_exact(traj, 0.02, 30.0)
    fine = _run_exact(traj, 0.01, 30.0)
    for c, f in zip(coarse, fine):
        assert 3.6 < c / f < 4.4


def _finite_difference_jacobian(x, imu, dt, bias_tau=math.inf, eps=1e-6):
    """d(mechanize(x (+) dx) (-) mechanize(x)) / d(dx) by central differences."""
    base = ins.mechanize(x, imu, dt, bias_tau)
    J = np.zeros((ins.ERROR_DIM, ins.ERROR_DIM))
    for i in range(ins.ERROR_DIM):
        e = np.zeros(ins.ERROR_DIM)
        e[i] = eps
        plus = ins.mechanize(ins.inject(x, e), imu, dt, bias_tau)
        minus = ins.mechanize(ins.inject(x, -e), imu, dt, bias_tau)
        J[:, i] = (ins.state_error(plus, base) - ins.state_error(minus, base)) / (2 * eps)
    return J


@pytest.mark.parametrize("tau", [math.inf, 300.0], ids=["random-walk", "gauss-markov"])
def test_F_is_the_first_order_linearization_of_mechanize(tau):
    """F = I + A dt agrees with the finite-difference Jacobian of mechanize up to O(dt^2).

    First order leaves out the dt^2/2 terms: A^2, e.g. the tilt error reaching position,
    -[f x] dt^2/2 with |f| = 10.5 m/s^2, and the change of A over the step (the body turns at
    0.37 rad/s). Their largest entry is about 5 dt^2, hence the bound 8 dt^2; halving dt must
    quarter the residual, which a wrong sign or a missing block (an O(dt) residual) cannot do."""
    x, imu, spec = nominal(), manoeuvre_imu(), ins.ImuSpec(bias_tau=tau)
    residual = {}
    for dt in (0.01, 0.005):
        F, _ = ins.error_dynamics(x, imu, dt, spec)
        residual[dt] = np.abs(_finite_difference_jacobian(x, imu, dt, tau) - F).max()
        assert residual[dt] < 8 * dt**2
    assert 3.6 < residual[0.01] / residual[0.005] < 4.4


def test_Q_is_the_noise_of_the_first_order_transition():
    """Q against Van Loan's exact discretisation of the continuous model: equal to first order
    (correlation-normalised difference under 0.5% at 10 ms, halving with dt), symmetric, PSD."""
    x, imu, spec = nominal(), manoeuvre_imu(), ins.ImuSpec()
    A, W = ins.error_jacobian(x, imu, spec), ins.noise_intensity(spec)
    err = {}
    for dt in (0.01, 0.005):
        _, Q = ins.error_dynamics(x, imu, dt, spec)
        E = expm(np.block([[-A, W], [np.zeros_like(A), A.T]]) * dt)
        Phi = E[16:, 16:].T
        Q_exact = Phi @ E[:16, 16:]
        d = np.sqrt(np.diag(Q_exact))
        err[dt] = (np.abs(Q - Q_exact) / np.outer(d, d)).max()
        np.testing.assert_array_equal(Q, Q.T)
        assert np.linalg.eigvalsh(Q).min() > -1e-12 * np.abs(Q).max()
    assert err[0.01] < 5e-3
    assert 1.8 < err[0.01] / err[0.005] < 2.2
    # Velocity noise reaches position through the dt^3/3 term: q_a dt^3 / 3.
    _, Q = ins.error_dynamics(x, imu, 0.1, spec)
    assert Q[0, 0] == pytest.approx(spec.accel_vrw**2 * 0.1**3 / 3, rel=1e-3)


def test_error_covariance_matches_monte_carlo():
    """The propagated P = F P F^T + Q is the covariance of real errors: 400 truths fed the
    IMU minus white noise, with random-walk biases and clock, against one nominal run fed the
    measured IMU. Noise is 30-100x the defaults so the errors are far above rounding yet linear."""
    spec = ins.ImuSpec(gyro_arw=3e-3, accel_vrw=0.05, gyro_bias_rw=1e-3, accel_bias_rw=1e-2)
    clock = ins.ClockSpec(filter_psd=2.0)
    dt, steps, runs = 0.05, 40, 400
    rng = np.random.default_rng(11)
    imu = manoeuvre_imu()
    est = [nominal()]
    P = np.zeros((16, 16))
    for _ in range(steps):
        F, Q = ins.error_dynamics(est[-1], imu, dt, spec, clock)
        P = F @ P @ F.T + Q
        est.append(ins.mechanize(est[-1], imu, dt))
    errors = np.empty((runs, 16))
    for r in range(runs):
        truth = nominal()
        for _ in range(steps):
            z = rng.standard_normal(13)
            noisy = ins.ImuSample(imu.gyro - z[0:3] * spec.gyro_arw / math.sqrt(dt),
                                  imu.accel - z[3:6] * spec.accel_vrw / math.sqrt(dt))
            truth = ins.mechanize(truth, noisy, dt)
            truth.gyro_bias += z[6:9] * spec.gyro_bias_rw * math.sqrt(dt)
            truth.accel_bias += z[9:12] * spec.accel_bias_rw * math.sqrt(dt)
            truth.clock_bias += z[12] * math.sqrt(clock.filter_psd * dt)
        errors[r] = ins.state_error(truth, est[-1])
    sample = errors.T @ errors / runs
    # A sample variance of 400 draws has a relative std of 7%: these bounds are about 4 sigma.
    ratio = np.diag(sample) / np.diag(P)
    assert np.all((ratio > 0.72) & (ratio < 1.33)), ratio
    # The couplings, as correlations: position-velocity (0.87), velocity-tilt (+-0.48, the sign
    # of -[f x]), position-tilt (0.30), tilt-gyro bias. A correlation from 400 draws has a std
    # of (1 - rho^2)/20 at most 0.05: the bound is 3 of those.
    corr_model = P / np.sqrt(np.outer(np.diag(P), np.diag(P)))
    corr_sample = sample / np.sqrt(np.outer(np.diag(sample), np.diag(sample)))
    for i, j in [(0, 3), (1, 4), (2, 5), (3, 7), (4, 6), (0, 7), (6, 9)]:
        assert abs(corr_sample[i, j] - corr_model[i, j]) < 0.15, (i, j, corr_sample[i, j], corr_model[i, j])


def test_inject_zero_is_identity_and_inverts_state_error():
    x = nominal()
    y = ins.inject(x, np.zeros(16))
    for name in ("position", "velocity", "quaternion", "gyro_bias", "accel_bias"):
        np.testing.assert_array_equal(getattr(y, name), getattr(x, name))
    assert (y.clock_bias, y.clock_drift) == (x.clock_bias, x.clock_drift)
    dx = np.random.default_rng(2).normal(size=16) * 0.1
    z = ins.inject(x, dx)
    np.testing.assert_allclose(ins.state_error(z, x), dx, atol=1e-13)
    # Attitude error is in the navigation frame: the correction premultiplies.
    np.testing.assert_allclose(z.dcm, ins.quat_to_dcm(ins.quat_from_rotvec(dx[ins.ATT])) @ x.dcm, atol=1e-14)


def test_biases_are_removed_before_integration():
    """An IMU reading bias + truth, with the bias in the state, mechanizes like a perfect one."""
    bg, ba = np.array([1e-3, -2e-3, 4e-3]), np.array([0.1, -0.2, 0.05])
    clean = ins.InsState(np.zeros(3), [5.0, 0.0, 0.0], ins.quat_from_euler(0.1, 0.0, 0.3))
    biased = ins.InsState(clean.position, clean.velocity, clean.quaternion, bg, ba)
    imu = manoeuvre_imu()
    a = ins.mechanize(clean, imu, 0.01)
    b = ins.mechanize(biased, ins.ImuSample(imu.gyro + bg, imu.accel + ba), 0.01)
    np.testing.assert_allclose(b.position, a.position, atol=1e-14)
    np.testing.assert_allclose(b.velocity, a.velocity, atol=1e-14)
    np.testing.assert_allclose(b.quaternion, a.quaternion, atol=1e-15)


def test_imu_spec_datasheet_units():
    """The defaults are the datasheet numbers the docstring quotes."""
    assert ins.ImuSpec.from_datasheet(0.3, 0.06, 10.0, 100.0, 100.0, 3.0) == ins.ImuSpec()
    assert ins.ImuSpec().gyro_arw == pytest.approx(8.7266e-5, rel=1e-4)
    assert ins.ImuSpec().accel_bias_sigma0 == pytest.approx(0.0294, rel=1e-3)
