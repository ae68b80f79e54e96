"""The one Kalman core every estimator in swarmloc is built on.

Centralized and distributed filters call the same functions; the distributed ones merely call
them on a smaller slice of the state. That is what makes "distributed equals centralized"
a statement about arithmetic, not about two code bases agreeing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np


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
        self, x: np.ndarray, S: np.ndarray, h: Callable[[np.ndarray], np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Predicted measurement, its covariance (without R) and the state cross-covariance.

        Returns (z_mean, Pzz, Y) where Pxz = S @ Y: Y is the part of the cross-covariance that
        does not depend on which state it is paired with, so a node holding its own row of S
        gets its own Pxz block as S_i @ Y (eq. 20) without seeing anyone else's state.
        """
        n = x.shape[0]
        w0, wi = self.weights(n)
        Z = h(self.sigma_points(x, S))
        z_mean = w0 * Z[0] + wi * Z[1:].sum(axis=0)
        dZ = Z - z_mean
        Pzz = w0 * np.outer(dZ[0], dZ[0]) + wi * dZ[1:].T @ dZ[1:]
        Y = wi * np.sqrt(self.spread) * (dZ[1 : n + 1] - dZ[n + 1 :])
        return z_mean, Pzz, Y


def solve_lower(L: np.ndarray, B: np.ndarray) -> np.ndarray:
    """L^-1 B for lower-triangular L (eq. 15's forward substitution).

    numpy's general solve rather than scipy's triangular one: the blocks are a few rows, where
    the two cost the same, and scipy.linalg adds 27 MB to every agent process."""
    return np.linalg.solve(L, B)
