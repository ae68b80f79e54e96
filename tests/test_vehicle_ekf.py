"""The vehicle EKFs of swarmloc/estimators/vehicles/filters.py: the joint (centralized EKF-CL) filter
against the single-vehicle one and against the paper's per-vehicle equations 45-47, and a
simulated hover of two quadrotors for consistency."""

from __future__ import annotations

import math

import numpy as np
import pytest

from swarmloc.estimators.vehicles.filters import Q_FLOOR, JointVehicleEkf, VehicleEkf, process_noise
from swarmloc.models.vehicles import MODELS, relpos, relpos_jacobian

QUAD = MODELS["quadrotor"]
GROUND = MODELS["ground-robot"]
ACT = {"quadrotor": np.array([0.05, 1e-3, 1e-3, 1e-3]), "ground-robot": np.array([0.1, 1e-3])}
TOL = 1e-12


def p0(model) -> np.ndarray:
    if model.name == "quadrotor":
        return np.diag([0.05**2] * 3 + [0.01**2] * 4 + [0.01**2] * 3 + [0.01**2] * 3)
    return np.diag([0.05**2] * 3 + [0.01**2] + [0.01**2] * 3)


def nominal_input(model) -> np.ndarray:
    if model.name == "quadrotor":
        return QUAD.hover_input() + np.array([0.2, 1e-4, -2e-4, 3e-4])
    return np.array([0.5, 0.01])


def moving_state(model, position, yaw, rng) -> np.ndarray:
    """A state away from rest, so every Jacobian block is exercised."""
    x = model.initial_state(position, yaw)
    if model.name == "quadrotor":
        x[3:7] += 0.05 * rng.standard_normal(4)
        x[3:7] /= np.linalg.norm(x[3:7])
        x[7:13] = 0.3 * rng.standard_normal(6)
    else:
        x[4:7] = [0.4, 0.05, 0.3]
    return x


def noisy_attitude(model, x, std, rng, flip=False) -> np.ndarray:
    z = np.asarray(model.orientation(x), float) + std * rng.standard_normal(model.orientation_dim)
    return -z if flip else z


def random_spd(n, rng, scale=1e-3) -> np.ndarray:
    A = rng.standard_normal((n, n))
    return scale * (A @ A.T / n + 0.1 * np.eye(n))


# ---------------------------------------------------------------------------------------------
# 1, 2: the joint filter reduces to the single-vehicle one


@pytest.mark.parametrize("project", [True, False])
@pytest.mark.parametrize("name", ["quadrotor", "ground-robot"])
def test_joint_with_one_member_equals_single(name, project):
    model = MODELS[name]
    rng = np.random.default_rng(1)
    x0 = moving_state(model, [1.0, 2.0, 3.0], 0.4, rng)
    single = VehicleEkf(model, x0, p0(model), ACT[name], project_quaternion=project)
    joint = JointVehicleEkf(project_quaternion=project)
    joint.add(7, model, x0, p0(model), ACT[name])
    assert joint.members == [7] and joint.slice(7) == slice(0, model.state_dim)
    truth = x0.copy()
    u = nominal_input(model)
    for k in range(40):
        dt = 0.02 if k % 5 else 0.03
        truth = model.step(truth, u, dt)
        single.predict(u, dt)
        joint.predict({7: (u, dt)})
        za = noisy_attitude(model, truth, 0.05, rng, flip=(k % 3 == 0))
        assert abs(single.update_attitude(za, 0.05) - joint.update_attitude(7, za, 0.05)) < TOL
        if k % 2 == 0:
            zg = truth[:3] + 0.01 * rng.standard_normal(3)
            assert abs(single.update_gps(zg, 0.01, std_vertical=0.02) - joint.update_gps(7, zg, 0.01, std_vertical=0.02)) < TOL
        x, P = joint.marginal(7)
        np.testing.assert_allclose(x, single.x, rtol=0, atol=TOL)
        np.testing.assert_allclose(P, single.P, rtol=0, atol=TOL)
        assert np.array_equal(single.P, single.P.T)
    if model.orientation_dim == 4:
        assert abs(np.linalg.norm(single.x[3:7]) - 1.0) < 1e-14


def test_two_members_without_relative_measurements_stay_independent():
    rng = np.random.default_rng(2)
    xq = moving_state(QUAD, [0.0, 0.0, 2.0], 0.1, rng)
    xg = moving_state(GROUND, [3.0, -1.0, 0.0], 2.0, rng)
    fq = VehicleEkf(QUAD, xq, p0(QUAD), ACT["quadrotor"])
    fg = VehicleEkf(GROUND, xg, p0(GROUND), ACT["ground-robot"])
    joint = JointVehicleEkf()
    joint.add(3, QUAD, xq, p0(QUAD), ACT["quadrotor"])
    joint.add(1, GROUND, xg, p0(GROUND), ACT["ground-robot"])
    assert joint.members == [3, 1] and joint.slice(1) == slice(13, 20)
    tq, tg = xq.copy(), xg.copy()
    uq, ug = nominal_input(QUAD), nominal_input(GROUND)
    for k in range(50):
        dtq, dtg = 0.02, (0.02 if k % 4 else 0.0)  # a member may not advance this tick
        tq, tg = QUAD.step(tq, uq, dtq), GROUND.step(tg, ug, dtg)
        fq.predict(uq, dtq)
        fg.predict(ug, dtg)
        joint.predict({3: (uq, dtq), 1: (ug, dtg)})
        za, zb = noisy_attitude(QUAD, tq, 0.1, rng), noisy_attitude(GROUND, tg, 0.02, rng)
        assert abs(fq.update_attitude(za, 0.1) - joint.update_attitude(3, za, 0.1)) < TOL
        assert abs(fg.update_attitude(zb, 0.02) - joint.update_attitude(1, zb, 0.02)) < TOL
        if k % 3 == 0:
            zg = tg[:3] + 0.005 * rng.standard_normal(3)
            assert abs(fg.update_gps(zg, 0.005) - joint.update_gps(1, zg, 0.005)) < TOL
        for aid, f in ((3, fq), (1, fg)):
            x, P = joint.marginal(aid)
            np.testing.assert_allclose(x, f.x, rtol=0, atol=TOL)
            np.testing.assert_allclose(P, f.P, rtol=0, atol=TOL)
        assert not joint.P[joint.slice(3), joint.slice(1)].any()  # exactly zero


# ---------------------------------------------------------------------------------------------
# 3: eqs. 45-47 written out per vehicle


def three_members(rng, project):
    joint = JointVehicleEkf(project_quaternion=project)
    joint.add(0, QUAD, moving_state(QUAD, [0.0, 0.0, 1.5], 0.3, rng), p0(QUAD), ACT["quadrotor"])
    joint.add(1, GROUND, moving_state(GROUND, [2.0, 1.0, 0.0], -0.7, rng), p0(GROUND), ACT["ground-robot"])
    joint.add(2, QUAD, moving_state(QUAD, [-1.0, 3.0, 2.0], 1.2, rng), p0(QUAD), ACT["quadrotor"])
    # correlated with everyone, as after earlier relative measurements
    joint.P = random_spd(joint.x.size, rng)
    return joint


@pytest.mark.parametrize("base, target", [(0, 1), (1, 0)])
def test_joint_relpos_equals_paper_per_vehicle_form(base, target):
    rng = np.random.default_rng(3)
    joint = three_members(rng, project=False)
    models = {0: QUAD, 1: GROUND, 2: QUAD}
    xs = {a: joint.x[joint.slice(a)].copy() for a in joint.members}
    Pb = {(i, j): joint.P[joint.slice(i), joint.slice(j)].copy() for i in joint.members for j in joint.members}
    mb, mt = models[base], models[target]
    z = relpos(mb, xs[base], mt, xs[target]) + np.array([0.03, -0.02, 0.01])
    std = 0.005

    # eq. 45-47, term by term
    Hb, Ht = relpos_jacobian(mb, xs[base], mt, xs[target])
    e = z - relpos(mb, xs[base], mt, xs[target])
    R = std**2 * np.eye(3)
    S = (Hb @ Pb[base, base] @ Hb.T + Ht @ Pb[target, target] @ Ht.T
         + Hb @ Pb[base, target] @ Ht.T + Ht @ Pb[target, base] @ Hb.T + R)
    Sinv = np.linalg.inv(S)
    K = {i: (Pb[i, target] @ Ht.T + Pb[i, base] @ Hb.T) @ Sinv for i in joint.members}
    x_exp = {i: xs[i] + K[i] @ e for i in joint.members}
    for i in joint.members:
        if models[i].orientation_dim == 4:
            x_exp[i][3:7] /= np.linalg.norm(x_exp[i][3:7])
    P_exp = {(i, j): Pb[i, j] - K[i] @ S @ K[j].T for i in joint.members for j in joint.members}

    nis = joint.update_relpos(base, target, z, std)
    assert nis == pytest.approx(float(e @ Sinv @ e), rel=1e-10)
    for i in joint.members:
        np.testing.assert_allclose(joint.x[joint.slice(i)], x_exp[i], rtol=0, atol=TOL)
        for j in joint.members:
            np.testing.assert_allclose(joint.P[joint.slice(i), joint.slice(j)], P_exp[i, j], rtol=0, atol=TOL)
    # the uninvolved member 2, correlated, is corrected too
    assert np.linalg.norm(joint.x[joint.slice(2)] - xs[2]) > 1e-4
    assert np.trace(joint.P[joint.slice(2), joint.slice(2)]) < np.trace(Pb[2, 2]) - 1e-6
    assert np.array_equal(joint.P, joint.P.T)


def test_quaternion_projection_after_update():
    """With project_quaternion (the default) P is mapped through d(q/|q|)/dq after the update:
    nothing but Q_FLOOR is left along each quaternion, in its own block or across members."""
    rng = np.random.default_rng(4)
    joint = three_members(rng, project=True)
    joint.update_relpos(0, 2, relpos(QUAD, joint.x[0:13], QUAD, joint.x[20:33]) + 0.02, 0.005)
    for aid in (0, 2):
        sl = joint.slice(aid)
        q = joint.x[sl][3:7]
        assert abs(np.linalg.norm(q) - 1.0) < 1e-14
        rows = joint.P[sl.start + 3:sl.start + 7, :]
        radial = q @ rows
        qs = slice(sl.start + 3, sl.start + 7)
        assert radial[qs] @ q == pytest.approx(Q_FLOOR, rel=1e-6)
        others = np.delete(radial, np.r_[sl.start + 3:sl.start + 7])
        assert np.abs(others).max() < 1e-15
    assert np.linalg.eigvalsh(joint.P)[0] > 0.0


# ---------------------------------------------------------------------------------------------
# 4: a simulated hover


def hover_run(seed=0, T=20.0, dt=0.02):
    """Two quadrotors hovering open loop (nominal input mg, the world's input perturbed by
    actuator noise held over each tick); vehicle 1 has GPS, both the IMU's quaternion (std 0.1 per
    component, the paper's), vehicle 2 measures vehicle 1 in its body frame."""
    rng = np.random.default_rng(seed)
    # Moment noise 1e-6 N m: at 1e-3 the open-loop vehicles tumble and fly hundreds of metres
    # apart in 20 s (no controller), far outside what a 5 mm relative position linearises over.
    act = np.array([0.05, 1e-6, 1e-6, 1e-6])
    P0 = p0(QUAD)
    truth = [QUAD.initial_state([0.0, 0.0, 2.0]), QUAD.initial_state([2.0, 1.0, 2.0], yaw=0.5)]
    joint = JointVehicleEkf()
    est0 = []
    for a, xt in enumerate(truth):
        x = xt + rng.multivariate_normal(np.zeros(13), P0)
        x[3:7] /= np.linalg.norm(x[3:7])
        est0.append(x)
        joint.add(a, QUAD, x, P0, act)
    alone = VehicleEkf(QUAD, est0[1], P0, act)
    u = QUAD.hover_input()
    out = {"nees": [[], []], "err": [[], []], "nis_relpos": []}
    for _ in range(int(round(T / dt))):
        truth = [QUAD.step(x, u + act * rng.standard_normal(4), dt) for x in truth]
        joint.predict({0: (u, dt), 1: (u, dt)})
        alone.predict(u, dt)
        for a in (0, 1):
            za = noisy_attitude(QUAD, truth[a], 0.1, rng)
            joint.update_attitude(a, za, 0.1)
            if a == 1:
                alone.update_attitude(za, 0.1)
        joint.update_gps(0, truth[0][:3] + 0.005 * rng.standard_normal(3), 0.005)
        z = relpos(QUAD, truth[1], QUAD, truth[0]) + 0.005 * rng.standard_normal(3)
        out["nis_relpos"].append(joint.update_relpos(1, 0, z, 0.005))
        for a in (0, 1):
            x, P = joint.marginal(a)
            e = truth[a][:3] - x[:3]
            out["nees"][a].append(float(e @ np.linalg.solve(P[:3, :3], e)))
            out["err"][a].append(float(np.linalg.norm(e)))
    out["alone_end"] = float(np.linalg.norm(alone.x[:3] - truth[1][:3]))
    out["separation_end"] = float(np.linalg.norm(truth[0][:3] - truth[1][:3]))
    return out


@pytest.mark.slow
def test_hover_consistency():
    r = hover_run()
    nees1, nees2 = np.mean(r["nees"][0]), np.mean(r["nees"][1])
    err2 = np.array(r["err"][1])
    print(f"\nhover: mean position NEES v1 {nees1:.2f} v2 {nees2:.2f}; v2 error max {err2.max():.4f} m "
          f"end {err2[-1]:.4f} m; v2 alone end {r['alone_end']:.3f} m; mean relpos NIS "
          f"{np.mean(r['nis_relpos']):.2f}; v1 error max {max(r['err'][0]):.4f} m; "
          f"separation at the end {r['separation_end']:.2f} m")
    assert err2.max() < 0.1
    assert 0.3 * 3 < nees2 < 3 * 3
    assert 0.3 * 3 < nees1 < 3 * 3
    assert 0.3 * 3 < np.mean(r["nis_relpos"]) < 3 * 3
    assert r["alone_end"] > err2[-1]
    assert r["alone_end"] > 1.0  # no position information at all: it drifts by metres


# ---------------------------------------------------------------------------------------------
# 5: a ground robot measuring a quadrotor


def test_ground_robot_base_measures_quadrotor():
    rng = np.random.default_rng(5)
    xg_true = GROUND.initial_state([0.0, 0.0, 0.0], yaw=0.3)
    xq_true = QUAD.initial_state([1.5, 0.5, 1.0], yaw=-0.4)
    Pg = np.diag([0.1**2] * 3 + [0.02**2] + [0.01**2] * 3)
    Pq = np.diag([0.1**2] * 3 + [0.01**2] * 4 + [0.01**2] * 6)
    joint = JointVehicleEkf()
    joint.add(10, GROUND, xg_true + rng.multivariate_normal(np.zeros(7), Pg), Pg, ACT["ground-robot"])
    joint.add(20, QUAD, xq_true + 0.05 * np.r_[rng.standard_normal(3), np.zeros(10)], Pq, ACT["quadrotor"])
    joint.predict({10: (np.zeros(2), 0.02), 20: (QUAD.hover_input(), 0.02)})
    tr = {a: np.trace(joint.marginal(a)[1][:3, :3]) for a in (10, 20)}
    err_before = np.linalg.norm(joint.x[joint.slice(20)][:3] - joint.x[joint.slice(10)][:3] - (xq_true[:3] - xg_true[:3]))
    z = relpos(GROUND, xg_true, QUAD, xq_true)
    nis = joint.update_relpos(10, 20, z, 0.01)
    assert math.isfinite(nis) and nis >= 0.0
    for a in (10, 20):
        assert np.trace(joint.marginal(a)[1][:3, :3]) < tr[a]
    # the two are now correlated, and their relative position moved toward the truth
    assert np.abs(joint.P[joint.slice(10), joint.slice(20)]).max() > 0.0
    err_after = np.linalg.norm(joint.x[joint.slice(20)][:3] - joint.x[joint.slice(10)][:3] - (xq_true[:3] - xg_true[:3]))
    assert err_after < err_before


def test_anchor_update_counts_target_covariance():
    rng = np.random.default_rng(6)
    xb = GROUND.initial_state([0.0, 0.0, 0.0], yaw=0.3)
    xt = QUAD.initial_state([1.5, 0.5, 1.0])
    z = relpos(GROUND, xb, QUAD, xt) + 0.02
    a = VehicleEkf(GROUND, xb, p0(GROUND), ACT["ground-robot"])
    b = VehicleEkf(GROUND, xb, p0(GROUND), ACT["ground-robot"])
    nis_a = a.update_relpos_anchor(z, 0.005, QUAD, xt)
    nis_b = b.update_relpos_anchor(z, 0.005, QUAD, xt, Pt=random_spd(13, rng, 1e-2))
    assert nis_b < nis_a  # the target's own uncertainty explains part of the innovation
    assert np.trace(b.P[:3, :3]) > np.trace(a.P[:3, :3])  # and the base learns less
    assert np.trace(a.P[:3, :3]) < np.trace(p0(GROUND)[:3, :3])


def test_yaw_innovation_wraps():
    f = VehicleEkf(GROUND, GROUND.initial_state([0.0, 0.0, 0.0], yaw=math.pi - 0.01), p0(GROUND), ACT["ground-robot"])
    nis = f.update_attitude([-math.pi + 0.01], 0.01)  # 0.02 rad away across the cut
    assert nis == pytest.approx(0.02**2 / (0.01**2 + 0.01**2), rel=1e-6)
    assert f.x[3] == pytest.approx(math.pi, abs=1e-9)


def test_remove_marginalises_and_predict_needs_every_member():
    rng = np.random.default_rng(7)
    joint = three_members(rng, project=False)
    before = {a: joint.marginal(a) for a in (0, 2)}
    cross = joint.P[joint.slice(0), joint.slice(2)].copy()
    joint.remove(1)
    assert joint.members == [0, 2] and joint.slice(2) == slice(13, 26)
    for a in (0, 2):
        np.testing.assert_array_equal(joint.marginal(a)[0], before[a][0])
        np.testing.assert_array_equal(joint.marginal(a)[1], before[a][1])
    np.testing.assert_array_equal(joint.P[joint.slice(0), joint.slice(2)], cross)
    with pytest.raises(ValueError):
        joint.predict({0: (QUAD.hover_input(), 0.02)})
    with pytest.raises(ValueError):
        joint.marginal(1)


def test_process_noise():
    x = QUAD.initial_state([0.0, 0.0, 1.0])
    Q = process_noise(QUAD, x, 0.02, ACT["quadrotor"])
    G = QUAD.g(x)
    np.testing.assert_allclose(Q, 0.02**2 * G @ np.diag(ACT["quadrotor"] ** 2) @ G.T + Q_FLOOR * np.eye(13), rtol=0, atol=1e-18)
    assert np.linalg.eigvalsh(Q)[0] > 0.0
    assert not process_noise(GROUND, GROUND.initial_state([0, 0, 0]), 0.0, ACT["ground-robot"]).any()


# ---------------------------------------------------------------------------------------------
# 6: wrong shapes


def test_shape_errors_raise_value_error():
    xq, Pq, aq = QUAD.initial_state([0, 0, 1]), p0(QUAD), ACT["quadrotor"]
    xg = GROUND.initial_state([1, 0, 0])
    bad_inits = [
        (xq[:12], Pq, aq), (xq, Pq[:12, :12], aq), (xq, Pq, aq[:3]), (np.r_[xq[:12], np.nan], Pq, aq),
    ]
    for args in bad_inits:
        with pytest.raises(ValueError):
            VehicleEkf(QUAD, *args)
    f = VehicleEkf(QUAD, xq, Pq, aq)
    calls = [
        lambda: f.predict(np.zeros(2), 0.02),
        lambda: f.predict(np.zeros(4), -0.02),
        lambda: f.update_gps(np.zeros(2), 0.01),
        lambda: f.update_gps(np.zeros(3), [0.01, 0.01]),
        lambda: f.update_gps(np.zeros(3), 0.0),
        lambda: f.update_attitude(np.zeros(3), 0.1),
        lambda: f.update_attitude([1.0, 0, 0, 0], [0.1, 0.1]),
        lambda: f.update_relpos_anchor(np.zeros(2), 0.01, GROUND, xg),
        lambda: f.update_relpos_anchor(np.zeros(3), 0.01, GROUND, xq),
        lambda: f.update_relpos_anchor(np.zeros(3), 0.01, GROUND, xg, Pt=np.eye(13)),
    ]
    joint = JointVehicleEkf()
    joint.add(1, QUAD, xq, Pq, aq)
    joint.add(2, GROUND, xg, p0(GROUND), ACT["ground-robot"])
    calls += [
        lambda: joint.add(1, QUAD, xq, Pq, aq),  # already a member
        lambda: joint.add(3, GROUND, xq, p0(GROUND), ACT["ground-robot"]),
        lambda: joint.add(3, GROUND, xg, Pq, ACT["ground-robot"]),
        lambda: joint.add(3, GROUND, xg, p0(GROUND), aq),
        lambda: joint.predict({1: (np.zeros(4), 0.02), 2: (np.zeros(4), 0.02)}),
        lambda: joint.predict({1: (np.zeros(4), 0.02), 2: (np.zeros(2), 0.02), 9: (np.zeros(2), 0.02)}),
        lambda: joint.predict({1: (np.zeros(4), 0.02), 2: np.zeros(2)}),
        lambda: joint.update_gps(1, np.zeros(4), 0.01),
        lambda: joint.update_gps(9, np.zeros(3), 0.01),
        lambda: joint.update_attitude(2, np.zeros(4), 0.1),
        lambda: joint.update_relpos(1, 2, np.zeros(4), 0.01),
        lambda: joint.update_relpos(1, 1, np.zeros(3), 0.01),
        lambda: joint.update_relpos(1, 9, np.zeros(3), 0.01),
    ]
    for call in calls:
        x, P = joint.x.copy(), joint.P.copy()
        with pytest.raises(ValueError):
            call()
        np.testing.assert_array_equal(joint.x, x)  # a refused input changes nothing
        np.testing.assert_array_equal(joint.P, P)


def test_singular_innovation_raises_linalg_error():
    f = VehicleEkf(GROUND, GROUND.initial_state([0, 0, 0]), p0(GROUND), ACT["ground-robot"])
    f.P = -np.eye(7)  # S = -I + R: not positive definite
    with pytest.raises(np.linalg.LinAlgError):
        f.update_gps(np.zeros(3), 0.01)
