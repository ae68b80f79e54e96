"""What every distributed estimator needs from its neighbourhood, apart from its maths:
who is around (from their beacons) and unicast that tries again after a NACK.

A node keeps a `NeighbourTable` of the beacons it heard and a `RetryBudget` for its unicasts;
both are plain state, reset or pruned by the node at the start of a tick.
"""

from __future__ import annotations

import numpy as np

from swarmloc.wire.messages import Beacon


class NeighbourTable:
    """Beacons heard, per neighbour and tick: position and its covariance.

    `snapshot(k)` is the neighbourhood a node acts on in tick k: those heard in the `window`
    ticks before k, at their latest position. In lockstep every beacon of earlier ticks has
    arrived by the time tick k starts, so every node sees the same snapshot whatever the order
    of deliveries; the window rides out a lost beacon or two on a lossy radio."""

    def __init__(self, me: int, position_dim: int, window: int = 3):
        self.me, self.p, self.window = me, position_dim, window
        self.beacons: dict[int, dict[int, tuple[np.ndarray, np.ndarray]]] = {}  # j -> {tick: (position, cov)}

    def valid(self, src: int, msg: Beacon) -> bool:
        """A beacon another node could have sent: the right shapes, finite, not our own."""
        return (src != self.me and msg.position.shape == (self.p,) and msg.cov.shape == (self.p, self.p)
                and bool(np.isfinite(msg.position).all() and np.isfinite(msg.cov).all()))

    def hear(self, src: int, msg: Beacon) -> None:
        self.beacons.setdefault(src, {})[msg.k] = (msg.position, msg.cov)

    def get(self, j: int, k: int) -> tuple[np.ndarray, np.ndarray] | None:
        """Neighbour j's beacon of tick k, if heard."""
        return self.beacons.get(j, {}).get(k)

    def heard(self, j: int, k: int) -> bool:
        return k in self.beacons.get(j, {})

    def __len__(self) -> int:
        return len(self.beacons)

    def snapshot(self, k: int) -> dict[int, np.ndarray]:
        """Prune beacons older than the window and return {j: latest position before tick k}."""
        lo = k - self.window
        for j in list(self.beacons):
            self.beacons[j] = {t: p for t, p in self.beacons[j].items() if t >= lo}
        return {j: b[max(t for t in b if t < k)][0] for j, b in self.beacons.items() if any(t < k for t in b)}


class RetryBudget:
    """How often a unicast has been sent again after a NACK, per key (message, hop, tick...).

    `again(key, budget)` says whether one more try is allowed and counts it; `clear()` at the
    start of a tick, since a frame of a tick that is over is not worth resending."""

    def __init__(self):
        self.tries: dict[tuple, int] = {}

    def again(self, key: tuple, budget: int) -> bool:
        n = self.tries.get(key, 0)
        if n >= budget:
            return False
        self.tries[key] = n + 1
        return True

    def clear(self) -> None:
        self.tries.clear()
