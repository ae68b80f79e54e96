"""Nonparametric belief propagation (NBP) primitives: the maths behind the dNBP estimator family.

Wan, Yu, Wu, Feng, Zhang, "Cooperative localization of multi-UAV via dynamic nonparametric
belief propagation under GPS signal loss condition" (IJDSN 2014), built on Ihler, Fisher,
Moses, Willsky, "Nonparametric belief propagation for self-localization of sensor networks"
(IEEE JSAC 2005). Beliefs and messages are Gaussian mixtures (kernel density estimates) over a
node's position; the message a neighbour sends for a range measurement is a "ring" (Ihler
section IV-A, Wan Algorithm 1); the belief is the product of the incoming messages (and the
forward-time prediction, Wan Algorithm 4), computed by mixture importance sampling (Ihler
section IV-B, Wan Algorithm 2) because the exact product of k M-component mixtures has M^k
components; the prediction is a particle-filter step through the linear Markov motion model
(Wan Algorithm 3). `least_squares_position` is the "traditional" baseline of Wan section 4
(a fault UAV multilaterates from the normal UAVs it can range to).

Conventions: points are rows, x of shape (n, d); d is the state dimension (2 or 3 for a
position; any d >= 1 works for the mixture itself, e.g. a position-velocity state in
`predict`). Weights are normalised. Kernel covariances ("bandwidths") are positive definite.
Randomness comes only from the `rng` (a numpy Generator) passed in, so runs are reproducible.
Everything is vectorised over samples and components; the only Python loops run over the few
incoming messages or over memory-bounded blocks of points.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

RULES = ("silverman", "scott")

# logpdf evaluates an (n, M) table of kernel densities; block the points so the (n, M, d)
# intermediate stays around this many floats (8 MB) however large n * M gets.
_BLOCK_FLOATS = 1 << 20


def _logsumexp(a: np.ndarray, axis: int) -> np.ndarray:
    """log sum exp along axis, safe for -inf entries (zero weights). numpy, not scipy.special:
    agents load only what they use."""
    m = np.max(a, axis=axis, keepdims=True)
    m = np.where(np.isfinite(m), m, 0.0)  # an all -inf slice gives -inf, not NaN
    e = a - m
    np.exp(e, out=e)
    with np.errstate(divide="ignore"):
        out = np.log(np.sum(e, axis=axis, keepdims=True)) + m
    return np.squeeze(out, axis=axis)


def _normalise_log(logw: np.ndarray) -> np.ndarray:
    """exp(logw) / sum exp(logw), computed without overflow or underflow to all-zero."""
    logw = np.asarray(logw, dtype=float)
    if not np.any(np.isfinite(logw)):
        raise ValueError("all importance weights are zero")
    w = np.exp(logw - np.max(logw[np.isfinite(logw)]))
    return w / w.sum()


@dataclass(frozen=True, eq=False)
class GaussianMixture:
    """p(x) = sum_i w_i N(x; mu_i, H_i), a kernel density estimate when the mu_i are samples.

    means (M, d); weights (M,) non-negative, normalised here; bandwidth H either one (d, d)
    kernel covariance shared by all components (the KDE case, Ihler eq. 14-15) or per
    component (M, d, d) (e.g. a GNSS fix, or an exactly propagated mixture).
    """

    means: np.ndarray
    weights: np.ndarray
    bandwidth: np.ndarray
    # Cholesky factors, and their inverses and log-determinants, computed once here (which also
    # rejects a bandwidth that is not positive definite) because logpdf and sample reuse them.
    _chol: np.ndarray = field(init=False, repr=False)
    _chol_inv: np.ndarray = field(init=False, repr=False)
    _logdet: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        means = np.atleast_2d(np.asarray(self.means, dtype=float))
        M, d = means.shape
        weights = np.asarray(self.weights, dtype=float).reshape(-1)
        if weights.shape != (M,):
            raise ValueError(f"weights shape {weights.shape}, expected ({M},)")
        if np.any(weights < 0) or not np.all(np.isfinite(weights)) or weights.sum() <= 0:
            raise ValueError("weights must be finite, non-negative and not all zero")
        H = np.asarray(self.bandwidth, dtype=float)
        if H.shape not in ((d, d), (M, d, d)):
            raise ValueError(f"bandwidth shape {H.shape}, expected ({d}, {d}) or ({M}, {d}, {d})")
        H = 0.5 * (H + np.swapaxes(H, -1, -2))
        L = np.linalg.cholesky(H)  # raises LinAlgError unless positive definite
        object.__setattr__(self, "means", means)
        object.__setattr__(self, "weights", weights / weights.sum())
        object.__setattr__(self, "bandwidth", H)
        object.__setattr__(self, "_chol", L)
        object.__setattr__(self, "_chol_inv", np.linalg.inv(L))
        object.__setattr__(self, "_logdet", 2.0 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(-1))

    @property
    def dim(self) -> int:
        return self.means.shape[1]

    @property
    def size(self) -> int:
        return self.means.shape[0]

    @property
    def shared(self) -> bool:
        """True when all components share one kernel covariance."""
        return self.bandwidth.ndim == 2

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """n i.i.d. draws (n, d): a component by weight, plus its kernel noise L z."""
        idx = rng.choice(self.size, size=n, p=self.weights)
        z = rng.standard_normal((n, self.dim))
        if self.shared:
            noise = z @ self._chol.T
        else:
            noise = np.einsum("nij,nj->ni", self._chol[idx], z)
        return self.means[idx] + noise

    def mean(self) -> np.ndarray:
        """sum_i w_i mu_i."""
        return self.weights @ self.means

    def cov(self) -> np.ndarray:
        """Law of total covariance: sum_i w_i H_i + sum_i w_i (mu_i - m)(mu_i - m)^T."""
        dm = self.means - self.mean()
        spread = (self.weights[:, None] * dm).T @ dm
        kernel = self.bandwidth if self.shared else np.einsum("i,ijk->jk", self.weights, self.bandwidth)
        C = kernel + spread
        return 0.5 * (C + C.T)

    def component_logpdf(self, x: np.ndarray) -> np.ndarray:
        """log N(x_n; mu_i, H_i) for points x (n, d): an (n, M) table."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        if x.shape[1] != self.dim:
            raise ValueError(f"points of dimension {x.shape[1]}, mixture of dimension {self.dim}")
        const = self.dim * np.log(2.0 * np.pi) + self._logdet  # scalar or (M,)
        if self.shared:
            # One kernel: whiten once, then |y_x - y_m|^2 = |y_x|^2 + |y_m|^2 - 2 y_x . y_m, a
            # matrix product instead of an (n, M, d) table: 5-10 times faster at M = 300.
            yx = x @ self._chol_inv.T
            ym = self.means @ self._chol_inv.T
            d2 = yx @ ym.T
            d2 *= -2.0
            d2 += (yx * yx).sum(1)[:, None]
            d2 += (ym * ym).sum(1)[None]
            np.maximum(d2, 0.0, out=d2)  # rounding can make a tiny distance negative
            d2 += const
            d2 *= -0.5
            return d2
        out = np.empty((x.shape[0], self.size))
        block = max(1, _BLOCK_FLOATS // (self.size * self.dim))
        for s in range(0, x.shape[0], block):
            diff = x[s : s + block, None, :] - self.means[None]  # (b, M, d)
            # Whitened residual y = L^-1 (x - mu): Mahalanobis distance |y|^2.
            y = np.einsum("mij,bmj->bmi", self._chol_inv, diff)
            out[s : s + block] = -0.5 * (np.einsum("bmi,bmi->bm", y, y) + const)
        return out

    def logpdf(self, x: np.ndarray) -> np.ndarray | float:
        """log p(x) for points x (n, d) -> (n,), or one point (d,) -> float; in log space
        (logsumexp over components), so far-out points give large negative values, not -inf."""
        x = np.asarray(x, dtype=float)
        with np.errstate(divide="ignore"):
            logw = np.log(self.weights)
        if self.shared:
            # The (n, M) table is the cost of a belief update (one per factor), so it is touched
            # as few times as possible. With whitened y, log w_j N(x_i; mu_j, H) =
            # y_i . y_j + c_j - |y_i|^2 / 2, c_j = log w_j - |y_j|^2 / 2 - const / 2: the row
            # term leaves the sum over j, so the table is one matrix product plus c.
            xs = np.atleast_2d(x)
            if xs.shape[1] != self.dim:
                raise ValueError(f"points of dimension {xs.shape[1]}, mixture of dimension {self.dim}")
            yx, ym = xs @ self._chol_inv.T, self.means @ self._chol_inv.T
            const = self.dim * np.log(2.0 * np.pi) + self._logdet
            t = yx @ ym.T
            t += logw - 0.5 * ((ym * ym).sum(1) + const)
            row = -0.5 * (yx * yx).sum(1)
        else:
            t = self.component_logpdf(x)
            t += logw[None]
            row = 0.0
        m = t.max(axis=1, keepdims=True)
        m[~np.isfinite(m)] = 0.0  # a point every component gives -inf (zero weights)
        t -= m
        # Below e^-708 exp's results are subnormal, and computing them had doubled the time of
        # a belief update; terms that small (relative to the largest, 1) change nothing.
        np.maximum(t, -700.0, out=t)
        np.exp(t, out=t)
        with np.errstate(divide="ignore"):
            lp = np.log(t.sum(axis=1)) + m[:, 0] + row
        return float(lp[0]) if x.ndim == 1 else lp

    @staticmethod
    def bandwidth_for(samples: np.ndarray, weights: np.ndarray | None = None, rule: str = "silverman",
                      min_std: float = 1e-6) -> np.ndarray:
        """Kernel covariance H = c(n_eff, d) * Sigma_w + min_std^2 I by a rule of thumb.

        Sigma_w is the weighted sample covariance (with the reliability-weight correction
        1 / (1 - sum w^2), which is n / (n - 1) for equal weights), and n_eff = 1 / sum w^2 the
        effective sample size of the weights (n for equal weights), so a degenerate
        importance-weighted set is smoothed as the few samples it really is.
          silverman: c = (4 / ((d + 2) n_eff))^(2 / (d + 4))   (Silverman 1986, eq. 4.14, squared)
          scott:     c = n_eff^(-2 / (d + 4))
        Both are optimal for a Gaussian target and oversmooth a multimodal one: a ring of
        radius r gets a kernel standard deviation of about 0.27 r at n = 300, d = 2.
        min_std keeps H positive definite when all samples coincide (a point belief).
        """
        x = np.atleast_2d(np.asarray(samples, dtype=float))
        n, d = x.shape
        w = np.full(n, 1.0 / n) if weights is None else np.asarray(weights, dtype=float) / np.sum(weights)
        sw2 = float(w @ w)
        n_eff = 1.0 / sw2
        dx = x - w @ x
        Sigma = (w[:, None] * dx).T @ dx
        if sw2 < 1.0:
            Sigma /= 1.0 - sw2
        if rule == "silverman":
            c = (4.0 / ((d + 2.0) * n_eff)) ** (2.0 / (d + 4.0))
        elif rule == "scott":
            c = n_eff ** (-2.0 / (d + 4.0))
        else:
            raise ValueError(f"unknown bandwidth rule {rule!r}; expected one of {RULES}")
        H = c * Sigma + min_std**2 * np.eye(d)
        return 0.5 * (H + H.T)

    @classmethod
    def from_samples(cls, samples: np.ndarray, weights: np.ndarray | None = None, rule: str = "silverman",
                     bandwidth: np.ndarray | float | None = None, min_std: float = 1e-6) -> "GaussianMixture":
        """The KDE sum_i w_i N(x; x_i, H) of weighted samples (Ihler eq. 14-15).

        H comes from `bandwidth_for(samples, weights, rule, min_std)` unless `bandwidth` is
        given: a (d, d) covariance, or a scalar standard deviation h meaning h^2 I.
        """
        x = np.atleast_2d(np.asarray(samples, dtype=float))
        n, d = x.shape
        w = np.full(n, 1.0 / n) if weights is None else np.asarray(weights, dtype=float)
        if bandwidth is None:
            H = cls.bandwidth_for(x, w, rule, min_std)
        elif np.ndim(bandwidth) == 0:
            H = float(bandwidth) ** 2 * np.eye(d)
        else:
            H = np.asarray(bandwidth, dtype=float)
        return cls(x, w, H)


def gnss_message(z: np.ndarray, cov: np.ndarray) -> GaussianMixture:
    """The local evidence of a normal node with a GNSS fix z ~ N(x, cov): one Gaussian."""
    z = np.asarray(z, dtype=float).reshape(1, -1)
    return GaussianMixture(z, np.ones(1), np.asarray(cov, dtype=float))


def _unit_directions(n: int, d: int, rng: np.random.Generator) -> np.ndarray:
    """n directions uniform on the unit circle (d = 2) or sphere (d = 3): a normalised
    isotropic Gaussian is uniform on the sphere in any dimension."""
    u = rng.standard_normal((n, d))
    norm = np.linalg.norm(u, axis=1, keepdims=True)
    # Probability zero, but a zero draw would give NaN: replace it by the first axis.
    bad = norm[:, 0] == 0.0
    u[bad], norm[bad] = np.eye(d)[0], 1.0
    return u / norm


def range_message(belief_samples: np.ndarray, belief_weights: np.ndarray | None, z: float, sigma: float,
                  rng: np.random.Generator, M_out: int, rule: str = "silverman",
                  bandwidth: np.ndarray | float | None = None) -> GaussianMixture:
    """The NBP message m_ts(x_s) node t sends node s for a range z = |x_s - x_t| + N(0, sigma^2).

    Ihler section IV-A (Wan Algorithm 1): draw x_t^(i) from t's weighted samples, then
    x_ts^(i) = x_t^(i) + (z + nu^(i)) u^(i), nu ~ N(0, sigma^2), u uniform on the unit
    circle/sphere; the message is the KDE of these ring samples, kernel by `rule` (or an
    explicit `bandwidth`, see `GaussianMixture.from_samples`).

    belief_weights are t's sample weights; for BP proper they should be t's belief divided by
    the message s sent t (Ihler: w ∝ w_t / m_st(x_t)), and may include the probability of
    detection P_o(x_t); the caller forms them (None = equal weights).
    A negative z + nu lands on the opposite side of the ring, which the uniform direction makes
    equally likely anyway, so no truncation is needed.
    """
    x = np.atleast_2d(np.asarray(belief_samples, dtype=float))
    n, d = x.shape
    if d not in (2, 3):
        raise ValueError(f"range messages are for 2D or 3D positions, got d = {d}")
    p = None if belief_weights is None else np.asarray(belief_weights, dtype=float) / np.sum(belief_weights)
    idx = rng.choice(n, size=M_out, p=p)
    r = z + sigma * rng.standard_normal(M_out)
    ring = x[idx] + r[:, None] * _unit_directions(M_out, d, rng)
    return GaussianMixture.from_samples(ring, None, rule=rule, bandwidth=bandwidth)


def belief_update(prior: GaussianMixture | None, messages: list[GaussianMixture], M: int,
                  rng: np.random.Generator, rule: str = "silverman",
                  guide: GaussianMixture | None = None) -> GaussianMixture:
    """The belief b(x) ∝ prior(x) prod_j m_j(x) by mixture importance sampling.

    Ihler section IV-B (Wan Algorithm 2; with the forward-time prediction as prior, Algorithm 4):
    draw M samples from the proposal q(x) = (1/k) sum_k f_k(x), the equal mixture of the
    k incoming factors (messages and prior), which covers every mode any one of them has;
    weight them by w ∝ prior(x) prod_j m_j(x) / q(x) (log space throughout, so a product of
    many narrow factors does not underflow), normalise, and smooth with the bandwidth rule
    (on the weighted samples, n_eff from the weights).

    guide (optional, not in the papers' algorithms) is one more proposal component only, e.g.
    the node's belief from the previous NBP iteration: it puts samples where the product
    concentrates, which raises the effective sample size when the messages are wide rings that
    overlap in a small region. It is not a factor of the target, so it changes only the
    Monte Carlo variance, not what is estimated (unlike passing it as `prior`, which would
    count the same evidence again).
    """
    factors = list(messages) + ([prior] if prior is not None else [])
    if not factors:
        raise ValueError("belief_update needs a prior or at least one message")
    proposal = factors + ([guide] if guide is not None else [])
    d = factors[0].dim
    if any(f.dim != d for f in proposal):
        raise ValueError("all messages, the prior and the guide must have the same dimension")
    k = len(proposal)
    # Stratified draw from the equal mixture: a multinomial count per component, then one
    # vectorised sample call per component (k is a handful; the samples are not looped over).
    counts = rng.multinomial(M, np.full(k, 1.0 / k))
    x = np.concatenate([f.sample(c, rng) for f, c in zip(proposal, counts) if c > 0])
    logf = np.stack([f.logpdf(x) for f in proposal])  # (k, M)
    log_q = _logsumexp(logf, axis=0) - np.log(k)
    log_target = logf[: len(factors)].sum(axis=0)
    w = _normalise_log(log_target - log_q)
    return GaussianMixture.from_samples(x, w, rule=rule)


def predict(belief: GaussianMixture, F: np.ndarray, Q: np.ndarray, rng: np.random.Generator,
            M: int, rule: str = "silverman", u: np.ndarray | None = None) -> GaussianMixture:
    """The forward-time message through x' = F x + u + w, w ~ N(0, Q) (Wan Algorithm 3).

    u is an optional known input term (e.g. B a for a measured acceleration a, as in Wan's
    accelerometer-driven model); None means x' = F x + w.

    A particle-filter step: draw M samples from the belief (kernel noise included, since the
    KDE is the belief), propagate each through F with its own process noise, and smooth the
    result with the bandwidth rule. Q may be singular (e.g. noise only on velocity): it is
    sampled through an eigendecomposition, not a Cholesky factor.
    (For a linear model the mixture could also be propagated exactly, component i to
    N(F mu_i, F H_i F^T + Q); sampling keeps the message size M and matches the paper.)
    """
    F = np.asarray(F, dtype=float)
    Q = np.asarray(Q, dtype=float)
    D = belief.dim
    if F.shape != (D, D) or Q.shape != (D, D):
        raise ValueError(f"F and Q must be ({D}, {D}) for a belief of dimension {D}")
    lam, V = np.linalg.eigh(0.5 * (Q + Q.T))
    S = V * np.sqrt(np.clip(lam, 0.0, None))  # S S^T = Q
    x = belief.sample(M, rng) @ F.T + rng.standard_normal((M, D)) @ S.T
    if u is not None:
        x = x + np.asarray(u, dtype=float).reshape(D)
    return GaussianMixture.from_samples(x, None, rule=rule)


def least_squares_position(anchors: np.ndarray, ranges: np.ndarray, sigma: float,
                           x0: np.ndarray | None = None, max_cond: float = 1e6
                           ) -> tuple[np.ndarray, np.ndarray] | None:
    """Multilateration from K >= d + 1 anchors at known positions: the baseline of Wan section 4.

    Minimises sum_k (|x - a_k| - r_k)^2 / sigma^2 (scipy.optimize.least_squares,
    Levenberg-Marquardt, i.e. damped Gauss-Newton) and returns (x, cov) with
    cov = sigma^2 (U^T U)^-1, the inverse Gauss-Newton normal matrix at the solution (U rows:
    unit vectors from the anchors to x). Without x0 it starts
    from the linearised solution (differences of squared ranges against anchor 0:
    2 (a_k - a_0)^T x = |a_k|^2 - |a_0|^2 - r_k^2 + r_0^2), which is exact for exact ranges and
    avoids the local minima a centroid start can fall into.
    None when K < d + 1, or the geometry is degenerate: the linear system's matrix
    [a_k - a_0] (collinear anchors in 2D, coplanar in 3D) or J^T J has a condition number
    above max_cond.
    """
    a = np.atleast_2d(np.asarray(anchors, dtype=float))
    r = np.asarray(ranges, dtype=float).reshape(-1)
    K, d = a.shape
    if r.shape != (K,):
        raise ValueError(f"{K} anchors but {r.shape[0]} ranges")
    if K < d + 1:
        return None
    A = 2.0 * (a[1:] - a[0])
    if np.linalg.cond(A) > max_cond:
        return None
    if x0 is None:
        b = (a[1:] ** 2).sum(1) - (a[0] ** 2).sum() - r[1:] ** 2 + r[0] ** 2
        x0 = np.linalg.lstsq(A, b, rcond=None)[0]
    x0 = np.asarray(x0, dtype=float)

    from scipy.optimize import least_squares  # only the baseline needs scipy.optimize

    def residual(x):
        return (np.linalg.norm(x - a, axis=1) - r) / sigma

    def jacobian(x):
        diff = x - a
        dist = np.linalg.norm(diff, axis=1, keepdims=True)
        # At an anchor the gradient does not exist; a zero row adds no information there.
        return np.divide(diff, dist, out=np.zeros_like(diff), where=dist > 0) / sigma

    sol = least_squares(residual, x0, jac=jacobian, method="lm")
    J = jacobian(sol.x)
    N = J.T @ J
    if np.linalg.cond(N) > max_cond**2:
        return None
    cov = np.linalg.inv(N)
    return sol.x, 0.5 * (cov + cov.T)
