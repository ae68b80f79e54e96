"""EKF update, covariance intersection (full and partial), naive fusion: exactness and consistency."""

import numpy as np
import pytest
import scipy.stats

from swarmloc.filters import fusion
from swarmloc.models.measurements import Bearing, RelativePosition, StateLayout


def random_spd(n, rng, floor=0.1):
    A = rng.normal(size=(n, n))
    return A @ A.T / n + floor * np.eye(n)


def assert_psd(M, tol=1e-9):
    np.testing.assert_array_equal(M, M.T)
    assert np.linalg.eigvalsh(M).min() >= -tol * max(1.0, np.abs(M).max())


# --- EKF update -------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(4))
def test_ekf_update_is_the_kalman_update_for_linear_h(seed):
    rng = np.random.default_rng(seed)
    n, m = 5, 3
    x, P = rng.normal(size=n), random_spd(n, rng)
    H, R = rng.normal(size=(m, n)), random_spd(m, rng)
    z = rng.normal(size=m)
    x1, P1, nu, S = fusion.ekf_update(x, P, z, H @ x, H, R)
    S_ref = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S_ref)
    np.testing.assert_allclose(nu, z - H @ x, atol=1e-12)
    np.testing.assert_allclose(S, S_ref, atol=1e-12)
    np.testing.assert_allclose(x1, x + K @ (z - H @ x), atol=1e-10)
    np.testing.assert_allclose(P1, (np.eye(n) - K @ H) @ P, atol=1e-10)
    assert_psd(P1)
    # Callables of x give the same update.
    x2, P2, _, _ = fusion.ekf_update(x, P, z, lambda s: H @ s, lambda s: H, R)
    np.testing.assert_array_equal(x2, x1)
    np.testing.assert_array_equal(P2, P1)


def test_joseph_form_keeps_what_the_short_form_rounds_away():
    """A 1e-9 m^2 fix of a coordinate with 1e10 m^2 prior variance: K H rounds to exactly 1,
    so (I - KH) P claims a zero posterior variance; the Joseph form keeps K R K^T ~ R."""
    P = np.array([[1e10, 0.99e5], [0.99e5, 1.0]])
    H = np.array([[1.0, 0.0]])
    R = np.array([[1e-9]])
    K = P @ H.T / (H @ P @ H.T + R)
    assert ((np.eye(2) - K @ H) @ P)[0, 0] == 0.0
    _, P1, _, _ = fusion.ekf_update(np.zeros(2), P, np.zeros(1), np.zeros(1), H, R)
    assert P1[0, 0] == pytest.approx(1e-9, rel=1e-6)
    assert_psd(P1, tol=0.0)


def test_ekf_update_with_model_residual_does_not_jump_across_pi():
    model = Bearing(StateLayout.planar(), std=0.01)
    xa = np.zeros(2)
    eps = 1e-2
    xb = np.array([np.cos(np.pi - eps), np.sin(np.pi - eps)]) * 10
    P = np.eye(2) * 0.5
    z = np.array([-np.pi + eps])  # 2 eps counter-clockwise of the prediction, across the cut
    _, Hb = model.jacobians(xa, xb)
    x1, _, nu, _ = fusion.ekf_update(xb, P, z, model.h(xa, xb), Hb, model.R, model.residual)
    assert nu[0] == pytest.approx(2 * eps)
    assert np.linalg.norm(x1 - xb) < 0.5
    _, _, nu_raw, _ = fusion.ekf_update(xb, P, z, model.h(xa, xb), Hb, model.R)
    assert abs(nu_raw[0]) > 6.0  # what wrapping prevents


def test_nis_and_nees_are_chi_square_for_a_consistent_filter():
    rng = np.random.default_rng(8)
    n, m, N = 3, 2, 2000
    P = random_spd(n, rng)
    H, R = rng.normal(size=(m, n)), random_spd(m, rng)
    Lp, Lr = np.linalg.cholesky(P), np.linalg.cholesky(R)
    nis_sum = nees_sum = 0.0
    for _ in range(N):
        truth = Lp @ rng.normal(size=n)  # the prior mean 0 is consistent with P
        z = H @ truth + Lr @ rng.normal(size=m)
        x1, P1, nu, S = fusion.ekf_update(np.zeros(n), P, z, np.zeros(m), H, R)
        nis_sum += fusion.nis(nu, S)
        nees_sum += fusion.nees(x1 - truth, P1)
    for total, dof in ((nis_sum, m), (nees_sum, n)):
        lo, hi = scipy.stats.chi2.ppf([0.025, 0.975], N * dof) / N
        assert lo <= total / N <= hi
    nu = np.array([1.0, -2.0])
    assert fusion.nis(nu, R) == pytest.approx(nu @ np.linalg.solve(R, nu))


# --- covariance intersection --------------------------------------------------------------


def test_ci_with_omega_zero_or_one_returns_that_input_exactly():
    rng = np.random.default_rng(0)
    xa, xb = rng.normal(size=3), rng.normal(size=3)
    Pa, Pb = random_spd(3, rng), random_spd(3, rng)
    x, P, w = fusion.covariance_intersection(xa, Pa, xb, Pb, omega=1.0)
    assert w == 1.0 and np.array_equal(x, xa) and np.array_equal(P, Pa)
    x, P, w = fusion.covariance_intersection(xa, Pa, xb, Pb, omega=0.0)
    assert w == 0.0 and np.array_equal(x, xb) and np.array_equal(P, Pb)
    x, P, w = fusion.ci_update(xa, Pa, xb, Pb, np.eye(3), omega=1.0)
    assert np.array_equal(x, xa) and np.array_equal(P, Pa)
    x, P, w = fusion.ci_update(xa, Pa, xb, Pb, np.eye(3), omega=0.0)
    assert np.array_equal(x, xb) and np.array_equal(P, Pb)
    # A dominated input: the optimum is the bound itself, returned exactly.
    for criterion in fusion.CRITERIA:
        x, P, w = fusion.covariance_intersection(xa, Pa, xb, 4.0 * Pa, criterion=criterion)
        assert w == 1.0 and np.array_equal(x, xa) and np.array_equal(P, Pa)
        x, P, w = fusion.covariance_intersection(xa, 4.0 * Pb, xb, Pb, criterion=criterion)
        assert w == 0.0 and np.array_equal(x, xb) and np.array_equal(P, Pb)


def cost(P, criterion):
    return np.trace(P) if criterion == "trace" else np.linalg.det(P)


@pytest.mark.parametrize("criterion", fusion.CRITERIA)
@pytest.mark.parametrize("seed", range(6))
def test_optimised_omega_beats_every_grid_value(criterion, seed):
    rng = np.random.default_rng(seed)
    n = 4
    xa, xb = rng.normal(size=n), rng.normal(size=n)
    Pa, Pb = random_spd(n, rng), random_spd(n, rng)
    _, P, w = fusion.covariance_intersection(xa, Pa, xb, Pb, criterion=criterion)
    grid = [cost(fusion.covariance_intersection(xa, Pa, xb, Pb, omega=g)[1], criterion) for g in np.linspace(0, 1, 101)]
    assert 0.0 <= w <= 1.0
    assert cost(P, criterion) <= min(grid) * (1 + 1e-9)
    # The same for a partial observation: 6 states, the first 2 observed (a position).
    x, P6 = rng.normal(size=6), random_spd(6, rng)
    H = np.eye(2, 6)
    z, Pz = rng.normal(size=2), random_spd(2, rng)
    _, P, w = fusion.ci_update(x, P6, z, Pz, H, criterion=criterion)
    grid = [cost(fusion.ci_update(x, P6, z, Pz, H, omega=g)[1], criterion) for g in np.linspace(0.01, 1, 100)]
    assert 0.0 < w <= 1.0
    assert cost(P, criterion) <= min(grid) * (1 + 1e-9)


@pytest.mark.parametrize("seed", range(4))
def test_ci_update_with_identity_h_is_covariance_intersection(seed):
    rng = np.random.default_rng(seed)
    n = 4
    xa, xb = rng.normal(size=n), rng.normal(size=n)
    Pa, Pb = random_spd(n, rng), random_spd(n, rng)
    for w in (0.05, 0.3, 0.5, 0.9):
        xc, Pc, _ = fusion.covariance_intersection(xa, Pa, xb, Pb, omega=w)
        xu, Pu, _ = fusion.ci_update(xa, Pa, xb, Pb, np.eye(n), omega=w)
        np.testing.assert_allclose(xu, xc, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(Pu, Pc, rtol=1e-9, atol=1e-10)
    for criterion in fusion.CRITERIA:
        xc, Pc, wc = fusion.covariance_intersection(xa, Pa, xb, Pb, criterion=criterion)
        xu, Pu, wu = fusion.ci_update(xa, Pa, xb, Pb, np.eye(n), criterion=criterion)
        # Near its minimum the cost is flat: omega agrees to ~sqrt(eps), the cost to ~eps.
        assert wu == pytest.approx(wc, abs=1e-6)
        assert cost(Pu, criterion) == pytest.approx(cost(Pc, criterion), rel=1e-10)
        np.testing.assert_allclose(Pu, Pc, rtol=1e-5, atol=1e-7)


def test_ci_update_is_the_information_form_on_the_observed_subspace():
    rng = np.random.default_rng(12)
    x, P = rng.normal(size=6), random_spd(6, rng)
    H = rng.normal(size=(3, 6))
    z, Pz = rng.normal(size=3), random_spd(3, rng)
    Ip, Iz = np.linalg.inv(P), np.linalg.inv(Pz)
    for w in (0.1, 0.5, 0.8):
        P_ref = np.linalg.inv(w * Ip + (1 - w) * H.T @ Iz @ H)
        x_ref = P_ref @ (w * Ip @ x + (1 - w) * H.T @ Iz @ z)
        x1, P1, _ = fusion.ci_update(x, P, z, Pz, H, omega=w)
        np.testing.assert_allclose(P1, P_ref, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(x1, x_ref, rtol=1e-8, atol=1e-10)
        assert_psd(P1)


@pytest.mark.parametrize("seed", range(6))
def test_ci_update_bounds_the_true_error_for_any_cross_covariance(seed):
    """x+ = (I - KH) x + K z_est, so its error covariance is A J A^T with A = [I - KH, K] and J
    the joint covariance of (x, z_est) errors. CI must bound it without being told J's
    off-diagonal block; here that block is random (J itself is a random SPD matrix)."""
    rng = np.random.default_rng(100 + seed)
    n, m = 5, 2
    J = random_spd(n + m, rng, floor=0.05)
    P, Pz = J[:n, :n], J[n:, n:]
    H = rng.normal(size=(m, n))
    x, z = np.zeros(n), rng.normal(size=m)
    for omega in (None, 0.2, 0.7):
        for criterion in fusion.CRITERIA:
            x1, P1, w = fusion.ci_update(x, P, z, Pz, H, criterion=criterion, omega=omega)
            # The gain actually applied, recovered from the mean map x+ = x + K (z - H x).
            K = np.column_stack([fusion.ci_update(x, P, e, Pz, H, omega=w)[0] for e in np.eye(m)])
            A = np.hstack([np.eye(n) - K @ H, K])
            true = A @ J @ A.T
            assert np.linalg.eigvalsh(P1 - true).min() >= -1e-9


def correlated_pair():
    """Two estimates of a 2D state sharing a common error c (as when a neighbour's estimate
    already holds our own information): e_a = c + u_a, e_b = c + u_b."""
    C = np.array([[2.0, 0.6], [0.6, 1.0]])
    Ua, Ub = np.diag([0.3, 0.8]), np.diag([0.9, 0.2])
    Pa, Pb = C + Ua, C + Ub
    joint = np.block([[Pa, C], [C, Pb]])
    return Pa, Pb, joint


def test_ci_consistent_and_naive_overconfident_on_correlated_estimates():
    rng = np.random.default_rng(2024)
    Pa, Pb, joint = correlated_pair()
    n, N = 2, 2000
    L = np.linalg.cholesky(joint)
    truth = np.array([3.0, -1.0])
    _, P_ci, w = fusion.covariance_intersection(truth, Pa, truth, Pb)
    _, P_nv = fusion.naive_fusion(truth, Pa, truth, Pb, np.eye(n))
    # The weights each rule applies (mean maps are linear): true covariance of the fused error.
    Wa_ci = w * P_ci @ np.linalg.inv(Pa)
    Wa_nv = P_nv @ np.linalg.inv(Pa)
    for W_a, P in ((Wa_ci, P_ci), (Wa_nv, P_nv)):
        A = np.hstack([W_a, np.eye(n) - W_a])
        np.testing.assert_allclose(A[:, :n] + A[:, n:], np.eye(n))
        true = A @ joint @ A.T
        if P is P_ci:
            assert np.linalg.eigvalsh(P - true).min() >= -1e-12
        else:
            assert np.linalg.eigvalsh(P - true).min() < 0  # naive claims more than it has
    nees_ci = nees_nv = 0.0
    for _ in range(N):
        e = L @ rng.normal(size=2 * n)
        xa, xb = truth + e[:n], truth + e[n:]
        x_ci, P1, _ = fusion.covariance_intersection(xa, Pa, xb, Pb, omega=w)
        x_nv, P2 = fusion.naive_fusion(xa, Pa, xb, Pb, np.eye(n))
        nees_ci += fusion.nees(x_ci - truth, P1)
        nees_nv += fusion.nees(x_nv - truth, P2)
    upper = scipy.stats.chi2.ppf(0.975, N * n) / N
    assert nees_nv / N > upper
    assert nees_ci / N <= upper


def test_distributed_step_with_relative_position_on_uas_states():
    """Paper section 4.1: node i (16-state UAS, no GNSS) fuses node j's estimate through a
    measured relative position; its position is pulled in, the rest follows by correlation."""
    lay = StateLayout.uas16()
    rng = np.random.default_rng(6)
    rel = RelativePosition(lay, std=0.05)
    xi_true, xj_true = rng.normal(size=16), rng.normal(size=16)
    Pi = random_spd(16, rng) + np.diag([25.0] * 3 + [0.0] * 13)  # i has drifted
    Pj = np.diag([0.02] * 3 + [0.1] * 13)  # j has GNSS
    xi = xi_true + np.linalg.cholesky(Pi) @ rng.normal(size=16)
    z = rel.h(xj_true, xi_true)  # j measures i (noise-free here)
    p_est, P_est = rel.implied_position(xj_true, Pj, z, known="a")
    np.testing.assert_allclose(p_est, xi_true[:3], atol=1e-12)
    H = lay.position_matrix()
    x1, P1, w = fusion.ci_update(xi, Pi, p_est, P_est, H)
    assert 0.0 < w < 1.0
    assert np.trace(P1) < np.trace(Pi)
    assert np.trace(P1[:3, :3]) < np.trace(Pi[:3, :3])
    assert np.linalg.norm(x1[:3] - xi_true[:3]) < np.linalg.norm(xi[:3] - xi_true[:3])
    assert_psd(P1)
    xn, Pn = fusion.naive_fusion(xi, Pi, p_est, P_est, H)
    assert np.trace(Pn) < np.trace(P1)  # the independence assumption buys apparent precision


def test_argument_errors():
    P = np.eye(3)
    with pytest.raises(ValueError):
        fusion.covariance_intersection(np.zeros(3), P, np.zeros(3), P, criterion="max")
    with pytest.raises(ValueError):
        fusion.covariance_intersection(np.zeros(3), P, np.zeros(3), P, omega=1.5)
    with pytest.raises(ValueError):
        fusion.ci_update(np.zeros(3), P, np.zeros(2), np.eye(2), np.eye(2, 3), omega=0.0)


def test_ci_split_bounds_the_group_it_cuts():
    """Cutting one member out of a correlated pair by CI (weights 1/2, 1/2): the scaled,
    decorrelated blocks bound the true joint covariance for every direction."""
    rest, own = fusion.ci_split(2, 1)
    assert (rest, own) == (2.0, 2.0)
    P = np.array([[2.0, 1.5], [1.5, 3.0]])
    bound = np.diag([own * P[0, 0], rest * P[1, 1]])
    assert np.linalg.eigvalsh(bound - P).min() >= -1e-12
    with pytest.raises(ValueError):
        fusion.ci_split(3, 3)
