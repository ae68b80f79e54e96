"""EKF update and covariance intersection: the fusion steps of the EKF-CI estimator family.

Goel, Kealy, Lohani, "Cooperative UAS localization using low cost sensors" (ISPRS 2016):
a centralized EKF over the joint swarm state (section 3), and a distributed one (section 4)
in which node i fuses node j's estimate, mapped through a relative measurement, with
covariance intersection because their cross-covariance is unknown. `naive_fusion` is the
baseline that pretends it is zero.

Conventions: covariances are positive definite numpy arrays; every returned covariance is
exactly symmetric. omega is the weight of the node's own estimate (the first argument):
omega = 1 keeps it, omega = 0 takes the other one. The paper's (W1, W2) is (omega, 1 - omega).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from swarmloc.filters import kalman

CRITERIA = ("trace", "det")


def _pd_inverse(P: np.ndarray) -> np.ndarray:
    """P^-1 of a positive definite P (LinAlgError otherwise). numpy, not scipy.linalg: agents
    load only what they use, and scipy.linalg is 27 MB of it."""
    np.linalg.cholesky(P)  # the check: raises unless positive definite
    return np.linalg.inv(P)


def _sym(P: np.ndarray) -> np.ndarray:
    # (a + b) / 2 == (b + a) / 2 in floating point, so the result is exactly symmetric.
    return 0.5 * (P + P.T)


def nis(nu: np.ndarray, S: np.ndarray) -> float:
    """Normalised innovation squared nu^T S^-1 nu (chi-square with len(nu) dof if consistent)."""
    y = np.linalg.solve(np.linalg.cholesky(S), nu)  # raises LinAlgError unless S is positive definite
    return float(y @ y)


def nees(error: np.ndarray, P: np.ndarray) -> float:
    """Normalised estimation error squared e^T P^-1 e, e = estimate - truth."""
    return nis(np.asarray(error, dtype=float), P)


def ekf_update(
    x: np.ndarray,
    P: np.ndarray,
    z: np.ndarray,
    h: np.ndarray | Callable[[np.ndarray], np.ndarray],
    H: np.ndarray | Callable[[np.ndarray], np.ndarray],
    R: np.ndarray,
    residual: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """EKF measurement update; returns (x+, P+, innovation nu, innovation covariance S).

    h and H are the predicted measurement h(x) and its Jacobian at x, or callables of x.
    residual(z, h) forms nu (default z - h); pass a model's `residual` to wrap angles.
    P+ is in Joseph form, (I - KH) P (I - KH)^T + K R K^T, then symmetrised: it stays PSD
    under rounding and for any gain, which also makes it the consistent bound CI relies on.
    """
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    R = np.asarray(R, dtype=float)
    z_hat = h(x) if callable(h) else np.asarray(h, dtype=float)
    H = H(x) if callable(H) else np.asarray(H, dtype=float)
    nu = residual(z, z_hat) if residual is not None else np.asarray(z, dtype=float) - z_hat
    PHt = P @ H.T
    S = _sym(H @ PHt + R)
    K = kalman.gain(PHt, S)
    A = np.eye(x.shape[0]) - K @ H
    return x + K @ nu, _sym(A @ P @ A.T + K @ R @ K.T), nu, S


def objective(criterion: str) -> Callable[[np.ndarray], float]:
    """The cost a fusion weight minimises, as a function of the fused covariance: its trace
    ("trace") or its log determinant ("det")."""
    if criterion == "trace":
        return lambda P: float(np.trace(P))
    if criterion == "det":
        # log det: same minimiser, no under/overflow for 16-state covariances in metres.
        def logdet(P):
            sign, ld = np.linalg.slogdet(P)
            return ld if sign > 0 else np.inf

        return logdet
    raise ValueError(f"criterion is one of {CRITERIA}, got {criterion!r}")


def best_omega(cost: Callable[[float], float]) -> float:
    """argmin of cost on [0, 1].

    Both criteria are convex in omega, so bounded Brent finds the interior minimum; but it
    never evaluates the bounds, and a dominated input puts the minimum exactly at 0 or 1,
    so the end points are compared too.
    """
    import scipy.optimize  # here: an agent that never intersects covariances need not carry it (~40 MB)

    res = scipy.optimize.minimize_scalar(cost, bounds=(0.0, 1.0), method="bounded", options={"xatol": 1e-10})
    candidates = [(cost(0.0), 0.0), (cost(1.0), 1.0), (float(res.fun), float(res.x))]
    # min over (cost, omega): on a tie the smaller omega wins, deterministically.
    return min(candidates)[1]


def _check_omega(omega: float) -> float:
    omega = float(omega)
    if not 0.0 <= omega <= 1.0:
        raise ValueError(f"omega must lie in [0, 1], got {omega}")
    return omega


def covariance_intersection(
    xa: np.ndarray,
    Pa: np.ndarray,
    xb: np.ndarray,
    Pb: np.ndarray,
    criterion: str = "trace",
    omega: float | None = None,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Covariance intersection of two estimates of the same state, cross-covariance unknown.

    P^-1 = w Pa^-1 + (1 - w) Pb^-1, x = P (w Pa^-1 xa + (1 - w) Pb^-1 xb). With omega None,
    w minimises trace(P) or det(P) over [0, 1]. Returns (x, P, w); w = 1 returns (xa, Pa)
    and w = 0 returns (xb, Pb), as copies, exactly.
    """
    xa, Pa, xb, Pb = (np.asarray(a, dtype=float) for a in (xa, Pa, xb, Pb))
    Ia, Ib = _pd_inverse(Pa), _pd_inverse(Pb)
    ya, yb = Ia @ xa, Ib @ xb

    def fuse(w: float) -> tuple[np.ndarray, np.ndarray]:
        if w == 1.0:
            return xa.copy(), Pa.copy()
        if w == 0.0:
            return xb.copy(), Pb.copy()
        P = _sym(_pd_inverse(_sym(w * Ia + (1.0 - w) * Ib)))
        return P @ (w * ya + (1.0 - w) * yb), P

    if omega is None:
        f = objective(criterion)
        omega = best_omega(lambda w: f(fuse(w)[1]))
    omega = _check_omega(omega)
    x, P = fuse(omega)
    return x, P, omega


def ci_update(
    x: np.ndarray,
    P: np.ndarray,
    z_est: np.ndarray,
    Pz_est: np.ndarray,
    H: np.ndarray,
    criterion: str = "trace",
    omega: float | None = None,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Covariance intersection of the state (x, P) with an estimate z_est of H x only.

    The partial-observation generalisation of CI (information form on the observed subspace):

        P+^-1      = w P^-1 + (1 - w) H^T Pz^-1 H
        P+^-1 x+   = w P^-1 x + (1 - w) H^T Pz^-1 z_est

    computed as the paper's eq. 18-21, a Kalman update with both covariances inflated,
    P1 = P / w and P2 = Pz / (1 - w) (equal by the matrix inversion lemma, and it needs
    neither P^-1 nor a full-rank H). Inflating both is exactly what makes it consistent for
    any cross-covariance between x and z_est: diag(P/w, Pz/(1-w)) bounds every joint
    covariance with those marginals, and the Joseph form carries the bound through.

    z_est is typically a neighbour's estimate mapped through a relative measurement, e.g.
    RelativePosition.implied_position, with H = layout.position_matrix(). With omega None,
    w minimises trace(P+) or det(P+) over [0, 1] (paper eq. 22). Returns (x+, P+, w).
    w = 1 returns (x, P) as copies. w = 0 discards the prior: allowed only when H is square
    and invertible (the unobserved part of the state would have unbounded covariance).
    """
    x, P, z_est, Pz_est, H = (np.asarray(a, dtype=float) for a in (x, P, z_est, Pz_est, H))
    n = x.shape[0]
    invertible = H.shape == (n, n) and np.linalg.matrix_rank(H) == n

    def fuse(w: float) -> tuple[np.ndarray, np.ndarray]:
        if w == 1.0:
            return x.copy(), P.copy()
        if w == 0.0:
            if not invertible:
                raise ValueError("omega = 0 discards the prior; H observes only part of the state")
            Hi = np.linalg.inv(H)
            return Hi @ z_est, _sym(Hi @ Pz_est @ Hi.T)
        x_new, P_new, _, _ = ekf_update(x, P / w, z_est, H @ x, H, Pz_est / (1.0 - w))
        return x_new, P_new

    if omega is None:
        f = objective(criterion)

        def cost(w: float) -> float:
            if w == 0.0 and not invertible:
                return np.inf
            return f(fuse(w)[1])

        omega = best_omega(cost)
    omega = _check_omega(omega)
    x_new, P_new = fuse(omega)
    return x_new, P_new, omega


def ci_split(size: int, removed: int) -> tuple[float, float]:
    """Covariance intersection that cuts `removed` members out of a correlated group of `size`.

    A group whose joint covariance is known but whose members' cross-covariances with the
    removed ones are not (UKF-DCL's orphans) is bounded by CI over the parts with weights
    1/size for each removed member and (size - removed)/size for the rest: each part's
    covariance is divided by its weight and the cross-covariances between parts are dropped.
    Returns (the factor of the rest's covariances, the factor of a removed member's own
    covariance), i.e. (size / (size - removed), size)."""
    if not 0 <= removed < size:
        raise ValueError(f"cannot remove {removed} of a group of {size}")
    return size / (size - removed), float(size)


def naive_fusion(
    x: np.ndarray, P: np.ndarray, z_est: np.ndarray, Pz_est: np.ndarray, H: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The baseline: z_est fused as if independent of x, a Kalman update with R = Pz_est.

    Overconfident whenever the two estimates share information (a neighbour that earlier
    fused our own estimate): that double counting is what CI exists to avoid.
    """
    H = np.asarray(H, dtype=float)
    x_new, P_new, _, _ = ekf_update(x, P, z_est, H @ np.asarray(x, dtype=float), H, np.asarray(Pz_est, dtype=float))
    return x_new, P_new
