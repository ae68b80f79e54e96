"""EKF-CCL: the centralized EKF of Goel, Kealy, Lohani 2016, section 3, over the joint state of
any set of UAS.

Each member keeps its own nominal `InsState` (mechanized from its own IMU, swarmloc/models/ins.py);
the filter estimates the joint 16N error state X = [dx_1; ...; dx_N] (section 3.1) with one
joint covariance. Members are held in id order, whatever the order they joined in, so that the
same members and measurements give the same arithmetic.

Time update (eqs. 10-12 and the block-diagonal joint F of section 3.1): every member's samples
of the tick are mechanized and its transition over the tick is formed as the product of its
per-sample F with the noise accumulated through them, Phi = F_n ... F_1 and
Q = F_n (... (F_1 Q_0 F_1^T + Q_1) ...) F_n^T + Q_n. UAS move independently, so the joint
transition is block-diagonal and P <- Phi P Phi^T + Q is applied a block row and a block column
at a time, O(N^2) 16x16 products instead of a dense (16N)^3 one.

Measurement update (eqs. 13-17): the measurements of a tick are stacked into joint vectors with
the super matrix H_k of section 3.2 and processed as EKF updates of the joint error state
(Joseph form, swarmloc.filters.fusion.ekf_update), in this order:

1. every member's own GNSS, members in id order: its position fix (3 rows), then its
   pseudoranges (eq. 14, one row per satellite);
2. the relative measurements whose measurer and target are both members and differ, by key
   (measurer id, target id, kind, q): kind 0 for a range (eq. 15) and 1 for a relative position
   (p_target - p_measurer), q counting the earlier measurements of that kind to that target in
   the measurer's frame.

The rows are cut into batches, one EKF update each. The GNSS rows form one batch: each member's
own GNSS touches only its own block, so the batch is the same whether a member was taken in
with its GNSS applied already or not (what lets the fusion centre take a UAS in from its own
estimate of the tick, swarmloc/estimators/ekf/centre.py). Each measurer's relative rows are
a group, and consecutive groups fill a batch until it holds at least 8N rows, half the joint
state's dimension. After each update every member's block of the error estimate is injected
into its nominal state (the error state returns to zero, the covariance is kept: the usual
first-order reset), so the next batch is linearised at the corrected state. Position fixes and
relative positions are linear in the error state, so for them the cut changes nothing but
rounding; ranges and pseudoranges gain a relinearisation.

Why batches: an update costs two (16N)^3 products for the Joseph form plus terms in
rows^2 16N and rows^3. One update per measurement pays the first once per measurement, one
update for the whole tick pays the others on every row at once (a swarm of 20 with relative
positions among all pairs has 1140 rows against a 320-dim state). Measured at N = 20 with one
BLAS thread, 8N-row batches take half the time of either extreme.

When every relative measurement of the tick is a world-frame relative position (the paper's
case), they need no batches: they are linear in the members' positions, and one update in
information form on those 3N positions (`JointEkf._update_linear`) costs a 3N system however
many rows there are. It is the stacked update to rounding; against 8N-row batches it differs
only in where the nominal states are reset (once instead of once per batch, which moves an
attitude by the second-order term of composing its corrections: 2e-5 m in position after 15 s
of goel10). Measured side by side (benchmarks/bench_ekf.py --update-only): the epoch tick
of the centralized EKF at 20 UAS drops from about 88-99 ms to about 28 ms.

NIS: the innovation of each measurement (a fix, a satellite set, one relative measurement) is
scored against its own diagonal block of the stacked innovation covariance S, which is its
marginal: chi-square with that many degrees of freedom when the filter is consistent. Each is
filed under the measurer.
"""

from __future__ import annotations

from typing import Iterable, Mapping

import numpy as np

from swarmloc.estimators.ekf.local import imu_spec
from swarmloc.filters import fusion
from swarmloc.models import ins
from swarmloc.models.ins import ClockSpec, ImuSample, ImuSpec, InsState
from swarmloc.models.measurements import PositionFix, Pseudorange, Range, RelativePosition
from swarmloc.models.motion import MOTION_MODELS
from swarmloc.node import Estimate
from swarmloc.wire.messages import ImuMsg, Sensors

D = ins.ERROR_DIM
UAS = MOTION_MODELS["uas-ins"]
LAYOUT = UAS.layout

RANGE, RELPOS = 0, 1
"""Kind ranks in the key of a relative measurement: ranges before relative positions of a pair."""


def transition(state: InsState, imu: ImuMsg | None, spec: ImuSpec,
               clock: ClockSpec) -> tuple[InsState, np.ndarray, np.ndarray]:
    """Mechanize one UAS over a tick's samples: (new nominal state, Phi, Q) of the tick.

    Phi is the product of the per-sample F of eq. 10 (ins.error_dynamics), Q the per-sample
    noise carried through the later samples' F. No samples (or no IMU message) leave the state
    as it is, with Phi = I and Q = 0."""
    Phi, Q = np.eye(D), np.zeros((D, D))
    if imu is None:
        return state, Phi, Q
    for row in np.asarray(imu.samples, float):
        sample = ImuSample(row[:3], row[3:6])
        F, Qs = ins.error_dynamics(state, sample, imu.dt, spec, clock)
        state = ins.mechanize(state, sample, imu.dt, spec.bias_tau)
        Phi = F @ Phi
        Q = F @ Q @ F.T + Qs
    return state, Phi, 0.5 * (Q + Q.T)


def gnss_models(s: Sensors) -> Iterable[tuple[str, object, np.ndarray]]:
    """(kind, one-platform model, z) of a frame's own GNSS: its position fix, then its
    pseudoranges."""
    if s.gnss is not None:
        g = s.gnss
        vertical = g.std if g.std_vertical is None else g.std_vertical
        yield "fix", PositionFix(LAYOUT, std=[g.std, g.std, vertical]), np.asarray(g.position, float)
    if s.pseudoranges is not None and len(s.pseudoranges.rho):
        p = s.pseudoranges
        yield "pseudoranges", Pseudorange(LAYOUT, p.sats, std=p.std), np.asarray(p.rho, float)


def keyed_relative(measurer: int, s: Sensors) -> Iterable[tuple[tuple[int, int, int, int], object, np.ndarray]]:
    """(key, two-platform model, z) of a frame's relative measurements, key = (measurer,
    target, kind, q) as in the module docstring."""
    for kind, items in ((RANGE, s.ranges), (RELPOS, s.relpos)):
        counts: dict[int, int] = {}
        for m in items:
            q = counts.get(m.target, 0)
            counts[m.target] = q + 1
            if kind == RANGE:
                yield (measurer, m.target, kind, q), Range(LAYOUT, std=m.std), np.array([m.range], float)
            else:
                yield (measurer, m.target, kind, q), RelativePosition(LAYOUT, std=m.std), np.asarray(m.z, float)


def _linear(model) -> bool:
    """A world-frame relative position: linear in the two members' position errors."""
    return isinstance(model, RelativePosition) and not model.body_frame


class JointEkf:
    """The joint error-state EKF of a changing set of UAS (module docstring).

    `ids` (sorted), `states` (aid -> nominal InsState) and `P` (16N x 16N, blocks in id order)
    are the filter; `nis` holds, after `update`, aid -> [(nis, dof), ...] of that tick's
    measurements taken by aid, in row order."""

    # World-frame relative positions in one information-form update (module docstring); False
    # sends them through the 8N-row batches like every other measurement (for benchmarks).
    linear_relpos: bool = True

    def __init__(self, imu: ImuSpec = ImuSpec(), clock: ClockSpec = ClockSpec()):
        self.imu, self.clock = imu, clock
        self.ids: list[int] = []
        self.states: dict[int, InsState] = {}
        self.P = np.zeros((0, 0))
        self.nis: dict[int, list[tuple[float, int]]] = {}

    def __contains__(self, aid: int) -> bool:
        return aid in self.states

    def __len__(self) -> int:
        return len(self.ids)

    def block(self, aid: int) -> slice:
        i = self.ids.index(aid)
        return slice(i * D, (i + 1) * D)

    def add(self, aid: int, x, P, clock_drift: float = 0.0) -> None:
        """Take UAS aid in from its own estimate (x in the uas-ins layout, P of its error
        state), uncorrelated with the members: it shared no measurement with them yet. A
        member is replaced."""
        x, P = np.asarray(x, float), np.asarray(P, float)
        if x.shape != (D,) or P.shape != (D, D):
            raise ValueError(f"UAS {aid}: x must be ({D},) and P ({D}, {D}), got {x.shape} and {P.shape}")
        if aid in self.states:
            self.remove(aid)
        ids = sorted(self.ids + [aid])
        # Old blocks move to their places in the new order; the new one starts uncorrelated.
        old = np.array([ids.index(a) * D + c for a in self.ids for c in range(D)], dtype=int)
        new = np.zeros((len(ids) * D,) * 2)
        new[np.ix_(old, old)] = self.P
        i = ids.index(aid) * D
        new[i:i + D, i:i + D] = 0.5 * (P + P.T)
        self.ids, self.P = ids, new
        self.states[aid] = UAS.unpack(x, clock_drift)

    def remove(self, aid: int) -> None:
        """Drop UAS aid: its block and its cross-covariances go (marginalising it out)."""
        b = self.block(aid)
        keep = np.r_[0:b.start, b.stop:self.P.shape[0]]
        self.P = self.P[np.ix_(keep, keep)]
        self.ids.remove(aid)
        del self.states[aid]

    def predict(self, imus: Mapping[int, ImuMsg | None]) -> None:
        """Time update (eqs. 10-12, the block-diagonal joint F) of every member in `imus` over
        its tick's samples. A member absent from `imus` is not propagated: it joined this tick
        with an estimate of this tick's time. An IMU message of None, or without samples, lets
        no time pass for its member, as EkfNode does."""
        steps = {i: transition(self.states[a], imus[a], self.imu, self.clock)
                 for i, a in enumerate(self.ids) if a in imus}
        P = self.P.copy()
        # Phi P Phi^T with Phi = diag(Phi_i): each block row by its Phi_i, then each block column.
        for i, (_, Phi, _) in steps.items():
            P[i * D:(i + 1) * D, :] = Phi @ P[i * D:(i + 1) * D, :]
        for i, (_, Phi, _) in steps.items():
            P[:, i * D:(i + 1) * D] = P[:, i * D:(i + 1) * D] @ Phi.T
        for i, (state, _, Q) in steps.items():
            P[i * D:(i + 1) * D, i * D:(i + 1) * D] += Q
            self.states[self.ids[i]] = state
        self.P = 0.5 * (P + P.T)

    def batches(self, frames: Mapping[int, Sensors]) -> list[list[tuple[int, list[int], object, np.ndarray]]]:
        """The tick's updates in processing order (module docstring), each a list of rows
        (measurer, indices of the members the model reads, model, z); no empty batch."""
        index = {a: i for i, a in enumerate(self.ids)}
        groups = [[(a, [index[a]], model, z) for a in self.ids if a in frames
                   for _, model, z in gnss_models(frames[a])]]
        for a in self.ids:
            if a in frames:
                rel = sorted(((key, model, z) for key, model, z in keyed_relative(a, frames[a])
                              if key[1] in index and key[1] != a), key=lambda r: r[0])
                groups.append([(a, [index[a], index[key[1]]], model, z) for key, model, z in rel])
        out, batch, rows = [groups[0]] if groups[0] else [], [], 0
        relative = [r for g in groups[1:] for r in g]
        if self.linear_relpos and relative and all(_linear(model) for _, _, model, _ in relative):
            return out + [relative]  # one information-form update (_update_linear), whatever its size
        for group in groups[1:]:
            batch += group
            rows += sum(len(z) for *_, z in group)
            if rows >= 8 * len(self.ids):
                out.append(batch)
                batch, rows = [], 0
        return out + ([batch] if batch else [])

    def update(self, frames: Mapping[int, Sensors]) -> dict[int, list[tuple[float, int]]]:
        """Measurement updates of the members with the tick's frames (eqs. 13-17, batched as
        the module docstring says); returns and keeps `nis`. Frames of non-members are
        ignored, and so are relative measurements to non-members."""
        self.nis = {a: [] for a in self.ids}
        for rows in self.batches(frames):
            if self.linear_relpos and all(_linear(model) for _, _, model, _ in rows) and len(rows[0][1]) == 2:
                self._update_linear(rows)
            else:
                self._update(rows)
        return self.nis

    def _update_linear(self, rows) -> None:
        """The update of a batch of world-frame relative positions, in information form on the
        members' positions. H reads positions only (-I at the measurer, I at the target), so with
        Y = H^T R^-1 H and b = H^T R^-1 nu, both 3N-sized, the Kalman update is

            dx = P[:, p] (I + Y P[p, p])^-1 b,   P+ = P - P[:, p] (I + Y P[p, p])^-1 Y P[p, :]

        (push-through identity: H^T (H P H^T + R)^-1 = (I + Y P_pp)^-1 H^T R^-1): a 3N system
        instead of one as large as the rows, 1140 of them at N = 20. The same update as the
        stacked EKF's to rounding. Each measurement's NIS is scored against its own block of
        the stacked S, H_r P H_r^T + R_r."""
        n = len(self.ids)
        pos = np.concatenate([np.arange(k * D, k * D + 3) for k in range(n)])
        p = np.stack([self.states[a].position for a in self.ids])
        # Vectorised over the rows (1140 at N = 20): a Python loop per row cost more than the solve.
        i, j = (np.array([r[1][t] for r in rows]) for t in (0, 1))
        R = np.stack([r[2].R for r in rows])
        Ri = np.linalg.inv(R)
        nu = np.stack([r[3] for r in rows]) - (p[j] - p[i])
        Y4 = np.zeros((n, n, 3, 3))  # block (measurer, target) of Y, summed in row order
        for u, v, sign in ((i, i, 1.0), (j, j, 1.0), (i, j, -1.0), (j, i, -1.0)):
            np.add.at(Y4, (u, v), sign * Ri)
        Y = Y4.transpose(0, 2, 1, 3).reshape(3 * n, 3 * n)
        Rnu = np.einsum("mab,mb->ma", Ri, nu)
        b = np.zeros((n, 3))
        np.add.at(b, i, -Rnu)
        np.add.at(b, j, Rnu)
        Ppp = self.P[np.ix_(pos, pos)]
        P4 = Ppp.reshape(n, 3, n, 3).transpose(0, 2, 1, 3)
        S = P4[i, i] + P4[j, j] - P4[i, j] - P4[j, i] + R
        S = 0.5 * (S + S.transpose(0, 2, 1))
        w = np.linalg.solve(np.linalg.cholesky(S), nu[..., None])[..., 0]  # as fusion.nis, per row
        nis = np.einsum("ma,ma->m", w, w)
        G = np.linalg.solve(np.eye(3 * n) + Y @ Ppp, np.column_stack([b.ravel(), Y]))
        Pxp = self.P[:, pos]
        dx = Pxp @ G[:, 0]
        P = self.P - Pxp @ G[:, 1:] @ Pxp.T
        self.P = 0.5 * (P + P.T)
        for r, value in zip(rows, nis):
            self.nis[r[0]].append((float(value), 3))
        for i, a in enumerate(self.ids):
            self.states[a] = ins.inject(self.states[a], dx[i * D:(i + 1) * D])

    def _update(self, rows) -> None:
        X = np.concatenate([UAS.pack(self.states[a]) for a in self.ids])
        hs, Hs = [], []
        for _, idx, model, _ in rows:
            h, H = model.joint(X, [i * D for i in idx])
            hs.append(h)
            Hs.append(H)
        z = np.concatenate([r[3] for r in rows])
        Rs = [r[2].R for r in rows]
        for j, (_, idx, model, _) in enumerate(rows):
            if isinstance(model, Range):
                # Second-order terms of the range (Range.second_order): without them a 2 cm
                # range against metres of cross-track uncertainty makes the EKF overconfident.
                a, b = (slice(i * D, i * D + 3) for i in idx)
                P_rel = self.P[a, a] + self.P[b, b] - self.P[a, b] - self.P[b, a]
                bias, var = model.second_order(X[a], X[b], P_rel)
                hs[j] = hs[j] + bias
                Rs[j] = Rs[j] + var
        R = np.zeros((sum(len(r) for r in Rs),) * 2)
        at = 0
        for r in Rs:  # block-diagonal, without scipy.linalg in a fusion-centre process
            R[at:at + len(r), at:at + len(r)] = r
            at += len(r)
        dx, self.P, nu, S = fusion.ekf_update(np.zeros(X.shape[0]), self.P, z, np.concatenate(hs), np.vstack(Hs), R)
        start = 0
        for (a, _, _, _), h in zip(rows, hs):
            own = slice(start, start + len(h))
            self.nis[a].append((fusion.nis(nu[own], S[own, own]), len(h)))
            start += len(h)
        for i, a in enumerate(self.ids):
            self.states[a] = ins.inject(self.states[a], dx[i * D:(i + 1) * D])

    def estimate(self, aid: int) -> tuple[np.ndarray, np.ndarray]:
        """Member aid's marginal: its nominal state in the uas-ins layout and its error covariance."""
        b = self.block(aid)
        return UAS.pack(self.states[aid]), self.P[b, b].copy()


class CentralizedEkf:
    """The offline reference "ekf-ccl": one JointEkf over every localized UAS of the scenario,
    fed every frame. A UAS joins at its first frame that carries an alignment (tick 0), from
    that alignment, and is not propagated with that frame's IMU: the alignment is the state at
    the frame's time. `nis` is the current tick's aid -> [(nis, dof), ...], which `estimate`
    carries too."""

    algorithm = "ekf-ccl"

    def __init__(self, ids: Iterable[int], imu: ImuSpec = ImuSpec(), clock: ClockSpec = ClockSpec()):
        self.ids = sorted(ids)
        self.joint = JointEkf(imu, clock)
        self.k = -1
        self.nis: dict[int, list[tuple[float, int]]] = {}

    @classmethod
    def from_scenario(cls, scenario, ids, settings=None):
        """The joint filter of the scenario's UAS and that of its planar-pose robots
        (swarmloc/estimators/ekf/pose.py), apart: the two never measure each other."""
        uas = cls([a for a in ids if scenario.agent(a).model == UAS.name], imu_spec(scenario))
        if not any(scenario.agent(a).model == "planar-pose" for a in ids):
            return uas
        from swarmloc.estimators.ekf.pose import PoseCentralizedEkf

        robots = PoseCentralizedEkf.from_scenario(scenario, ids, settings)
        return robots if not uas.ids else Apart([uas, robots])

    def step(self, frames: Mapping[int, Sensors]) -> None:
        """One tick: the members' time updates, then the tick's measurement updates."""
        joined = []
        for a in self.ids:
            if a not in self.joint:
                align = frames[a].align
                if align is None:
                    raise ValueError(f"UAS {a}: tick {frames[a].k} has no alignment to start from")
                self.joint.add(a, align.x, align.P)
                joined.append(a)
        self.joint.predict({a: frames[a].imu for a in self.ids if a not in joined})
        self.nis = self.joint.update({a: frames[a] for a in self.ids})
        self.k = frames[self.ids[0]].k if self.ids else self.k

    def estimate(self, aid: int) -> Estimate:
        x, P = self.joint.estimate(aid)
        return Estimate(self.k, x, P, tuple(self.nis.get(aid, ())))


class Apart:
    """Joint filters of parts of one swarm that never measure each other, stepped together."""

    algorithm = "ekf-ccl"

    def __init__(self, parts: list):
        self.parts = parts
        self.owner = {a: p for p in parts for a in p.ids}

    def step(self, frames: Mapping[int, Sensors]) -> None:
        for p in self.parts:
            p.step(frames)

    def estimate(self, aid: int) -> Estimate:
        return self.owner[aid].estimate(aid)


__all__ = ["JointEkf", "CentralizedEkf", "Apart", "transition", "keyed_relative", "gnss_models"]
