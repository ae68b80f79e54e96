"""The one Kalman core every estimator in swarmloc is built on.

Centralized and distributed filters call the same functions; the distributed ones merely call
them on a smaller slice of the state. That is what makes "distributed equals centralized"
a statement about arithmetic, not about two code bases agreeing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from swarmloc.models.measurements import wrap_angle


def predict(x: np.ndarray, P: np.ndarray, F: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear(ised) time update of a mean already propagated by the model."""
    return x, F @ P @ F.T + Q


def block_diag(blocks: list[np.ndarray]) -> np.ndarray:
    """scipy.linalg.block_diag for square blocks, without importing scipy.linalg (agents that
    build a joint state need not carry it)."""
    out = np.zeros((sum(b.shape[0] for b in blocks),) * 2)
    i = 0
    for b in blocks:
        out[i:i + b.shape[0], i:i + b.shape[0]] = b
        i += b.shape[0]
    return out


def gain(Pxz: np.ndarray, Pz: np.ndarray) -> np.ndarray:
    """K = Pxz Pz^-1 (eq. 12), solved rather than inverted."""
    return np.linalg.solve(Pz.T, Pxz.T).T


def covariance_decrement(Ki: np.ndarray, Pz: np.ndarray, Kj: np.ndarray) -> np.ndarray:
    """Block (i, j) of K Pz K^T (eq. 22); eq. 23 subtracts it (erratum: eq. 11's plus is wrong)."""
    return Ki @ Pz @ Kj.T


def update(x: np.ndarray, P: np.ndarray, Pxz: np.ndarray, Pz: np.ndarray, innovation: np.ndarray):
    """Full-state Kalman measurement update from cross- and innovation covariances."""
    K = gain(Pxz, Pz)
    return x + K @ innovation, P - covariance_decrement(K, Pz, K), K


def permuted_cholesky(P: np.ndarray, first: list[int], block: int) -> np.ndarray:
    """Lower Cholesky factor of P after moving the given blocks to the front (UKF-DCL eq. 17).

    Returned in the original ordering (rows permuted back), so S @ S.T == P. The ordering of
    the remaining blocks does not matter for a measurement that only involves `first`: the
    first len(first) column blocks of a lower factor depend only on those rows and columns.
    """
    return cholesky_first(P, np.concatenate([np.arange(b * block, (b + 1) * block) for b in first]))


def cholesky_first(P: np.ndarray, first: np.ndarray) -> np.ndarray:
    """permuted_cholesky by component indices: `first` in the given order, then the rest in
    ascending order (blocks of any sizes)."""
    rest = np.setdiff1d(np.arange(P.shape[0]), first)
    idx = np.concatenate([np.asarray(first, dtype=np.intp), rest])
    L = np.linalg.cholesky(P[np.ix_(idx, idx)])
    S = np.empty_like(L)
    S[idx] = L
    return S


@dataclass(frozen=True)
class UnscentedTransform:
    """Symmetric sigma points with the spread fixed as n + lambda.

    Parameterising by the spread rather than lambda makes the transform of a measurement that
    touches only k state components identical whether computed on those k components or on
    the whole swarm state: the extra sigma points sit at the mean and their weight folds into
    the centre weight. UKF-DCL relies on exactly this.

    Choose spread >= the dimension k of what the measurement touches (the (m, n) pair: 2 state
    dims): then the folded centre weight 1 - k/spread is not negative, Pzz is a positive
    combination and the posterior P - Pxz Pz^-1 Pxz^T stays positive semi-definite. Julier's
    n + kappa = 3 gives a negative centre weight for k = 4; with the range measurement of two
    close, uncertain platforms we saw it drive a covariance negative (docs/ukf-dcl.md).
    """

    @staticmethod
    def for_pair(state_dim: int, spread: float | None) -> "UnscentedTransform":
        """The default spread for a pairwise measurement: the pair's dimension."""
        return UnscentedTransform(float(2 * state_dim) if spread is None else float(spread))

    spread: float

    def weights(self, n: int) -> tuple[float, float]:
        """(centre weight, weight of each of the 2n outer points); mean and covariance alike."""
        return 1.0 - n / self.spread, 0.5 / self.spread

    def sigma_points(self, x: np.ndarray, S: np.ndarray) -> np.ndarray:
        """Rows: x, x + sqrt(spread) S[:, p], x - sqrt(spread) S[:, p] (erratum: minus uses column p-n)."""
        D = np.sqrt(self.spread) * S.T
        return np.concatenate([x[None, :], x + D, x - D], axis=0)

    def measurement_moments(
        self, x: np.ndarray, S: np.ndarray, h: Callable[[np.ndarray], np.ndarray], angles: tuple[int, ...] = ()
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Predicted measurement, its covariance (without R) and the state cross-covariance.

        Returns (z_mean, Pzz, Y) where Pxz = S @ Y: Y is the part of the cross-covariance that
        does not depend on which state it is paired with, so a node holding its own row of S
        gets its own Pxz block as S_i @ Y (eq. 20) without seeing anyone else's state.

        `angles`: components of z that are angles. Their sigma points are averaged as offsets
        from the centre point's, wrapped, so a bearing near +-pi is not averaged to 0; the
        returned mean is wrapped to [-pi, pi).
        """
        n = x.shape[0]
        w0, wi = self.weights(n)
        Z = h(self.sigma_points(x, S))
        if angles:
            Z = Z.copy()
            ref = Z[0, list(angles)]
            Z[:, list(angles)] = ref + wrap_angle(Z[:, list(angles)] - ref)
        z_mean = w0 * Z[0] + wi * Z[1:].sum(axis=0)
        dZ = Z - z_mean
        if angles:
            z_mean[list(angles)] = wrap_angle(z_mean[list(angles)])
        Pzz = w0 * np.outer(dZ[0], dZ[0]) + wi * dZ[1:].T @ dZ[1:]
        Y = wi * np.sqrt(self.spread) * (dZ[1 : n + 1] - dZ[n + 1 :])
        return z_mean, Pzz, Y


def chi2_quantile(p: float, dof: int) -> float:
    """The p-quantile of a chi-square distribution with dof degrees of freedom: exact for 1 and 2
    dof, the Wilson-Hilferty approximation above (against scipy for p in [0.9, 0.9999]: within
    3.5 % at 3 dof, 2 % at 6; a gate's threshold needs no more). Without scipy.stats, which an agent process does not carry."""
    from statistics import NormalDist

    if not 0.0 < p < 1.0 or dof < 1:
        raise ValueError(f"chi2_quantile needs 0 < p < 1 and dof >= 1, got p={p}, dof={dof}")
    if dof == 1:
        return NormalDist().inv_cdf(0.5 + p / 2) ** 2
    if dof == 2:
        return -2.0 * np.log1p(-p)
    z = NormalDist().inv_cdf(p)
    c = 2.0 / (9.0 * dof)
    return float(dof * (1.0 - c + z * np.sqrt(c)) ** 3)


class Gate:
    """A chi-square innovation gate that cannot lock a platform out for good.

    A measurement is admitted when its NIS is below the chi-square quantile `p` for its
    dimension. After `open_after` consecutive rejections under one key (a platform, or a pair),
    the gate stands open for that key: every measurement is admitted until one passes the
    test again. Why: after a bad stretch of odometry the estimate may sit farther from the
    truth than the gate allows, and then every later measurement, the only thing that could
    bring it back, is rejected; a streak of rejections is that state's signature (an outlier
    is one rejection among admissions). Deterministic for the sequence of NIS values it sees,
    so two filters that compute the same NIS decide the same.
    p None: no gate (everything is admitted)."""

    def __init__(self, p: float | None = None, open_after: int = 10):
        self.p, self.open_after = p, int(open_after)
        self.streak: dict = {}
        self.rejected = 0
        self.forced = 0  # admitted while the gate stood open
        self._limit: dict[int, float] = {}

    def limit(self, dof: int) -> float:
        if dof not in self._limit:
            self._limit[dof] = chi2_quantile(self.p, dof)
        return self._limit[dof]

    def admit(self, key, nis: float, dof: int) -> bool:
        if self.p is None:
            return True
        if nis <= self.limit(dof):
            self.streak.pop(key, None)
            return True
        n = self.streak.get(key, 0)
        if n >= self.open_after:
            self.forced += 1
            return True
        self.streak[key] = n + 1
        self.rejected += 1
        return False


def solve_lower(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """L^-1 B for lower-triangular L (eq. 15's forward substitution).

    numpy's general solve rather than scipy's triangular one: the blocks are a few rows, where
    the two cost the same, and scipy.linalg adds 27 MB to every agent process."""
    return np.linalg.solve(L, B)
