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

from swarmloc.estimators.neighbours import NeighbourTable, RetryBudget
from swarmloc.estimators.ukf.ccl import Observations
from swarmloc.estimators.ukf.chains import ChainSteps
from swarmloc.estimators.ukf.commits import CommitHistory
from swarmloc.estimators.ukf.protocol import GIVE_UP_TICKS, LOG_COMMITS, NEIGHBOUR_TICKS, Key
from swarmloc.estimators.ukf.rejoin import Multilateration
from swarmloc.filters import kalman, plausibility
from swarmloc.models.motion import PlanarPoseBias, reported_dim
from swarmloc.node import (
    LANDMARK,
    RANGE,
    Estimate,
    Node,
    NodeSpec,
    Send,
    keyed_measurements,
    odometry_of,
)
from swarmloc.wire.messages import (
    Beacon,
    DclCommit,
    DclLog,
    DclStart,
    DclSync,
    DclToken,
    Sensors,
)

log = logging.getLogger(__name__)


class UkfDclNode(ChainSteps, CommitHistory, Node):
    algorithm = "ukf-dcl"

    @classmethod
    def spec(cls, scenario, aid, settings=None) -> NodeSpec:
        est = scenario.estimation
        x0, P0 = scenario.prior(aid)
        model = scenario.agent(aid).model
        bias = PlanarPoseBias.from_settings(settings) if model == "planar-pose" else None
        return NodeSpec.of(cls, aid=aid, x0=x0, P0=P0, model=model, spread=est.spread,
                           rejoin_std=est.rejoin_std, max_chain=getattr(settings, "max_chain", None),
                           landmarks=[[m.id, *m.position] for m in scenario.world.landmarks], gate=est.gate,
                           gate_open_after=est.gate_open_after, odometry_bias=None if bias is None else bias.args())

    def __init__(self, aid, x0, P0, model="planar-speed-heading", spread: float | None = None, max_retries: int = 3,
                 rejoin_std: float | None = 15.0, max_chain: int | None = None, landmarks=(), gate: float | None = None,
                 gate_open_after: int = 10, odometry_bias: list[float] | None = None):
        if odometry_bias is not None:
            # The pose with its odometry's bias states, as UKF-CCL's with the same settings (so
            # the two stay equal): the chains carry 5-dimensional blocks, estimates the pose.
            model = PlanarPoseBias(*odometry_bias)
            x0, P0 = model.augment(x0, P0)
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
        self.plausible = plausibility.LIMITS  # what a neighbour's chain frame must satisfy (finding 7)
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
        r = reported_dim(self.model)
        return Estimate(self.k, self.x[:r].copy(), self.row[self.id][:r, :r].copy())

    def resume(self, k, x, P) -> None:
        """Continue from a checkpoint: own mean and covariance only. The cross-covariances are
        gone, so the node is an orphan: the others drop theirs with it (covariance
        intersection) when a chain next meets it, and it catches up on versions meanwhile. A
        checkpoint holds the estimate, the pose alone: bias states start again from their prior."""
        x, P = np.array(x, float), np.array(P, float)
        if x.shape[0] < self.model.state_dim:
            x, P = self.model.augment(x, P)
        self.k, self.x = int(k), x
        self.row = {self.id: P}
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

    def on_timer(self, tag: str, t: float) -> list:
        return self._arm(self._expire(tag))

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
