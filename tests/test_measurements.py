"""Measurement models: analytic Jacobians against finite differences, angle wrapping, registry."""

import inspect

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from swarmloc.models import measurements as ms
from swarmloc.models.measurements import MEASUREMENT_MODELS, StateLayout

LAYOUTS = {
    "planar": StateLayout.planar(),
    "planar-pose": StateLayout.planar_pose(),
    "planar-clock": StateLayout(3, slice(0, 2), clock=2),
    "pose3d": StateLayout.pose3d(),
    "uas16": StateLayout.uas16(),
    # swarmloc/models/ins.py's error state: attitude columns w.r.t. a world-frame small rotation.
    "uas16-rotvec": StateLayout.uas16("rotation-vector"),
    # Position not first: nothing may assume it is.
    "pose3d-shuffled": StateLayout(7, slice(4, 7), attitude=slice(0, 3), clock=3),
}
# Heterogeneous pairs: a UAS ranging to a ground pose, a robot with heading to one without.
OTHER = {"uas16": "pose3d", "planar-pose": "planar", "pose3d-shuffled": "uas16", "uas16-rotvec": "uas16"}
SEEDS = range(5)


def instances():
    """(id, model, finite-difference step) for every registered model on every layout it reads."""
    for name, cls in MEASUREMENT_MODELS.items():
        for lname, lay in LAYOUTS.items():
            if not cls.supports(lay):
                continue
            variants = [({}, "")]
            if cls.platforms == 2 and lname in OTHER:
                variants.append(({"other": LAYOUTS[OTHER[lname]]}, "+" + OTHER[lname]))
            if "body_frame" in inspect.signature(cls.__init__).parameters and lay.attitude is not None:
                variants += [({**kw, "body_frame": True}, tag + "-body") for kw, tag in variants]
            for kw, tag in variants:
                if cls is ms.Pseudorange:
                    rng = np.random.default_rng(99)
                    # Pseudolites 100 m away and GNSS satellites 2e7 m away: at that scale a
                    # 1e-6 m step is lost in rounding, so the difference step grows with it.
                    for scale, step in ((100.0, 1e-6), (2.0e7, 1e-2)):
                        sats = rng.normal(size=(4, lay.pos_dim)) * scale
                        yield f"{name}-{lname}-{scale:g}", cls(lay, sats, std=3.0), step
                else:
                    yield f"{name}-{lname}{tag}", cls(lay, std=0.1, **kw), 1e-6


CASES = list(instances())


def random_state(layout, rng):
    x = rng.normal(size=layout.dim) * 10.0
    x[list(layout.att_idx)] = rng.uniform(-np.pi, np.pi, size=len(layout.att_idx))
    return x


def perturbed(layout, x, k, delta):
    """x moved by delta along column k of the Jacobian: added, except a rotation-vector
    attitude, whose columns are world-frame small rotations, C <- exp([d x]) C."""
    x = x.copy()
    if layout.attitude_kind == "rotation-vector" and k in layout.att_idx:
        d = np.zeros(3)
        d[layout.att_idx.index(k)] = delta
        C = Rotation.from_rotvec(d) * Rotation.from_rotvec(layout.attitude_of(x))
        x[list(layout.att_idx)] = C.as_rotvec()
    else:
        x[k] += delta
    return x


def numeric_jacobian(model, xs, i, step):
    """Central differences of h w.r.t. platform i; residual() keeps angle differences unwrapped."""
    x, lay = xs[i], model.layouts[i]
    J = np.zeros((model.dim, x.shape[0]))
    for k in range(x.shape[0]):
        e = step * max(1.0, abs(x[k]))
        plus, minus = list(xs), list(xs)
        plus[i], minus[i] = perturbed(lay, x, k, e), perturbed(lay, x, k, -e)
        J[:, k] = model.residual(model.h(*plus), model.h(*minus)) / (2 * e)
    return J


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
@pytest.mark.parametrize("seed", SEEDS)
def test_jacobians_match_central_differences(case, seed):
    _, model, step = case
    rng = np.random.default_rng(seed)
    xs = [random_state(lay, rng) for lay in model.layouts]
    Hs = model.jacobians(*xs)
    assert len(Hs) == model.platforms
    scale = max(1.0, np.abs(model.h(*xs)).max()) if step > 1e-6 else 1.0
    for i, (H, lay) in enumerate(zip(Hs, model.layouts)):
        assert H.shape == (model.dim, lay.dim)
        np.testing.assert_allclose(H, numeric_jacobian(model, xs, i, step), atol=1e-7 * scale, rtol=1e-6)


def test_every_model_checked_in_2d_and_in_3d_where_it_applies():
    ids = [c[0] for c in CASES]
    for name, cls in MEASUREMENT_MODELS.items():
        assert any(i.startswith(name + "-planar") for i in ids), name
        if cls.supports(LAYOUTS["pose3d"]) or cls.supports(LAYOUTS["uas16"]):
            assert any(i.startswith(name + "-uas16") for i in ids), name
    for name in ("relative-position", "bearing", "range-bearing"):
        assert any(i.startswith(name) and i.endswith("-body") for i in ids), name
    for layout in ("uas16", "uas16-rotvec", "planar-pose"):
        assert any(f"relative-position-{layout}-body" in i for i in ids), layout


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_h_is_vectorised_over_leading_axes(case):
    _, model, _ = case
    rng = np.random.default_rng(5)
    batch = [np.stack([random_state(lay, rng) for _ in range(4)]) for lay in model.layouts]
    Z = model.h(*batch)
    assert Z.shape == (4, model.dim)
    for j in range(4):
        np.testing.assert_allclose(Z[j], model.h(*[b[j] for b in batch]), rtol=1e-13, atol=1e-12)


def test_registry_lists_every_model():
    concrete = {
        c
        for c in vars(ms).values()
        if inspect.isclass(c) and issubclass(c, ms.MeasurementModel) and "name" in vars(c)
    }
    assert set(MEASUREMENT_MODELS.values()) == concrete
    assert set(MEASUREMENT_MODELS) == {
        "range", "relative-position", "pseudorange", "position-fix", "bearing", "range-bearing"
    }
    for name, cls in MEASUREMENT_MODELS.items():
        assert cls.name == name


def test_wrap_angle_range_and_branch():
    a = np.array([-np.pi, np.pi, 3 * np.pi, -3 * np.pi + 1e-9, 0.5, 7.0])
    w = ms.wrap_angle(a)
    assert np.all(w >= -np.pi) and np.all(w < np.pi)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-9)


@pytest.mark.parametrize("eps", [1e-3, 1e-9])
def test_bearing_residual_wraps_across_plus_minus_pi(eps):
    bearing = ms.Bearing(StateLayout.planar(), std=0.01)
    xa = np.zeros(2)
    xb = np.array([np.cos(np.pi - eps), np.sin(np.pi - eps)])  # just above the negative x axis
    z_hat = bearing.h(xa, xb)
    assert z_hat[0] == pytest.approx(np.pi - eps, abs=1e-12)
    z = np.array([-np.pi + eps])  # the same ray seen 2 eps away, across the branch cut
    nu = bearing.residual(z, z_hat)
    assert nu[0] == pytest.approx(2 * eps, abs=1e-12)
    assert bearing.residual(z_hat, z)[0] == pytest.approx(-2 * eps, abs=1e-12)


def test_body_frame_bearing_wraps_heading_offset_and_range_component_is_not_wrapped():
    rb = ms.RangeBearing(StateLayout.planar_pose(), std=[0.1, 0.01], body_frame=True)
    xa = np.array([0.0, 0.0, 3.0])  # heading near pi
    xb = np.array([0.0, -5.0, 0.0])  # world bearing -pi/2
    z_hat = rb.h(xa, xb)
    assert -np.pi <= z_hat[1] < np.pi
    assert z_hat[1] == pytest.approx(ms.wrap_angle(-np.pi / 2 - 3.0), abs=1e-12)
    nu = rb.residual(np.array([12.0, z_hat[1] + 2 * np.pi - 1e-4]), z_hat)
    np.testing.assert_allclose(nu, [12.0 - 5.0, -1e-4], atol=1e-12)


def test_rotations_match_scipy():
    rng = np.random.default_rng(21)
    att = rng.uniform(-np.pi, np.pi, size=(5, 3))
    # ZYX: yaw about z, then pitch about the new y, then roll about the new x (intrinsic).
    ref = Rotation.from_euler("ZYX", att[:, ::-1]).as_matrix()
    np.testing.assert_allclose(ms.rotation(att), ref, atol=1e-12)
    phi = att / 2
    np.testing.assert_allclose(ms.rotation(phi, "rotation-vector"), Rotation.from_rotvec(phi).as_matrix(), atol=1e-12)
    np.testing.assert_array_equal(ms.rotation(np.zeros(3), "rotation-vector"), np.eye(3))
    np.testing.assert_allclose(ms.rotation(np.array([0.3])), Rotation.from_euler("z", 0.3).as_matrix()[:2, :2])
    u, v = rng.normal(size=3), rng.normal(size=3)
    np.testing.assert_allclose(ms.skew(u) @ v, np.cross(u, v), atol=1e-12)


@pytest.mark.parametrize("kind", ms.ATTITUDE_KINDS)
def test_relative_position_body_frame_inverts_rotation(kind):
    rp = ms.RelativePosition(StateLayout.uas16(kind), std=0.05, body_frame=True)
    rng = np.random.default_rng(3)
    xa, xb = random_state(rp.layout, rng), random_state(rp.layout, rng)
    C = ms.rotation(xa[6:9], kind)
    np.testing.assert_allclose(C.T @ C, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(C @ rp.h(xa, xb), xb[:3] - xa[:3], atol=1e-12)
    # Yaw of +90 degrees (both kinds: a rotation vector along z is a yaw): a point on the
    # world y axis is ahead on the body x axis.
    xa = np.zeros(16)
    xa[8] = np.pi / 2
    xb = np.zeros(16)
    xb[1] = 4.0
    np.testing.assert_allclose(rp.h(xa, xb), [4.0, 0.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("body_frame,kind", [(False, "euler"), (True, "euler"), (True, "rotation-vector")])
def test_implied_position_round_trip_and_first_order_covariance(body_frame, kind):
    lay = StateLayout.uas16(kind)
    R = np.diag([0.01, 0.02, 0.03])
    rp = ms.RelativePosition(lay, cov=R, body_frame=body_frame)
    rng = np.random.default_rng(11)
    xa, xb = random_state(lay, rng), random_state(lay, rng)
    A = rng.normal(size=(16, 16))
    Pa = A @ A.T / 16 + 0.1 * np.eye(16)
    z = rp.h(xa, xb)
    p, Pp = rp.implied_position(xa, Pa, z, known="a")
    np.testing.assert_allclose(p, xb[:3], atol=1e-10)
    # J by central differences of x_a -> p_a + C(att_a) z, for the linearised covariance.
    f = lambda x: x[:3] + (ms.rotation(x[6:9], kind) @ z if body_frame else z)
    J = np.column_stack([(f(perturbed(lay, xa, k, 1e-6)) - f(perturbed(lay, xa, k, -1e-6))) / 2e-6 for k in range(16)])
    C = ms.rotation(xa[6:9], kind) if body_frame else np.eye(3)
    np.testing.assert_allclose(Pp, J @ Pa @ J.T + C @ R @ C.T, rtol=1e-6, atol=1e-8)
    if body_frame:
        with pytest.raises(ValueError):
            rp.implied_position(xb, Pa, z, known="b")
    else:
        p, Pp = rp.implied_position(xb, Pa, z, known="b")
        np.testing.assert_allclose(p, xa[:3], atol=1e-10)
        np.testing.assert_allclose(Pp, Pa[:3, :3] + R)


def test_joint_places_blocks_in_a_swarm_state():
    """The centralized EKF's H: three 16-state UASs, range between the third and the first."""
    lay = StateLayout.uas16()
    rng_model = ms.Range(lay, std=0.02)
    rng = np.random.default_rng(4)
    X = np.concatenate([random_state(lay, rng) for _ in range(3)])
    z_hat, H = rng_model.joint(X, [32, 0])
    Ha, Hb = rng_model.jacobians(X[32:48], X[0:16])
    assert H.shape == (1, 48)
    np.testing.assert_array_equal(H[:, 32:48], Ha)
    np.testing.assert_array_equal(H[:, 0:16], Hb)
    np.testing.assert_array_equal(H[:, 16:32], 0.0)
    assert z_hat[0] == pytest.approx(np.linalg.norm(X[0:3] - X[32:35]))
    with pytest.raises(ValueError):
        rng_model.joint(X, [0])
    with pytest.raises(ValueError):
        rng_model.joint(X, [40, 0])  # runs past the end


def test_degenerate_geometry_gives_zero_jacobian_not_nan():
    x = np.array([1.0, 2.0])
    for model in (ms.Range(StateLayout.planar(), std=1.0), ms.Bearing(StateLayout.planar(), std=1.0),
                  ms.RangeBearing(StateLayout.planar(), std=[1.0, 1.0])):
        for H in model.jacobians(x, x.copy()):
            assert np.all(np.isfinite(H)) and np.all(H[:, :2] == 0.0)


def test_noise_and_layout_validation():
    lay = StateLayout.planar()
    np.testing.assert_allclose(ms.RangeBearing(lay, std=[2.0, 0.1]).R, np.diag([4.0, 0.01]), rtol=1e-15)
    np.testing.assert_array_equal(ms.PositionFix(StateLayout.uas16(), std=0.5).R, 0.25 * np.eye(3))
    with pytest.raises(ValueError):
        ms.Range(lay)  # no noise given
    with pytest.raises(ValueError):
        ms.Range(lay, std=1.0, cov=[[1.0]])
    with pytest.raises(np.linalg.LinAlgError):
        ms.PositionFix(lay, cov=[[1.0, 2.0], [2.0, 1.0]])
    with pytest.raises(ValueError):
        ms.Pseudorange(lay, np.zeros((4, 2)), std=1.0)  # no clock in the layout
    with pytest.raises(ValueError):
        ms.Bearing(StateLayout.pose3d(), std=0.1)  # planar only
    with pytest.raises(ValueError):
        ms.RelativePosition(lay, std=0.1, body_frame=True)  # no heading to rotate by
    with pytest.raises(ValueError):
        ms.Range(lay, std=0.1, other=StateLayout.pose3d())  # 2D to 3D
    assert {StateLayout.uas16(): "uas"}[StateLayout.uas16()] == "uas"  # usable as a key
    with pytest.raises(ValueError):
        StateLayout(4, slice(0, 2), attitude=slice(1, 2))  # overlap
    with pytest.raises(ValueError):
        StateLayout(6, slice(0, 3), attitude=slice(3, 4))  # 3D needs three angles
    with pytest.raises(ValueError):
        StateLayout(3, slice(0, 2), attitude=slice(2, 3), attitude_kind="rotation-vector")
    with pytest.raises(ValueError):
        StateLayout.pose3d("quaternion")


def test_range_second_order_terms_match_monte_carlo():
    """Mean and variance of ||p_b - p_a|| for a Gaussian relative position with metres of
    cross-track uncertainty at 20 m: the second-order terms against 400k samples."""
    lay = StateLayout(3, slice(0, 3))
    rng = np.random.default_rng(4)
    xa, xb = np.zeros(3), np.array([20.0, 0.0, 0.0])
    P_rel = np.diag([0.01, 9.0, 4.0])
    d = np.linalg.norm(xb + rng.multivariate_normal(np.zeros(3), P_rel, 400_000), axis=1)
    bias, var = ms.Range(lay, std=0.02).second_order(xa, xb, P_rel)
    first_order_var = 0.01  # u^T P_rel u
    assert bias == pytest.approx(d.mean() - 20.0, rel=0.1)  # ~0.33 m: the range reads long
    assert first_order_var + var == pytest.approx(d.var(), rel=0.15)
