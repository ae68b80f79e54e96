"""UKF-CCL's measurement update from the measured platforms' columns of the factor only
(swarmloc/estimators/ukf/ccl.py): the same filter as the unscented transform over a Cholesky
factor of the whole joint covariance, to rounding."""

import numpy as np

from swarmloc.estimators.ukf.ccl import CentralizedUKF
from swarmloc.filters import kalman


def whole_factor_update(f: CentralizedUKF, m, n, z, R):
    """The update as it was: sigma points of every column of a full factor (eq. 17)."""
    key = (m, 0, n, 0)
    idx = np.r_[f.block(m), f.block(n)]
    S = kalman.cholesky_first(f.P, idx)
    h, angles = f.obs.h(key)
    z_bar, Pzz, Y = f.ut.measurement_moments(f.x, S, lambda X: h(X[..., idx]), angles)
    nu = f.obs.innovation(z, z_bar, angles)
    x, P, _ = kalman.update(f.x, f.P, S @ Y, Pzz + R, nu)
    return x, P


def test_reduced_sigma_points_equal_the_whole_factor():
    rng = np.random.default_rng(3)
    n = 7
    x0 = {a: rng.uniform(0, 50, 2) for a in range(1, n + 1)}
    f = CentralizedUKF(x0, np.eye(2), model="planar-speed-heading")
    A = rng.normal(size=(2 * n, 2 * n))
    f.P = A @ A.T + 0.5 * np.eye(2 * n)  # a dense joint covariance: every platform correlated
    for m, t in ((2, 5), (7, 1), (3, 4)):
        z = np.array([np.linalg.norm(f.x[f.block(m)] - f.x[f.block(t)]) + rng.normal()])
        R = np.array([[1.0]])
        x_ref, P_ref = whole_factor_update(f, m, t, z, R)
        assert f.update(m, t, z, R) is not None
        np.testing.assert_allclose(f.x, x_ref, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(f.P, P_ref, rtol=1e-9, atol=1e-9)
        assert not np.allclose(f.P, A @ A.T + 0.5 * np.eye(2 * n))  # the update did something
