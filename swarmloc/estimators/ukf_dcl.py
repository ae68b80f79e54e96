"""UKF-DCL (Wang et al. 2019) as a sans-I/O node, extended to reach the whole connected swarm.

Each node keeps its own mean x_i and its row of the joint covariance, P_ij for every j in its
correlation group (outside the group the blocks are exactly zero). One relative measurement
z_mn runs one chain (docs/ukf-dcl.md has the picture):

1. start   m -> n: the measurement, x_m, P_mm and m's group. n now holds the (m, n) pair,
           forms the lower Cholesky factor L of its 2x2-block covariance (A11, A21, A22 of
           eq. 15-16, after the eq. 17 reordering), runs the unscented transform on
           [x_m; x_n] and gets z_bar, Pz and Y, with Pxz_i = A_i Y for every node i (eq. 20).
2. token   depth first through the radio graph: each node it reaches for the first time
           solves its A_i = [P_im P_in] L^-T from its own row, adds its gain K_i and its group.
           The next hop is the nearest unvisited neighbour (the paper's serial path); a node
           with none sends the token back to the node it came from. Nothing is applied yet.
3. commit  when the token is back at m with nobody left to visit, every gain is known and m
           floods a commit down the chain's tree: every node applies x_i += K_i nu and
           P_ij -= K_i Pz K_j^T for all j (eq. 21-23, minus per the erratum). Every node
           applies the same gains, so each row equals the centralized P.

Correlation groups keep this exact-or-conservative when the radio splits the swarm. A
measurement touches exactly the nodes correlated with m or n, i.e. the groups of m and n; if
the chain reached every member of every group it met, the update is exact and the two groups
merge. If some member was out of reach, the chain commits a split instead: the reachable part
p of group G scales its covariance block by |G|/|p| and drops its cross-covariances with the
rest. Each part of G does the same when it next meets the split, and the fractions |p|/|G|
sum to one, so the block-diagonal result bounds the true joint covariance (covariance
intersection with weights |p|/|G|). The measurement then runs again on the split groups.
Copies of a cross-covariance can therefore never go out of step: either both holders update
it in the same commit, or both drop it.

Several measurements in one tick run as successive chains in key order (m, n, q). Every
measurer starts its chain at once; a node drops any token whose key is larger than one of its
own pending keys, so only the smallest chain of a connected part can complete. Its token
gathers every pending key it meets; after the commit the owner of the next key starts the next
chain. `epoch` counts commits within the tick: a frame of another epoch or tick is stale
(dropped) or early (held until its epoch comes), so no frame ever mixes two versions of P.
"""

from __future__ import annotations

import logging
from collections import defaultdict, deque

import numpy as np

from swarmloc import kalman
from swarmloc.messages import (CHAIN_OK, CHAIN_REFUSED, CHAIN_UNREACHABLE, Beacon, DclCommit, DclStart, DclToken,
                               Sensors)
from swarmloc.models import Range
from swarmloc.node import Estimate, Node, Send, odometry_of

log = logging.getLogger(__name__)
Key = tuple[int, int, int]
NEIGHBOUR_TICKS = 3
LATE_TICKS = 2  # how long a late commit is kept in case an earlier missed one arrives


class UkfDclNode(Node):
    algorithm = "ukf-dcl"

    def __init__(self, aid, x0, P0, model="planar-speed-heading", spread: float | None = None, max_retries: int = 3):
        super().__init__(aid, x0, P0, model)
        self.max_retries = max_retries
        self.retries: dict[tuple, int] = {}  # (k, epoch, message type, dst) -> resends so far
        self.ut = kalman.UnscentedTransform.for_pair(self.model.state_dim, spread)
        self.meas = Range(self.model)
        self.row: dict[int, np.ndarray] = {self.id: self.P}
        del self.P  # the own block lives in self.row; one copy only
        self.gid: list[int] = [0, 0, self.id]  # every node starts alone, uncorrelated
        self.members: list[int] = [self.id]
        self.epoch = 0
        self.pending: dict[Key, tuple[np.ndarray, np.ndarray]] = {}  # own measurements not yet finished
        self.known_pending: set[Key] = set()  # keys of this tick seen from others
        self.beacons: dict[int, dict[int, np.ndarray]] = {}  # j -> {tick: position}
        self.neighbours: dict[int, np.ndarray] = {}  # snapshot for this tick
        self.held: list[tuple[int, object]] = []  # early frames: (src, msg)
        self.late: list[tuple[int, DclCommit]] = []  # missed commits that may still apply
        self.applied: deque[DclCommit] = deque(maxlen=16)  # recent state-changing commits, to resend
        self.resyncs: dict[Key, int] = {}  # resync attempts per chain key (this tick)
        self.stats = {"chains_committed": 0, "measurements_used": 0, "measurements_dropped": 0, "group_splits": 0,
                      "late_commits": 0}

    # ------------------------------------------------------------------ state

    def estimate(self) -> Estimate:
        return Estimate(self.k, self.x.copy(), self.row[self.id].copy())

    def resume(self, k, x, P) -> None:
        """Continue from a checkpoint: own mean and covariance only. Cross-covariances are
        gone, so the node rejoins as a group of its own under a fresh id; its former group
        splits from it (conservatively) when a chain next meets it."""
        self.k, self.x = int(k), np.array(x, float)
        self.row = {self.id: np.array(P, float)}
        self.gid, self.members = [int(k), 2**40, self.id], [self.id]

    def _group(self) -> list[int]:
        return [*self.gid, *self.members]

    def _block(self, j: int) -> np.ndarray:
        b = self.row.get(j)
        return np.zeros((self.model.state_dim,) * 2) if b is None else b

    # ------------------------------------------------------------------ tick

    def step(self, sensors: Sensors) -> list[Send]:
        if sensors.k <= self.k:
            return self.drop("stale-tick", f"sensors k={sensors.k} at k={self.k}")
        if not self.model.identity_transition:
            raise NotImplementedError("UKF-DCL here needs F = I (cross-covariances kept by prediction)")
        self.stats["measurements_dropped"] += len(self.pending)  # chains that never finished
        gap = self.missed_motion(sensors)
        if gap is not None:
            self.row[self.id] = self.row[self.id] + gap
        self.k, self.epoch = sensors.k, 0
        self.pending.clear()
        self.known_pending.clear()
        self.retries.clear()
        self.resyncs.clear()
        x, _, Q = self.model.predict(self.x, odometry_of(sensors))
        self.x = x
        self.row[self.id] = self.row[self.id] + Q

        # Neighbours are those heard in the last NEIGHBOUR_TICKS ticks before this one (their
        # latest position): in lockstep all those beacons have arrived by now, so every node
        # routes on the same snapshot whatever the delivery order; the window rides out a lost
        # beacon or two on a lossy radio (a stale neighbour costs a NACK, a missing one a split).
        lo = self.k - NEIGHBOUR_TICKS
        for j in list(self.beacons):
            self.beacons[j] = {t: p for t, p in self.beacons[j].items() if t >= lo}
        self.neighbours = {j: b[max(t for t in b if t < self.k)] for j, b in self.beacons.items()
                           if any(t < self.k for t in b)}

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
        msg = DclStart(self.k, self.epoch, list(key), z, R, self.x.copy(), self.row[self.id].copy(), self._group(),
                       [list(k) for k in sorted(self.pending)])
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
            if isinstance(msg, DclCommit):
                return self._late_commit(src, msg)
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
        out = []
        for s, m in self.held:
            if (s, m) in ready or (s, m) in later:
                continue
            if isinstance(m, DclCommit):
                out += self._late_commit(s, m)  # overtaken, but a commit may still apply
            else:
                self.drop("stale", "held frame overtaken")
        self.held = later
        for src, m in ready:
            out += self.receive(src, m)
        return out

    def _preempted(self, key: Key) -> bool:
        """True if we know a smaller pending key: this chain cannot be the one to run now."""
        self.known_pending.add(key)
        return min(set(self.pending) | self.known_pending) < key

    # ------------------------------------------------------------------ chain steps

    def _token(self, key, status, order, parent, groups, pending, L=None, Y=None, Pz=None, nu=None, gains=None):
        d, dz = self.model.state_dim, self.meas.dim
        return DclToken(
            self.k, self.epoch, list(key), status,
            np.eye(2 * d) if L is None else L, np.zeros((2 * d, dz)) if Y is None else Y,
            np.eye(dz) if Pz is None else Pz, np.zeros(dz) if nu is None else nu,
            order, parent, gains or {}, groups, [list(k) for k in sorted(pending)],
        )

    def _on_start(self, src: int, msg: DclStart) -> list[Send]:
        key = tuple(msg.key)
        m, n, _ = key
        d, dz = self.model.state_dim, self.meas.dim
        if n != self.id or m != src:
            return self.drop("misrouted", f"start {key}")
        if msg.x_m.shape != (d,) or msg.P_mm.shape != (d, d) or msg.z.shape != (dz,) or msg.R.shape != (dz, dz):
            return self.drop("shape", "start")
        if len(msg.group_m) < 4 or m not in msg.group_m[3:]:
            return self.drop("invalid", "start group")
        self.known_pending.update(tuple(k) for k in msg.pending)
        if self._preempted(key):
            return self.drop("preempted", str(key))

        pending = {tuple(k) for k in msg.pending} | set(self.pending)
        groups = {m: msg.group_m, n: self._group()}
        P_nm = self._block(m)
        P_sub = np.block([[msg.P_mm, P_nm.T], [P_nm, self.row[self.id]]])
        try:
            L = np.linalg.cholesky(P_sub)
        except np.linalg.LinAlgError:
            # Cannot happen with consistent groups; if it does, refuse rather than compute
            # garbage, and let the chain run empty so the keys it preempted get their turn.
            self.drop("not-positive-definite", str(key))
            return self._forward(self._token(key, CHAIN_REFUSED, [m, n], {n: m}, groups, pending))
        z_bar, Pzz, Y = self.ut.measurement_moments(np.concatenate([msg.x_m, self.x]), L, self.meas.h_joint)
        Pz = Pzz + msg.R
        gains = {m: kalman.gain(L[:d] @ Y, Pz), n: kalman.gain(L[d:] @ Y, Pz)}
        token = self._token(key, CHAIN_OK, [m, n], {n: m}, groups, pending, L, Y, Pz, msg.z - z_bar, gains)
        return self._forward(token)

    def _on_token(self, src: int, msg: DclToken) -> list[Send]:
        key = tuple(msg.key)
        d, dz = self.model.state_dim, self.meas.dim
        if msg.L.shape != (2 * d, 2 * d) or msg.Y.shape != (2 * d, dz) or msg.Pz.shape != (dz, dz) or msg.nu.shape != (dz,):
            return self.drop("shape", "token")
        if any(g.shape != (d, dz) for g in msg.gains.values()) or any(len(g) < 4 for g in msg.groups.values()):
            return self.drop("shape", "token gains")
        self.known_pending.update(tuple(k) for k in msg.pending)
        if self._preempted(key):
            return self.drop("preempted", str(key))
        if self.id in msg.order:
            return self._forward(msg)  # backtracking through us
        gains = dict(msg.gains)
        if msg.status == CHAIN_OK:
            m, n, _ = key
            P_i_mn = np.hstack([self._block(m), self._block(n)])
            A_i = kalman.solve_lower(msg.L, P_i_mn.T).T
            gains[self.id] = kalman.gain(A_i @ msg.Y, msg.Pz)
        pending = {tuple(k) for k in msg.pending} | set(self.pending)
        token = DclToken(
            msg.k, msg.epoch, msg.key, msg.status, msg.L, msg.Y, msg.Pz, msg.nu, msg.order + [self.id],
            {**msg.parent, self.id: src}, gains, {**msg.groups, self.id: self._group()},
            [list(k) for k in sorted(pending)],
        )
        return self._forward(token)

    def _forward(self, token: DclToken) -> list[Send]:
        """Depth-first step: nearest unvisited neighbour, else back to our parent, else finish."""
        visited = set(token.order)
        here = self.model.position(self.x)
        candidates = [(float(np.linalg.norm(p - here)), j) for j, p in self.neighbours.items() if j not in visited]
        if candidates:
            return [Send(token, min(candidates)[1])]
        if self.id in token.parent:
            return [Send(token, token.parent[self.id])]
        if self.id != token.key[0]:
            return self.drop("orphan-token", str(token.key))
        commit, resync = self._decide(token)
        return (resync or []) + self._on_commit(self.id, commit)

    def _decide(self, token: DclToken) -> tuple[DclCommit, list[Send]]:
        """At the measurer, all nodes visited: apply; or bring nodes that missed a commit up to
        date and run again; or split the groups first; or drop."""
        by_gid: dict[tuple, list[int]] = defaultdict(list)
        for i, g in token.groups.items():
            by_gid[tuple(g[:3])].append(i)
        claims = {gid: {j for i in nodes for j in token.groups[i][3:]} for gid, nodes in by_gid.items()}
        # Only the groups of m and n are touched by the measurement; broken groups elsewhere are
        # left to the chains that touch them (splitting costs accuracy).
        touched = {tuple(token.groups[a][:3]) for a in token.key[:2] if a in token.groups}
        broken = [(gid, nodes) for gid, nodes in sorted(by_gid.items()) if gid in touched and claims[gid] != set(nodes)]
        common = dict(k=token.k, epoch=token.epoch, key=token.key, parent=token.parent,
                      groups=token.groups, pending=token.pending)
        retry = token.status != CHAIN_UNREACHABLE
        if broken and retry:
            resync = self._resync(token, broken)
            if resync is not None:
                # Those nodes only missed commits we hold: send them and run the chain again.
                self.resyncs[tuple(token.key)] = self.resyncs.get(tuple(token.key), 0) + 1
                return DclCommit(Pz=token.Pz, nu=token.nu, gains={}, merge=[], splits=[], finished=False, **common), resync
        if broken:
            splits = []
            for gid, nodes in broken:
                # The part's weight is relative to every member list that names one of its
                # nodes: a node that missed a merge still counts in the merged group's size.
                cluster = set().union(*(c for c in claims.values() if c & set(nodes)))
                splits.append([len(cluster), *sorted(nodes)])
            log.info("node %s: chain %s (k=%d epoch=%d) splits %s; visited %s reporting %s", self.id, token.key,
                     token.k, token.epoch, splits, token.order, token.groups)
            return DclCommit(Pz=token.Pz, nu=token.nu, gains={}, merge=[], splits=splits, finished=not retry, **common), []
        if token.status != CHAIN_OK:
            return DclCommit(Pz=token.Pz, nu=token.nu, gains={}, merge=[], splits=[], finished=True, **common), []
        m, n, _ = token.key
        merge = sorted(set(token.groups[m][3:]) | set(token.groups[n][3:]))
        return DclCommit(Pz=token.Pz, nu=token.nu, gains=token.gains, merge=merge, splits=[], finished=True, **common), []

    def _resync(self, token: DclToken, broken) -> list[Send] | None:
        """Commits to resend so every node of the broken groups reaches our group id (none if
        only our own report was behind), or None if some node's state is not one we can bring
        forward (then the groups must split)."""
        if self.resyncs.get(tuple(token.key), 0) >= 2 or tuple(self.gid) not in {gid for gid, _ in broken}:
            return None
        out = []
        for gid, nodes in broken:
            if list(gid) == self.gid:
                continue
            for j in nodes:
                if j == self.id:
                    continue  # our own report is old (a late commit came meanwhile): just run again
                behind = [c for c in self.applied if j in c.groups and list(c.groups[j][:3]) == list(gid)]
                if not behind:
                    return None
                start = self.applied.index(behind[0])
                out += [Send(c, j) for c in list(self.applied)[start:] if j in c.groups]
        return out

    def link_failed(self, dst: int, msg) -> list[Send]:
        """A unicast did not arrive. Try the same hop again a few times (a lossy link often
        passes the next frame); then route around it, forgetting that neighbour for the tick."""
        if not isinstance(msg, (DclStart, DclToken, DclCommit)) or (msg.k != self.k and not isinstance(msg, DclCommit)):
            return self.drop("undeliverable", type(msg).__name__)  # a chain step of a tick that is over
        tries = self.retries.get((msg.k, msg.epoch, msg.TYPE, dst), 0)
        # A lost commit costs a group split later; a lost token only a detour: try commits harder.
        if tries < self.max_retries * (3 if isinstance(msg, DclCommit) else 1):
            self.retries[(msg.k, msg.epoch, msg.TYPE, dst)] = tries + 1
            return [Send(msg, dst)]
        self.neighbours.pop(dst, None)
        if isinstance(msg, DclCommit):
            # dst (and the tree below it) misses this commit. It keeps its old group id, so the
            # next chain that meets it splits it from those who applied the commit.
            return self.drop("commit-undelivered", f"to {dst}")
        if msg.epoch != self.epoch:
            return self.drop("undeliverable", type(msg).__name__)
        if isinstance(msg, DclStart):
            # The measured platform is out of reach: the measurement is lost, but the chain
            # still has to run (empty) so the keys it preempted get their turn.
            return self._forward(self._token(msg.key, CHAIN_UNREACHABLE, [self.id], {}, {self.id: self._group()},
                                             set(self.pending)))
        if msg.parent.get(self.id) == dst:
            return self.drop("chain-broken", f"parent {dst} unreachable")
        return self._forward(msg)

    def _on_commit(self, src: int, msg: DclCommit) -> list[Send]:
        key = tuple(msg.key)
        if not self._apply_commit(src, msg):
            return []
        self.epoch += 1
        if key in self.pending and msg.finished:
            del self.pending[key]
            self.stats["measurements_used" if msg.gains else "measurements_dropped"] += 1
        self.known_pending = {tuple(k) for k in msg.pending} - ({key} if msg.finished else set())
        out = [Send(msg, c) for c, p in sorted(msg.parent.items()) if p == self.id]
        out += self._retry_late()
        out += self._start_next()
        out += self._release_held()
        return out

    def _late_commit(self, src: int, msg: DclCommit) -> list[Send]:
        """A commit of an earlier tick or epoch (we moved on before it reached us). If our group
        id is the one we reported to that chain, nothing has touched our row since and the
        prediction since commutes with it (F = I), so applying it now is exact. If not, an
        earlier commit we also missed may still arrive and make it apply: keep it a while.
        Either way it goes on down the tree: whether it applies is each node's own question."""
        if msg.groups.get(self.id) is None:
            return self.drop("stale", f"commit k={msg.k} epoch={msg.epoch}")
        # Down the tree once, when it comes from our parent; a measurer's resend is for us alone.
        tree = msg.parent.get(self.id, msg.key[0]) == src
        out = [Send(msg, c) for c, p in sorted(msg.parent.items()) if p == self.id] if tree else []
        if msg.k < self.k - LATE_TICKS or len(self.late) >= 64:
            return out + self.drop("stale", f"commit k={msg.k} epoch={msg.epoch}")
        self.late.append((src, msg))
        return out + self._retry_late()

    def _retry_late(self) -> list[Send]:
        """Apply kept late commits whose reported group id is ours now, oldest first."""
        changed = True
        while changed:
            changed = False
            for item in sorted(self.late, key=lambda sm: (sm[1].k, sm[1].epoch)):
                src, msg = item
                if list(msg.groups[self.id][:3]) == self.gid:
                    self.late.remove(item)
                    if self._apply_commit(src, msg, route=False):
                        self.stats["late_commits"] += 1
                        changed = True
                        break
        for item in [sm for sm in self.late if sm[1].k < self.k - LATE_TICKS]:
            self.late.remove(item)
            self.drop("stale", f"late commit k={item[1].k} epoch={item[1].epoch} never applicable")
        return []

    def _apply_commit(self, src: int, msg: DclCommit, route: bool = True) -> bool:
        """Check a commit and apply it to the state; False (and a counted drop) if unfit.
        route=False for late commits: any holder may resend one, the group id check decides."""
        key = tuple(msg.key)
        d, dz = self.model.state_dim, self.meas.dim
        if (route and msg.parent.get(self.id, key[0]) != src) or (self.id != key[0] and self.id not in msg.parent):
            self.drop("misrouted", f"commit {key}")
            return False
        if msg.gains and self.id not in msg.gains:
            self.drop("misrouted", f"commit {key} without our gain")
            return False
        if msg.Pz.shape != (dz, dz) or msg.nu.shape != (dz,) or any(g.shape != (d, dz) for g in msg.gains.values()):
            self.drop("shape", "commit")
            return False
        if any(len(s) < 2 or s[0] < len(s) - 1 for s in msg.splits):
            self.drop("invalid", "commit splits")
            return False
        row, gid, members = dict(self.row), self.gid, self.members
        for size, *part in msg.splits:
            if self.id in part:
                # Covariance-intersection bound with weight |part|/|G| (module docstring).
                f = size / len(part)
                row = {j: f * b for j, b in row.items() if j in part}
                gid, members = [msg.k, msg.epoch, min(part)], sorted(part)
                self.stats["group_splits"] += 1
        x = self.x
        if msg.gains:
            K_i = msg.gains[self.id]
            for j, K_j in msg.gains.items():
                row[j] = row.get(j, np.zeros((d, d))) - kalman.covariance_decrement(K_i, msg.Pz, K_j)
            x = self.x + K_i @ msg.nu
            if self.id in msg.merge:
                gid, members = [msg.k, msg.epoch, key[0]], list(msg.merge)
            row = {j: b for j, b in row.items() if j in members}
        if not np.isfinite(x).all() or not all(np.isfinite(b).all() for b in row.values()):
            self.drop("invalid", "non-finite update")
            return False
        self.x, self.row, self.gid, self.members = x, row, gid, members
        self.stats["chains_committed"] += 1
        if msg.gains or msg.splits:
            self.applied.append(msg)
        return True
