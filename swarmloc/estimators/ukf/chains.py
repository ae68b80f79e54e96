"""UKF-DCL's chain steps: starting a chain, the start and token hops, the decision at the measurer,
NACKs and timeouts (the protocol of dcl.py's docstring, steps 1-3)."""

from __future__ import annotations

import logging

import numpy as np

from swarmloc.estimators.ukf.protocol import (
    BUSY_RETRIES,
    HOLD_TICKS,
    HOP_TIMEOUT_TICKS,
    MAX_QUEUED,
    VERSION_RETRIES,
    Key,
)
from swarmloc.filters import fusion, kalman, plausibility
from swarmloc.node import (
    LANDMARK,
    RANGE,
    Send,
    Timer,
)
from swarmloc.wire.messages import (
    CHAIN_OK,
    CHAIN_REFUSED,
    CHAIN_UNREACHABLE,
    CHAIN_VERSION,
    DclCommit,
    DclLog,
    DclStart,
    DclSync,
    DclToken,
)

log = logging.getLogger("swarmloc.estimators.ukf.dcl")


class ChainSteps:
    """The chain half of UkfDclNode (a mixin: it shares the node's state)."""

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
        reason = plausibility.update(transform["nu"], transform["Pz"], transform["Y"], self.plausible)
        if reason is not None:
            # m's measurement (or m's numbers) far outside what our two estimates allow: the
            # chain runs empty, nobody's state moves.
            self.drop(reason, f"start {key} from {m}")
            return self._forward(token(CHAIN_REFUSED, *head))
        return self._forward(token(CHAIN_OK, *head, **transform))

    def _on_token(self, src: int, msg: DclToken) -> list[Send]:
        key = tuple(msg.key)
        if not self._valid_transform(msg):
            return self.drop("shape", "token")
        if msg.status == CHAIN_OK:
            reason = plausibility.update(msg.nu, msg.Pz, msg.Y, self.plausible) or (
                None if plausibility.finite(*msg.gains.values()) else "implausible-numbers")
            if reason is not None:
                return self.drop(reason, f"token {key} from {src}")
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
        reason = plausibility.update(token.nu, token.Pz, token.Y, self.plausible)
        if reason is not None:
            # Our receivers would refuse this commit (CommitHistory._valid_commit): commit nothing.
            self.drop(reason, f"token {key} back at the measurer")
            self.pending.pop(key, None)
            return DclCommit(finished=True, **nothing), out
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
