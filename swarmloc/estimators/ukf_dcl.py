"""UKF-DCL (Wang et al. 2019) as a sans-I/O node, extended to reach the whole connected swarm
and to stay exact when the radio splits it.

Each node keeps its own mean x_i and its row of the joint covariance, P_ij for every j it is
correlated with (absent blocks are exactly zero). One relative measurement z_mn runs one chain
(docs/ukf-dcl.md has the picture):

1. start   m -> n: the measurement, x_m and m's row. n holds both rows, forms the lower
           Cholesky factor L of the pair's 2x2-block covariance (A11, A21, A22 of eq. 15-16,
           after the eq. 17 reordering), runs the unscented transform on [x_m; x_n] and forms
           the gain K_j = [P_jm P_jn] L^-T Y Pz^-1 (eq. 20) of every node j correlated with m
           or n (T, the touched set).
2. token   depth first through the radio graph (nearest unvisited neighbour, the paper's serial
           path; back to the parent when stuck); each node adds its version. Nothing is applied.
3. commit  back at m with nobody left to visit, m floods a commit down the chain's tree.

Versions make this exact under loss and partitions. A node's version counts the
state-changing commits it has applied per measurer; a commit is applied once by every node,
in an order consistent with the versions it was computed at, so two nodes with equal versions
hold equal copies of every cross-covariance. The participants of a commit are the nodes the
token reached whose version equals m's; they apply the full update. Every other node of T
(out of reach, or behind) is an outsider: with gain zero (a Schmidt, or consider, update) its
mean and own block stay, and only its cross-covariances with the participants change, by
-K_a Pz g^T with g its gain formula evaluated on its own row when it applies the commit. Commits
of parts that were apart touch disjoint participants, so as matrices they commute and each
side can apply the other's later (dcl.sync / dcl.log, asked for when a beacon shows a newer
version): the joint covariance after a healed partition is exactly that of the filter that
was run, with no inflation. Orphans, nodes that lost their cross-covariances (restart from a
checkpoint, a commit they took part in but can no longer apply), are removed from the others'
rows with a covariance-intersection bound when a chain meets them.

Measurements: ranges, range-bearing to another agent and to a landmark of the map (which
involves m alone: m is its own n, and starts its token itself), optionally through a
chi-square gate that m applies before committing. With F != I (planar-pose) rows are kept in
core coordinates, C_ij = Phi_i^-1 P_ij Phi_j^-T with Phi_i the product of i's transition
Jacobians, which time updates leave alone; gains travel as core gains and each node applies
its own Phi (docs/ukf-dcl.md, "F != I").

Several measurements in one tick run as successive chains in key order (m, kind, target, q). Every
measurer starts its chain at once; a node drops any token whose key is larger than one of its
own pending keys, so only the smallest chain of a connected part can complete. Its token
gathers every pending key it meets; after the commit the owner of the next key starts the next
chain. `epoch` counts commits within the tick: a chain frame of another epoch or tick is stale
(dropped) or early (held until its epoch comes). A node that reported its version to the
current epoch's chain applies nothing else until that chain's commit (or the next tick).

Without a radio that NACKs (direct mode: frames go straight between agents over Zenoh), every
step that waits on a peer has a node timer in real time: a start or token whose token has not
come back, a dcl.sync unanswered, a start queued at a busy platform, a hold. Expiry is the NACK
the radio never sent (docs/ukf-dcl.md, "Timeouts"); in lockstep no timer is armed. A peer that
left (the driver's membership, `peer_left`) is unreachable at once until it returns.
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np

from swarmloc import fusion, kalman
from swarmloc.messages import (CHAIN_OK, CHAIN_REFUSED, CHAIN_UNREACHABLE, CHAIN_VERSION, Beacon, DclCommit, DclLog,
                               DclStart, DclSync, DclToken, Sensors)
from swarmloc.estimators.neighbours import NeighbourTable, RetryBudget
from swarmloc.estimators.rejoin import Multilateration
from swarmloc.estimators.ukf_ccl import Observations
from swarmloc.node import (LANDMARK, RANGE, RANGE_BEARING, Estimate, Node, NodeSpec, Send, Timer, keyed_measurements,
                           odometry_of)

log = logging.getLogger(__name__)
Key = tuple[int, int, int, int]
NEIGHBOUR_TICKS = 3
VERSION_RETRIES = 2  # chain reruns when m and n are at different versions
LOG_COMMITS = 2048  # applied commits kept to replay to nodes that missed them
LOG_BATCH = 16  # commits per dcl.log frame
GIVE_UP_TICKS = 40  # a commit whose history never arrives makes the node an orphan after this
BUSY_RETRIES = 4  # bounded chains: reruns of a measurement whose measured platform was in another chain
MAX_QUEUED = 64  # bounded chains: starts waiting at a busy measured platform
HOLD_TICKS = 10  # real time: longest wait for the commit of a chain we reported to
# Real time: the unit of a chain step's timeout, a share of the tick (docs/ukf-dcl.md, "Timeouts").
HOP_TIMEOUT_TICKS = 1 / 64


class UkfDclNode(Node):
    algorithm = "ukf-dcl"

    @classmethod
    def spec(cls, scenario, aid, settings=None) -> NodeSpec:
        est = scenario.estimation
        x0, P0 = scenario.prior(aid)
        return NodeSpec.of(cls, aid=aid, x0=x0, P0=P0, model=scenario.agent(aid).model, spread=est.spread,
                           rejoin_std=est.rejoin_std, max_chain=getattr(settings, "max_chain", None),
                           landmarks=[[m.id, *m.position] for m in scenario.world.landmarks], gate=est.gate,
                           gate_open_after=est.gate_open_after)

    def __init__(self, aid, x0, P0, model="planar-speed-heading", spread: float | None = None, max_retries: int = 3,
                 rejoin_std: float | None = 15.0, max_chain: int | None = None, landmarks=(), gate: float | None = None,
                 gate_open_after: int = 10):
        super().__init__(aid, x0, P0, model)
        d = self.model.state_dim
        # F != I: the product of our transition Jacobians, the basis of our cross-covariance
        # rows (core coordinates, docs/ukf-dcl.md). None when F = I: rows are real covariances.
        self.phi: np.ndarray | None = None if self.model.identity_transition else np.eye(d)
        # Bounded chains ("local" mode): a chain stops exploring after max_chain platforms and
        # chains run concurrently; a platform gives its version to one chain at a time (the
        # `reported` lock) and is an outsider to every other. `epoch` then numbers the
        # measurer's own chains instead of the commits of the tick.
        self.max_chain = max_chain
        self.bounded = max_chain is not None
        # Finding oneself again by multilateration is for F = I only (docs/ukf-dcl.md, "F != I").
        self.rejoin_std = rejoin_std if self.phi is None else None
        self.lost = False  # position too uncertain to linearize a range at: finding itself (rejoin.py)
        self.finder = Multilateration(self.model.position_dim)
        self.lost_ranges: list[tuple[int, int, float, float]] = []  # own ranges while lost: (k, target, r, var)
        self.max_retries = max_retries
        self.retries = RetryBudget()  # keyed (message type, dst, k, epoch)
        self.ut = kalman.UnscentedTransform.for_pair(self.model.state_dim, spread)
        self.obs = Observations(self.model, {int(i): (x, y) for i, x, y in landmarks})
        # The measurer gates the measurements it commits; each key is always its own, so its
        # gate sees the NIS sequence the centralized filter's does.
        self.gate = kalman.Gate(gate, gate_open_after)
        self._upper = {n * d: np.triu_indices(n * d, 1) for n in (1, 2)}  # must be zero in a Cholesky factor
        self._zero = np.zeros((d, d))  # an absent block; never written to
        self.row: dict[int, np.ndarray] = {self.id: self.P}
        del self.P  # the own block lives in self.row; one copy only
        self.version: dict[int, int] = {}  # measurer -> its state-changing commits applied here
        self.orphan = False
        self.orphan_base: np.ndarray | None = None  # own block when we became an orphan
        self.log: deque[DclCommit] = deque(maxlen=LOG_COMMITS)  # applied, in order
        self.waiting: dict[tuple[int, int], DclCommit] = {}  # (measurer, seq) -> not yet applicable
        # The chain we reported our version to and whose commit has not come: (k, epoch, key,
        # m's own version count at the report). Until it comes we apply no other commit, so the
        # report stays true; a report to two chains at one version would make one inapplicable.
        self.reported: tuple | None = None
        self.asked: set[int] = set()  # neighbours asked for commits this tick
        self.epoch = 0
        self.pending: dict[Key, tuple[np.ndarray, np.ndarray]] = {}  # own measurements not yet finished
        self.known_pending: set[Key] = set()  # keys of this tick seen from others
        self.beacons = NeighbourTable(self.id, self.model.position_dim, NEIGHBOUR_TICKS)
        self.neighbours: dict[int, np.ndarray] = {}  # snapshot for this tick
        self.held: list[tuple[int, object]] = []  # early frames: (src, msg)
        self.seen: set[tuple] = set()  # fingerprints of chain frames handled, this tick and later
        self.reruns: dict[Key, int] = {}  # version reruns per chain key (this tick)
        self.deferred: set[Key] = set()  # bounded chains: rerun when our version next changes
        self.busy_retries: dict[Key, int] = {}  # bounded chains: reruns after n was busy (this tick)
        self.queued: list[tuple[int, DclStart]] = []  # bounded chains: starts waiting for our lock
        self.nis: list[tuple[float, int]] = []  # (NIS, dof) of the measurements this node committed this tick
        # Real time (docs/ukf-dcl.md, "Timeouts"): the steps whose answer we wait for, by timer
        # tag; the hops given up this tick, whose late answer is stale; the report the hold
        # timer runs for; peers that left the swarm; the tick's length, which timeouts scale with.
        self.awaiting: dict[str, tuple[int, object]] = {}
        self.timed_out: set[tuple] = set()
        self.hold_armed: tuple | None = None
        self.gone: set[int] = set()
        self.tick_s: float | None = None
        self.stats = {"chains_committed": 0, "measurements_used": 0, "measurements_dropped": 0,
                      "outsider_commits": 0, "commits_replayed": 0, "orphaned": 0, "orphans_removed": 0,
                      "lost": 0, "refound": 0, "refused_holding": 0, "holds_expired": 0, "measurements_gated": 0}

    # ------------------------------------------------------------------ state

    def estimate(self) -> Estimate:
        return Estimate(self.k, self.x.copy(), self.row[self.id].copy())

    def resume(self, k, x, P) -> None:
        """Continue from a checkpoint: own mean and covariance only. The cross-covariances are
        gone, so the node is an orphan: the others drop theirs with it (covariance
        intersection) when a chain next meets it, and it catches up on versions meanwhile."""
        self.k, self.x = int(k), np.array(x, float)
        self.row = {self.id: np.array(P, float)}
        self.version, self.waiting, self.reported = {}, {}, None
        self.orphan, self.orphan_base = True, self.row[self.id].copy()
        if self.phi is not None:
            self.phi = np.eye(self.model.state_dim)  # no row refers to our old basis once we are removed
        self.lost = False  # decided again at the first tick, after the missed ticks' inflation
        self.finder.clear()
        self.lost_ranges.clear()

    def _block(self, j: int) -> np.ndarray:
        b = self.row.get(j)
        return self._zero if b is None else b

    # ------------------------------------------------------------------ tick

    def step(self, sensors: Sensors) -> list[Send]:
        if sensors.k <= self.k:
            return self.drop("stale-tick", f"sensors k={sensors.k} at k={self.k}")
        self.stats["measurements_dropped"] += len(self.pending)  # chains that never finished
        gap = self.missed_motion(sensors)
        if gap is not None:
            self.row[self.id] = self.row[self.id] + gap
        self.k, self.epoch = sensors.k, 0
        self.nis = []
        self._settle_report()
        self.pending.clear()
        self.known_pending.clear()
        self.retries.clear()
        self.reruns.clear()
        self.deferred.clear()
        self.queued.clear()
        self.busy_retries.clear()
        self.asked.clear()
        self.awaiting.clear()  # chain steps of a tick that is over: their answers are stale
        self.timed_out.clear()
        self.tick_s = sensors.odometry.dt
        self.seen = {f for f in self.seen if f[2] >= self.k}
        # F = I: prediction leaves every cross-covariance as it is, so it commutes with commits
        # applied late (their outsider part reads only cross-covariances). F != I: so do the
        # core rows; only the own block and Phi move.
        x, F, Q = self.model.predict(self.x, odometry_of(sensors))
        moved = self.model.position(x) - self.model.position(self.x)
        self.x = x
        if self.phi is None:
            self.row[self.id] = self.row[self.id] + Q
        else:
            self.row[self.id] = F @ self.row[self.id] @ F.T + Q
            self.phi = F @ self.phi
            if self.orphan_base is not None:
                self.orphan_base = F @ self.orphan_base @ F.T  # the correlated part of our error moves too
        self._track_lost(moved, Q)
        self._apply_ready()
        stuck = [c for c in self.waiting.values() if c.k < self.k - GIVE_UP_TICKS]
        if stuck:
            self._make_orphan(f"{len(stuck)} commits whose history never arrived")
            self._apply_ready()

        # Every node routes on the same snapshot whatever the delivery order (NeighbourTable); a
        # stale neighbour costs a NACK, a missing one a detour.
        self.neighbours = {j: p for j, p in self.beacons.snapshot(self.k).items() if j not in self.gone}
        self._find_self()

        for key, r in keyed_measurements(self.id, sensors):
            if self.lost and key[1] == RANGE and r.target != self.id:
                self.lost_ranges.append((self.k, r.target, r.range, r.std**2))  # anchored when its beacon is in
                continue
            if not self.obs.usable(key) or (key[1] != LANDMARK and r.target not in self.neighbours):
                self.stats["measurements_dropped"] += 1  # cannot reach the measured platform (or model it)
                continue
            self.pending[key] = self.obs.z(key[1], r)

        p = self.model.position_dim
        out: list[Send] = [Send(Beacon(self.k, self.model.position(self.x).copy(), self.row[self.id][:p, :p].copy(),
                                       dict(self.version)), None)]
        out += self._start_next()
        out += self._release_held()
        return self._arm(out)

    def _min_pending(self) -> Key | None:
        keys = set(self.pending) | self.known_pending
        return min(keys) if keys else None

    def _start_next(self) -> list[Send]:
        """Start our smallest pending chain if it is the smallest this node knows of."""
        ready = set(self.pending) - self.deferred
        if not ready:
            return []
        key = min(ready)
        if not self.bounded and key != self._min_pending():
            return []
        if self._holding():
            return []  # our own chain would be computed at a version we already reported elsewhere
        z, R = self.pending[key]
        if self.bounded:
            self.epoch += 1
        self.reported = (self.k, self.epoch, key, None)
        if key[1] == LANDMARK:
            return self._start_alone(key, z, R)
        msg = DclStart(self.k, self.epoch, list(key), z, R, self.x.copy(), dict(self.row), dict(self.version),
                       self.orphan, [list(k) for k in sorted(self.pending)], self._phi_of())
        if key[2] in self.gone:
            return self._unreachable(key[2], msg)  # it left during this tick
        return [Send(msg, key[2])]

    def _phi_of(self) -> dict:
        return {} if self.phi is None else {self.id: self.phi.copy()}

    def _start_alone(self, key: Key, z: np.ndarray, R: np.ndarray) -> list[Send]:
        """A landmark: m is its own n. It forms the transform and every gain from its own row,
        and the token goes round as for a pair, so every node correlated with m gets its gain."""
        m = self.id
        token = lambda status, **kw: self._token(key, status, [m], {}, {m: dict(self.version)},
                                                 [m] if self.orphan else [], set(self.pending), **kw)
        if self.orphan:
            return self._forward(token(CHAIN_REFUSED))  # removed from the others' rows first
        transform = self._transform(key, z, R, self.x, self.row, self._phi_of())
        if transform is None:
            self.drop("not-positive-definite", str(key))
            return self._forward(token(CHAIN_REFUSED))
        return self._forward(token(CHAIN_OK, **transform))

    # ------------------------------------------------------------------ radio

    def receive(self, src, msg) -> list[Send]:
        return self._arm(self._receive(src, msg))

    def _receive(self, src, msg) -> list[Send]:
        if isinstance(msg, Beacon):
            if self.beacons.valid(src, msg):
                self.beacons.hear(src, msg)
                out = self._on_version(src, msg.version)
                if self.reported is not None and msg.k > self.reported[0]:
                    out += self._resolve_report(src, m_version=msg.version)
                return out
            return self.drop("shape", "beacon")
        if isinstance(msg, DclSync):
            return self._on_sync(src, msg)
        if isinstance(msg, DclLog):
            self.awaiting.pop(self._sync_tag(src, msg.k), None)
            self.stats["commits_replayed"] += len(msg.commits)
            out = []
            for c in msg.commits:
                if self._valid_commit(c):
                    self._deliver(c)
                    out += self._resolve_report(c.key[0], commit=c)
            return out + (self._start_next() if self.bounded else [])
        if not isinstance(msg, (DclStart, DclToken, DclCommit)):
            return self.drop("unexpected-type", type(msg).__name__)
        if isinstance(msg, DclToken) and not self.synchronous:
            if (src, msg.k, msg.epoch, tuple(msg.key)) in self.timed_out:
                return self.drop("stale", f"token {msg.key} from {src}, given up on")  # we went on without it
            self.awaiting.pop(self._hop_tag(src, msg), None)
        # A radio may deliver a frame twice; a second copy of a chain step would run the chain
        # twice. A copy is the same step from the same sender: a token that legitimately comes
        # back (backtracking) has grown, and a resend after a NACK replaces a frame never heard.
        fingerprint = (src, msg.TYPE, msg.k, msg.epoch, tuple(msg.key),
                       tuple(msg.order) if isinstance(msg, DclToken) else (),
                       (msg.seq, msg.finished) if isinstance(msg, DclCommit) else ())
        if fingerprint in self.seen:
            return self.drop("duplicate", f"{msg.TYPE} {msg.key}")
        self.seen.add(fingerprint)
        return self._chain_frame(src, msg)

    def _when(self, msg) -> int:
        """-1: a frame of a tick (or epoch) that is over; 0: current; 1: early. Bounded chains
        have no tick-wide order of chains: any frame of this tick is current."""
        mine = (self.k, 0 if self.bounded else self.epoch)
        theirs = (msg.k, 0 if self.bounded else msg.epoch)
        return (theirs > mine) - (theirs < mine)

    def _chain_frame(self, src, msg) -> list[Send]:
        when = self._when(msg)
        if when < 0:
            if isinstance(msg, DclCommit):
                return self._late_commit(src, msg)
            return self.drop("stale", f"k={msg.k} epoch={msg.epoch}")
        if when > 0:
            if len(self.held) >= 256:
                return self.drop("held-overflow")
            self.held.append((src, msg))
            return []
        return self._dispatch(src, msg)

    def _dispatch(self, src, msg) -> list[Send]:
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
        ready, later, out = [], [], []
        for s, m in self.held:
            when = self._when(m)
            if when == 0:
                ready.append((s, m))
            elif when > 0:
                later.append((s, m))
            elif isinstance(m, DclCommit):
                out += self._late_commit(s, m)  # overtaken, but a commit may still apply
            else:
                self.drop("stale", "held frame overtaken")
        self.held = later
        for src, m in ready:
            out += self._chain_frame(src, m)
        return out

    def _preempted(self, key: Key) -> bool:
        """True if we know a smaller pending key: this chain cannot be the one to run now."""
        if self.bounded:
            return False  # chains run concurrently; the `reported` lock keeps versions apart
        self.known_pending.add(key)
        return min(set(self.pending) | self.known_pending) < key

    # ------------------------------------------------------------------ chain steps

    @property
    def busy(self) -> bool:
        return self.reported is not None

    def _report(self, key, m_version: dict) -> tuple[dict, list[int]]:
        """What this node adds to a chain: its version, and its id if it is an orphan. Until
        the chain's commit it applies nothing else, so the report stays true."""
        self.reported = (self.k, self.epoch, tuple(key), m_version.get(key[0], 0))
        return dict(self.version), ([self.id] if self.orphan else [])

    def _holding(self) -> bool:
        """Reported to a chain whose commit may still come: of an earlier tick (real time), or
        any other chain at all with bounded chains, which run concurrently."""
        return self.reported is not None and (self.bounded or self.reported[0] < self.k)

    def _settle_report(self) -> None:
        """A new tick. In lockstep every chain of the last tick is over: committed or dead. With
        an asynchronous clock the commit of the chain we reported to may still be on its way;
        we hold (no other chain gets our version, none of ours starts) until it comes, until
        the measurer's beacon shows it never committed, or for HOLD_TICKS at most."""
        if self.reported is None:
            return
        k, _, key, m_seq = self.reported
        if self.synchronous or m_seq is None or self.k - k > HOLD_TICKS:
            if not self.synchronous and m_seq is not None:
                self.stats["holds_expired"] += 1
            self.reported = None

    def _resolve_report(self, m: int, m_version: dict | None = None, commit: DclCommit | None = None) -> list[Send]:
        """Release a hold when the chain's commit has come, or m's beacon of a later tick shows
        m's own count unchanged since our report (m dropped the chain when its tick ended)."""
        if not self._holding() or self.reported[2][0] != m:
            return []
        k, epoch, key, m_seq = self.reported
        if commit is not None:
            if (commit.k, commit.epoch, tuple(commit.key)) != (k, epoch, key):
                return []
        elif m_version is None or m_version.get(m, 0) != m_seq:
            return []
        return self._release()

    def _release(self) -> list[Send]:
        """Our report is settled: apply what waited for it and take up our own chains again."""
        self.reported = None
        self._apply_ready()
        return (self._run_queued() if self.bounded else []) + self._start_next() + self._release_held()

    def _token(self, key, status, order, parent, versions, orphans, pending, L=None, Y=None, Pz=None, nu=None,
               gains=None, phi=None, epoch=None):
        n, dz = self._shape(key)
        return DclToken(
            self.k, self.epoch if epoch is None else epoch, list(key), status,
            np.eye(n) if L is None else L, np.zeros((n, dz)) if Y is None else Y,
            np.eye(dz) if Pz is None else Pz, np.zeros(dz) if nu is None else nu,
            order, parent, gains or {}, versions, orphans, [list(k) for k in sorted(pending)], phi or {},
        )

    def _shape(self, key) -> tuple[int, int]:
        """(dimension of the platforms the measurement reads, of z)."""
        return self.model.state_dim * (1 if key[1] == LANDMARK else 2), self.obs.dim(key[1])

    def _pair(self, key) -> list[int]:
        """The platforms the measurement reads: measurer, then measured."""
        return [key[0]] if key[1] == LANDMARK else [key[0], key[2]]

    def _transform(self, key, z, R, x_m, row_m, phi_m) -> dict | None:
        """The unscented transform of the measurement on the pair's joint block, and the gain of
        every node correlated with the pair (eq. 20 for the whole set at once), formed from m's
        and our copies of their cross-covariances (equal to their own at equal versions). None
        if the pair's block is not positive definite.

        F != I: rows are in core coordinates, C_ij = Phi_i^-1 P_ij Phi_j^-T, and so are the
        gains: Ktilde_j = Phi_j^-1 K_j = [C_jm Phi_m^T, C_jn Phi_n^T] L^-T Y Pz^-1, with the own
        blocks P_mm, P_nn (real) entering as Phi^-1 P. Each node applies its own Phi."""
        m, alone = key[0], key[1] == LANDMARK
        if alone:
            P_sub, x = row_m[m], x_m
        else:
            P_nm = self._block(m) if self.phi is None else self.phi @ self._block(m) @ phi_m[m].T
            P_sub, x = np.block([[row_m[m], P_nm.T], [P_nm, self.row[self.id]]]), np.concatenate([x_m, self.x])
        try:
            L = np.linalg.cholesky(P_sub)
        except np.linalg.LinAlgError:
            return None
        h, angles = self.obs.h(key)
        z_bar, Pzz, Y = self.ut.measurement_moments(x, L, h, angles)
        Pz = Pzz + R
        sides = [(m, row_m, phi_m.get(m))] + ([] if alone else [(self.id, self.row, self.phi)])
        touched = sorted(set().union(*(row for _, row, _ in sides)))
        zero = self._zero

        def core(a, row, phi, j):  # Phi_j^-1 P_ja as the rows give it (P_ja itself when F = I)
            b = row.get(j, zero).T
            if phi is None:
                return b
            return np.linalg.solve(phi, b) if j == a else b @ phi.T

        P_t = np.vstack([np.hstack([core(a, row, phi, j) for a, row, phi in sides]) for j in touched])
        K = kalman.gain(kalman.solve_lower(L, P_t.T).T @ Y, Pz)
        d = self.model.state_dim
        phi = {} if self.phi is None else {a: p for a, _, p in sides}
        return dict(L=L, Y=Y, Pz=Pz, nu=self.obs.innovation(z, z_bar, angles),
                    gains={j: K[i * d:(i + 1) * d] for i, j in enumerate(touched)}, phi=phi)

    def _on_start(self, src: int, msg: DclStart) -> list[Send]:
        key = tuple(msg.key)
        m, kind, n, _ = key
        d = self.model.state_dim
        if kind == LANDMARK or n != self.id or m != src:
            return self.drop("misrouted", f"start {key}")
        if (not self.obs.usable(key) or msg.x_m.shape != (d,) or msg.z.shape != (self.obs.dim(kind),)
                or msg.R.shape != (self.obs.dim(kind),) * 2 or m not in msg.row_m
                or any(b.shape != (d, d) for b in msg.row_m.values())
                or (self.phi is not None and (set(msg.phi) != {m} or msg.phi[m].shape != (d, d)))):
            return self.drop("shape", "start")
        self.known_pending.update(tuple(k) for k in msg.pending)
        if self._preempted(key):
            return self.drop("preempted", str(key))

        pending = {tuple(k) for k in msg.pending} | set(self.pending)
        token = lambda status, *args, **kw: self._token(key, status, *args, epoch=msg.epoch, **kw)
        if self.bounded and self._holding() and key > self.reported[2] and len(self.queued) < MAX_QUEUED:
            # Bounded chains: wait for the chain holding our lock. Only a larger key waits for a
            # smaller one, so waits cannot form a cycle; tokens never wait, so the smallest
            # chain of any wait always finishes.
            self.queued.append((src, msg))
            return []
        if self._holding():
            # Our version is promised to another chain (an earlier tick's, or with bounded
            # chains one running now). The measured pair must take part in its own update, or
            # it would not commute with that chain's: this run of the measurement is refused
            # (with bounded chains m runs it again).
            self.stats["refused_holding"] += 1
            return self._forward(token(CHAIN_REFUSED, [m, n], {n: m}, {m: msg.version}, [m] if msg.orphan else [],
                                       pending))
        version, orphans = self._report(key, msg.version)
        head = ([m, n], {n: m}, {m: msg.version, n: version}, ([m] if msg.orphan else []) + orphans, pending)
        if self.lost:
            # Not a range to linearize at our mean; an anchor to find ourselves with. The chain
            # runs empty so the keys it preempted get their turn.
            if kind == RANGE:
                p = self.model.position_dim
                self.finder.add(self.k, self.model.position(msg.x_m), msg.row_m[m][:p, :p], float(msg.z[0]),
                                float(msg.R[0, 0]))
            return self._forward(token(CHAIN_UNREACHABLE, *head))
        if head[3]:
            return self._forward(token(CHAIN_REFUSED, *head))  # m removes the orphans first
        if msg.version != self.version:
            out = []
            if self._behind(msg.version) and m not in self.asked:
                self.asked.add(m)
                out.append(Send(DclSync(self.k, dict(self.version)), m))
            return out + self._forward(token(CHAIN_VERSION, *head))
        transform = self._transform(key, msg.z, msg.R, msg.x_m, msg.row_m, msg.phi)
        if transform is None:
            # Cannot happen with equal versions; if it does, refuse rather than compute garbage,
            # and let the chain run empty so the keys it preempted get their turn.
            self.drop("not-positive-definite", str(key))
            return self._forward(token(CHAIN_REFUSED, *head))
        return self._forward(token(CHAIN_OK, *head, **transform))

    def _on_token(self, src: int, msg: DclToken) -> list[Send]:
        key = tuple(msg.key)
        if not self._valid_transform(msg):
            return self.drop("shape", "token")
        self.known_pending.update(tuple(k) for k in msg.pending)
        if self._preempted(key):
            return self.drop("preempted", str(key))
        if self.id in msg.order:
            return self._forward(msg)  # backtracking through us
        pending = {tuple(k) for k in msg.pending} | set(self.pending)
        if self._holding():
            # No version from us: the measurer makes us an outsider, and we apply its commit
            # (a Schmidt update) after the one we are holding for.
            versions, orphans = msg.versions, [self.id] if self.orphan else []
        else:
            version, orphans = self._report(key, msg.versions.get(key[0], {}))
            versions = {**msg.versions, self.id: version}
        token = DclToken(
            msg.k, msg.epoch, msg.key, msg.status, msg.L, msg.Y, msg.Pz, msg.nu, msg.order + [self.id],
            {**msg.parent, self.id: src}, msg.gains, versions, msg.orphans + orphans,
            [list(k) for k in sorted(pending)], msg.phi,
        )
        return self._forward(token)

    def _forward(self, token: DclToken) -> list[Send]:
        """Depth-first step: nearest unvisited neighbour, else back to our parent, else finish."""
        visited = set(token.order)
        here = self.model.position(self.x)
        full = self.bounded and len(visited) >= self.max_chain
        candidates = [] if full else [(float(np.linalg.norm(p - here)), j) for j, p in self.neighbours.items()
                                      if j not in visited]
        if candidates:
            return [Send(token, min(candidates)[1])]
        if self.id in token.parent:
            return [Send(token, token.parent[self.id])]
        if self.id != token.key[0]:
            return self.drop("orphan-token", str(token.key))
        commit, extra = self._decide(token)
        return extra + self._on_commit(self.id, commit)

    def _decide(self, token: DclToken) -> tuple[DclCommit, list[Send]]:
        """At the measurer, every reachable node visited: remove the orphans the measurement
        touches and run it again; or run it again after asking n for the commits we lack;
        or commit it, with the nodes at our version as participants."""
        key = tuple(token.key)
        m, n = key[0], self.obs.measured(key)
        common = dict(k=token.k, epoch=token.epoch, key=token.key, L=token.L, Y=token.Y, Pz=token.Pz, nu=token.nu,
                      parent=token.parent, pending=token.pending, phi=token.phi)
        nothing = dict(seq=0, version={}, gains={}, participants=[], removed=[], **common)
        rerun = token.status != CHAIN_UNREACHABLE and self.reruns.get(key, 0) < VERSION_RETRIES + 1
        touched = set(token.gains) | set(self.row) | {m, n}
        removed = sorted(set(token.orphans) & touched)
        if removed and rerun:
            self.reruns[key] = self.reruns.get(key, 0) + 1
            # Covariance intersection with weights 1/size for each orphan and (size - r)/size for
            # the rest of its former group, which is at most as big as the swarm we know of.
            size = max(len(self.beacons) + 1, len(token.order), len(token.gains), len(self.row))
            log.info("node %s: chain %s removes orphans %s (group size <= %d)", self.id, key, removed, size)
            return DclCommit(seq=self.version.get(self.id, 0) + 1, version=dict(self.version), gains={},
                             participants=[], removed=[[size, o] for o in removed], finished=False, **common), []
        out = []
        if token.status == CHAIN_VERSION:
            behind = self._behind(token.versions.get(n, {}))
            if behind and n not in self.asked:
                self.asked.add(n)
                out.append(Send(DclSync(self.k, dict(self.version)), n))
            if rerun and self.reruns.get(key, 0) < VERSION_RETRIES:
                self.reruns[key] = self.reruns.get(key, 0) + 1
                if behind and self.bounded:
                    # Run it again once n's commits are in, not at once into the same mismatch.
                    self.deferred.add(key)
                return DclCommit(finished=False, **nothing), out
        busy = token.status == CHAIN_REFUSED and n not in token.versions and not token.orphans
        if busy and self.bounded and self.busy_retries.get(key, 0) < BUSY_RETRIES:
            # n was in a chain with a larger key. Try again once our version moves: usually the
            # commit of that chain, overheard, which also frees n.
            self.busy_retries[key] = self.busy_retries.get(key, 0) + 1
            self.deferred.add(key)
            return DclCommit(finished=False, **nothing), out
        if token.status != CHAIN_OK:
            return DclCommit(finished=True, **nothing), out
        participants = sorted(i for i, v in token.versions.items()
                              if v == self.version and i in token.gains and i not in token.orphans)
        nis = fusion.nis(token.nu, token.Pz)
        if not self.gate.admit(key[:3], nis, len(token.nu)):
            self.stats["measurements_gated"] += 1
            self.pending.pop(key, None)  # done: neither used nor dropped
            return DclCommit(finished=True, **nothing), out
        self.nis.append((nis, len(token.nu)))  # the measurer's, once per measurement
        return DclCommit(seq=self.version.get(self.id, 0) + 1, version=dict(self.version), gains=token.gains,
                         participants=participants, removed=[], finished=True, **common), out

    def link_failed(self, dst: int, msg) -> list[Send]:
        if isinstance(msg, DclSync):
            self.awaiting.pop(self._sync_tag(dst, msg.k), None)  # the NACK settled it, not the timer
        elif isinstance(msg, (DclStart, DclToken)):
            self.awaiting.pop(self._hop_tag(dst, msg), None)
        return self._arm(self._link_failed(dst, msg))

    def _link_failed(self, dst: int, msg) -> list[Send]:
        """A unicast did not arrive. Try the same hop again a few times (a lossy link often
        passes the next frame); then route around it, forgetting that neighbour for the tick."""
        if isinstance(msg, (DclSync, DclLog)):
            if self.retries.again((msg.TYPE, dst, msg.k, -1), self.max_retries):
                return [Send(msg, dst)]
            return self.drop("undeliverable", msg.TYPE)  # the next beacon asks again
        if not isinstance(msg, (DclStart, DclToken, DclCommit)) or (msg.k != self.k and not isinstance(msg, DclCommit)):
            return self.drop("undeliverable", type(msg).__name__)  # a chain step of a tick that is over
        # A lost commit costs dst a replay later; a lost token only a detour: try commits harder.
        if self.retries.again((msg.TYPE, dst, msg.k, msg.epoch), self.max_retries * (3 if isinstance(msg, DclCommit) else 1)):
            return [Send(msg, dst)]
        return self._unreachable(dst, msg)

    def _unreachable(self, dst: int, msg) -> list[Send]:
        """dst cannot be reached for the rest of the tick (resends used up, a timeout, or it
        left): route around it, run the chain empty, or give the chain up."""
        self.neighbours.pop(dst, None)
        if isinstance(msg, DclCommit):
            # dst (and the tree below it) misses this commit; they ask for it (dcl.sync) when a
            # beacon shows them a newer version.
            return self.drop("commit-undelivered", f"to {dst}")
        if not self.bounded and msg.epoch != self.epoch:
            return self.drop("undeliverable", type(msg).__name__)
        if isinstance(msg, DclStart):
            # The measured platform is out of reach: the measurement is lost, but the chain
            # still has to run (empty) so the keys it preempted get their turn.
            version, orphans = dict(self.version), [self.id] if self.orphan else []
            return self._forward(self._token(msg.key, CHAIN_UNREACHABLE, [self.id], {}, {self.id: version}, orphans,
                                             set(self.pending), epoch=msg.epoch))
        if msg.parent.get(self.id) == dst:
            return self.drop("chain-broken", f"parent {dst} unreachable")
        return self._forward(msg)

    # ------------------------------------------------------------------ timeouts and membership

    def _hop_tag(self, dst: int, msg: DclStart | DclToken) -> str:
        return f"dcl.hop {dst} {msg.k} {msg.epoch} {tuple(msg.key)}"

    @staticmethod
    def _sync_tag(dst: int, k: int) -> str:
        return f"dcl.sync {dst} {k}"

    def _hop_delay(self, order) -> float:
        """How long the token sent out from `order` may take to come back: its hops out to every
        node it may still visit and back (2a + 2 for a nodes ahead), times a + 1 so that it also
        covers the waits of the nodes ahead running out one after the other; the node that sent
        the token there gives up only after they have."""
        visited = set(order)
        ahead = len((set(self.row) | set(self.version) | set(self.neighbours) | {self.id}) - visited) or 1
        if self.bounded:
            ahead = max(1, min(ahead, self.max_chain - len(visited)))
        return HOP_TIMEOUT_TICKS * self.tick_s * (2 * ahead + 2) * (ahead + 1)

    def _arm(self, out: list[Send]) -> list:
        """Real time: a timer for every step in `out` that now waits on a peer (a start or a
        token sent to an unvisited node waits for the token to come back from it; a dcl.sync
        for a dcl.log), for every start we queued, and for a new report (the hold). Lockstep:
        the radio NACKs what it cannot deliver and a tick ends only when the swarm is quiet, so
        nothing is armed."""
        if self.synchronous or self.tick_s is None:
            return out
        timers = []
        for s in out:
            if s.dst is None:
                continue
            if isinstance(s.msg, DclSync):
                tag, delay = self._sync_tag(s.dst, s.msg.k), 8 * HOP_TIMEOUT_TICKS * self.tick_s
            elif isinstance(s.msg, DclStart):
                tag, delay = self._hop_tag(s.dst, s.msg), self._hop_delay([self.id])
            elif isinstance(s.msg, DclToken) and s.dst not in s.msg.order:
                tag, delay = self._hop_tag(s.dst, s.msg), self._hop_delay(s.msg.order)
            else:
                continue
            self.awaiting[tag] = (s.dst, s.msg)
            timers.append(Timer(delay, tag))
        for src, msg in self.queued:
            # Given up before the measurer gives up on us (its wait counts one hop more), so we
            # never lock ourselves to a chain that has already run empty.
            tag = "dcl.queued " + self._hop_tag(src, msg)
            if tag not in self.awaiting:
                self.awaiting[tag] = (src, msg)
                timers.append(Timer(self._hop_delay([src]) / 2, tag))
        if self.reported is not None and self.reported != self.hold_armed:
            # Ticks end holds (HOLD_TICKS); this fires only if they stop coming. Half a tick
            # later than that rule, so it never anticipates it.
            self.hold_armed = self.reported
            timers.append(Timer((HOLD_TICKS + 1.5) * self.tick_s, "dcl.hold"))
        return out + timers

    def on_timer(self, tag: str, t: float) -> list:
        return self._arm(self._expire(tag))

    def _expire(self, tag: str) -> list[Send]:
        """A wait ran out: what netsim's NACK would have caused, unless the wait is moot (its
        answer came, its tick or epoch is over, or its chain was preempted: no answer is due)."""
        if tag == "dcl.hold":
            if self.reported is None or self.reported != self.hold_armed:
                return []
            self.stats["holds_expired"] += 1
            return self._release()
        entry = self.awaiting.pop(tag, None)
        if entry is None:
            return []
        dst, msg = entry
        if isinstance(msg, DclSync):
            if msg.k != self.k:
                return []
            if dst in self.gone:
                return self.drop("undeliverable", "dcl.sync to a peer that left")
            return self._link_failed(dst, msg)  # resent: the dcl.log may be what was lost
        if tag.startswith("dcl.queued"):
            waiting = [q for q in self.queued if q[1] is msg]
            if waiting:
                self.queued.remove(waiting[0])
                self.drop("timed-out", f"queued start {msg.key}")
            return []
        key = tuple(msg.key)
        if self._when(msg) != 0 or (not self.bounded and min(set(self.pending) | self.known_pending, default=key) < key):
            return []
        if isinstance(msg, DclStart) and (self.reported is None or self.reported[:3] != (msg.k, msg.epoch, key)):
            return []  # we gave our version to another chain since: ours was preempted
        self.drop("timed-out", f"{msg.TYPE} {key} to {dst}")
        self.timed_out.add((dst, msg.k, msg.epoch, key))
        return self._unreachable(dst, msg)

    def peer_left(self, aid: int) -> list:
        return self._arm(self._left(int(aid)))

    def _left(self, j: int) -> list[Send]:
        """j left the swarm: unreachable at once (every wait on it runs out now), out of our
        neighbours until it returns; its own chains can no longer finish, so they neither
        preempt others nor hold us."""
        if j == self.id:
            return []
        log.info("node %s: peer %s left; unreachable until it returns", self.id, j)
        self.gone.add(j)
        self.neighbours.pop(j, None)
        self.known_pending = {key for key in self.known_pending if key[0] != j}
        out: list[Send] = []
        for tag in [t for t, (dst, _) in self.awaiting.items() if dst == j]:
            out += self._expire(tag)
        if self.reported is not None and self.reported[2][0] == j:
            out += self._release()
        return out

    def peer_joined(self, aid: int) -> list:
        """aid is back: its beacons make it a neighbour again."""
        self.gone.discard(int(aid))
        return []

    # ------------------------------------------------------------------ commits

    def _on_commit(self, src: int, msg: DclCommit) -> list[Send]:
        """This epoch's commit, down the chain's tree: the chain is over here."""
        key = tuple(msg.key)
        if not self._valid_commit(msg):
            return []
        if self.bounded and self.id != key[0] and src == key[0] and msg.parent.get(self.id) != src:
            if self.id in msg.parent:
                return self.drop("overheard", f"commit {key}: ours comes from our parent")
            return self._overheard(msg)
        if msg.parent.get(self.id, key[0]) != src or (self.id != key[0] and self.id not in msg.parent):
            return self.drop("misrouted", f"commit {key}")
        if self.bounded:
            if self.reported is not None and self.reported[:3] == (msg.k, msg.epoch, key):
                self.reported = None  # our lock was this chain's
        else:
            self.epoch += 1
            if not self._holding():
                self.reported = None
        if key in self.pending and msg.finished:
            del self.pending[key]
            self.stats["measurements_used" if msg.gains else "measurements_dropped"] += 1
        self.known_pending = {tuple(k) for k in msg.pending} - ({key} if msg.finished else set())
        out = [Send(msg, c) for c, p in sorted(msg.parent.items()) if p == self.id]
        if self.bounded and self.id == key[0] and msg.seq:
            # Bounded chains leave most of the swarm out; the measurer's radio neighbours
            # overhear the commit and apply it now, so their versions stay close to ours and
            # the next chains around here meet equal versions. (The tree still gets it by
            # unicast, with retries; those copies of the broadcast are duplicates.)
            out.append(Send(msg, None))
        self._deliver(msg)
        self._apply_ready()  # what arrived while we were busy (commits asked for by a version rerun)
        if self.bounded:
            out += self._run_queued()
        out += self._start_next()
        out += self._release_held()
        return out

    def _run_queued(self) -> list[Send]:
        """Bounded chains: our lock is free; serve the smallest start that waited for it."""
        out: list[Send] = []
        while self.queued and not self._holding():
            self.queued.sort(key=lambda item: tuple(item[1].key))
            src, msg = self.queued.pop(0)
            if msg.k == self.k:
                out += self._dispatch(src, msg)
        return out

    def _overheard(self, msg: DclCommit) -> list[Send]:
        """A bounded chain's commit, broadcast by its measurer, at a node outside the chain."""
        self._deliver(msg)
        return self._start_next()

    def _late_commit(self, src: int, msg: DclCommit) -> list[Send]:
        """A commit of an earlier tick or epoch: we moved on before it reached us (real time,
        or an earlier commit was missing). Its state change still applies, in version order.
        It goes on down the tree once, when it comes from our parent."""
        if not self._valid_commit(msg):
            return []
        if msg.seq == 0 or self._applied(msg) or (msg.key[0], msg.seq) in self.waiting:
            return self.drop("stale", f"commit k={msg.k} epoch={msg.epoch}")
        out = [Send(msg, c) for c, p in sorted(msg.parent.items()) if p == self.id] \
            if msg.parent.get(self.id, msg.key[0]) == src else []
        self._deliver(msg)
        return out + self._resolve_report(msg.key[0], commit=msg)

    def _valid_transform(self, msg: DclToken | DclCommit) -> bool:
        """Shapes fit this swarm, L is a Cholesky factor (lower, positive diagonal), Pz is
        positive definite: what the gain formulas need to be well defined."""
        if msg.key[1] not in (RANGE, RANGE_BEARING, LANDMARK):
            return False
        d, (n, dz) = self.model.state_dim, self._shape(msg.key)
        if not (msg.L.shape == (n, n) and msg.Y.shape == (n, dz) and msg.Pz.shape == (dz, dz)
                and msg.nu.shape == (dz,) and all(g.shape == (d, dz) for g in msg.gains.values())):
            return False
        if self.phi is not None and msg.gains and (set(msg.phi) != set(self._pair(msg.key))
                                                   or any(p.shape != (d, d) for p in msg.phi.values())):
            return False
        if msg.L.diagonal().min() <= 0 or msg.L[self._upper[n]].any():
            return False
        if dz == 1:
            return bool(msg.Pz[0, 0] > 0)
        try:
            np.linalg.cholesky(msg.Pz)
        except np.linalg.LinAlgError:
            return False
        return True

    def _valid_commit(self, msg: DclCommit) -> bool:
        if not self._valid_transform(msg):
            self.drop("shape", "commit")
            return False
        if msg.seq and msg.version.get(msg.key[0], 0) != msg.seq - 1:
            self.drop("invalid", f"commit {msg.key} seq {msg.seq} after version {msg.version}")
            return False
        if not set(msg.participants) <= set(msg.gains) or any(size < 1 for size, _ in msg.removed):
            self.drop("invalid", f"commit {msg.key} participants or removed")
            return False
        return True

    def _applied(self, c: DclCommit) -> bool:
        return self.version.get(c.key[0], 0) >= c.seq

    def _behind(self, version: dict) -> bool:
        """True if `version` holds commits we have not applied."""
        return any(s > self.version.get(a, 0) for a, s in version.items())

    def _deliver(self, c: DclCommit) -> None:
        if c.seq == 0 or self._applied(c):
            return
        if len(self.waiting) >= 2 * LOG_COMMITS:
            self.drop("waiting-overflow", str(c.key))
            return
        self.waiting[(c.key[0], c.seq)] = c
        self._apply_ready()

    def _apply_ready(self) -> None:
        """Apply waiting commits whose history we have; none while we are busy. A commit we took
        part in at our present version goes first: after any other it could no longer apply
        as computed."""
        def order(kv):
            c = kv[1]
            return (not (self.id in c.participants and c.version == self.version), c.k, c.epoch, kv[0])

        progress = True
        while progress and not self.busy:
            progress = False
            for cid, c in sorted(self.waiting.items(), key=order):
                if self._applied(c):
                    del self.waiting[cid]
                elif self.orphan or all(self.version.get(a, 0) >= s for a, s in c.version.items()):
                    del self.waiting[cid]
                    self._apply(c)
                    progress = True
                    break

    def _apply(self, c: DclCommit) -> None:
        """Apply one commit whose history we have: as a participant (it was computed at our
        version and counts on our mean moving), or as an outsider (gain zero)."""
        if self.orphan:
            # No cross-covariances: every commit is nothing to us but a version, except the one
            # that removes us from our former group's rows: our covariance-intersection weight
            # 1/size. It applies to the part of our error that can be correlated with the group,
            # the block we had when we became an orphan; what was added since (process noise,
            # the motion of the ticks a restarted agent missed) is independent of everyone.
            for size, o in c.removed:
                if o == self.id:
                    _, own = fusion.ci_split(size, 1)
                    self.row[self.id] = self.row[self.id] + (own - 1) * self.orphan_base
                    self.orphan, self.orphan_base = False, None
            return self._advance(c)
        zero = self._zero
        row, x = dict(self.row), self.x
        gone = {o: size for size, o in c.removed if o in row and o != self.id}
        if gone:
            # Covariance intersection (fusion.ci_split): each orphan takes weight 1/size (it
            # scales its own block when it gets this commit), the rest of its former group
            # (size - |gone|)/size.
            f, _ = fusion.ci_split(max(gone.values()), len(gone))
            row = {j: f * b for j, b in row.items() if j not in gone}
            self.stats["orphans_removed"] += len(gone)
        if c.gains:
            participant = self.id in c.participants
            if participant and self.version != c.version:
                # We took part, then moved on (a new tick) before the commit reached us. With
                # every touched node a participant, being an outsider instead changes nothing
                # for anyone else; otherwise our cross-covariances with the outsiders are wrong.
                if set(c.gains) - set(c.participants):
                    self._make_orphan(f"commit {c.key} of k={c.k} came after we moved on")
                    return self._advance(c)
                participant = False
            if participant and self.phi is None:
                K_i = c.gains[self.id]
                x = x + K_i @ c.nu
                for j, K_j in c.gains.items():
                    row[j] = row.get(j, zero) - kalman.covariance_decrement(K_i, c.Pz, K_j)
            elif participant:
                # Core gains: our real gain is Phi K_i; core rows change by the core gains alone.
                K_i = c.gains[self.id]
                G = self.phi @ K_i
                x = x + G @ c.nu
                for j, K_j in c.gains.items():
                    A, B = (G, G) if j == self.id else (K_i, K_j)
                    row[j] = row.get(j, zero) - kalman.covariance_decrement(A, c.Pz, B)
            else:
                g = self._outsider_gain(c, row)
                if g is not None:
                    for a in c.participants:
                        if a != self.id:
                            row[a] = row.get(a, zero) - kalman.covariance_decrement(g, c.Pz, c.gains[a])
                    self.stats["outsider_commits"] += 1
        if not np.isfinite(x).all() or not all(np.isfinite(b).all() for b in row.values()):
            self.drop("invalid", "non-finite update")
            self._make_orphan("non-finite update")
            return self._advance(c)
        self.x, self.row = x, row
        self.stats["chains_committed"] += 1
        self._advance(c)

    def _outsider_gain(self, c: DclCommit, row: dict) -> np.ndarray | None:
        """Our gain formula on our own row (eq. 20): what the participants' cross-covariances
        with us change by. None when we are not correlated with m or n."""
        pair = self._pair(c.key)
        if not any(a in row for a in pair):
            return None
        zero = self._zero
        if self.phi is None:
            P_i_mn = np.hstack([row.get(a, zero) for a in pair])
        else:
            # Core coordinates: C_ia Phi_a^T with the Phi the gains were formed with; our own
            # block (we were m or n and moved on) as Phi^-1 P_ii, now.
            P_i_mn = np.hstack([np.linalg.solve(self.phi, row[a]) if a == self.id else row.get(a, zero) @ c.phi[a].T
                                for a in pair])
        return kalman.gain(kalman.solve_lower(c.L, P_i_mn.T).T @ c.Y, c.Pz)

    def _advance(self, c: DclCommit) -> None:
        for a, s in c.version.items():  # a no-op unless we are an orphan catching up
            self.version[a] = max(self.version.get(a, 0), s)
        self.version[c.key[0]] = max(self.version.get(c.key[0], 0), c.seq)
        self.log.append(c)
        self.deferred.clear()

    def _make_orphan(self, why: str) -> None:
        """Our cross-covariances can no longer be kept equal to the others' copies: drop them.
        Our own block is still our own error's covariance; the chain that removes us from the
        others' rows sets the covariance-intersection weights for both sides."""
        if self.orphan:
            return
        log.warning("node %s becomes an orphan: %s", self.id, why)
        self.row = {self.id: self.row[self.id]}
        self.orphan, self.orphan_base = True, self.row[self.id].copy()
        self.stats["orphaned"] += 1

    # ------------------------------------------------------------------ lost and found

    def _track_lost(self, moved: np.ndarray, Q: np.ndarray) -> None:
        """Once per tick, after the time update: become lost when the position is too uncertain,
        and while lost, log the move so ranges of earlier ticks can be tied to the position now."""
        p = self.model.position_dim
        block = self.row[self.id][:p, :p]
        # The trace bounds the largest eigenvalue from above: the eigen-solve, every tick on
        # every node, only when the trace says the node might be lost.
        if not self.lost and self.rejoin_std is not None and np.trace(block) > self.rejoin_std**2:
            if np.linalg.eigvalsh(block).max() > self.rejoin_std**2:
                self.lost = True
                self.stats["lost"] += 1
                self.finder.clear()
                self.lost_ranges.clear()
                log.warning("node %s is lost (position std above %.1f m): finding itself by multilateration",
                            self.id, self.rejoin_std)
        if self.lost:
            self.finder.moved(self.k, moved, Q[:p, :p])

    def _find_self(self) -> None:
        """Anchor the ranges of earlier ticks with the neighbours' beacons of those ticks, and try
        the window. A fix replaces our position: we become an orphan with it as our block, so the
        next chain that meets us removes us from the others' rows with a covariance-intersection
        bound, as after a restart, and from then on we fuse ranges again."""
        if not self.lost:
            return
        for k, j, r, var in self.lost_ranges:
            beacon = self.beacons.get(j, k)
            if beacon is not None:
                self.finder.add(k, beacon[0], beacon[1], r, var)
        self.lost_ranges = [(k, j, r, var) for k, j, r, var in self.lost_ranges
                            if not self.beacons.heard(j, k) and k >= self.k - NEIGHBOUR_TICKS]
        fix = self.finder.solve(self.model.position(self.x))
        # Half the threshold: the covariance-intersection removal that follows scales the block
        # by the group's size, and a fix that leaves us lost again is no fix.
        if fix is None or np.linalg.eigvalsh(fix.cov).max() > (self.rejoin_std / 2) ** 2:
            return
        p = self.model.position_dim
        self._make_orphan("position found again by multilateration")
        x, P = self.x.copy(), self.row[self.id].copy()
        x[:p], P[:p, :], P[:, :p] = fix.position, 0.0, 0.0
        P[:p, :p] = fix.cov
        self.x, self.row[self.id] = x, P
        self.orphan_base = P.copy()
        self.lost = False
        self.finder.clear()
        self.stats["refound"] += 1
        log.warning("node %s found itself from %d ranges: position %s, std %.2f m", self.id, fix.ranges,
                    np.round(fix.position, 2), float(np.sqrt(np.trace(fix.cov))))

    # ------------------------------------------------------------------ catching up

    def _on_version(self, src: int, version: dict) -> list[Send]:
        """A neighbour's beacon showed its version: ask it for commits we lack. An orphan has
        no cross-covariances for those commits to touch, so it just takes the version."""
        if self.k < 0 or not self._behind(version):
            return []  # not started: there is no tick to ask in (it asks at its first tick's beacons)
        if self.orphan:
            for a, s in version.items():
                self.version[a] = max(self.version.get(a, 0), s)
            return []
        if self.asked:
            return []  # one neighbour per tick: they would all send the same commits
        self.asked.add(src)
        return [Send(DclSync(self.k, dict(self.version)), src)]

    def _on_sync(self, src: int, msg: DclSync) -> list[Send]:
        """Send what the asker lacks from our log, oldest first, in frames of bounded size."""
        if self.k < 0:
            return self.drop("not-started", f"sync from {src}")
        missing = [c for c in self.log if c.seq > msg.version.get(c.key[0], 0)]
        out, batch, weight = [], [], 0
        for c in missing:
            batch.append(c)
            weight += len(c.gains) + len(c.parent) // 4 + 1
            if len(batch) == LOG_BATCH or weight > 256:
                out.append(Send(DclLog(self.k, batch), src))
                batch, weight = [], 0
        if batch:
            out.append(Send(DclLog(self.k, batch), src))
        return out[:8]  # the rest on the next request
