"""RDL's maths: the cross-covariance factors a platform holds, and the updates on them.

Platform i holds its mean x_i, its covariance P_ii and, for every platform j it is correlated
with, its side sigma_ij of the cross-covariance Sigma_ij = sigma_ij sigma_ji^T (j holds the
other side). Nothing else of the joint covariance exists anywhere (Luft et al. 2018, docs/rdl.md):

- time update: P_ii <- F P_ii F^T + Q and sigma_ij <- F sigma_ij, alone (exact);
- a pair (a, b) that measured each other forms its joint block from the two sides, runs the
  unscented transform and the Kalman update on it (exact for the pair), sets sigma_ab to the
  posterior Sigma_ab and sigma_ba to I, and scales its other sides by A_p = P_pp+ P_pp^-1
  (Luft et al.'s approximation of the cross-covariances with the platforms not involved);
- a platform's update against a landmark (a pair of one) scales its sides the same way.

Every function here is pure numpy; the node (node.py) moves their inputs over the radio.
"""

from __future__ import annotations

import numpy as np

from swarmloc.filters import kalman


class Factors:
    """One platform's sides sigma_ij, stacked (n, d, d) so that scaling all of them is one product."""

    def __init__(self, d: int):
        self.d = d
        self.ids: list[int] = []
        self.slot: dict[int, int] = {}
        self.M = np.zeros((0, d, d))

    def __contains__(self, j) -> bool:
        return j in self.slot

    def __len__(self) -> int:
        return len(self.ids)

    def get(self, j: int) -> np.ndarray | None:
        i = self.slot.get(j)
        return None if i is None else self.M[i]

    def set(self, j: int, m: np.ndarray) -> None:
        i = self.slot.get(j)
        if i is None:
            self.slot[j] = len(self.ids)
            self.ids.append(j)
            self.M = np.concatenate([self.M, np.asarray(m, float)[None]], axis=0)
        else:
            self.M[i] = m

    def clear(self) -> None:
        self.ids, self.slot, self.M = [], {}, np.zeros((0, self.d, self.d))

    def scale(self, A: np.ndarray, keep=()) -> None:
        """sigma_ij <- A sigma_ij for every j except those in `keep`."""
        kept = [(j, self.M[self.slot[j]].copy()) for j in keep if j in self.slot]
        self.M = np.matmul(A, self.M)
        for j, m in kept:
            self.M[self.slot[j]] = m

    def pack(self, ids=None) -> tuple[dict, dict]:
        """The sides toward `ids` (every one held when None) as wire mantissas and exponents."""
        return pack({j: self.M[self.slot[j]] for j in (self.ids if ids is None else ids) if j in self.slot})


def pack(blocks: dict) -> tuple[dict, dict]:
    """{j: m} -> ({j: mantissa}, {j: exponent}), m = mantissa * 2**exponent exactly, the mantissa's
    largest magnitude in [0.5, 1) (zero for a zero block), so any double fits the wire's bounds."""
    mant, exp = {}, {}
    for j, m in blocks.items():
        peak = float(np.abs(m).max()) if m.size else 0.0
        e = int(np.frexp(peak)[1]) if peak > 0 else 0
        mant[j], exp[j] = np.ldexp(m, -e), e
    return mant, exp


def unpack(mant: dict, exp: dict) -> dict:
    """The inverse of pack; a mantissa without an exponent is taken as is."""
    return {j: np.ldexp(m, exp.get(j, 0)) for j, m in mant.items()}



def is_covariance(P: np.ndarray) -> bool:
    """Finite, symmetric to rounding and positive definite: what a peer's P must be before we
    take it (a Cholesky factor alone reads one triangle and would pass an asymmetric matrix)."""
    if not np.isfinite(P).all() or not np.allclose(P, P.T, rtol=1e-9, atol=1e-12):
        return False
    try:
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        return False
    return True


def scaling(P_before: np.ndarray, P_after: np.ndarray) -> np.ndarray:
    """A = P_after P_before^-1, the factor by which a platform's sides follow its own update."""
    return np.linalg.solve(P_before, P_after).T


def joint(Ps: list[np.ndarray], cross: np.ndarray | None) -> np.ndarray:
    """The pair's (or a lone platform's) covariance block, members in order."""
    if len(Ps) == 1:
        return Ps[0]
    return np.block([[Ps[0], cross], [cross.T, Ps[1]]])


def pair_update(ut: kalman.UnscentedTransform, h, angles, x: np.ndarray, P: np.ndarray, z: np.ndarray,
                R: np.ndarray, innovation) -> dict | None:
    """The unscented Kalman update of the pair's joint block: NIS and the posterior mean and
    covariance of the block. None if the block is not positive definite."""
    try:
        L = np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        return None
    z_bar, Pzz, Y = ut.measurement_moments(x, L, h, angles)
    Pz = Pzz + R
    nu = innovation(z, z_bar, angles)
    x, P, _ = kalman.update(x, P, L @ Y, Pz, nu)
    # nu, Pz and Y (L Y = Pxz) for plausibility.update (issue 26, finding 7).
    return {"nis": float(nu @ np.linalg.solve(Pz, nu)), "x": x, "P": P, "nu": nu, "Pz": Pz, "Y": Y}
