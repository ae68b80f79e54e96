"""EKF, EKF-CI and EKF-CCL on planar-pose robots: the configurations of "ekf", "ekf-ci" and
"ekf-ccl" for a swarm of unicycles (state [x, y, heading]) that read odometry and observe known
landmarks and each other by range and bearing (the MR.CLAM robots). ekf.py, ekf_ci.py and
ekf_ccl.py dispatch here on the agent's model.

One core, `PoseEkf`, an EKF over the stacked poses of a fixed set of robots, serves all three:
a node's own EKF is the core of one robot, EKF-CCL the core of the whole swarm.

- Time update: `PlanarPose.predict` on each robot's odometry, a block-diagonal F and Q.
- A landmark observation by robot a: `RangeBearing(planar_pose, other=planar, body_frame=True)`
  with the landmark as a platform whose state is its mapped position, known exactly (no
  columns in H, nothing added to R). An EKF update (Joseph form, fusion.ekf_update).
- An observation of robot b by robot a (EKF-CCL): the same model between the two pose blocks.

Every update is gated (kalman.Gate, the scenario's `estimation.gate`): its NIS against the
chi-square quantile of its 2 (or 2m) dimensions; a rejected one changes nothing and is counted
(`gate.rejected`, a node's stats["gated"]). Gate keys are (measurer, kind, target), as in
UKF-CCL and UKF-DCL (swarmloc.node.keyed_measurements).

EKF-CI (`PoseCiNode`). Every tick a node broadcasts a `PoseBeacon`: its pose estimate and
covariance stamped with the tick, before any fusion of that tick (as ekf_ci.CiNode does with its
`Beacon`), and its observations of other robots in that tick. Who observes it cannot be known
in advance (a camera's field of view), so it goes out every tick. An observation between i
and j is used at both ends: on j's beacon of the tick, node i fuses its own observations of j
and j's observations of i (the beacon's), all against the one estimate x_j ~ N(x_hat_j, P_j)
the beacon carries. Each is z = h(x_a, x_b) + v with (a, b) = (i, j) or (j, i); stacked and
linearised about (x_hat_i, x_hat_j):

    z - h(x_hat) = H_i (x_i - x_hat_i) + [H_j (x_j - x_hat_j) + v]

so z gives an estimate of H_i x_i, z_est = H_i x_hat_i + residual (bearings wrapped), whose
error is the bracket. Its two parts are not alike: v is this tick's sensor noise, independent
of both estimates, while the H_j term is correlated with x_hat_i by an unknown amount (j's
estimate may hold i's earlier beacons, i's may hold j's). So z_est is fused by split covariance
intersection (Julier and Uhlmann; Li et al.; `split_ci_update`): x_hat_i, wholly of unknown
correlation, inflated to P_i / omega, the dependent part to H_j P_j H_j^T / (1 - omega), R
(block-diagonal over the observations) taken as it is, then a Kalman update; omega minimises
the trace or the determinant of the result (`criterion`). Plain CI (fusion.ci_update) would
inflate R as well. Observations of i by j and of j by i in one tick give z_est with 4 rows on
3 states: their bearings meet in the relative heading, which neither gives alone. Each
observation enters each end once, with the estimate of the other end; both ends then hold v,
which later fusions treat as part of the neighbour's estimate, of unknown correlation. The
implied-position form of ekf_ci (RelativePosition.implied_position) does not fit here: the
position of i that z and p_j imply depends on i's own heading, which the bearing is measured
from. The gate reads nu^T (H_i P_i H_i^T + H_j P_j H_j^T + R)^-1 nu, the NIS as if the two
were independent. No NIS is recorded for a CI fusion (as in ekf_ci: its innovation has no
known covariance); the landmarks' are. Beacon bookkeeping is ekf_ci.CiNode's: an earlier
tick's beacon is stale, a later tick's is held until this node steps to it, one per neighbour
and tick; one with no observation between the two is counted (stats["unmeasured"]) and
otherwise ignored.

EKF-CCL (`PoseCentralizedEkf`): the core over every planar-pose robot, fed every frame; a
tick's observations are processed one EKF update each, in the key order of
swarmloc.node.keyed_measurements (measurer, kind, target, q): a measurer's robots
(RANGE_BEARING) before its landmarks, q counting the earlier observations of that kind and
target in its frame. Ranges, and observations of robots outside the swarm, are ignored. Each
NIS (its own update's S, 2 dof) is filed under the measurer, as ukf_ccl does. With the
setting odometry_bias each robot's block is PlanarPoseBias's [pose, speed scale, turn-rate
bias]; its estimate is the pose block.
"""

from __future__ import annotations

from collections import Counter
from typing import Mapping

import numpy as np

from swarmloc.estimators.ekf.common import (
    RejectedInput,
    beacon_timing,
    checked,
    checked_covariance,
    checked_std,
    guarded,
    release_held,
)
from swarmloc.filters import fusion, kalman, plausibility
from swarmloc.models.measurements import RangeBearing, StateLayout
from swarmloc.models.motion import MOTION_MODELS, Odometry, PlanarPoseBias
from swarmloc.node import LANDMARK, RANGE_BEARING, Estimate, Node, NodeSpec, Send, keyed_measurements, odometry_of
from swarmloc.wire.messages import PoseBeacon, RangeBearingMsg, Sensors

MODEL = MOTION_MODELS["planar-pose"]
LAYOUT = MODEL.layout
D = MODEL.state_dim
POINT = StateLayout.planar()  # a landmark, or a neighbour as its beacon gives it: a position only


def reading(msg: RangeBearingMsg) -> tuple[np.ndarray, list[float]]:
    """(z = [range, bearing], [range std, bearing std]) of an observation; RejectedInput if unusable."""
    z = checked([msg.range, msg.bearing], (2,), f"range-bearing to {msg.target}")
    return z, [checked_std(msg.range_std, "range std"), checked_std(msg.bearing_std, "bearing std")]


def landmark_rows(scenario) -> np.ndarray:
    """The scenario's landmark map as rows [id, x, y]: a NodeSpec value."""
    return np.array([[m.id, *m.position] for m in scenario.world.landmarks], float).reshape(-1, 3)


class PoseEkf:
    """An EKF over the stacked poses of the robots `ids` (sorted), blocks in id order.

    x, P: the joint state and covariance. landmarks: id -> position. Updates are gated by `gate`.
    model: each robot's motion model, planar-pose or its bias-augmented PlanarPoseBias (blocks of
    its state_dim; the pose leads each block)."""

    def __init__(self, x0: Mapping[int, np.ndarray], P0: Mapping[int, np.ndarray], landmarks, gate: kalman.Gate,
                 model=MODEL):
        self.model, self.d = model, model.state_dim
        self.ids = sorted(x0)
        self.start = {a: self.d * i for i, a in enumerate(self.ids)}
        self.x = np.concatenate([np.asarray(x0[a], float) for a in self.ids])
        self.P = kalman.block_diag([np.asarray(P0[a], float) for a in self.ids])
        self.landmarks = {int(i): np.array([px, py]) for i, px, py in np.reshape(landmarks, (-1, 3))}
        self.gate = gate

    def block(self, a: int) -> slice:
        return slice(self.start[a], self.start[a] + self.d)

    def predict(self, odometry: Mapping[int, Odometry], gaps: Mapping[int, np.ndarray] | None = None) -> None:
        """Time update of the robots in `odometry` (the others stay put, as no time passed for
        them); gaps: aid -> covariance added first, for ticks that robot's filter never saw."""
        n = len(self.x)
        x, F, Q, P = self.x.copy(), np.eye(n), np.zeros((n, n)), self.P.copy()
        for a, u in odometry.items():
            b = self.block(a)
            if gaps and a in gaps:
                P[b, b] += gaps[a]
            x[b], F[b, b], Q[b, b] = self.model.predict(x[b], u)
        self.x, self.P = kalman.predict(x, P, F, Q)
        self.P = 0.5 * (self.P + self.P.T)

    def observe_landmark(self, a: int, msg: RangeBearingMsg) -> tuple[float, int] | None:
        """Robot a's observation of a mapped landmark: (NIS, dof), or None if the gate rejected it."""
        z, std = reading(msg)
        if msg.target not in self.landmarks:
            raise RejectedInput("unknown-landmark", f"landmark {msg.target} is not on the map")
        model = RangeBearing(self.model.layout, std=std, other=POINT, body_frame=True)
        xa, mark = self.x[self.block(a)], self.landmarks[msg.target]
        H = np.zeros((2, len(self.x)))
        H[:, self.block(a)] = model.jacobians(xa, mark)[0]
        return self._update((a, LANDMARK, msg.target), model, z, model.h(xa, mark), H)

    def observe_robot(self, a: int, msg: RangeBearingMsg) -> tuple[float, int] | None:
        """Robot a's observation of robot msg.target, both in this filter: (NIS, dof) or None."""
        z, std = reading(msg)
        model = RangeBearing(self.model.layout, std=std, body_frame=True)
        h, H = model.joint(self.x, [self.start[a], self.start[msg.target]])
        return self._update((a, RANGE_BEARING, msg.target), model, z, h, H)

    def _update(self, key, model, z, h, H) -> tuple[float, int] | None:
        x, P, nu, S = fusion.ekf_update(self.x, self.P, z, h, H, model.R, model.residual)
        value = fusion.nis(nu, S)
        if not self.gate.admit(key, value, len(z)):
            return None
        self.x, self.P = x, P
        return value, len(z)


class PoseEkfNode(Node):
    """"ekf" on planar-pose: each robot's own EKF, nothing shared. A tick: the odometry time
    update (after inflating for ticks never seen, as il does), then the frame's landmark
    observations in frame order; observations of robots are ignored. `nis` holds the (NIS,
    dof) of this tick's admitted updates. A rejected input is counted in `drops`."""

    algorithm = "ekf"

    def __init__(self, aid, x0, P0, landmarks=(), gate: float | None = None, gate_open_after: int = 10):
        super().__init__(aid, x0, P0, MODEL)
        self.filter = PoseEkf({self.id: self.x}, {self.id: self.P}, landmarks, kalman.Gate(gate, gate_open_after))
        self.nis: list[tuple[float, int]] = []
        self.stats = {"landmark_updates": 0, "gated": 0, "gate_forced": 0}

    @classmethod
    def spec(cls, scenario, aid, settings=None) -> NodeSpec:
        if scenario.agent(aid).model != MODEL.name:
            raise ValueError(f"{cls.__name__} is for {MODEL.name} platforms; agent {aid} is "
                             f"{scenario.agent(aid).model}")
        x0, P0 = scenario.prior(aid)
        est = scenario.estimation
        return NodeSpec.of(cls, aid=aid, x0=x0, P0=P0, landmarks=landmark_rows(scenario), gate=est.gate,
                           gate_open_after=est.gate_open_after)

    def resume(self, k, x, P) -> None:
        super().resume(k, x, P)
        self.filter.x, self.filter.P = self.x.copy(), self.P.copy()

    def step(self, sensors: Sensors) -> list[Send]:
        if sensors.k <= self.k:
            return self.drop("stale-tick", f"sensors k={sensors.k} at k={self.k}")
        self.nis = []
        if sensors.odometry is not None:
            gap = self.missed_motion(sensors)
            self.filter.predict({self.id: odometry_of(sensors)}, None if gap is None else {self.id: gap})
        self.k = sensors.k
        for msg in sensors.landmarks:
            result = self._guard(f"landmark {msg.target}", self.filter.observe_landmark, self.id, msg)
            if result is not None:
                self.nis.append(result)
                self.stats["landmark_updates"] += 1
        self._sync()
        return []

    def _sync(self) -> None:
        self.x, self.P = self.filter.x, self.filter.P
        self.stats.update(gated=self.filter.gate.rejected, gate_forced=self.filter.gate.forced)

    def _guard(self, what: str, action, *args):
        """guarded(...); a gated update also returns None, and is counted by the gate."""
        return guarded(self, what, action, *args)


def split_ci_update(x: np.ndarray, P: np.ndarray, z_est: np.ndarray, Pz_dep: np.ndarray, Pz_ind: np.ndarray,
                    H: np.ndarray, criterion: str = "trace") -> tuple[np.ndarray, np.ndarray, float]:
    """Split covariance intersection of the state (x, P) with an estimate z_est of H x.

    (x, P) is wholly of unknown correlation with z_est; z_est's error is a part of unknown
    correlation (covariance Pz_dep) plus a part independent of everything (Pz_ind). The joint
    covariance is bounded by diag(P / w, Pz_dep / (1 - w) + Pz_ind) for every w in (0, 1]
    (Julier and Uhlmann's split CI with the own estimate all dependent), which a Kalman update
    then carries through: consistent for any cross-covariance, and unlike fusion.ci_update it
    does not inflate the independent part. w minimises trace or det of the result; w = 1
    returns (x, P) as copies. Returns (x+, P+, w)."""
    objective = fusion.objective(criterion)

    def fuse(w: float) -> tuple[np.ndarray, np.ndarray]:
        if w == 1.0:
            return x.copy(), P.copy()
        x_new, P_new, _, _ = fusion.ekf_update(x, P / w, z_est, H @ x, H, Pz_dep / (1.0 - w) + Pz_ind)
        return x_new, P_new

    # w = 0 would take z_est alone, which leaves what H does not observe unbounded.
    omega = fusion.best_omega(lambda w: np.inf if w == 0.0 else objective(fuse(w)[1]))
    return (*fuse(omega), omega)


class PoseCiNode(PoseEkfNode):
    """"ekf-ci" on planar-pose: PoseEkfNode plus a PoseBeacon every tick and the split
    covariance intersection, with each neighbour's beacon, of the observations between the two
    (module docstring)."""

    algorithm = "ekf-ci"

    def __init__(self, aid, x0, P0, landmarks=(), gate: float | None = None, gate_open_after: int = 10,
                 criterion: str = "trace"):
        super().__init__(aid, x0, P0, landmarks, gate, gate_open_after)
        if criterion not in fusion.CRITERIA:
            raise ValueError(f"criterion {criterion!r}: one of {fusion.CRITERIA}")
        self.criterion = criterion
        self.measured: dict[int, list[RangeBearingMsg]] = {}  # neighbour -> its observations in tick k
        self.heard: set[int] = set()
        self.held: list[tuple[int, PoseBeacon]] = []
        self.fused: list[tuple[int, float]] = []  # (neighbour, omega) of this tick's fusions, in order
        # seen_by: the neighbours' observations of this robot fused.
        self.stats.update({"fused": 0, "seen_by": 0, "unmeasured": 0, "held": 0})

    @classmethod
    def spec(cls, scenario, aid, settings=None) -> NodeSpec:
        return super().spec(scenario, aid).with_(criterion=getattr(settings, "criterion", "trace"))

    def resume(self, k, x, P) -> None:
        super().resume(k, x, P)
        self.measured, self.heard, self.fused = {}, set(), []
        self.held = [(src, b) for src, b in self.held if b.k > self.k]

    def step(self, sensors: Sensors) -> list[Send]:
        before = self.k
        out = super().step(sensors)
        if self.k == before:
            return out
        self.measured, self.heard, self.fused = {}, set(), []
        seen = []
        for msg in sensors.rb:
            if msg.target == self.id:
                self.drop("malformed", "an observation of itself")
            else:
                self.measured.setdefault(msg.target, []).append(msg)
                seen.append(msg)
        return out + [Send(PoseBeacon(self.k, self.x.copy(), self.P.copy(), seen), None)] + release_held(self)

    def receive(self, src, msg) -> list[Send]:
        if not isinstance(msg, PoseBeacon):
            return self.drop("unexpected-type", type(msg).__name__)
        early = beacon_timing(self, src, msg)
        if early is not None:
            return early
        try:
            x_j = checked(msg.pose, (D,), "beacon pose")
            P_j = checked_covariance(msg.cov, D, "beacon covariance")
        except RejectedInput as exc:
            return self.drop(exc.reason, f"from {src}: {exc.detail}")
        if src in self.heard:
            return self.drop("duplicate", f"beacon of tick {self.k} from {src}")
        self.heard.add(src)
        mine = self.measured.get(src, [])
        theirs = [m for m in msg.seen if isinstance(m, RangeBearingMsg) and m.target == self.id]
        if not mine and not theirs:
            self.stats["unmeasured"] += 1
            return []
        try:
            omega = self.fuse(src, mine, theirs, x_j, P_j)
        except RejectedInput as exc:
            return self.drop(exc.reason, f"observations between {src} and {self.id}: {exc.detail}")
        except (np.linalg.LinAlgError, ValueError) as exc:
            return self.drop("numerical", f"fusing {src}'s beacon: {exc}")
        if omega is not None:
            self.fused.append((src, omega))
            self.stats["fused"] += 1
            self.stats["seen_by"] += len(theirs)
        self._sync()
        return []

    def fuse(self, j: int, mine: list[RangeBearingMsg], theirs: list[RangeBearingMsg], x_j: np.ndarray,
             P_j: np.ndarray) -> float | None:
        """Split CI of this node's observations of j (`mine`) and j's of it (`theirs`) with j's
        beacon (module docstring): omega, or None if the gate rejected them."""
        x, P = self.filter.x, self.filter.P
        nus, His, Hjs, Rs = [], [], [], []
        rows = [(msg, x, x_j, False) for msg in mine] + [(msg, x_j, x, True) for msg in theirs]
        for msg, observer, target, by_j in rows:
            z, std = reading(msg)
            model = RangeBearing(LAYOUT, std=std, body_frame=True)
            Ha, Hb = model.jacobians(observer, target)
            nus.append(model.residual(z, model.h(observer, target)))
            His.append(Hb if by_j else Ha)
            Hjs.append(Ha if by_j else Hb)
            Rs.append(model.R)
        nu, Hi, Hj = np.concatenate(nus), np.vstack(His), np.vstack(Hjs)
        dep = Hj @ P_j @ Hj.T
        dep = 0.5 * (dep + dep.T)
        R = kalman.block_diag(Rs)
        S = Hi @ P @ Hi.T + dep + R
        # Before the gate, which stands open after a streak: a neighbour's pose (one member's
        # lie, issue 26 finding 7) that puts the innovation past the plausibility bound is
        # refused whatever the gate's state.
        if (why := plausibility.innovation(nu, S)) is not None:
            raise RejectedInput(why, f"NIS {fusion.nis(nu, S):.3g} from {j}'s beacon")
        if not self.filter.gate.admit((self.id, RANGE_BEARING, j), fusion.nis(nu, S), len(nu)):
            return None
        x_new, P_new, omega = split_ci_update(x, P, Hi @ x + nu, dep, R, Hi, self.criterion)
        if (why := plausibility.covariance(P_new)) is not None:
            raise RejectedInput(why, f"fusing {j}'s beacon")
        self.filter.x, self.filter.P = x_new, P_new
        return omega


class PoseCentralizedEkf:
    """"ekf-ccl" on planar-pose: one PoseEkf over every robot, fed every frame (module
    docstring). `nis`: this tick's aid -> [(NIS, dof), ...] of the observations aid made."""

    algorithm = "ekf-ccl"

    def __init__(self, x0: Mapping[int, np.ndarray], P0: Mapping[int, np.ndarray], landmarks=(),
                 gate: float | None = None, gate_open_after: int = 10, bias: PlanarPoseBias | None = None):
        if bias is not None:
            pairs = {a: bias.augment(x0[a], P0[a]) for a in x0}
            x0, P0 = {a: p[0] for a, p in pairs.items()}, {a: p[1] for a, p in pairs.items()}
        self.filter = PoseEkf(x0, P0, landmarks, kalman.Gate(gate, gate_open_after), bias or MODEL)
        self.ids = self.filter.ids
        self.k = -1
        self.nis: dict[int, list[tuple[float, int]]] = {}
        self.drops: Counter[str] = Counter()

    @classmethod
    def from_scenario(cls, scenario, ids, settings=None) -> "PoseCentralizedEkf":
        priors = {a: scenario.prior(a) for a in ids if scenario.agent(a).model == MODEL.name}
        est = scenario.estimation
        return cls({a: p[0] for a, p in priors.items()}, {a: p[1] for a, p in priors.items()},
                   landmark_rows(scenario), est.gate, est.gate_open_after, PlanarPoseBias.from_settings(settings))

    def observations(self, frames: Mapping[int, Sensors]) -> list[tuple[tuple[int, int, int, int], RangeBearingMsg]]:
        """The tick's usable observations, keyed (measurer, kind, target, q), in key order."""
        keyed = [(key, msg) for a in self.ids for key, msg in keyed_measurements(a, frames[a])
                 if key[1] == LANDMARK or (key[1] == RANGE_BEARING and key[2] != a and key[2] in self.filter.start)]
        return sorted(keyed, key=lambda o: o[0])

    def step(self, frames: Mapping[int, Sensors]) -> None:
        """One tick: every robot's odometry time update, then the tick's observations in key order."""
        self.filter.predict({a: odometry_of(frames[a]) for a in self.ids if frames[a].odometry is not None})
        self.k = frames[self.ids[0]].k if self.ids else self.k
        self.nis = {a: [] for a in self.ids}
        for (a, kind, _, _), msg in self.observations(frames):
            observe = self.filter.observe_landmark if kind == LANDMARK else self.filter.observe_robot
            try:
                result = observe(a, msg)
            except RejectedInput as exc:
                self.drops[exc.reason] += 1
                continue
            except np.linalg.LinAlgError:
                self.drops["numerical"] += 1
                continue
            if result is not None:
                self.nis[a].append(result)

    def estimate(self, aid: int) -> Estimate:
        s = self.filter.start[aid]
        b = slice(s, s + D)  # the pose: bias states, if any, are the filter's own
        return Estimate(self.k, self.filter.x[b].copy(), self.filter.P[b, b].copy(), tuple(self.nis.get(aid, ())))


__all__ = ["PoseEkf", "PoseEkfNode", "PoseCiNode", "PoseCentralizedEkf", "split_ci_update"]
