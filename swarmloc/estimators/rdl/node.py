"""RDL as a sans-I/O node: pairwise updates over one radio hop, corrections by the neighbours.

One relative measurement between platforms a < b (ids), measured by either:

1. meas     m -> n when the measurer m is the higher id: the measurement is handed to n.
2. req      a -> b: the measurement, a's mean, covariance and its sides of every cross-
            covariance it holds (factors.py). a now waits for the result and takes part in
            nothing else: frames that arrive meanwhile wait in `later`.
3. commit   b -> a: b forms the pair's block (Sigma_ab = sigma_ab sigma_ba^T), gates and
            updates it, applies its own half and sends a its half.

Only the lower id waits on the higher one, so waits cannot form a cycle and every measurement
of a tick finishes in lockstep. A landmark (planar-pose) is the measurer's alone. No one but
the pair hears of a measurement: Luft et al.'s algorithm as published.

Real time: a tick that comes while we wait is run once the result is in (or the wait has run
out); a request or meas of another tick is refused or dropped (its ranges were taken at other
positions).
"""

from __future__ import annotations

import logging

import numpy as np

from swarmloc.estimators.neighbours import NeighbourTable, RetryBudget
from swarmloc.estimators.rdl import factors as fx
from swarmloc.estimators.ukf.ccl import Observations
from swarmloc.filters import kalman, plausibility
from swarmloc.node import LANDMARK, Estimate, Node, NodeSpec, Send, Timer, keyed_measurements, odometry_of
from swarmloc.wire.messages import RDL_GATED, RDL_OK, RDL_REFUSED, Beacon, RdlCommit, RdlMeas, RdlRequest, Sensors

log = logging.getLogger(__name__)

NEIGHBOUR_TICKS = 3
WAIT_TICKS = 0.8
"""Real time: how long a's wait for b's commit may last, in ticks. Under one tick, so a wait
spans at most one tick boundary: it holds at most the next tick's sensor frame (run when it
ends), and leaves a fifth of a tick for the rest of that frame's lag. Not half a tick: a pair's
round trip is two radio hops, and at swarm256's load a hop takes 125-185 ms (median), so half a
tick gave up a quarter to a half of the ranges half-way, each leaving the pair's two sides from
different updates (docs/benchmarks.md, "RDL's wait in real time")."""
MAX_LATER = 256  # frames held while we wait


class RdlNode(Node):
    algorithm = "rdl"

    @classmethod
    def spec(cls, scenario, aid, settings=None) -> NodeSpec:
        est = scenario.estimation
        x0, P0 = scenario.prior(aid)
        return NodeSpec.of(cls, aid=aid, x0=x0, P0=P0, model=scenario.agent(aid).model, spread=est.spread,
                           landmarks=[[m.id, *m.position] for m in scenario.world.landmarks], gate=est.gate,
                           gate_open_after=est.gate_open_after, beacon_every=getattr(settings, "beacon_every", 1))

    def __init__(self, aid, x0, P0, model="planar-speed-heading", spread: float | None = None,
                 landmarks=(), gate: float | None = None, gate_open_after: int = 10, max_retries: int = 3,
                 beacon_every: int = 1):
        super().__init__(aid, x0, P0, model)
        d = self.model.state_dim
        self.ut = kalman.UnscentedTransform.for_pair(d, spread)
        self.obs = Observations(self.model, {int(i): (x, y) for i, x, y in landmarks})
        # The pair's higher id gates, so every key (measurer, kind, target) meets one gate.
        self.gate = kalman.Gate(gate, gate_open_after)
        self.factors = fx.Factors(d)
        self.beacons = NeighbourTable(self.id, self.model.position_dim, NEIGHBOUR_TICKS)
        self.neighbours: dict[int, np.ndarray] = {}
        if not 1 <= beacon_every <= NEIGHBOUR_TICKS:  # a neighbour must beacon again before it is forgotten
            raise ValueError(f"beacon_every {beacon_every} not in 1..{NEIGHBOUR_TICKS}")
        self.beacon_every, self.first_k = int(beacon_every), None
        self.jobs: list[tuple] = []  # (key, z, R) this node runs as the pair's lower id, in key order
        self.open: set = set()  # own measurements of this tick not yet applied, gated or dropped
        self.waiting: tuple | None = None  # (k, key, b): the request whose commit we wait for
        self.later: list[tuple[int, object]] = []  # frames that came while we waited
        self.held: list[tuple[int, object]] = []  # real time: frames of a tick we have not reached
        self.deferred: Sensors | None = None  # real time: a tick that came while we waited
        self.retries = RetryBudget()
        self.max_retries = max_retries
        self.gone: set[int] = set()
        self.tick_s: float | None = None
        self.nis: list[tuple[float, int]] = []
        self.stats = {"measurements_used": 0, "measurements_dropped": 0, "measurements_gated": 0,
                      "pair_updates": 0, "handed_over": 0,
                      "waits_expired": 0}

    # ------------------------------------------------------------------ state

    def estimate(self) -> Estimate:
        return Estimate(self.k, self.x.copy(), self.P.copy())

    def resume(self, k, x, P) -> None:
        """Continue from a checkpoint: own mean and covariance. Our sides are gone, so every
        product with them is zero: we are uncorrelated with the swarm until pairs meet again."""
        super().resume(k, x, P)
        self.factors.clear()
        self.first_k = None  # beacons in its first ticks again, as at a start
        self.jobs, self.open, self.waiting, self.later, self.held, self.deferred = [], set(), None, [], [], None

    # ------------------------------------------------------------------ tick

    def step(self, sensors: Sensors) -> list:
        if sensors.k <= self.k:
            return self.drop("stale-tick", f"sensors k={sensors.k} at k={self.k}")
        if self.waiting is not None:
            # Real time only (lockstep ends a tick once every commit is in): our half of the
            # pair must be applied to the state the request carried.
            if self.deferred is not None:
                self.drop("tick-skipped", f"k={self.deferred.k}")  # missed_motion covers it
            self.deferred = sensors
            return []
        return self._tick(sensors)

    def _tick(self, sensors: Sensors) -> list:
        self.stats["measurements_dropped"] += len(self.open)  # of a tick that is over
        self.open.clear()
        self.jobs.clear()
        gap = self.missed_motion(sensors)
        if gap is not None:
            self.P = self.P + gap
        x, F, Q = self.model.predict(self.x, odometry_of(sensors))
        self.x, self.P = kalman.predict(x, self.P, F, Q)
        if not self.model.identity_transition:
            self.factors.scale(F)  # Sigma_ij <- F_i Sigma_ij F_j^T: each side takes its own F
        self.k, self.tick_s = sensors.k, sensors.odometry.dt
        self.nis = []
        self.retries.clear()
        self.neighbours = {j: p for j, p in self.beacons.snapshot(self.k).items() if j not in self.gone}
        out: list = []
        if self.first_k is None:
            self.first_k = self.k
        # Staggered by id, so a tick carries 1/beacon_every of the swarm's beacons; all in the
        # first tick, so every neighbour is known from the second tick on as with a beacon a
        # tick (the staggered one comes within the NEIGHBOUR_TICKS the first stays known).
        # Only the first: beaconing in each of the first beacon_every ticks made ticks 1.. carry
        # every beacon too, a burst that cost swarm256 early ticks in real time (docs/rdl.md).
        if self.k == self.first_k or (self.k + self.id) % self.beacon_every == 0:
            out.append(Send(Beacon(self.k, self.model.position(self.x).copy(),
                                   self.P[:self.model.position_dim, :self.model.position_dim].copy(), {}), None))
        for key, r in keyed_measurements(self.id, sensors):
            if not self.obs.usable(key) or (key[1] != LANDMARK and r.target not in self.neighbours):
                self.stats["measurements_dropped"] += 1  # cannot model it, or the measured platform is out of reach
                continue
            z, R = self.obs.z(key[1], r)
            self.open.add(tuple(key))
            if key[1] == LANDMARK or self.id < key[2]:
                self.jobs.append((tuple(key), z, R))
            else:
                self.stats["handed_over"] += 1
                out.append(Send(RdlMeas(self.k, list(key), z, R), key[2]))
        out += self._release_held()
        return self._arm(out + self._next())

    def _next(self) -> list:
        """Start our next pair (a landmark runs at once), unless we wait for one."""
        out: list = []
        while self.waiting is None and self.jobs:
            key, z, R = self.jobs.pop(0)
            if key[1] == LANDMARK:
                out += self._alone(key, z, R)
                continue
            b = key[2] if key[0] == self.id else key[0]
            if b in self.gone:
                self._resolve(key, "dropped")
                continue
            mant, exp = self.factors.pack([b])
            self.waiting = (self.k, key, b)
            out.append(Send(RdlRequest(self.k, list(key), z, R, self.x.copy(), self.P.copy(), mant, exp), b))
        return out

    def _resolve(self, key, how: str) -> None:
        """One of our own measurements is done: "used", "gated" or "dropped"."""
        if tuple(key) in self.open:
            self.open.discard(tuple(key))
            self.stats[f"measurements_{how}"] += 1

    # ------------------------------------------------------------------ radio

    def receive(self, src, msg) -> list:
        return self._arm(self._receive(src, msg))

    def _receive(self, src, msg) -> list:
        if isinstance(msg, Beacon):
            if self.beacons.valid(src, msg):
                self.beacons.hear(src, msg)
                return []
            return self.drop("shape", "beacon")
        if not isinstance(msg, (RdlMeas, RdlRequest, RdlCommit)):
            return self.drop("unexpected-type", type(msg).__name__)
        if isinstance(msg, RdlCommit):
            if self.waiting is None:
                return self.drop("stale", f"commit {msg.key} from {src}, given up on")
            return self._own_commit(src, msg)
        if msg.k > self.k:  # real time: a peer is a tick ahead of us
            if len(self.held) >= MAX_LATER:
                return self.drop("held-overflow")
            self.held.append((src, msg))
            return []
        if self.waiting is not None:
            if len(self.later) >= MAX_LATER:
                return self.drop("later-overflow")
            self.later.append((src, msg))
            return []
        return self._handle(src, msg)

    def _handle(self, src, msg) -> list:
        try:
            if isinstance(msg, RdlMeas):
                return self._on_meas(src, msg)
            return self._on_request(src, msg)
        except (ValueError, np.linalg.LinAlgError) as exc:
            # Numbers that decode but do not fit this swarm: drop, state untouched.
            return self.drop("invalid", repr(exc))

    def _release_held(self) -> list:
        ready, self.held = [(s, m) for s, m in self.held if m.k <= self.k], [(s, m) for s, m in self.held if m.k > self.k]
        out: list = []
        for src, msg in ready:
            out += self._receive(src, msg)
        return out

    def _key_of(self, msg) -> tuple | None:
        key = tuple(msg.key)
        return key if self.obs.usable(key) else None

    def _on_meas(self, src, msg: RdlMeas) -> list:
        key = self._key_of(msg)
        if key is None or key[1] == LANDMARK or key[0] != src or key[2] != self.id or src < self.id:
            return self.drop("misrouted", f"meas {msg.key}")
        if msg.z.shape != (self.obs.dim(key[1]),) or msg.R.shape != (self.obs.dim(key[1]),) * 2:
            return self.drop("shape", "meas")
        if not np.isfinite(msg.z).all() or not fx.is_covariance(msg.R):
            return self.drop("invalid", "meas")
        if msg.k != self.k:
            return self.drop("stale", f"meas k={msg.k}")  # the measurer counts it dropped at its next tick
        self.jobs.append((key, msg.z, msg.R))
        self.jobs.sort(key=lambda j: j[0])
        return self._next()

    def _refuse(self, a, msg, status=RDL_REFUSED) -> list:
        d = self.model.state_dim
        return [Send(RdlCommit(msg.k, list(msg.key), status, msg.x, msg.P, np.zeros((d, d))), a)]

    def _on_request(self, a, msg: RdlRequest) -> list:
        key = self._key_of(msg)
        d = self.model.state_dim
        if key is None or key[1] == LANDMARK or {key[0], key[2]} != {a, self.id} or a > self.id:
            return self.drop("misrouted", f"request {msg.key}")
        if (msg.z.shape != (self.obs.dim(key[1]),) or msg.R.shape != (self.obs.dim(key[1]),) * 2
                or msg.x.shape != (d,) or msg.P.shape != (d, d) or set(msg.exponent) - set(msg.factor)
                or any(m.shape != (d, d) for m in msg.factor.values())):
            return self.drop("shape", "request")
        if (not fx.is_covariance(msg.P) or not fx.is_covariance(msg.R) or not np.isfinite(msg.x).all()
                or not np.isfinite(msg.z).all() or not all(np.isfinite(m).all() for m in msg.factor.values())):
            return self.drop("invalid", "request")
        if msg.k != self.k:
            return self._refuse(a, msg)  # taken at other positions than ours now
        theirs = fx.unpack(msg.factor, msg.exponent)
        mine = self.factors.get(a)
        s_ab = theirs.get(self.id)
        cross = np.zeros((d, d)) if mine is None or s_ab is None else s_ab @ mine.T  # Sigma_ab
        pair = [key[0], key[2]]  # measurer first: the order h reads the stacked states in
        xs = {a: msg.x, self.id: self.x}
        Ps = {a: msg.P, self.id: self.P}
        C = cross if pair[0] == a else cross.T
        h, angles = self.obs.h(key)
        up = fx.pair_update(self.ut, h, angles, np.concatenate([xs[p] for p in pair]),
                            fx.joint([Ps[p] for p in pair], C), msg.z, msg.R, self.obs.innovation)
        if up is None:
            self.drop("not-positive-definite", str(key))
            self._resolve(key, "dropped")
            return self._refuse(a, msg)
        # One member's lie (issue 26, finding 7): a's measurement or state past the innovation
        # bound, or claiming more information than the innovation allows, touches nothing. Before
        # the gate, which stands open after a streak and would take it.
        reason = plausibility.update(up["nu"], up["Pz"], up["Y"])
        if reason is not None:
            self.drop(reason, f"request {key} from {a}")
            self._resolve(key, "dropped")
            return self._refuse(a, msg)
        if not self.gate.admit(tuple(key[:3]), up["nis"], len(msg.z)):
            self._resolve(key, "gated")
            return self._refuse(a, msg, RDL_GATED)
        if key[0] == self.id:
            self.nis.append((up["nis"], len(msg.z)))
            self._resolve(key, "used")
        blk = {p: slice(i * d, (i + 1) * d) for i, p in enumerate(pair)}
        post = {p: (up["x"][blk[p]], up["P"][blk[p], blk[p]]) for p in pair}
        new_cross = up["P"][blk[a], blk[self.id]]  # Sigma_ab after: a's new side (ours is I)
        commit = RdlCommit(self.k, list(key), RDL_OK, post[a][0], post[a][1], new_cross, up["nis"])
        # Our half: the sides toward everyone else follow our own update (Luft et al.'s approximation).
        self.factors.scale(fx.scaling(self.P, post[self.id][1]), keep=(a,))
        self.factors.set(a, np.eye(d))
        self.x, self.P = post[self.id]
        self.stats["pair_updates"] += 1
        return [Send(commit, a)]

    def _own_commit(self, b, msg: RdlCommit) -> list:
        """b's answer to our request: apply our half (or give the measurement up), then what waited."""
        k, key, partner = self.waiting
        if (msg.k, tuple(msg.key)) != (k, key) or b != partner:
            return self.drop("stale", f"commit {msg.key} from {b}")
        d = self.model.state_dim
        if msg.status != RDL_OK:
            self._resolve(key, "gated" if msg.status == RDL_GATED else "dropped")
        elif msg.x.shape != (d,) or msg.P.shape != (d, d) or msg.cross.shape != (d, d):
            self.drop("shape", "commit")
            self._resolve(key, "dropped")
        elif not (fx.is_covariance(msg.P) and np.isfinite(msg.x).all() and np.isfinite(msg.cross).all()):
            self.drop("invalid", "commit")
            self._resolve(key, "dropped")
        elif (why := plausibility.reduction(self.P, msg.P, self.obs.dim(key[1]))
              or plausibility.shift(msg.x - self.x, self.P)) is not None:
            # One member's lie (issue 26, finding 7): b's answer must be one update of our own
            # prior (the P we sent is still ours: we waited): its covariance reduced by at most
            # a rank-dim(z) part, its mean moved within the innovation bound in our own metric.
            self.drop(why, f"commit {msg.key} from {b}")
            self._resolve(key, "dropped")
        else:
            try:
                A = fx.scaling(self.P, msg.P)  # the P we sent is still ours: we waited
            except np.linalg.LinAlgError:
                A = None
            if A is None or not np.isfinite(A).all():
                self.drop("invalid", "commit")
                self._resolve(key, "dropped")
                return self._unlock()
            self.factors.scale(A, keep=(b,))
            self.factors.set(b, msg.cross)
            self.x, self.P = msg.x.copy(), msg.P.copy()
            self.stats["pair_updates"] += 1
            if key[0] == self.id:
                self.nis.append((msg.nis, self.obs.dim(key[1])))
                self._resolve(key, "used")
        return self._unlock()

    def _unlock(self) -> list:
        """The wait is over: the tick that came meanwhile, the frames that waited, our next pair."""
        self.waiting = None
        out: list = []
        if self.deferred is not None:  # real time: the tick that is due first; what waited is then stale
            sensors, self.deferred = self.deferred, None
            out += self._tick(sensors)
        later, self.later = self.later, []
        for src, msg in later:
            out += self._receive(src, msg)  # waits again in `later` if a pair has started meanwhile
        return out + self._next()

    # ------------------------------------------------------------------ landmarks

    def _alone(self, key, z, R) -> list:
        """A landmark: our own update, exact for us; our sides follow it as a pair's do."""
        h, angles = self.obs.h(key)
        up = fx.pair_update(self.ut, h, angles, self.x, self.P, z, R, self.obs.innovation)
        if up is None:
            self.drop("not-positive-definite", str(key))
            self._resolve(key, "dropped")
            return []
        if not self.gate.admit(tuple(key[:3]), up["nis"], len(z)):
            self._resolve(key, "gated")
            return []
        self.nis.append((up["nis"], len(z)))
        self._resolve(key, "used")
        self.factors.scale(fx.scaling(self.P, up["P"]))
        self.x, self.P = up["x"], up["P"]
        return []

    # ------------------------------------------------------------------ failures and timers

    def link_failed(self, dst: int, msg) -> list:
        """A unicast did not arrive: send it again a few times, then give the measurement up."""
        if not isinstance(msg, (RdlMeas, RdlRequest, RdlCommit)) or msg.k != self.k:
            return self.drop("undeliverable", type(msg).__name__)
        if self.retries.again((msg.TYPE, dst, msg.k, tuple(msg.key)), self.max_retries):
            return [Send(msg, dst)]
        if isinstance(msg, RdlRequest):
            return self._arm(self._give_up(f"request {msg.key} to {dst}"))
        if isinstance(msg, RdlMeas):
            self._resolve(msg.key, "dropped")
        return self.drop("undeliverable", msg.TYPE)

    def _give_up(self, why: str) -> list:
        """Our request or its commit is lost. If b applied its half, the pair's cross-covariance
        now differs between the two sides; nothing here can tell (docs/rdl.md, "Failures")."""
        if self.waiting is None:
            return []
        self._resolve(self.waiting[1], "dropped")
        self.drop("no-commit", why)
        return self._unlock()

    def on_timer(self, tag: str, t: float) -> list:
        if self.waiting is not None and tag == self._wait_tag():
            self.stats["waits_expired"] += 1
            return self._arm(self._give_up(f"no commit for {self.waiting[1]}"))
        return []

    def _wait_tag(self) -> str:
        k, key, b = self.waiting
        return f"rdl.wait {k} {key} {b}"

    def _arm(self, out: list) -> list:
        """Real time: a timer on the wait for our commit (in lockstep the radio NACKs what it
        cannot deliver and every commit is in before the tick ends)."""
        if self.synchronous or self.tick_s is None or self.waiting is None:
            return out
        if not any(isinstance(s, Send) and isinstance(s.msg, RdlRequest) for s in out):
            return out
        return out + [Timer(WAIT_TICKS * self.tick_s, self._wait_tag())]

    def peer_left(self, aid: int) -> list:
        self.gone.add(int(aid))
        self.neighbours.pop(int(aid), None)
        if self.waiting is not None and self.waiting[2] == int(aid):
            return self._arm(self._give_up(f"peer {aid} left"))
        return []

    def peer_joined(self, aid: int) -> list:
        self.gone.discard(int(aid))
        return []

