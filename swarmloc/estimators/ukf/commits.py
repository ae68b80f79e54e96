"""UKF-DCL's commit history: applying commits in version order (as a participant or an outsider),
the log that lets a node catch up after a partition, orphans, and finding a lost node again."""

from __future__ import annotations

import logging

import numpy as np

from swarmloc.estimators.ukf.protocol import LOG_BATCH, LOG_COMMITS, NEIGHBOUR_TICKS
from swarmloc.filters import fusion, kalman, plausibility
from swarmloc.node import (
    LANDMARK,
    RANGE,
    RANGE_BEARING,
    Send,
)
from swarmloc.wire.messages import (
    DclCommit,
    DclLog,
    DclSync,
    DclToken,
)

log = logging.getLogger("swarmloc.estimators.ukf.dcl")


class CommitHistory:
    """The commit half of UkfDclNode (a mixin: it shares the node's state)."""

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
        if msg.gains:
            # What every receiver can check from the commit alone, so all refuse it alike and
            # nobody's copies of the cross-covariances part: the innovation within the
            # chi-square bound, no more information than its covariance allows, finite gains.
            reason = plausibility.update(msg.nu, msg.Pz, msg.Y, self.plausible) or (
                None if plausibility.finite(*msg.gains.values()) else "implausible-numbers")
            if reason is not None:
                self.drop(reason, f"commit {msg.key} from measurer {msg.key[0]}")
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
            if participant and c.k == self.k:
                # Our gain from our own rows (equal to the chain's copies at equal versions, within
                # the tick: a time update since has grown our own block): a gain handed to us that
                # differs, or an own block the update would leave indefinite, is refused here
                # alone, and our cross-covariances are no longer the others' copies: we become
                # an orphan, as after a non-finite update.
                own = self._outsider_gain(c, row)
                reason = plausibility.gain(c.gains[self.id], np.zeros_like(c.gains[self.id]) if own is None else own,
                                           self.plausible)
                if reason is not None:
                    self.drop(reason, f"commit {c.key} from measurer {c.key[0]}")
                    self._make_orphan(f"{reason} in commit {c.key}")
                    return self._advance(c)
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
        if row[self.id] is not self.row[self.id] and plausibility.covariance(row[self.id], self.plausible):
            self.drop("implausible-covariance", f"commit {c.key} from measurer {c.key[0]}")
            self._make_orphan(f"commit {c.key} would leave our covariance indefinite")
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
