"""Finding a lost node again: batch multilateration over a window of ticks.

A node whose position covariance is very wide (an agent restarted after missing many ticks,
or one cut off for long) must not feed a range to a Kalman update as if its prior were
Gaussian enough: with a prior of tens of metres and neighbours nearly in a line, a range
linearized at the wrong mean can pull it onto the mirror image of its position, with a
covariance that then shrinks around the wrong point. A lost node instead collects ranges to
neighbours (with the neighbours' own estimates at the time) for a few ticks, ties them to one
position through its odometry, and solves them together by least squares from many starting
points. It accepts the answer only when it fits the ranges and no other point does: moving
neighbours and the node's own measured motion make a mirror image that fits one tick fit the
whole window badly.

Pure numpy/scipy: the node (ukf_dcl.UkfDclNode) decides when it is lost and what to do with
the answer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Fix:
    """A multilateration result: position now and its covariance."""

    position: np.ndarray
    cov: np.ndarray
    ranges: int
    cost: float


@dataclass
class _Constraint:
    k: int
    anchor: np.ndarray  # the neighbour's estimated position at tick k
    anchor_cov: np.ndarray
    range: float
    var: float


class Multilateration:
    """Ranges of the last `window` ticks, tied to the node's position now by its odometry."""

    def __init__(self, dim: int, window: int = 80, min_ranges: int = 6, gate: float = 0.99):
        self.dim, self.window, self.min_ranges, self.gate = dim, window, min_ranges, gate
        self.constraints: list[_Constraint] = []
        self.shift: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # tick -> (sum of moves, sum of Q) up to it

    def clear(self) -> None:
        self.constraints.clear()
        self.shift.clear()

    def moved(self, k: int, delta: np.ndarray, Q: np.ndarray) -> None:
        """The node's odometry moved it by delta (noise Q) into tick k."""
        last = self.shift[max(self.shift)] if self.shift else (np.zeros(self.dim), np.zeros((self.dim, self.dim)))
        self.shift[k] = (last[0] + delta, last[1] + Q)
        for old in [t for t in self.shift if t < k - self.window]:
            del self.shift[old]
        self.constraints = [c for c in self.constraints if c.k in self.shift]

    def add(self, k: int, anchor: np.ndarray, anchor_cov: np.ndarray, rng: float, var: float) -> None:
        if k in self.shift and np.isfinite(anchor).all() and np.isfinite(anchor_cov).all() and rng >= 0:
            self.constraints.append(_Constraint(k, np.array(anchor, float), np.array(anchor_cov, float), rng, var))

    def solve(self, guess: np.ndarray) -> Fix | None:
        """The position now, if the window pins it down without ambiguity; else None."""
        cs = self.constraints
        if len(cs) < self.min_ranges or len({tuple(c.anchor.round(3)) for c in cs}) < self.dim + 1:
            return None
        now = max(self.shift)
        S_now, Q_now = self.shift[now]
        # p_k = p_now - (S_now - S_k): each anchor, moved into the node's frame of now.
        offset = np.array([c.anchor + (S_now - self.shift[c.k][0]) for c in cs])
        ranges = np.array([c.range for c in cs])
        extra = [c.anchor_cov + (Q_now - self.shift[c.k][1]) for c in cs]

        def sigmas(p):
            u = p - offset
            u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-9)
            return np.sqrt(np.array([c.var for c in cs]) + np.einsum("ni,nij,nj->n", u, np.array(extra), u))

        # Imported here, not at the top: only a lost node gets this far, and scipy.optimize with
        # scipy.special adds about 40 MB to every agent process that loads them.
        from scipy.optimize import least_squares
        from scipy.special import chdtri

        def fit(start):
            s = sigmas(start)
            for _ in range(3):  # weights depend on the direction to each anchor: refit twice
                r = least_squares(lambda p: (np.linalg.norm(p - offset, axis=1) - ranges) / s, start, method="lm")
                start, s = r.x, sigmas(r.x)
            res = (np.linalg.norm(r.x - offset, axis=1) - ranges) / s
            return r.x, float(res @ res), s

        spread = max(float(ranges.max()), 1.0)
        starts = [guess] + [offset[-1] + spread * np.array([np.cos(a), np.sin(a)])
                            for a in np.linspace(0, 2 * np.pi, 12, endpoint=False)] if self.dim == 2 else [guess]
        fits = sorted((fit(np.array(s, float)) for s in starts), key=lambda f: f[1])
        best, cost, s = fits[0]
        limit = chdtri(len(cs) - self.dim, 1.0 - self.gate)  # chi-square quantile; scipy.stats costs 0.35 s to import
        if cost > limit:
            return None  # nothing fits: a bad anchor or odometry; wait for a new window
        u = best - offset
        d = np.linalg.norm(u, axis=1)
        J = u / np.maximum(d, 1e-9)[:, None] / s[:, None]
        info = J.T @ J
        if np.linalg.cond(info) > 1e8:
            return None
        cov = np.linalg.inv(info)
        # Another minimum that also fits, away from this one: ambiguous (a mirror image).
        sd = np.sqrt(np.trace(cov))
        for p, c, _ in fits[1:]:
            if c <= limit and np.linalg.norm(p - best) > 3 * sd + 1.0:
                return None
        # The anchors' errors are correlated over the window and do not average out: keep the
        # mean of their covariances as a floor.
        cov = cov + np.mean([c.anchor_cov for c in cs], axis=0)
        return Fix(best, cov, len(cs), cost)
