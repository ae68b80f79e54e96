"""Plausibility of what a neighbour sends, checked before it touches a filter (issue 26, finding 7).

A member holding the swarm key can send frames that decode, authenticate and fit every shape,
with wrong numbers in them. The checks here are what the receiver can verify from the frame and
its own state alone:

- every number finite;
- an innovation nu with covariance S is within a bound (`Limits.max_sigma` standard
  deviations): far looser than any measurement gate, so honest traffic never reaches it; a lie
  larger than that is refused, a smaller one moves an estimate by at most max_sigma of its own
  standard deviations per update (docs/security.md, "A member's damage (finding 7)");
- the information an update carries is bounded by its innovation covariance: with Pxz = L Y
  (L a Cholesky factor of the prior), the joint [[P, Pxz], [Pxz^T, S]] is a covariance only if
  S - Y^T Y is positive semi-definite, and then P - Pxz S^-1 Pxz^T is too: a frame that claims
  more (gains x100, Y inflated) would shrink a covariance below zero;
- a gain the receiver can form from its own rows matches the one it is handed;
- information matrices symmetric positive semi-definite, covariances symmetric positive definite;
- a posterior handed to us for our own prior (RDL's commit) is one update of it (`reduction`:
  P_prior - P_post positive semi-definite, of rank at most dim z) and moved within the bound
  (`shift`).

`step_bound` is the derived bound on how far one update that passes can move a block of the
receiver's state (docs/security.md, "A member's damage (finding 7)"; benchmarks/member_damage.py
measures it and the damage of whole runs of lies).

Each returns the reason a frame is refused ("implausible-..."), or None; the caller counts the
reason in its node's drops and leaves its state untouched. Pure functions, no I/O: the
equivalence and determinism tests hold only if none of them fires on honest traffic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from swarmloc.filters.kalman import chi2_quantile


@dataclass(frozen=True)
class Limits:
    """The thresholds (defaults: `LIMITS`)."""

    # The innovation bound, in standard deviations: NIS at most max_sigma^2 (or the chi-square
    # 1 - 1e-12 quantile, for many degrees of freedom). Far outside any measurement gate on
    # purpose: a gate (kalman.Gate) stands open after a streak of rejections so that a platform
    # whose estimate drifted can be pulled back, and this bound must not undo that; what a lie
    # inside it can do is measured (docs/security.md, "A member's damage (finding 7)"). 100:
    # the tests' faulty sensors (tests/test_ukf_dcl_pose.py) hand the gate a range-bearing 78
    # standard deviations off and, once it stands open, landmark sightings up to 49 off.
    max_sigma: float = 100.0
    # Relative tolerance of a recomputed gain (same formula, other rounding) and of symmetry.
    rtol: float = 1e-6
    # Slack, relative to the matrix's scale, for a positive semi-definite test (rounding only).
    psd_tol: float = 1e-9

    def nis_limit(self, dof: int) -> float:
        return max(self.max_sigma**2, _limit(1.0 - 1e-12, dof))


LIMITS = Limits()
_LIMITS: dict[tuple[float, int], float] = {}


def _limit(p: float, dof: int) -> float:
    if (p, dof) not in _LIMITS:
        _LIMITS[(p, dof)] = chi2_quantile(p, dof)
    return _LIMITS[(p, dof)]


def finite(*arrays) -> bool:
    return all(np.isfinite(a).all() for a in arrays)


def _symmetric(A: np.ndarray, rtol: float) -> bool:
    scale = np.abs(A).max(initial=0.0)
    return bool(np.abs(A - A.T).max(initial=0.0) <= rtol * scale)


def psd(A: np.ndarray, limits: Limits = LIMITS) -> bool:
    """Symmetric positive semi-definite, up to rounding."""
    if not finite(A) or not _symmetric(A, limits.rtol):
        return False
    if A.size == 0:
        return True
    scale = np.abs(A).max()
    return bool(np.linalg.eigvalsh(A).min() >= -limits.psd_tol * max(scale, 1.0))


def positive_definite(P: np.ndarray, limits: Limits = LIMITS) -> bool:
    """Symmetric positive definite (a Cholesky factor exists): what a covariance must stay."""
    if not finite(P) or not _symmetric(P, limits.rtol):
        return False
    try:
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        return False
    return True


def nis(nu: np.ndarray, S: np.ndarray) -> float:
    return float(nu @ np.linalg.solve(S, nu))


def innovation(nu: np.ndarray, S: np.ndarray, limits: Limits = LIMITS) -> str | None:
    """nu with covariance S within the chi-square bound."""
    if not finite(nu, S) or not positive_definite(S, limits):
        return "implausible-numbers"
    if nis(nu, S) > limits.nis_limit(len(nu)):
        return "implausible-innovation"
    return None


def information(Y: np.ndarray, S: np.ndarray, limits: Limits = LIMITS) -> str | None:
    """An update whose cross-covariance with the prior is L Y (L the prior's Cholesky factor)
    may remove at most S of information: S - Y^T Y positive semi-definite."""
    if not finite(Y):
        return "implausible-numbers"
    if not psd(S - Y.T @ Y, limits):
        return "implausible-information"
    return None


def update(nu: np.ndarray, S: np.ndarray, Y: np.ndarray | None = None, limits: Limits = LIMITS) -> str | None:
    """An unscented or Kalman update's frame (innovation, its covariance, and Y where it has one)."""
    return innovation(nu, S, limits) or (None if Y is None else information(Y, S, limits))


def gain(claimed: np.ndarray, own: np.ndarray, limits: Limits = LIMITS) -> str | None:
    """A gain handed to us against the one our own rows give (equal up to rounding)."""
    if not finite(claimed):
        return "implausible-numbers"
    scale = max(np.abs(own).max(initial=0.0), np.abs(claimed).max(initial=0.0))
    if np.abs(claimed - own).max(initial=0.0) > limits.rtol * scale + 1e-300:
        return "implausible-gain"
    return None


def covariance(P: np.ndarray, limits: Limits = LIMITS) -> str | None:
    """A covariance after an update (or a neighbour's): symmetric positive definite."""
    return None if positive_definite(P, limits) else "implausible-covariance"


def information_matrix(Y: np.ndarray, limits: Limits = LIMITS) -> str | None:
    """An information matrix (inverse covariance, or a factor's): finite, symmetric, PSD."""
    return None if psd(Y, limits) else "implausible-information"


def shift(dx: np.ndarray, P: np.ndarray, limits: Limits = LIMITS) -> str | None:
    """A mean moved by dx against the covariance P it had: within the chi-square bound."""
    if not finite(dx):
        return "implausible-numbers"
    try:
        d2 = float(dx @ np.linalg.solve(P, dx))
    except np.linalg.LinAlgError:
        return "implausible-covariance"
    return "implausible-shift" if d2 > limits.nis_limit(len(dx)) else None


def reduction(P_prior: np.ndarray, P_post: np.ndarray, dof: int, limits: Limits = LIMITS) -> str | None:
    """A posterior handed to us for our own prior (RDL's commit): one update of a dof-dimensional
    measurement removes P_prior - P_post = Pxz S^-1 Pxz^T, positive semi-definite and of rank at
    most dof, and leaves P_post positive definite. Whitened by the prior's Cholesky factor L, the
    reduction's eigenvalues lie in [0, 1) and all but the dof largest are zero (to rounding). A
    posterior that claims more (a smaller covariance than any one measurement can give, or
    information in more directions than it measures) is refused."""
    if not finite(P_post) or not positive_definite(P_post, limits):
        return "implausible-covariance"
    try:
        L = np.linalg.cholesky(P_prior)
    except np.linalg.LinAlgError:
        return "implausible-covariance"
    W = np.linalg.solve(L, np.linalg.solve(L, P_prior - P_post).T)  # L^-1 (P_prior - P_post) L^-T
    W = 0.5 * (W + W.T)
    ev = np.linalg.eigvalsh(W)
    tol = 1e3 * limits.psd_tol
    if ev[0] < -tol or ev[-1] >= 1.0 or (len(ev) > dof and ev[-dof - 1] > tol):
        return "implausible-information"
    return None


def step_bound(S: np.ndarray, dof: int, P_block: np.ndarray | None = None, limits: Limits = LIMITS) -> float:
    """The derived bound on how far one update that passes `innovation` (and `shift`) can move a
    block of the receiver's state, in its own units (metres, for a position block): the update
    moves the state by dx = K nu, and for a Kalman update of a consistent joint
    dx^T P^-1 dx <= nu^T S^-1 nu <= nis_limit(dof) (Pxz^T P^-1 Pxz <= Pzz <= S), so
    |dx_block| <= sqrt(nis_limit * lambda_max(P_block)). For a fusion checked with `shift` against
    S (EKF-CI), P_block is S itself. docs/security.md, "A member's damage (finding 7)"."""
    B = S if P_block is None else P_block
    return float(np.sqrt(limits.nis_limit(dof) * np.linalg.eigvalsh(B).max()))
