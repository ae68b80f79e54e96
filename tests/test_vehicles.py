"""Vehicle models, relative-position measurement and tracking controllers (swarmloc/models/vehicles.py)."""

import math

import numpy as np
import pytest
from scipy.linalg import expm

from swarmloc.models import vehicles as V

DT = 0.02
QUAD = V.Quadrotor()
GROUND = V.GroundRobot()


def random_state(model, rng):
    if isinstance(model, V.Quadrotor):
        q = rng.normal(size=4)
        return np.concatenate([rng.normal(size=3) * 3, q / np.linalg.norm(q), rng.normal(size=3), rng.normal(size=3)])
    return np.concatenate([rng.normal(size=3) * 3, [rng.uniform(-math.pi, math.pi)], rng.normal(size=3)])


def random_input(model, rng):
    return rng.normal(size=model.input_dim) * (np.array([10.0, 0.1, 0.1, 0.05]) if model.input_dim == 4 else [2.0, 0.05])


def num_jac(fun, x, eps=1e-6):
    x = np.asarray(x, float)
    cols = []
    for i in range(x.size):
        dx = np.zeros_like(x)
        dx[i] = eps
        cols.append((fun(x + dx) - fun(x - dx)) / (2 * eps))
    return np.column_stack(cols)


def close(a, b, rtol=1e-6):
    scale = max(1.0, float(np.abs(b).max()))
    np.testing.assert_allclose(a, b, rtol=0, atol=rtol * scale)


@pytest.mark.parametrize("model", [QUAD, GROUND], ids=lambda m: m.name)
def test_jacobian_input_matrix_and_transition_match_finite_differences(model):
    rng = np.random.default_rng(1)
    for _ in range(5):
        x, u = random_state(model, rng), random_input(model, rng)
        close(model.jacobian(x, u), num_jac(lambda y: model.xdot(y, u), x))
        close(model.g(x), num_jac(lambda w: model.xdot(x, w), u))
        close(model.noise_input(x), model.g(x))
        close(model.xdot(x, u), model.f(x) + model.g(x) @ u)
        x1, F = model.transition(x, u, DT)
        np.testing.assert_allclose(F, np.eye(model.state_dim) + DT * model.jacobian(x, u), atol=1e-15)
        np.testing.assert_allclose(x1, model.step(x, u, DT))
    assert model.f(x).shape == (model.state_dim,)
    assert model.g(x).shape == (model.state_dim, model.input_dim)


@pytest.mark.parametrize("base", [QUAD, GROUND], ids=lambda m: m.name)
@pytest.mark.parametrize("target", [QUAD, GROUND], ids=lambda m: m.name)
def test_relpos_jacobian_matches_finite_differences(base, target):
    rng = np.random.default_rng(2)
    for _ in range(5):
        xb, xt = random_state(base, rng), random_state(target, rng)
        Hb, Ht = V.relpos_jacobian(base, xb, target, xt)
        assert Hb.shape == (3, base.state_dim) and Ht.shape == (3, target.state_dim)
        close(Hb, num_jac(lambda y: V.relpos(base, y, target, xt), xb))
        close(Ht, num_jac(lambda y: V.relpos(base, xb, target, y), xt))


@pytest.mark.parametrize("base", [QUAD, GROUND], ids=lambda m: m.name)
def test_relpos_is_in_the_base_body_frame(base):
    # base faces north (yaw 90 deg); a target 2 m due east is on its right: -y in FLU
    xb = base.initial_state([1.0, 1.0, 0.5], math.pi / 2)
    xt = GROUND.initial_state([3.0, 1.0, 0.5])
    np.testing.assert_allclose(V.relpos(base, xb, GROUND, xt), [0.0, -2.0, 0.0], atol=1e-12)
    xt = QUAD.initial_state([1.0, 4.0, 1.5])  # 3 m north, 1 m up: straight ahead and above
    np.testing.assert_allclose(V.relpos(base, xb, QUAD, xt), [3.0, 0.0, 1.0], atol=1e-12)


@pytest.mark.parametrize("model", [QUAD, GROUND], ids=lambda m: m.name)
def test_orientation_and_its_jacobian(model):
    rng = np.random.default_rng(3)
    x = random_state(model, rng)
    H = model.orientation_jacobian(x)
    assert H.shape == (model.orientation_dim, model.state_dim)
    close(H, num_jac(model.orientation, x))
    x0 = model.initial_state([1.0, 2.0, 3.0], 0.7)
    assert model.yaw(x0) == pytest.approx(0.7)
    np.testing.assert_allclose(model.rotation(x0), V.rot_z(0.7), atol=1e-15)
    np.testing.assert_allclose(model.position(x0), [1.0, 2.0, 3.0])


def test_quadrotor_hovers_in_place():
    x0 = QUAD.initial_state([1.0, -2.0, 1.5], 0.4)
    x = x0
    for _ in range(500):
        x = QUAD.step(x, QUAD.hover_input(x), DT)
    assert np.abs(x[:3] - x0[:3]).max() < 1e-9
    assert np.abs(x[7:]).max() < 1e-9


def test_quaternion_kinematics_match_body_rate_rotation():
    # spherical inertia: any constant body rate stays constant, so R(t) = R0 expm(S(w) t)
    model = V.Quadrotor(V.QuadrotorParams(inertia=(0.01, 0.01, 0.01)))
    rng = np.random.default_rng(4)
    x = random_state(model, rng)
    x[10:13] = [0.3, -0.5, 0.8]
    R0 = model.rotation(x)
    u = np.zeros(4)
    for _ in range(200):
        x = model.step(x, u, DT)
        assert abs(np.linalg.norm(x[3:7]) - 1.0) < 1e-12
    np.testing.assert_allclose(model.rotation(x), R0 @ expm(V.skew([0.3, -0.5, 0.8]) * 4.0), atol=1e-8)


def test_constant_yaw_rate_turns_the_quaternion_about_z():
    x = QUAD.initial_state([0.0, 0.0, 1.0])
    x[12] = 0.5
    for _ in range(100):
        x = QUAD.step(x, QUAD.hover_input(x), DT, substeps=2)
    np.testing.assert_allclose(x[3:7], [math.cos(0.5), 0.0, 0.0, math.sin(0.5)], atol=1e-10)
    assert QUAD.yaw(x) == pytest.approx(1.0, abs=1e-10)
    np.testing.assert_allclose(x[:3], [0.0, 0.0, 1.0], atol=1e-9)


def test_ground_robot_coasts_straight():
    x = GROUND.initial_state([1.0, 2.0, 0.0], 0.6)
    x[4] = 1.0
    for _ in range(250):
        x = GROUND.step(x, GROUND.hover_input(), DT)
    np.testing.assert_allclose(x[:3], [1.0 + 5 * math.cos(0.6), 2.0 + 5 * math.sin(0.6), 0.0], atol=1e-9)
    assert x[3] == pytest.approx(0.6) and x[4] == pytest.approx(1.0) and x[6] == 0.0


def fly(model, reference, seconds, x0=None):
    """Closed loop with perfect state feedback: position and yaw errors at each sample."""
    ctl = V.controller_for(model, reference)
    x = reference.start_state(model) if x0 is None else x0
    pos, yaw = [], []
    for k in range(int(round(seconds / DT))):
        x = model.step(x, ctl.command(x, k * DT, DT if k else 0.0), DT)
        t = (k + 1) * DT
        pos.append(np.linalg.norm(x[:3] - reference.derivatives(t, 0)[0]))
        yaw.append(abs(V.wrap_yaw(model.yaw(x) - reference.yaw_derivatives(t)[0])))
    return np.array(pos), np.array(yaw)


def test_quadrotor_controller_recovers_hover():
    ref = V.CircleReference(center=(0.0, 0.0, 1.5), radius=0.0, period=20.0)
    x0 = QUAD.initial_state([0.3, 0.3, 1.5 - math.sqrt(0.5**2 - 0.18)], math.radians(10))
    pos, yaw = fly(QUAD, ref, 10.0, x0)
    assert pos[0] > 0.45
    assert pos[-1] < 0.02 and yaw[-1] < 0.02


def test_quadrotor_controller_tracks_a_circle():
    ref = V.CircleReference(center=(0.0, 0.0, 1.5), radius=1.5, period=20.0)
    pos, yaw = fly(QUAD, ref, 25.0)
    tail = pos[int(15 / DT):]
    assert tail.max() < 0.05
    assert yaw[int(15 / DT):].max() < 0.02


def test_ground_controller_tracks_a_circle():
    ref = V.CircleReference(center=(0.0, 0.0, 0.0), radius=1.5, period=30.0)
    pos, _ = fly(GROUND, ref, 25.0)
    assert pos[int(15 / DT):].max() < 0.05


def test_controllers_stay_finite_on_a_wild_estimate():
    rng = np.random.default_rng(5)
    ref = V.CircleReference(center=(0.0, 0.0, 1.5), radius=1.5, period=20.0)
    for model in (QUAD, GROUND):
        ctl = V.controller_for(model, ref)
        for k in range(50):
            x = random_state(model, rng) * 3
            x[:3] += 100.0
            if model is QUAD:
                x[3:7] /= np.linalg.norm(x[3:7])
            u = ctl.command(x, k * DT, DT)
            assert u.shape == (model.input_dim,) and np.all(np.isfinite(u))
            if model is QUAD:
                assert 0.0 <= u[0] <= 4 * model.params.mass * V.GRAVITY
                assert np.all(np.abs(u[1:]) <= ctl.tau_max)


def test_reference_derivatives_are_consistent():
    ref = V.CircleReference(center=(1.0, 2.0, 1.5), radius=1.5, period=-20.0, phase=0.3)
    d = ref.derivatives(2.0)
    for k in range(4):
        fd = (ref.derivatives(2.0 + 1e-6)[k] - ref.derivatives(2.0 - 1e-6)[k]) / 2e-6
        np.testing.assert_allclose(d[k + 1], fd, atol=1e-6)
    psi, psid, _ = ref.yaw_derivatives(2.0)
    assert psi == pytest.approx(math.atan2(d[1][1], d[1][0]))
    assert psid == pytest.approx(ref.rate)
    x = ref.start_state(QUAD)
    np.testing.assert_allclose(x[:3], ref.derivatives(0.0, 0)[0])
    assert np.all(x[7:] == 0.0)
    assert QUAD.yaw(x) == pytest.approx(ref.yaw_derivatives(0.0)[0])
    assert set(V.MODELS) == {"quadrotor", "ground-robot"}


@pytest.mark.parametrize("name", ["quadrotor", "ground-robot"])
def test_rot_jacobian_matches_finite_differences(name):
    model = V.MODELS[name]
    rng = np.random.default_rng(3)
    x = model.initial_state([0.3, -0.2, 1.0], yaw=0.7)
    o = model._orientation_slice
    x[o] = x[o] + 0.05 * rng.standard_normal(o.stop - o.start)
    a = np.array([0.4, -1.1, 0.3])
    J = model.rot_jacobian(x, a)
    num = np.zeros_like(J)
    for i, j in enumerate(range(o.start, o.stop)):
        d = np.zeros_like(x)
        d[j] = 1e-6
        num[:, i] = (model.rotation(x + d) @ a - model.rotation(x - d) @ a) / 2e-6
    np.testing.assert_allclose(J, num, atol=1e-8)
