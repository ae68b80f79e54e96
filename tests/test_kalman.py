"""The shared Kalman core: unscented transform, reordered Cholesky, full-vs-reduced equality."""

import numpy as np
import pytest

from swarmloc.filters import kalman


def random_spd(n, rng):
    A = rng.normal(size=(n, n))
    return A @ A.T + n * np.eye(n)


def test_linear_measurement_matches_kalman_filter():
    rng = np.random.default_rng(0)
    x, P = rng.normal(size=4), random_spd(4, rng)
    H = rng.normal(size=(2, 4))
    ut = kalman.UnscentedTransform(3.0)
    S = np.linalg.cholesky(P)
    z, Pzz, Y = ut.measurement_moments(x, S, lambda X: X @ H.T)
    np.testing.assert_allclose(z, H @ x, atol=1e-12)
    np.testing.assert_allclose(Pzz, H @ P @ H.T, atol=1e-10)
    np.testing.assert_allclose(S @ Y, P @ H.T, atol=1e-10)


def test_permuted_cholesky_is_a_square_root_with_chosen_blocks_first():
    rng = np.random.default_rng(1)
    P = random_spd(8, rng)
    S = kalman.permuted_cholesky(P, [2, 0], block=2)
    np.testing.assert_allclose(S @ S.T, P, atol=1e-10)
    # Block 2 comes first: its rows have nothing beyond the first two columns.
    assert np.all(S[4:6, 2:] == 0)
    # Block 0 comes second: nothing beyond the first four columns.
    assert np.all(S[0:2, 4:] == 0)


@pytest.mark.parametrize("spread", [0.5, 3.0, 10.0])
def test_reduced_transform_equals_full_transform(spread):
    """The property UKF-DCL rests on: with the spread fixed, a measurement of blocks (m, n)
    transforms the same on [x_m; x_n] as on the whole swarm state."""
    rng = np.random.default_rng(2)
    N, d = 5, 2
    P = random_spd(N * d, rng)
    x = rng.normal(size=N * d) * 30
    m, n = 3, 1
    ut = kalman.UnscentedTransform(spread)
    idx = np.r_[m * d:(m + 1) * d, n * d:(n + 1) * d]
    h = lambda X: np.linalg.norm(X[..., :2] - X[..., 2:4], axis=-1, keepdims=True)
    S = kalman.permuted_cholesky(P, [m, n], d)
    z_full, Pzz_full, Y_full = ut.measurement_moments(x, S, lambda X: h(X[..., idx]))
    L = np.linalg.cholesky(P[np.ix_(idx, idx)])
    z_sub, Pzz_sub, Y_sub = ut.measurement_moments(x[idx], L, h)
    np.testing.assert_allclose(z_sub, z_full, rtol=1e-12)
    np.testing.assert_allclose(Pzz_sub, Pzz_full, rtol=1e-10)
    # Node i's weight from its own row only (eq. 20): [P_im P_in] L^-T Y.
    for i in range(N):
        rows = P[i * d:(i + 1) * d][:, idx]
        mine = kalman.solve_lower(L, rows.T).T @ Y_sub
        np.testing.assert_allclose(mine, (S @ Y_full)[i * d:(i + 1) * d], atol=1e-10)


def test_update_subtracts_gain_term():
    """Erratum of eq. 11: the covariance shrinks, P+ = P - K Pz K^T."""
    rng = np.random.default_rng(3)
    P = random_spd(4, rng)
    Pxz = rng.normal(size=(4, 1))
    Pz = np.array([[5.0]])
    _, P_new, K = kalman.update(np.zeros(4), P, Pxz, Pz, np.zeros(1))
    assert np.trace(P_new) < np.trace(P)
    np.testing.assert_allclose(P_new, P - K @ Pz @ K.T)


def test_spread_at_least_pair_dimension_keeps_posterior_positive():
    """With spread >= the dimension of what the measurement touches, no sigma weight is
    negative and P - Pxz Pz^-1 Pxz^T stays PSD for any prior. Julier's n + kappa = 3 on the
    4-dimensional pair can go negative for close, uncertain platforms (what we saw in a run)."""
    rng = np.random.default_rng(7)
    h = lambda X: np.linalg.norm(X[..., :2] - X[..., 2:4], axis=-1, keepdims=True)
    R = np.array([[1.0]])
    worst = {3.0: np.inf, 4.0: np.inf}
    for _ in range(3000):
        P = random_spd(4, rng) * rng.uniform(0.1, 50)
        x = np.concatenate([np.zeros(2), rng.normal(size=2) * rng.uniform(0.1, 5)])  # close platforms
        for spread in worst:
            _, Pzz, Y = kalman.UnscentedTransform(spread).measurement_moments(x, np.linalg.cholesky(P), h)
            S = np.linalg.cholesky(P)
            post = P - (S @ Y) @ np.linalg.solve(Pzz + R, (S @ Y).T)
            worst[spread] = min(worst[spread], np.linalg.eigvalsh(post).min())
    assert worst[4.0] > -1e-9
    assert worst[3.0] < -1e-3  # the failure the default avoids
