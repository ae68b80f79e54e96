"""NBP primitives: Gaussian mixtures, range (ring) messages, mixture importance sampling, prediction,
and the least-squares baseline. Monte Carlo tolerances are stated in standard errors."""

import time

import numpy as np
import pytest
import scipy.stats

from swarmloc.estimators.nbp import mixtures as nbp
from swarmloc.estimators.nbp.mixtures import GaussianMixture


def random_spd(n, rng, floor=0.1):
    A = rng.normal(size=(n, n))
    return A @ A.T / n + floor * np.eye(n)


def three_component(d, rng, shared):
    means = rng.normal(scale=3.0, size=(3, d))
    weights = np.array([0.5, 0.3, 0.2])
    H = random_spd(d, rng) if shared else np.stack([random_spd(d, rng) for _ in range(3)])
    return GaussianMixture(means, weights, H)


# --- GaussianMixture --------------------------------------------------------------------


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("shared", [True, False])
def test_sampling_reproduces_mixture_moments(d, shared):
    rng = np.random.default_rng(10 * d + shared)
    gm = three_component(d, rng, shared)
    # The analytic moments, written out independently of mean() and cov().
    H = gm.bandwidth if not shared else np.broadcast_to(gm.bandwidth, (3, d, d))
    m_ref = sum(w * mu for w, mu in zip(gm.weights, gm.means))
    C_ref = sum(w * (Hi + np.outer(mu, mu)) for w, mu, Hi in zip(gm.weights, gm.means, H)) - np.outer(m_ref, m_ref)
    np.testing.assert_allclose(gm.mean(), m_ref, atol=1e-12)
    np.testing.assert_allclose(gm.cov(), C_ref, atol=1e-12)

    n = 200_000
    x = gm.sample(n, rng)
    assert x.shape == (n, d)
    # Sample mean: standard error sqrt(C_ii / n); 5 standard errors.
    se_mean = np.sqrt(np.diag(C_ref) / n)
    assert np.all(np.abs(x.mean(0) - m_ref) < 5 * se_mean)
    # Sample covariance entries are means of the products p_ij = dx_i dx_j, so their standard
    # error is std(p_ij) / sqrt(n), estimated from the same samples; 5 standard errors.
    dx = x - m_ref
    p = dx[:, :, None] * dx[:, None, :]
    se_cov = p.std(0) / np.sqrt(n)
    assert np.all(np.abs(p.mean(0) - C_ref) < 5 * se_cov)


@pytest.mark.parametrize("d", [2, 3])
def test_logpdf_matches_scipy(d):
    rng = np.random.default_rng(d)
    mu, H = rng.normal(size=d), random_spd(d, rng)
    x = rng.normal(scale=2.0, size=(50, d))
    one = GaussianMixture(mu[None], np.ones(1), H)
    ref = scipy.stats.multivariate_normal(mu, H).logpdf(x)
    np.testing.assert_allclose(one.logpdf(x), ref, rtol=1e-10)
    assert one.logpdf(x[0]) == pytest.approx(ref[0], rel=1e-10)
    # Far from the mean the density underflows, the log density does not.
    far = one.logpdf(mu + 1e3)
    assert np.isfinite(far) and far < -1e4
    # Several components, shared and per-component kernels: the weighted sum of scipy pdfs.
    gm = three_component(d, rng, shared=False)
    ref = np.log(sum(w * scipy.stats.multivariate_normal(m, Hi).pdf(x)
                     for w, m, Hi in zip(gm.weights, gm.means, gm.bandwidth)))
    np.testing.assert_allclose(gm.logpdf(x), ref, rtol=1e-10)
    shared = GaussianMixture(gm.means, gm.weights, gm.bandwidth[0])
    per = GaussianMixture(gm.means, gm.weights, np.broadcast_to(gm.bandwidth[0], (3, d, d)))
    np.testing.assert_allclose(shared.logpdf(x), per.logpdf(x), rtol=1e-12)


def test_weights_are_normalised_and_bad_inputs_rejected():
    gm = GaussianMixture(np.zeros((2, 2)), np.array([2.0, 6.0]), np.eye(2))
    np.testing.assert_allclose(gm.weights, [0.25, 0.75])
    with pytest.raises(ValueError):
        GaussianMixture(np.zeros((2, 2)), np.array([1.0, -1.0]), np.eye(2))
    with pytest.raises(np.linalg.LinAlgError):
        GaussianMixture(np.zeros((1, 2)), np.ones(1), np.diag([1.0, -1.0]))


def test_silverman_bandwidth():
    rng = np.random.default_rng(3)
    d, n = 2, 400
    x = rng.multivariate_normal([1.0, -2.0], [[4.0, 1.0], [1.0, 2.0]], size=n)
    H = GaussianMixture.bandwidth_for(x, rule="silverman", min_std=0.0)
    c = (4.0 / ((d + 2) * n)) ** (2.0 / (d + 4))
    np.testing.assert_allclose(H, c * np.cov(x.T), rtol=1e-12)
    # Weights concentrated on half the samples: n_eff = n / 2, a wider kernel.
    w = np.r_[np.ones(n // 2), np.zeros(n // 2)]
    Hw = GaussianMixture.bandwidth_for(x, w, rule="silverman", min_std=0.0)
    np.testing.assert_allclose(Hw, (4.0 / ((d + 2) * n / 2)) ** (2.0 / (d + 4)) * np.cov(x[: n // 2].T), rtol=1e-10)
    # A point belief still has a positive definite kernel.
    GaussianMixture.from_samples(np.zeros((10, 3)))


# --- Range messages -----------------------------------------------------------------------


@pytest.mark.parametrize("d", [2, 3])
def test_range_message_of_a_point_is_a_ring(d):
    rng = np.random.default_rng(20 + d)
    z, sigma, M_out = 20.0, 1.0, 4000
    msg = nbp.range_message(np.zeros((50, d)), None, z, sigma, rng, M_out)
    # The ring samples themselves: distances z + N(0, sigma^2).
    r0 = np.linalg.norm(msg.means, axis=1)
    assert abs(r0.mean() - z) < 5 * sigma / np.sqrt(M_out)
    assert r0.std() == pytest.approx(sigma, rel=5 / np.sqrt(2 * M_out))
    # The message (ring + kernel): radial spread sqrt(sigma^2 + h^2), and the kernel's cross-track
    # part lengthens distances by (d - 1) h^2 / (2 z) to second order (Range.second_order).
    h2 = np.trace(msg.bandwidth) / d
    n = 40_000
    x = msg.sample(n, rng)
    r = np.linalg.norm(x, axis=1)
    s = np.sqrt(sigma**2 + h2)
    assert abs(r.mean() - (z + (d - 1) * h2 / (2 * z))) < 5 * s / np.sqrt(n) + 0.05 * h2 / z
    assert r.std() == pytest.approx(s, rel=0.05)
    # Directions uniform: in 2D the angle is uniform on [-pi, pi); in 3D (Archimedes) the
    # z-component of the unit vector is uniform on [-1, 1] and the azimuth on [-pi, pi).
    # Tested on the M_out i.i.d. ring samples: draws from the KDE resample those same M_out
    # directions, so a KS test on more of them would detect the finite base sample instead.
    u = msg.means / r0[:, None]
    az = np.arctan2(u[:, 1], u[:, 0])
    assert scipy.stats.kstest(az, scipy.stats.uniform(-np.pi, 2 * np.pi).cdf).pvalue > 1e-3
    if d == 3:
        assert scipy.stats.kstest(u[:, 2], scipy.stats.uniform(-1, 2).cdf).pvalue > 1e-3
    # And it is centred on the sender, not biased to one side.
    # (The mixture mean is the mean of the M_out ring samples, whose own spread is about z.)
    assert np.all(np.abs(msg.mean()) < 5 * np.sqrt(z**2 / d / M_out))


def test_range_message_with_explicit_bandwidth():
    rng = np.random.default_rng(5)
    msg = nbp.range_message(np.ones((10, 2)), np.ones(10), 10.0, 0.5, rng, 500, bandwidth=0.5)
    np.testing.assert_allclose(msg.bandwidth, 0.25 * np.eye(2))
    with pytest.raises(ValueError):
        nbp.range_message(np.ones((10, 4)), None, 10.0, 0.5, rng, 500)


# --- Belief update: mixture importance sampling ------------------------------------------

ANCHORS = np.array([[0.0, 0.0], [20.0, 0.0], [5.0, 18.0]])
TRUTH = np.array([8.0, 6.0])
MIRROR = np.array([8.0, -6.0])  # TRUTH reflected in the line through the first two anchors
SIGMA = 0.5


def localise(seed, bandwidth, iterations=3, M=300, n_anchors=3):
    """NBP iterations for one fault node ranging to exact-position anchors (narrow GNSS beliefs).
    Returns (belief, LS estimate or None) for the same ranges."""
    rng = np.random.default_rng(seed)
    anchors = ANCHORS[:n_anchors]
    ranges = np.linalg.norm(anchors - TRUTH, axis=1) + SIGMA * rng.standard_normal(n_anchors)
    beliefs = [nbp.gnss_message(a, 0.01**2 * np.eye(2)) for a in anchors]
    b = None
    for _ in range(iterations):
        msgs = [nbp.range_message(bel.sample(M, rng), None, z, SIGMA, rng, M, bandwidth=bandwidth)
                for bel, z in zip(beliefs, ranges)]
        b = nbp.belief_update(None, msgs, M, rng, guide=b)
    return b, nbp.least_squares_position(anchors, ranges, SIGMA)


@pytest.mark.parametrize("bandwidth, tol", [(SIGMA, 1.5 * SIGMA), (None, 2.5 * SIGMA)])
def test_belief_update_with_three_anchors_localises(bandwidth, tol):
    """Over 10 noise draws the belief mean is as good as the least-squares fix: within about the
    range noise (RMS), the error the ranges themselves leave. The Silverman kernel on a ring is
    wide (about 0.27 z), which blurs and biases the product, hence the looser tolerance."""
    err, err_ls, spread = [], [], []
    for seed in range(10):
        b, (x_ls, _) = localise(seed, bandwidth)
        err.append(np.linalg.norm(b.mean() - TRUTH))
        err_ls.append(np.linalg.norm(x_ls - TRUTH))
        spread.append(np.sqrt(np.trace(b.cov()) / 2))
    rms = np.sqrt(np.mean(np.square(err)))
    assert rms < tol, (rms, np.sqrt(np.mean(np.square(err_ls))))
    assert max(err) < 3 * tol
    if bandwidth is not None:
        # A unimodal belief about as wide as the noise, not a ring or two clusters.
        assert np.median(spread) < 3 * SIGMA


@pytest.mark.parametrize("bandwidth", [SIGMA, None])
def test_belief_update_with_two_anchors_stays_bimodal(bandwidth):
    for seed in range(3):
        b, ls = localise(seed, bandwidth, n_anchors=2)
        assert ls is None  # two anchors are not enough for the baseline
        near_truth = np.linalg.norm(b.means - TRUTH, axis=1) < 4.0
        near_mirror = np.linalg.norm(b.means - MIRROR, axis=1) < 4.0
        assert b.weights[near_truth].sum() > 0.2
        assert b.weights[near_mirror].sum() > 0.2
        if bandwidth is not None:
            # Two clusters and nothing between them: the mean sits in the empty middle.
            assert b.weights[near_truth | near_mirror].sum() > 0.95
            assert abs(b.mean()[1]) < 4.0


def test_belief_update_weights_by_the_product():
    """Two 1-component messages: the product of Gaussians is a Gaussian with known moments."""
    rng = np.random.default_rng(7)
    P1, P2 = np.diag([4.0, 1.0]), np.diag([1.0, 4.0])
    m1, m2 = np.array([0.0, 0.0]), np.array([2.0, 1.0])
    msgs = [GaussianMixture(m1[None], np.ones(1), P1), GaussianMixture(m2[None], np.ones(1), P2)]
    P = np.linalg.inv(np.linalg.inv(P1) + np.linalg.inv(P2))
    m = P @ (np.linalg.solve(P1, m1) + np.linalg.solve(P2, m2))
    b = nbp.belief_update(None, msgs, 20_000, rng)
    n_eff = 1.0 / np.sum(b.weights**2)
    assert np.all(np.abs(b.mean() - m) < 5 * np.sqrt(np.diag(P) / n_eff))
    # The KDE adds its kernel to the weighted sample covariance.
    np.testing.assert_allclose(b.cov() - b.bandwidth, P, atol=0.1 * P.max())
    # A prior is one more factor: prior = msgs[1] gives the same product as the message did.
    b2 = nbp.belief_update(msgs[1], msgs[:1], 20_000, rng)
    assert np.all(np.abs(b2.mean() - m) < 5 * np.sqrt(np.diag(P) / n_eff))
    with pytest.raises(ValueError):
        nbp.belief_update(None, [], 10, rng)


def test_belief_update_timing_is_measured():
    """Not asserted (machine dependent); run with -s to see it."""
    rng = np.random.default_rng(8)
    M = 300
    msgs = [nbp.range_message(np.tile(a, (M, 1)), None, float(np.linalg.norm(a - TRUTH)), SIGMA, rng, M)
            for a in ANCHORS]
    msgs.append(nbp.gnss_message(TRUTH, 4.0 * np.eye(2)))
    msgs[-1] = GaussianMixture.from_samples(msgs[-1].sample(M, rng))  # a 300-component one too
    times = []
    for _ in range(20):
        t = time.perf_counter()
        nbp.belief_update(None, msgs, M, rng)
        times.append(time.perf_counter() - t)
    print(f"\nbelief_update, M = {M}, 4 messages of {M} components: median {1e3 * np.median(times):.2f} ms")


# --- Prediction -------------------------------------------------------------------------


def test_predict_propagates_moments():
    rng = np.random.default_rng(9)
    dt = 0.5
    F = np.block([[np.eye(2), dt * np.eye(2)], [np.zeros((2, 2)), np.eye(2)]])
    Q = np.diag([0.0, 0.0, 0.1, 0.1])  # singular: noise on velocity only
    C0 = random_spd(4, rng)
    belief = GaussianMixture(np.array([[1.0, 2.0, 3.0, -1.0]]), np.ones(1), C0)
    M = 20_000
    pred = nbp.predict(belief, F, Q, rng, M)
    C = F @ C0 @ F.T + Q
    np.testing.assert_allclose(pred.mean(), F @ belief.mean(), atol=5 * np.sqrt(np.diag(C).max() / M))
    # The KDE adds its kernel: covariance (1 + c) C with Silverman's c.
    c = (4.0 / (6 * M)) ** (2.0 / 8)
    np.testing.assert_allclose(pred.cov(), (1 + c) * C, atol=0.1 * np.abs(C).max())
    # A known input term shifts the prediction.
    u = np.array([0.0, 0.0, 1.0, -2.0])
    shifted = nbp.predict(belief, F, Q, rng, M, u=u)
    np.testing.assert_allclose(shifted.mean(), F @ belief.mean() + u, atol=5 * np.sqrt(np.diag(C).max() / M))


# --- Least squares baseline ---------------------------------------------------------------


def test_least_squares_recovers_position_with_consistent_cov():
    rng = np.random.default_rng(11)
    sigma = 0.2
    true_r = np.linalg.norm(ANCHORS - TRUTH, axis=1)
    x, cov = nbp.least_squares_position(ANCHORS, true_r, sigma)
    np.testing.assert_allclose(x, TRUTH, atol=1e-8)  # exact ranges: exact fix
    est = np.array([nbp.least_squares_position(ANCHORS, true_r + sigma * rng.standard_normal(3), sigma)[0]
                    for _ in range(300)])
    err = est - TRUTH
    # Errors are of the size the returned covariance says (NEES averages to d = 2; 300 draws).
    nees = np.einsum("ni,ij,nj->n", err, np.linalg.inv(cov), err)
    assert 1.6 < nees.mean() < 2.5
    assert np.all(np.linalg.norm(err, axis=1) < 6 * np.sqrt(np.trace(cov)))


def test_least_squares_3d_and_degenerate_geometries():
    truth = np.array([3.0, 4.0, 5.0])
    a3 = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]])
    x, _ = nbp.least_squares_position(a3, np.linalg.norm(a3 - truth, axis=1), 0.1)
    np.testing.assert_allclose(x, truth, atol=1e-8)
    r = np.linalg.norm(ANCHORS - TRUTH, axis=1)
    assert nbp.least_squares_position(ANCHORS[:2], r[:2], 0.1) is None  # too few
    collinear = np.array([[0.0, 0.0], [10.0, 0.0], [25.0, 0.0]])
    assert nbp.least_squares_position(collinear, np.linalg.norm(collinear - TRUTH, axis=1), 0.1) is None
    coplanar = a3.copy()
    coplanar[3] = [10.0, 10.0, 0.0]
    assert nbp.least_squares_position(coplanar, np.linalg.norm(coplanar - truth, axis=1), 0.1) is None
