"""Cooperative target-localization fused with cooperative self-localization (CSL-CTL).

Wang et al., "A parallel integration method of cooperative target-localization and
cooperative self-localization" (2022). Agents hold a Gaussian prior on their positions from a
Kalman CSL; some of them range an unknown target. All positions are re-estimated together by
minimising the stress (eqs. 1-3)

    S(X) = (X - X_hat)^T A (X - X_hat) + sum_e w_e (||x_i - x_j|| - z_e)^2,   w_e = 1 / sigma_e^2

with majorization (SMACOF, eqs. 5-13). The paper's eqs. (9)-(13) are a block-Jacobi sweep of
the majorizer; we take its exact minimiser instead, which has the same fixed points and makes
the stress monotone. The covariance is the unscented transform of the whole estimator (section
2.4), optionally including the range noise the paper leaves out.

Everything is generalised to K "nodes" (agents and targets alike) in `dim` dimensions; a node
without a prior has zero rows in the information matrix. numpy only, as in `kalman`: agents
load what they use, and scipy.linalg is 27 MB of it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from swarmloc.filters.kalman import UnscentedTransform

_TINY = np.finfo(float).tiny


def _fail(msg: str) -> None:
    raise ValueError(msg)


def _finite_array(a, name: str, shape: tuple[int | None, ...]) -> np.ndarray:
    """float array of the given shape (None: any length), all finite, else ValueError."""
    a = np.asarray(a, dtype=float)
    if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)):
        _fail(f"{name}: expected shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        _fail(f"{name}: non-finite values")
    return a


def _mask(m, K: int, name: str) -> np.ndarray:
    m = np.asarray(m)
    if m.shape != (K,) or m.dtype != bool:
        _fail(f"{name}: expected a boolean mask of shape ({K},), got {m.dtype} {m.shape}")
    return m


@dataclass(frozen=True)
class Edges:
    """Range measurements z[e] = ||x[i[e]] - x[j[e]]|| + N(0, sigma[e]^2) between nodes.

    Validated on construction: 1-D arrays of one length, integer node indices >= 0 with
    i != j, finite ranges >= 0 (SMACOF's bound needs z >= 0), finite sigma > 0. Whether the
    indices are < K is checked where K is known.
    """

    i: np.ndarray
    j: np.ndarray
    z: np.ndarray
    sigma: np.ndarray

    def __post_init__(self) -> None:
        idx = {}
        for name in ("i", "j"):
            a = np.asarray(getattr(self, name))
            if a.size == 0:
                a = a.astype(np.intp)
            if a.ndim != 1 or not np.issubdtype(a.dtype, np.integer):
                _fail(f"Edges.{name}: expected a 1-D integer array, got {a.dtype} {a.shape}")
            idx[name] = a.astype(np.intp)
        E = idx["i"].size
        z = _finite_array(self.z, "Edges.z", (E,))
        sigma = _finite_array(self.sigma, "Edges.sigma", (E,))
        if idx["j"].size != E:
            _fail(f"Edges: i has {E} entries, j has {idx['j'].size}")
        if np.any(idx["i"] < 0) or np.any(idx["j"] < 0):
            _fail("Edges: negative node index")
        if np.any(idx["i"] == idx["j"]):
            _fail("Edges: self-edge (i == j)")
        if np.any(z < 0):
            _fail("Edges.z: negative range")
        if np.any(sigma <= 0):
            _fail("Edges.sigma: must be > 0")
        for name, a in (("i", idx["i"]), ("j", idx["j"]), ("z", z), ("sigma", sigma)):
            a.setflags(write=False)
            object.__setattr__(self, name, a)

    def __len__(self) -> int:
        return int(self.z.size)

    @property
    def weights(self) -> np.ndarray:
        return 1.0 / self.sigma**2

    def with_z(self, z: np.ndarray) -> "Edges":
        """The same graph with other measured ranges."""
        return Edges(self.i, self.j, z, self.sigma)


@dataclass(frozen=True)
class Majorized:
    """Result of `majorize`. stress[0] is the stress of x0, stress[-1] that of x;
    iterations == len(stress) - 1 accepted majorization steps."""

    x: np.ndarray
    stress: np.ndarray
    iterations: int
    converged: bool


@dataclass(frozen=True)
class CtlEstimate:
    """Result of `estimate`: point estimate, its unscented covariance (node-major, dim-minor
    ordering, like x.ravel()), the central majorization and how many majorizations ran
    (central + sigma points). sigma_unconverged counts sigma-point runs that hit max_iter."""

    x: np.ndarray
    cov: np.ndarray
    majorized: Majorized
    runs: int
    sigma_unconverged: int


@dataclass(frozen=True)
class _Problem:
    """Validated, flattened problem plus the solve of the majorizer's constant matrix."""

    K: int
    dim: int
    A: np.ndarray  # (K dim, K dim) prior information
    i: np.ndarray
    j: np.ndarray
    w: np.ndarray
    incidence: np.ndarray  # (K, E): +1 at i, -1 at j
    M: np.ndarray  # A + L_w (x) I_dim
    free: np.ndarray  # flat indices of the free coordinates
    G: np.ndarray  # pseudo-inverse of M restricted to the free coordinates


def _prepare(info, edges: Edges, K: int, dim: int, fixed) -> _Problem:
    if not isinstance(edges, Edges):
        _fail(f"edges: expected Edges, got {type(edges).__name__}")
    n = K * dim
    A = _finite_array(info, "info", (n, n))
    scale = max(float(np.abs(A).max(initial=0.0)), _TINY)
    if np.abs(A - A.T).max(initial=0.0) > 1e-9 * scale:
        _fail("info: not symmetric")
    A = 0.5 * (A + A.T)
    if n and np.linalg.eigvalsh(A)[0] < -1e-9 * scale:
        _fail("info: not positive semi-definite")
    if len(edges) and max(edges.i.max(), edges.j.max()) >= K:
        _fail(f"edges: node index >= K = {K}")
    fixed = np.zeros(K, bool) if fixed is None else _mask(fixed, K, "fixed")

    E = len(edges)
    w = edges.weights
    incidence = np.zeros((K, E))
    incidence[edges.i, np.arange(E)] = 1.0
    incidence[edges.j, np.arange(E)] = -1.0
    L = (incidence * w) @ incidence.T  # weighted Laplacian
    M = A + np.kron(L, np.eye(dim))
    free = np.flatnonzero(np.repeat(~fixed, dim))
    Mff = M[np.ix_(free, free)]
    # Pseudo-inverse by eigen-decomposition: M is PSD, singular exactly along translations of
    # a connected group that neither a prior nor a fixed node pins (e.g. the whole swarm when
    # there is no prior; rotations are not null directions of M). The system is consistent
    # there (B(Y) and L annihilate those translations, A x_hat is orthogonal to null(A)), so
    # any solution minimises the majorizer; the truncated inverse makes the minimum-norm change.
    if free.size:
        lam, V = np.linalg.eigh(Mff)
        keep = lam > max(lam[-1], 0.0) * 100 * free.size * np.finfo(float).eps
        G = (V[:, keep] / lam[keep]) @ V[:, keep].T
    else:
        G = np.zeros((0, 0))
    return _Problem(K, dim, A, edges.i, edges.j, w, incidence, M, free, G)


def _stress_rows(p: _Problem, xhat: np.ndarray, z: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Stress of each row of x (R, K dim) against its own prior mean and ranges."""
    dx = x - xhat
    prior = np.einsum("ri,ij,rj->r", dx, p.A, dx)
    X = x.reshape(len(x), p.K, p.dim)
    d = np.linalg.norm(X[:, p.i] - X[:, p.j], axis=-1)
    return prior + ((d - z) ** 2 * p.w).sum(axis=-1)


def _step(p: _Problem, xhat: np.ndarray, z: np.ndarray, y: np.ndarray) -> np.ndarray:
    """argmin_X T(X, Y) for each row, fixed coordinates kept at y."""
    R = len(y)
    Y = y.reshape(R, p.K, p.dim)
    diff = Y[:, p.i] - Y[:, p.j]
    d = np.linalg.norm(diff, axis=-1)
    # SMACOF convention: a coincident pair contributes nothing to B(Y).
    coef = np.divide(p.w * z, d, out=np.zeros_like(d), where=d > 0)
    By = np.einsum("ke,red->rkd", p.incidence, coef[..., None] * diff).reshape(R, -1)
    resid = xhat @ p.A + By - y @ p.M  # A, M symmetric
    x = y.copy()
    x[:, p.free] += resid[:, p.free] @ p.G
    return x


def _iterate(p: _Problem, xhat: np.ndarray, z: np.ndarray, x: np.ndarray, tol: float, max_iter: int):
    """Majorize R problems in lockstep (shared A, graph and fixed set; own prior means,
    ranges and starts). A step that raises the stress (only possible by rounding, at the
    floor) is discarded and ends that run: the returned x is always the best seen."""
    R = len(x)
    x = x.copy()
    S = _stress_rows(p, xhat, z, x)
    hist = np.full((R, max_iter + 1), np.nan)
    hist[:, 0] = S
    iters = np.zeros(R, int)
    converged = np.zeros(R, bool)
    active = np.ones(R, bool)
    for _ in range(max_iter):
        r = np.flatnonzero(active)
        if r.size == 0:
            break
        xn = _step(p, xhat[r], z[r], x[r])
        Sn = _stress_rows(p, xhat[r], z[r], xn)
        S_old = S[r]
        ok = Sn <= S_old  # NaN compares False: never accepted
        a = r[ok]
        x[a], S[a] = xn[ok], Sn[ok]
        iters[a] += 1
        hist[a, iters[a]] = Sn[ok]
        done = r[~ok | (S_old - Sn <= tol * np.maximum(S_old, _TINY))]
        converged[done] = True
        active[done] = False
    return x, hist, iters, converged


def stress(X: np.ndarray, prior_mean: np.ndarray, info: np.ndarray, edges: Edges) -> float:
    """S(X) (eq. 3): prior Mahalanobis term plus weighted squared range residuals."""
    X = _finite_array(X, "X", (None, None))
    K, dim = X.shape
    xhat = _finite_array(prior_mean, "prior_mean", (K, dim))
    p = _prepare(info, edges, K, dim, None)
    return float(_stress_rows(p, xhat.reshape(1, -1), edges.z[None], X.reshape(1, -1))[0])


def majorizer(X: np.ndarray, Y: np.ndarray, prior_mean: np.ndarray, info: np.ndarray, edges: Edges) -> float:
    """T(X, Y) (eqs. 5-8): S with -||x_i - x_j|| replaced by its linear bound at Y, so
    T(X, Y) >= S(X) and T(Y, Y) = S(Y)."""
    X = _finite_array(X, "X", (None, None))
    K, dim = X.shape
    Y = _finite_array(Y, "Y", (K, dim))
    xhat = _finite_array(prior_mean, "prior_mean", (K, dim))
    A = _finite_array(info, "info", (K * dim, K * dim))
    if not isinstance(edges, Edges) or (len(edges) and max(edges.i.max(), edges.j.max()) >= K):
        _fail(f"edges: expected Edges with node indices < K = {K}")
    dx = (X - xhat).ravel()
    w, z = edges.weights, edges.z
    dX = X[edges.i] - X[edges.j]
    dY = Y[edges.i] - Y[edges.j]
    nY = np.linalg.norm(dY, axis=-1)
    cross = np.divide((dX * dY).sum(-1), nY, out=np.zeros_like(nY), where=nY > 0)
    return float(dx @ A @ dx + (w * (z**2 + (dX**2).sum(-1) - 2 * z * cross)).sum())


def majorize(
    prior_mean: np.ndarray,
    info: np.ndarray,
    edges: Edges,
    x0: np.ndarray,
    *,
    tol: float = 1e-9,
    max_iter: int = 200,
    fixed: np.ndarray | None = None,
) -> Majorized:
    """Minimise the stress from x0 by iterating X <- argmin T(X, Y=X) = (A + L_w)^+ (A X_hat + B(Y) Y).

    prior_mean, x0: (K, dim); info: (K dim, K dim) PSD, zero rows for nodes without a prior.
    fixed: boolean (K,) mask of nodes held at x0 (the reduced system over the free ones is
    solved). Stops when S^s - S^{s+1} <= tol * max(S^s, tiny) or after max_iter steps
    (converged False). Where nothing pins a translation down, each step makes the
    minimum-norm change (the centroid of such a group stays where x0 put it).
    """
    x0 = _finite_array(x0, "x0", (None, None))
    K, dim = x0.shape
    xhat = _finite_array(prior_mean, "prior_mean", (K, dim))
    if not (tol >= 0 and max_iter >= 0):
        _fail("tol and max_iter must be >= 0")
    p = _prepare(info, edges, K, dim, fixed)
    x, hist, iters, conv = _iterate(p, xhat.reshape(1, -1), edges.z[None], x0.reshape(1, -1), tol, int(max_iter))
    return Majorized(x[0].reshape(K, dim), hist[0, : iters[0] + 1].copy(), int(iters[0]), bool(conv[0]))


def majorize_many(
    prior_means: np.ndarray,
    info: np.ndarray,
    edges: Edges,
    z: np.ndarray,
    x0: np.ndarray,
    *,
    tol: float = 1e-9,
    max_iter: int = 200,
    fixed: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`majorize` of R problems sharing info, graph and sigma, vectorised (for Monte Carlo).

    prior_means (R, K, dim) and ranges z (R, E) per problem (z >= 0); x0 (K, dim) shared or
    (R, K, dim). Returns (x (R, K, dim), iterations (R,), converged (R,)); each problem
    stops by the same rule as `majorize`, so the results agree with it run by run.
    """
    xh = _finite_array(prior_means, "prior_means", (None, None, None))
    R, K, dim = xh.shape
    zs = _finite_array(z, "z", (R, len(edges) if isinstance(edges, Edges) else None))
    if np.any(zs < 0):
        _fail("z: negative range")
    x0 = np.asarray(x0, dtype=float)
    x0 = _finite_array(np.broadcast_to(x0, (R, K, dim)) if x0.shape == (K, dim) else x0, "x0", (R, K, dim))
    if not (tol >= 0 and max_iter >= 0):
        _fail("tol and max_iter must be >= 0")
    p = _prepare(info, edges, K, dim, fixed)
    x, _, iters, conv = _iterate(p, xh.reshape(R, -1), zs, x0.reshape(R, -1), tol, int(max_iter))
    return x.reshape(R, K, dim), iters, conv


def estimate(
    prior_mean: np.ndarray,
    prior_cov: np.ndarray,
    edges: Edges,
    x0: np.ndarray,
    *,
    has_prior: np.ndarray | None = None,
    noise: bool = True,
    tol: float = 1e-9,
    max_iter: int = 200,
    fixed: np.ndarray | None = None,
    spread: float | None = None,
) -> CtlEstimate:
    """Joint re-estimate of all nodes and its covariance by the unscented transform.

    has_prior: boolean (K,) mask of the nodes with a prior (default: all). prior_cov is the
    positive definite covariance over those nodes only, in node order:
    (n_prior dim, n_prior dim). prior_mean is (K, dim); rows of nodes without a prior are
    ignored (they may be NaN); x0 gives every node's start.

    x is majorize(prior_mean, prior_cov^-1 embedded, edges, x0). cov is the unscented
    covariance of the estimator map g(e, v) = majorize(prior_mean + e, info, z + v, x0=x)
    over symmetric sigma points of [e; v] ~ N(0, blockdiag(prior_cov, diag(sigma^2))), taken
    about the weighted sigma-point mean. noise=False propagates the prior only (the paper's
    4N+1 points). spread c = n + lambda >= n (default n: centre weight 0, the rest 1/(2c)).
    Sigma-point ranges below zero are clipped to zero (a range is not negative; this only
    happens when sqrt(c) sigma exceeds the range). Fixed nodes stay at x0 in every run,
    so their covariance rows are zero. With no prior at all the estimate is defined only up
    to a rigid motion and so is its covariance.
    """
    x0 = _finite_array(x0, "x0", (None, None))
    K, dim = x0.shape
    has_prior = np.ones(K, bool) if has_prior is None else _mask(has_prior, K, "has_prior")
    prior_idx = np.flatnonzero(np.repeat(has_prior, dim))
    n_e = prior_idx.size
    pm = np.asarray(prior_mean, dtype=float)
    if pm.shape != (K, dim):
        _fail(f"prior_mean: expected shape {(K, dim)}, got {pm.shape}")
    xhat = np.zeros(K * dim)
    xhat[prior_idx] = _finite_array(pm.ravel()[prior_idx], "prior_mean (rows with a prior)", (n_e,))
    P = _finite_array(prior_cov, "prior_cov", (n_e, n_e))
    if np.abs(P - P.T).max(initial=0.0) > 1e-9 * max(float(np.abs(P).max(initial=0.0)), _TINY):
        _fail("prior_cov: not symmetric")
    P = 0.5 * (P + P.T)
    try:
        Lp = np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        raise ValueError("prior_cov: not positive definite") from None
    Linv = np.linalg.inv(Lp)
    A = np.zeros((K * dim, K * dim))
    A[np.ix_(prior_idx, prior_idx)] = Linv.T @ Linv
    if not isinstance(edges, Edges):
        _fail(f"edges: expected Edges, got {type(edges).__name__}")
    if not (tol >= 0 and max_iter >= 0):
        _fail("tol and max_iter must be >= 0")

    p = _prepare(A, edges, K, dim, fixed)
    x, hist, iters, conv = _iterate(p, xhat[None], edges.z[None], x0.reshape(1, -1), tol, int(max_iter))
    central = Majorized(x[0].reshape(K, dim), hist[0, : iters[0] + 1].copy(), int(iters[0]), bool(conv[0]))

    E = len(edges) if noise else 0
    n = n_e + E
    if n == 0:  # nothing uncertain to propagate
        return CtlEstimate(central.x, np.zeros((K * dim, K * dim)), central, 1, 0)
    ut = UnscentedTransform(float(n) if spread is None else float(spread))
    if not ut.spread >= n:
        _fail(f"spread {ut.spread} < n = {n}: the centre weight would be negative")
    root = np.zeros((n, n))
    root[:n_e, :n_e] = Lp
    root[n_e:, n_e:] = np.diag(edges.sigma[:E])
    pts = ut.sigma_points(np.zeros(n), root)[1:]  # the centre is the central solution itself
    xhats = np.repeat(xhat[None], 2 * n, axis=0)
    xhats[:, prior_idx] += pts[:, :n_e]
    zs = np.repeat(edges.z[None], 2 * n, axis=0)
    if E:
        zs = np.maximum(zs + pts[:, n_e:], 0.0)
    g, _, _, sconv = _iterate(p, xhats, zs, np.repeat(x, 2 * n, axis=0), tol, int(max_iter))

    w0, wi = ut.weights(n)
    mean = w0 * x[0] + wi * g.sum(axis=0)
    d0, dg = x[0] - mean, g - mean
    cov = w0 * np.outer(d0, d0) + wi * dg.T @ dg
    cov = 0.5 * (cov + cov.T)
    fixed_idx = np.setdiff1d(np.arange(K * dim), p.free)
    cov[fixed_idx] = 0.0
    cov[:, fixed_idx] = 0.0
    return CtlEstimate(central.x, cov, central, 1 + 2 * n, int((~sconv).sum()))


def ls_target(
    anchors: np.ndarray,
    z: np.ndarray,
    sigma: np.ndarray,
    x0: np.ndarray,
    prior: tuple[np.ndarray, np.ndarray] | None = None,
    *,
    tol: float = 1e-10,
    max_iter: int = 100,
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted Gauss-Newton least squares of one point from ranges to known anchors.

    anchors (n, dim), z (n,), sigma (n,) > 0, x0 (dim,); prior = (mean (dim,), cov (dim, dim)
    positive definite) adds a Gaussian prior on the point, so an estimate can be accumulated
    over ticks. Returns (x, cov) with cov the inverse Gauss-Newton information at x.

    ValueError when: shapes or values are invalid; without a prior, fewer than dim + 1
    anchors or anchors not affinely spanning dim dimensions (the solution would be
    ambiguous by a reflection); the information at the solution is not positive definite;
    or no convergence within max_iter (step <= tol (1 + |x|)).
    """
    anchors = _finite_array(anchors, "anchors", (None, None))
    n, dim = anchors.shape
    z = _finite_array(z, "z", (n,))
    sigma = _finite_array(sigma, "sigma", (n,))
    x = _finite_array(x0, "x0", (dim,)).copy()
    if np.any(sigma <= 0):
        _fail("sigma: must be > 0")
    if prior is None:
        if n < dim + 1:
            _fail(f"ls_target: {n} anchors and no prior; need at least dim + 1 = {dim + 1}")
        if np.linalg.matrix_rank(anchors - anchors.mean(axis=0)) < dim:
            _fail("ls_target: anchors do not span the space (collinear); ambiguous without a prior")
        m, Pinv = np.zeros(dim), np.zeros((dim, dim))
    else:
        m = _finite_array(prior[0], "prior mean", (dim,))
        Pc = _finite_array(prior[1], "prior cov", (dim, dim))
        try:
            np.linalg.cholesky(Pc)
        except np.linalg.LinAlgError:
            raise ValueError("prior cov: not positive definite") from None
        Pinv = np.linalg.inv(Pc)
        Pinv = 0.5 * (Pinv + Pinv.T)

    def cost(x: np.ndarray) -> float:
        r = (np.linalg.norm(x - anchors, axis=1) - z) / sigma
        return float(r @ r + (x - m) @ Pinv @ (x - m))

    def linearise(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        diff = x - anchors
        d = np.linalg.norm(diff, axis=1)
        u = np.divide(diff, d[:, None], out=np.zeros_like(diff), where=d[:, None] > 0)
        J = u / sigma[:, None]
        return J.T @ J + Pinv, J.T @ ((d - z) / sigma) + Pinv @ (x - m)

    c = cost(x)
    for _ in range(max_iter):
        H, g = linearise(x)
        try:
            step = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            raise ValueError("ls_target: singular Gauss-Newton information") from None
        t = 1.0
        # Backtrack: a full Gauss-Newton step can overshoot far from the solution.
        while (cn := cost(x + t * step)) > c and t > 1e-12:
            t *= 0.5
        if cn > c:  # no descent left along the step: at the minimum to rounding
            break
        x, c = x + t * step, cn
        if np.linalg.norm(t * step) <= tol * (1.0 + np.linalg.norm(x)):
            break
    else:
        _fail(f"ls_target: no convergence in {max_iter} Gauss-Newton steps")
    H, _ = linearise(x)
    try:
        Lh = np.linalg.cholesky(H)
    except np.linalg.LinAlgError:
        raise ValueError("ls_target: information at the solution is not positive definite") from None
    Li = np.linalg.inv(Lh)
    if not np.all(np.isfinite(Li)):
        _fail("ls_target: information at the solution is singular")
    return x, Li.T @ Li
