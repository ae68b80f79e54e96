"""UKF-DCL (Wang et al. 2019) as a sans-I/O node, extended to reach the whole connected swarm.

Each node keeps its own mean x_i and its row of the joint covariance, P_ij for every j
(a missing block is zero: never correlated). One relative measurement z_mn runs one chain:

1. start   m -> n: the measurement, x_m and m's row. n now holds the (m, n) pair, forms the
           lower Cholesky factor L of its 2x2-block covariance (A11, A21, A22 of eq. 15-16,
           after the eq. 17 reordering), runs the unscented transform on [x_m; x_n] and gets
           z_bar, Pz and Y, with Pxz_i = A_i Y for every node i (eq. 20).
2. token   depth first through the radio graph: each node it reaches for the first time
           solves its A_i = [P_im P_in] L^-T from its own row and adds its gain K_i. The next
           hop is the nearest unvisited neighbour (the paper's serial path); a node with none
           sends the token back to the node it came from. Nothing is applied yet.
3. commit  when the token is back at m with nobody left to visit, every gain is known: m
           floods a commit down the chain's tree and every node applies
           x_i += K_i nu and P_ij -= K_i Pz K_j^T for all j (eq. 21-23, minus per the erratum).
           Because every node applies the same gains, each row equals the centralized P; the
           paper's "later node holds the fresh copy" problem does not arise.

Blocks P_ij with j outside the chain's reach are corrected with Pxz_j, which n computes from
m's row and its own (it needs only P_jm and P_jn), so the joint covariance stays the one of
the gain actually applied (K_j = 0 for unreached nodes). j's own copy of that block is then
stale until the links return; see docs/ukf-dcl.md.

Several measurements in one tick run as successive chains in key order (m, n, q). Every
measurer starts its chain at once; a node drops any token whose key is larger than one of its
own pending keys, so only the smallest chain of a connected part can complete. Its token
gathers every pending key it meets; after the commit the owner of the next key starts the next
chain. `epoch` counts commits within the tick: a frame of another epoch or tick is stale
(dropped) or early (held until its epoch comes), so no frame ever mixes two versions of P.
"""

from __future__ import annotations

import numpy as np

from swarmloc import kalman
from swarmloc.messages import Beacon, DclCommit, DclStart, DclToken, Sensors
from swarmloc.models import Range
from swarmloc.node import Estimate, Node, Send, odometry_of

Key = tuple[int, int, int]


class UkfDclNode(Node):
    algorithm = "ukf-dcl"

    def __init__(self, aid, x0, P0, model="planar-speed-heading", spread: float = 3.0):
        super().__init__(aid, x0, P0, model)
        self.ut = kalman.UnscentedTransform(spread)
        self.meas = Range(self.model)
        self.row: dict[int, np.ndarray] = {self.id: self.P}
        del self.P  # the own block lives in self.row; one copy only
        self.epoch = 0
        self.pending: dict[Key, tuple[np.ndarray, np.ndarray]] = {}  # own measurements not yet committed
        self.known_pending: set[Key] = set()  # keys of this tick seen from others
        self.beacons: dict[int, dict[int, np.ndarray]] = {}  # j -> {tick: position}
        self.neighbours: dict[int, np.ndarray] = {}  # snapshot for this tick
        self.held: list[tuple[int, object]] = []  # early frames: (src, msg)
        self.stats = {"chains_committed": 0, "measurements_used": 0, "measurements_dropped": 0}

    # ------------------------------------------------------------------ estimate

    def estimate(self) -> Estimate:
        return Estimate(self.k, self.x.copy(), self.row[self.id].copy())

    def covariance_row(self) -> dict[int, np.ndarray]:
        return {j: b.copy() for j, b in self.row.items()}

    # ------------------------------------------------------------------ tick

    def step(self, sensors: Sensors) -> list[Send]:
        if sensors.k <= self.k:
            return self.drop("stale-tick", f"sensors k={sensors.k} at k={self.k}")
        if not self.model.identity_transition:
            raise NotImplementedError("UKF-DCL here needs F = I (cross-covariances kept by prediction)")
        unfinished = len(self.pending)
        self.stats["measurements_dropped"] += unfinished
        self.k, self.epoch = sensors.k, 0
        self.pending.clear()
        self.known_pending.clear()
        x, _, Q = self.model.predict(self.x, odometry_of(sensors))
        self.x = x
        self.row[self.id] = self.row[self.id] + Q

        # Neighbours are those heard in the previous tick: in lockstep every beacon of k-1 has
        # arrived by now, so every node routes on the same snapshot whatever the delivery order.
        self.neighbours = {j: b[self.k - 1] for j, b in self.beacons.items() if self.k - 1 in b}
        for j in list(self.beacons):
            self.beacons[j] = {t: p for t, p in self.beacons[j].items() if t >= self.k - 1}

        counts: dict[int, int] = {}
        for r in sensors.ranges:
            q = counts.get(r.target, 0)
            counts[r.target] = q + 1
            if r.target == self.id or r.target not in self.neighbours:
                self.stats["measurements_dropped"] += 1  # cannot reach the measured platform
                continue
            self.pending[(self.id, r.target, q)] = (np.array([r.range]), np.array([[r.std**2]]))

        out: list[Send] = [Send(Beacon(self.k, self.model.position(self.x).copy()), None)]
        out += self._start_next()
        out += self._release_held()
        return out

    def _min_pending(self) -> Key | None:
        keys = set(self.pending) | self.known_pending
        return min(keys) if keys else None

    def _start_next(self) -> list[Send]:
        """Start our smallest pending chain if it is the smallest this node knows of."""
        if not self.pending:
            return []
        key = min(self.pending)
        if key != self._min_pending():
            return []
        z, R = self.pending[key]
        msg = DclStart(
            self.k, self.epoch, list(key), z, R, self.x.copy(), self.covariance_row(),
            [list(k) for k in sorted(self.pending)],
        )
        return [Send(msg, key[1])]

    # ------------------------------------------------------------------ radio

    def receive(self, src, msg) -> list[Send]:
        if isinstance(msg, Beacon):
            if msg.position.shape == (self.model.position_dim,) and src != self.id:
                self.beacons.setdefault(src, {})[msg.k] = msg.position
                return []
            return self.drop("shape", "beacon")
        if not isinstance(msg, (DclStart, DclToken, DclCommit)):
            return self.drop("unexpected-type", type(msg).__name__)
        if msg.k < self.k or (msg.k == self.k and msg.epoch < self.epoch):
            return self.drop("stale", f"k={msg.k} epoch={msg.epoch}")
        if msg.k > self.k or msg.epoch > self.epoch:
            if len(self.held) >= 256:
                return self.drop("held-overflow")
            self.held.append((src, msg))
            return []
        try:
            if isinstance(msg, DclStart):
                return self._on_start(src, msg)
            if isinstance(msg, DclToken):
                return self._on_token(src, msg)
            return self._on_commit(src, msg)
        except (ValueError, np.linalg.LinAlgError, KeyError) as exc:
            # Shapes or numbers that decode but do not fit this swarm: drop, state untouched.
            return self.drop("invalid", repr(exc))

    def _release_held(self) -> list[Send]:
        ready = [(s, m) for s, m in self.held if m.k == self.k and m.epoch == self.epoch]
        later = [(s, m) for s, m in self.held if m.k > self.k or (m.k == self.k and m.epoch > self.epoch)]
        for _ in range(len(self.held) - len(ready) - len(later)):
            self.drop("stale", "held frame overtaken")
        self.held = later
        out = []
        for src, m in ready:
            out += self.receive(src, m)
        return out

    def _preempted(self, key: Key) -> bool:
        """True if we know a smaller pending key: this chain cannot be the one to run now."""
        self.known_pending.add(key)
        return min(set(self.pending) | self.known_pending) < key

    # ------------------------------------------------------------------ chain steps

    def _on_start(self, src: int, msg: DclStart) -> list[Send]:
        key = tuple(msg.key)
        m, n, _ = key
        d, dz = self.model.state_dim, self.meas.dim
        if n != self.id or m != src:
            return self.drop("misrouted", f"start {key}")
        if msg.x_m.shape != (d,) or msg.z.shape != (dz,) or msg.R.shape != (dz, dz):
            return self.drop("shape", "start")
        if any(b.shape != (d, d) for b in msg.row_m.values()) or m not in msg.row_m:
            return self.drop("shape", "start row")
        self.known_pending.update(tuple(k) for k in msg.pending)
        if self._preempted(key):
            return self.drop("preempted", str(key))

        pending = {tuple(k) for k in msg.pending} | set(self.pending)
        P_mn = self.row.get(m, np.zeros((d, d))).T  # our copy of P_mn = P_nm^T
        P_sub = np.block([[msg.row_m[m], P_mn], [P_mn.T, self.row[self.id]]])
        try:
            L = np.linalg.cholesky(P_sub)
        except np.linalg.LinAlgError:
            # The pair's covariance is not positive definite (copies of P_mn out of step after
            # a partition): refuse the measurement, but run the chain empty so the keys it
            # preempted still get their turn.
            self.drop("not-positive-definite", str(key))
            empty = DclToken(self.k, self.epoch, list(key), np.eye(2 * d), np.zeros((2 * d, dz)), np.eye(dz),
                             np.zeros(dz), [m, n], {n: m}, {}, {}, [list(k) for k in sorted(pending)])
            return self._forward(empty)
        x_sub = np.concatenate([msg.x_m, self.x])
        z_bar, Pzz, Y = self.ut.measurement_moments(x_sub, L, self.meas.h_joint)
        Pz = Pzz + msg.R
        nu = msg.z - z_bar
        gains = {m: kalman.gain(L[:d] @ Y, Pz), n: kalman.gain(L[d:] @ Y, Pz)}

        # Pxz_j for every other node either row mentions, for blocks with nodes the chain
        # may not reach (see module docstring).
        xz = {}
        zero = np.zeros((d, d))
        for j in (set(msg.row_m) | set(self.row)) - {m, n}:
            P_j_mn = np.hstack([msg.row_m.get(j, zero).T, self.row.get(j, zero).T])
            if P_j_mn.any():
                xz[j] = kalman.solve_lower(L, P_j_mn.T).T @ Y

        token = DclToken(self.k, self.epoch, list(key), L, Y, Pz, nu, [m, n], {n: m}, gains, xz,
                         [list(k) for k in sorted(pending)])
        return self._forward(token)

    def _on_token(self, src: int, msg: DclToken) -> list[Send]:
        key = tuple(msg.key)
        d, dz = self.model.state_dim, self.meas.dim
        if msg.L.shape != (2 * d, 2 * d) or msg.Y.shape != (2 * d, dz) or msg.Pz.shape != (dz, dz) or msg.nu.shape != (dz,):
            return self.drop("shape", "token")
        if any(g.shape != (d, dz) for g in msg.gains.values()) or any(g.shape != (d, dz) for g in msg.xz.values()):
            return self.drop("shape", "token gains")
        self.known_pending.update(tuple(k) for k in msg.pending)
        if self._preempted(key):
            return self.drop("preempted", str(key))
        if self.id in msg.order:
            return self._forward(msg)  # backtracking through us
        gains = dict(msg.gains)
        if gains:  # an empty chain (measurement abandoned) only gathers keys and sequences
            m, n, _ = key
            zero = np.zeros((d, d))
            P_i_mn = np.hstack([self.row.get(m, zero), self.row.get(n, zero)])
            A_i = kalman.solve_lower(msg.L, P_i_mn.T).T
            gains[self.id] = kalman.gain(A_i @ msg.Y, msg.Pz)
        pending = {tuple(k) for k in msg.pending} | set(self.pending)
        token = DclToken(
            msg.k, msg.epoch, msg.key, msg.L, msg.Y, msg.Pz, msg.nu, msg.order + [self.id],
            {**msg.parent, self.id: src}, gains, msg.xz, [list(k) for k in sorted(pending)],
        )
        return self._forward(token)

    def _forward(self, token: DclToken) -> list[Send]:
        """Depth-first step: nearest unvisited neighbour, else back to our parent, else commit."""
        visited = set(token.order)
        here = self.model.position(self.x)
        candidates = [(float(np.linalg.norm(p - here)), j) for j, p in self.neighbours.items() if j not in visited]
        if candidates:
            return [Send(token, min(candidates)[1])]
        if self.id in token.parent:
            return [Send(token, token.parent[self.id])]
        if self.id != token.key[0]:
            return self.drop("orphan-token", str(token.key))
        commit = DclCommit(token.k, token.epoch, token.key, token.Pz, token.nu, token.parent,
                           token.gains, token.xz, token.pending)
        return self._on_commit(self.id, commit)

    def link_failed(self, dst: int, msg) -> list[Send]:
        """A unicast did not arrive: forget that neighbour for this tick and route around it."""
        self.neighbours.pop(dst, None)
        if not isinstance(msg, (DclStart, DclToken)) or msg.k != self.k or msg.epoch != self.epoch:
            return self.drop("undeliverable", type(msg).__name__)
        if isinstance(msg, DclStart):
            # The measured platform is out of reach: the measurement is lost, but the chain
            # still has to run (empty) so the keys it preempted get their turn.
            d, dz = self.model.state_dim, self.meas.dim
            token = DclToken(self.k, self.epoch, msg.key, np.eye(2 * d), np.zeros((2 * d, dz)), np.eye(dz),
                             np.zeros(dz), [self.id], {}, {}, {}, [list(k) for k in sorted(self.pending)])
            return self._forward(token)
        if msg.parent.get(self.id) == dst:
            return self.drop("chain-broken", f"parent {dst} unreachable")
        return self._forward(msg)

    def _on_commit(self, src: int, msg: DclCommit) -> list[Send]:
        key = tuple(msg.key)
        d, dz = self.model.state_dim, self.meas.dim
        if msg.parent.get(self.id, key[0]) != src or (self.id != key[0] and self.id not in msg.parent):
            return self.drop("misrouted", f"commit {key}")
        if msg.gains and self.id not in msg.gains:
            return self.drop("misrouted", f"commit {key} without our gain")
        if msg.Pz.shape != (dz, dz) or msg.nu.shape != (dz,) or any(g.shape != (d, dz) for g in msg.gains.values()):
            return self.drop("shape", "commit")
        if msg.gains:
            K_i = msg.gains[self.id]
            new_row = dict(self.row)
            for j, K_j in msg.gains.items():
                new_row[j] = new_row.get(j, np.zeros((d, d))) - kalman.covariance_decrement(K_i, msg.Pz, K_j)
            for j, xz_j in msg.xz.items():
                if j not in msg.gains:
                    new_row[j] = new_row.get(j, np.zeros((d, d))) - K_i @ xz_j.T
            if not all(np.isfinite(b).all() for b in new_row.values()):
                return self.drop("invalid", "non-finite update")
            self.x = self.x + K_i @ msg.nu
            self.row = new_row
        self.epoch += 1
        self.stats["chains_committed"] += 1
        if key in self.pending:
            del self.pending[key]
            self.stats["measurements_used" if msg.gains else "measurements_dropped"] += 1
        self.known_pending = {tuple(k) for k in msg.pending} - {key}

        out = [Send(msg, c) for c, p in sorted(msg.parent.items()) if p == self.id]
        out += self._start_next()
        out += self._release_held()
        return out
