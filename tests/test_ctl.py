"""CSL-CTL by majorization (swarmloc.estimators.ctl.majorization): convergence, the majorizer property, fixed nodes,
the unscented covariance against Monte Carlo, the anchor least squares, input checks."""

import numpy as np
import pytest

from swarmloc.estimators.ctl import majorization as ctl

# Four agents around a target, ranges 130-220 m: well conditioned.
TRUTH = np.array([[0.0, 0.0], [300.0, 20.0], [50.0, 250.0], [280.0, 300.0], [150.0, 120.0]])
N_AGENTS = 4


def full_graph(X, sigma):
    i, j = np.triu_indices(len(X), 1)
    return ctl.Edges(i, j, np.linalg.norm(X[i] - X[j], axis=1), np.broadcast_to(sigma, i.shape))


def target_edges(X, sigma, noise=None):
    i = np.arange(N_AGENTS)
    j = np.full(N_AGENTS, N_AGENTS)
    z = np.linalg.norm(X[i] - X[j], axis=1) + (0.0 if noise is None else noise)
    return ctl.Edges(i, j, z, np.full(N_AGENTS, float(sigma)))


def procrustes(Y, X):
    """Y moved onto X by the best rotation (or reflection) and translation."""
    Yc, Xc = Y - Y.mean(0), X - X.mean(0)
    U, _, Vt = np.linalg.svd(Yc.T @ Xc)
    return Yc @ (U @ Vt) + X.mean(0)


def correlated_prior(rng, std):
    n = std.size
    C = rng.normal(size=(n, n))
    C = C @ C.T
    d = np.sqrt(np.diag(C))
    corr = 0.5 * C / np.outer(d, d) + 0.5 * np.eye(n)
    return corr * np.outer(std, std)


def assert_monotone(stress):
    s = np.asarray(stress)
    assert np.all(s[1:] <= s[:-1] * (1 + 1e-12)), np.diff(s)


@pytest.mark.parametrize("seed", [0, 1])
def test_noiseless_without_prior_recovers_geometry_up_to_rigid_motion(seed):
    rng = np.random.default_rng(seed)
    K = 5
    X = rng.uniform(0, 100, (K, 2))
    edges = full_graph(X, rng.uniform(0.5, 2.0, K * (K - 1) // 2))
    x0 = X + rng.normal(0, 10, X.shape)
    r = ctl.majorize(np.zeros((K, 2)), np.zeros((2 * K, 2 * K)), edges, x0, max_iter=5000)
    assert r.converged
    assert r.iterations == len(r.stress) - 1 > 5
    assert r.stress[0] > 1 and r.stress[-1] < 1e-18
    assert_monotone(r.stress)
    np.testing.assert_allclose(procrustes(r.x, X), X, atol=1e-6)
    # Translations are free: every step is the minimum-norm change, so the centroid stays.
    np.testing.assert_allclose(r.x.mean(0), x0.mean(0), atol=1e-9)


def test_exact_prior_and_ranges_pin_the_target():
    A = np.zeros((10, 10))
    A[:8, :8] = np.eye(8) / 9.0
    x0 = TRUTH.copy()
    x0[4] = [60.0, 260.0]
    r = ctl.majorize(TRUTH, A, target_edges(TRUTH, 10.0), x0, tol=0.0, max_iter=500)
    assert r.converged
    assert_monotone(r.stress)
    np.testing.assert_allclose(r.x[4], TRUTH[4], atol=1e-8)
    np.testing.assert_allclose(r.x[:4], TRUTH[:4], atol=1e-8)
    assert r.stress[-1] < 1e-20


def test_majorizer_bounds_stress_and_touches_at_y():
    rng = np.random.default_rng(3)
    K = 5
    X0 = rng.uniform(0, 50, (K, 2))
    edges = full_graph(X0, rng.uniform(0.5, 3.0, 10)).with_z(rng.uniform(0, 80, 10))
    B = rng.normal(size=(2 * K, 2 * K))
    info = B @ B.T / 50
    info[8:, :] = info[:, 8:] = 0.0  # node 4 without a prior
    prior = X0 + rng.normal(0, 3, X0.shape)
    for _ in range(50):
        X, Y = rng.uniform(-20, 70, (2, K, 2))
        Y[1] = Y[2]  # a coincident pair: its B term is zero
        S_X = ctl.stress(X, prior, info, edges)
        assert ctl.majorizer(X, Y, prior, info, edges) >= S_X - 1e-9 * S_X
        S_Y = ctl.stress(Y, prior, info, edges)
        assert ctl.majorizer(Y, Y, prior, info, edges) == pytest.approx(S_Y, rel=1e-12)
    # One step is the exact minimiser of T(., Y): no perturbation lowers T.
    Y = rng.uniform(-20, 70, (K, 2))
    X1 = ctl.majorize(prior, info, edges, Y, max_iter=1, tol=0.0).x
    T1 = ctl.majorizer(X1, Y, prior, info, edges)
    for _ in range(20):
        D = rng.normal(0, 1e-3, X1.shape)
        assert ctl.majorizer(X1 + D, Y, prior, info, edges) >= T1 - 1e-9 * T1
    assert T1 <= ctl.stress(Y, prior, info, edges)


def test_fixed_agents_do_not_move_and_target_matches_anchor_least_squares():
    rng = np.random.default_rng(4)
    agents = TRUTH[:4] + rng.normal(0, 3, (4, 2))
    edges = target_edges(TRUTH, 10.0, noise=rng.normal(0, 10, 4))
    x0 = np.vstack([agents, [100.0, 200.0]])
    fixed = np.array([True] * 4 + [False])
    A = np.zeros((10, 10))
    A[:8, :8] = np.eye(8)  # a prior on the agents changes nothing while they are fixed
    r = ctl.majorize(x0, A, edges, x0, fixed=fixed, tol=0.0, max_iter=2000)
    assert r.converged
    assert_monotone(r.stress)
    np.testing.assert_array_equal(r.x[:4], agents)
    x_ls, cov_ls = ctl.ls_target(agents, edges.z, edges.sigma, x0[4])
    np.testing.assert_allclose(r.x[4], x_ls, atol=1e-6)

    # IL-CTL: agents taken as exact; the covariance is the range noise through the target fix.
    est = ctl.estimate(x0, np.eye(8), edges, x0, has_prior=fixed, fixed=fixed)
    np.testing.assert_array_equal(est.x[:4], agents)
    assert np.all(est.cov[:8] == 0) and np.all(est.cov[:, :8] == 0)
    np.testing.assert_allclose(est.cov[8:, 8:], cov_ls, rtol=0.05, atol=0.02 * np.trace(cov_ls))


def test_unscented_covariance_matches_monte_carlo():
    rng = np.random.default_rng(5)
    P = correlated_prior(rng, np.array([3.0, 4.0, 2.0, 5.0, 3.0, 3.0, 4.0, 2.0]))
    sigma = 10.0
    has_prior = np.array([True] * 4 + [False])
    edges = target_edges(TRUTH, sigma)
    prior_mean = TRUTH.copy()
    prior_mean[4] = np.nan  # no prior on the target: ignored
    est = ctl.estimate(prior_mean, P, edges, TRUTH, has_prior=has_prior)
    lit = ctl.estimate(prior_mean, P, edges, TRUTH, has_prior=has_prior, noise=False)
    assert est.runs == 2 * (8 + 4) + 1 and lit.runs == 4 * N_AGENTS + 1
    assert est.majorized.converged and est.sigma_unconverged == 0
    np.testing.assert_allclose(est.x, TRUTH, atol=1e-3)
    np.testing.assert_array_equal(est.cov, est.cov.T)

    # Monte Carlo of the same estimator: perturb the prior mean and the ranges around truth.
    n = 2000
    A = np.zeros((10, 10))
    A[:8, :8] = np.linalg.inv(P)
    means = np.repeat(TRUTH[None], n, axis=0)
    means[:, :4] += (rng.normal(size=(n, 8)) @ np.linalg.cholesky(P).T).reshape(n, 4, 2)
    z = edges.z + sigma * rng.normal(size=(n, 4))
    x, iters, conv = ctl.majorize_many(means, A, edges, z, TRUTH)
    assert conv.all()
    for k in range(3):  # the vectorised runs are the scalar ones
        r = ctl.majorize(means[k], A, edges.with_z(z[k]), TRUTH)
        np.testing.assert_allclose(x[k], r.x, atol=1e-9)
        assert iters[k] == r.iterations
    C = np.cov(x.reshape(n, -1).T)

    # A sample variance has relative standard error sqrt(2 / (n - 1)); allow 5 of them plus
    # 3% for the transform's linearisation.
    var_ut, var_mc = np.diag(est.cov), np.diag(C)
    np.testing.assert_array_less(np.abs(var_ut / var_mc - 1), 5 * np.sqrt(2 / (n - 1)) + 0.03)
    rho_ut = est.cov / np.sqrt(np.outer(var_ut, var_ut))
    rho_mc = C / np.sqrt(np.outer(var_mc, var_mc))
    np.testing.assert_array_less(np.abs(rho_ut - rho_mc), 5 * (1 - rho_mc**2) / np.sqrt(n) + 0.03)

    # Without the range noise the target is far too confident; agents barely differ.
    assert np.all(np.diag(lit.cov)[8:] < 0.3 * var_ut[8:])
    assert np.linalg.eigvalsh(est.cov - lit.cov)[0] > -1e-2 * np.abs(est.cov).max()
    assert np.trace(lit.cov) < np.trace(est.cov)


def test_estimate_with_all_nodes_having_a_prior_and_spread():
    rng = np.random.default_rng(6)
    P = correlated_prior(rng, np.full(10, 3.0))
    edges = target_edges(TRUTH, 10.0)
    a = ctl.estimate(TRUTH, P, edges, TRUTH)
    b = ctl.estimate(TRUTH, P, edges, TRUTH, spread=20.0)  # n = 14: positive centre weight
    assert np.all(np.isfinite(a.cov))
    np.testing.assert_allclose(b.cov, a.cov, rtol=0.05, atol=0.05)
    # Information only adds: the posterior is tighter than the prior (within UT error).
    assert np.linalg.eigvalsh(P - a.cov)[0] > -0.05
    with pytest.raises(ValueError, match="spread"):
        ctl.estimate(TRUTH, P, edges, TRUTH, spread=10.0)


def test_ls_target_exact_and_with_prior():
    anchors = TRUTH[:3]
    z = np.linalg.norm(anchors - TRUTH[4], axis=1)
    x, cov = ctl.ls_target(anchors, z, np.full(3, 5.0), np.array([0.0, 300.0]))
    np.testing.assert_allclose(x, TRUTH[4], atol=1e-8)
    np.testing.assert_array_equal(cov, cov.T)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    # Two anchors are ambiguous alone; with the previous tick's estimate as prior they are not.
    x2, cov2 = ctl.ls_target(anchors[:2], z[:2], np.full(2, 5.0), x, prior=(x, cov))
    np.testing.assert_allclose(x2, TRUTH[4], atol=1e-8)
    assert np.linalg.eigvalsh(cov - cov2)[0] > 0


@pytest.mark.slow
def test_ls_target_covariance_matches_monte_carlo():
    rng = np.random.default_rng(7)
    anchors, target = TRUTH[:4], TRUTH[4]
    sigma = np.array([5.0, 8.0, 5.0, 10.0])
    z0 = np.linalg.norm(anchors - target, axis=1)
    n = 2000
    xs = np.array([ctl.ls_target(anchors, z0 + sigma * rng.normal(size=4), sigma, target)[0] for _ in range(n)])
    _, cov = ctl.ls_target(anchors, z0, sigma, target)
    C = np.cov(xs.T)
    np.testing.assert_allclose(np.diag(C), np.diag(cov), rtol=5 * np.sqrt(2 / (n - 1)) + 0.05)
    np.testing.assert_array_less(np.abs(xs.mean(0) - target), 5 * np.sqrt(np.diag(cov) / n) + 0.1)


def test_coincident_nodes_give_finite_results():
    K = 3
    edges = full_graph(np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]]), 1.0)
    x0 = np.zeros((K, 2))  # every distance zero: B(Y) = 0
    r = ctl.majorize(np.zeros((K, 2)), np.zeros((6, 6)), edges, x0)
    assert np.all(np.isfinite(r.x)) and np.all(np.isfinite(r.stress))
    r = ctl.majorize(np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]]), np.eye(6), edges, x0)
    assert np.all(np.isfinite(r.x)) and r.stress[-1] < r.stress[0]


def test_bad_inputs_raise_value_error():
    good = dict(i=[0, 1], j=[1, 2], z=[1.0, 2.0], sigma=[1.0, 1.0])
    for bad in (
        dict(z=[1.0, np.nan]),
        dict(z=[1.0, -1.0]),
        dict(sigma=[1.0, 0.0]),
        dict(sigma=[1.0, np.inf]),
        dict(i=[0, 2]),  # self-edge 2-2
        dict(i=[0.0, 1.0]),
        dict(i=[0, -1]),
        dict(j=[1]),
        dict(z=[[1.0, 2.0]]),
    ):
        with pytest.raises(ValueError):
            ctl.Edges(**{**good, **bad})
    edges = ctl.Edges(**good)
    K = 3
    x, A = np.zeros((K, 2)), np.eye(2 * K)
    with pytest.raises(ValueError, match="x0"):
        ctl.majorize(x, A, edges, np.full((K, 2), np.nan))
    with pytest.raises(ValueError, match="prior_mean"):
        ctl.majorize(np.zeros((K + 1, 2)), A, edges, x)
    with pytest.raises(ValueError, match="info"):
        ctl.majorize(x, A[:4, :4], edges, x)
    with pytest.raises(ValueError, match="symmetric"):
        ctl.majorize(x, A + np.triu(np.ones_like(A), 1), edges, x)
    with pytest.raises(ValueError, match="semi-definite"):
        ctl.majorize(x, -A, edges, x)
    with pytest.raises(ValueError, match="K = 2"):
        ctl.majorize(x[:2], A[:4, :4], edges, x[:2])
    with pytest.raises(ValueError, match="fixed"):
        ctl.majorize(x, A, edges, x, fixed=np.array([1, 0, 0]))
    with pytest.raises(ValueError, match="not positive definite"):
        ctl.estimate(x, np.zeros((6, 6)), edges, x)
    with pytest.raises(ValueError, match="prior_cov"):
        ctl.estimate(x, np.eye(6), edges, x, has_prior=np.array([True, True, False]))
    with pytest.raises(ValueError, match="prior_mean"):
        ctl.estimate(np.full((K, 2), np.nan), np.eye(6), edges, x)
    with pytest.raises(ValueError, match="anchors"):
        ctl.ls_target(TRUTH[:2], np.ones(2), np.ones(2), np.zeros(2))
    with pytest.raises(ValueError, match="collinear"):
        ctl.ls_target(np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]), np.ones(3), np.ones(3), np.zeros(2))
    with pytest.raises(ValueError, match="z"):
        ctl.ls_target(TRUTH[:3], np.array([1.0, np.nan, 1.0]), np.ones(3), np.zeros(2))
    with pytest.raises(ValueError, match="not positive definite"):
        ctl.ls_target(TRUTH[:2], np.ones(2), np.ones(2), np.zeros(2), prior=(np.zeros(2), np.zeros((2, 2))))
