"""Distributed EKF-CI (Goel, Kealy, Lohani 2016, section 4): every UAS runs its own INS/GNSS
EKF (ekf.py) and fuses its neighbours' estimates, carried to itself through a relative-position
measurement, with covariance intersection, because it cannot know how correlated they are
with its own (they fused its estimate earlier, and it theirs).

Per tick k, at node i:

1. step: the local EKF (IMU, then GNSS). If the frame has relative-position measurements (a
   GNSS epoch), i broadcasts its position estimate and that estimate's covariance (a `Beacon`;
   computed before any fusion of tick k, so what it sends never echoes a neighbour's tick-k
   beacon back) and keeps its own measurements z_ij = p_j - p_i, keyed by j.
2. receive: the tick-k beacon (p_j, P_j) of each neighbour j that i measured gives the implied
   position of i, p_j - z_ij, with covariance P_j + R (eq. 19 and P_rel below it, through
   RelativePosition.implied_position). i fuses it into its own filter by covariance
   intersection, fusion.ci_update with H = the position rows (eq. 20): the Kalman update with
   P/w and P_rel/(1 - w) of eqs. 18 and 21, w minimising the trace (eq. 22) or the
   determinant of the fused covariance. As everywhere in ekf.py, the update is about the error
   state: the correction is injected into the nominal state.

CI inflates by 1/w what the position does not observe, and on the 16-state the two criteria
differ there (CiNode.fuse has the numbers): the trace, which adds m^2, (m/s)^2 and rad^2, is
held near w = 1 by the clock variance of a node without pseudoranges, so it fuses cautiously;
the determinant is unit-free and fuses more, with the clock, which it would inflate
geometrically, left out of the intersection (exactly: it is independent of the rest).

Only relative positions are fused: section 4 needs node i's position expressed explicitly
through j's state, which a single range (an implicit constraint) does not give. Ranges in a
frame are ignored. NIS is recorded for the EKF's own GNSS updates only: the innovation of a CI
fusion has no known covariance (that is the point of CI), so a NIS of it would mean nothing.

Beacons: one of an earlier tick is stale (dropped; the neighbour has moved on). One of a later
tick is held until this node steps to that tick: the radio may deliver a faster neighbour's
beacon before this node's own sensor frame. A neighbour's beacon is used at most once per tick;
a beacon from a neighbour this node did not measure is counted (`stats["unmeasured"]`) and
otherwise ignored. Fusions happen in the order the beacons arrive, so a node's result is
deterministic given the order of its deliveries.

`NaiveNode` is the same with the neighbour's estimate fused as if independent
(fusion.naive_fusion): the baseline whose overconfidence shows why CI exists.
"""

from __future__ import annotations

import numpy as np

from swarmloc.estimators.ekf.common import (
    RejectedInput,
    beacon_timing,
    checked,
    checked_covariance,
    checked_std,
    release_held,
)
from swarmloc.estimators.ekf.local import DIM, LAYOUT, EkfNode
from swarmloc.filters import fusion, plausibility
from swarmloc.models import ins
from swarmloc.models.measurements import RelativePosition, StateLayout
from swarmloc.node import NodeSpec, Send
from swarmloc.wire.messages import Beacon

POSITION_ONLY = StateLayout(3, slice(0, 3))  # what a beacon carries of the neighbour's state
H_POSITION = LAYOUT.position_matrix()  # eq. 20


class CiNode(EkfNode):
    algorithm = "ekf-ci"

    def __init__(self, aid, x0, P0, imu: ins.ImuSpec = ins.ImuSpec(), clock: ins.ClockSpec = ins.ClockSpec(),
                 criterion: str = "trace"):
        super().__init__(aid, x0, P0, imu, clock)
        if criterion not in ("trace", "det"):
            raise ValueError(f"criterion {criterion!r}: trace or det")
        self.criterion = criterion
        self.measured: dict[int, tuple[np.ndarray, float]] = {}  # target -> (z = p_target - p_me, std), tick k
        self.heard: set[int] = set()  # neighbours whose tick-k beacon arrived
        self.held: list[tuple[int, Beacon]] = []  # beacons of later ticks, in arrival order
        self.fused: list[tuple[int, float]] = []  # (neighbour, omega) of this tick's fusions, in order
        self.stats.update({"fused": 0, "unmeasured": 0, "held": 0})

    @classmethod
    def spec(cls, scenario, aid, settings=None) -> NodeSpec:
        return super().spec(scenario, aid).with_(criterion=getattr(settings, "criterion", "trace"))

    def resume(self, k, x, P) -> None:
        super().resume(k, x, P)
        self.measured, self.heard, self.fused = {}, set(), []
        self.held = [(src, b) for src, b in self.held if b.k > self.k]

    # ------------------------------------------------------------------ tick

    def step(self, sensors) -> list[Send]:
        before = self.k
        out = super().step(sensors)
        if self.k == before:
            return out  # a stale frame, dropped by the EKF step
        self.measured, self.heard, self.fused = {}, set(), []
        for r in sensors.relpos:
            try:
                z = checked(r.z, (3,), "relpos z")
                std = checked_std(r.std, "relpos std")
            except RejectedInput as exc:
                self.drop(exc.reason, f"relpos to {r.target}: {exc.detail}")
                continue
            if r.target == self.id:
                self.drop("malformed", "relpos to itself")
            elif r.target in self.measured:
                self.drop("duplicate", f"second relpos to {r.target} in tick {self.k}")  # its beacon is used once
            else:
                self.measured[r.target] = (z, std)
        if sensors.relpos:
            out = out + [Send(Beacon(self.k, self.filter.position(), self.filter.position_cov(), {}), None)]
        return out + release_held(self)

    # ------------------------------------------------------------------ radio

    def receive(self, src, msg) -> list[Send]:
        if not isinstance(msg, Beacon):
            return self.drop("unexpected-type", type(msg).__name__)
        early = beacon_timing(self, src, msg)
        if early is not None:
            return early
        try:
            p_j = checked(msg.position, (3,), "beacon position")
            P_j = checked_covariance(msg.cov, 3, "beacon covariance")
        except RejectedInput as exc:
            return self.drop(exc.reason, f"from {src}: {exc.detail}")
        if src in self.heard:
            return self.drop("duplicate", f"beacon of tick {self.k} from {src}")
        self.heard.add(src)
        if src not in self.measured:
            self.stats["unmeasured"] += 1
            return []
        z, std = self.measured[src]
        # i = a (this node), j = b (the neighbour, of which the beacon gives the position only).
        rel = RelativePosition(LAYOUT, std=std, other=POSITION_ONLY)
        p_i, P_i = rel.implied_position(p_j, P_j, z, known="b")
        dz = p_i - self.filter.state.position
        # One member's lie (issue 26, finding 7): an implied position past the plausibility
        # bound against our own, or a fusion that leaves no covariance, touches nothing.
        S = self.filter.position_cov() + P_i
        if (why := plausibility.innovation(dz, S)) is not None:
            return self.drop(why, f"{src}'s beacon implies a position {np.linalg.norm(dz):.3g} m off")
        try:
            dx, P, omega = self.fuse(dz, P_i)
            # Nor a fusion that moves our position further than the same bound in S's metric
            # (small omega can take nearly all of the innovation): at most
            # plausibility.step_bound(S, 3) metres per beacon.
            if (why := plausibility.covariance(P) or plausibility.shift(H_POSITION @ dx, S)) is not None:
                return self.drop(why, f"fusing {src}'s beacon")
            self.filter.correct(dx, P)
        except (np.linalg.LinAlgError, ValueError) as exc:
            return self.drop("numerical", f"fusing {src}'s beacon: {exc}")
        self.fused.append((src, omega))
        self.stats["fused"] += 1
        self._sync()
        return []

    def fuse(self, dz: np.ndarray, Pz: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """The error-state correction from an implied position: dz = implied - nominal position,
        an estimate of H dx with covariance Pz. Returns (dx, P+, omega).

        CI multiplies the covariance of whatever the measurement does not observe by 1/omega.
        A component whose error is uncorrelated with every other (P row exactly zero off the
        diagonal) and not measured gets no correction and, never having been in a beacon, is
        not correlated with the neighbour's estimate either, so its variance needs no
        inflation: leaving it out of the intersection stays consistent. In practice that is
        the clock bias of a node without pseudoranges.

        Only the "det" criterion leaves it out. The determinant does not care about scale, so
        nothing stops omega < 1 at every fusion and the clock variance would grow
        geometrically (measured on the two-UAS flight of tests/test_ekf_nodes.py, GNSS on one:
        x1.08 per epoch, a 300 m std after 120 s). The trace is the paper's eq. 22 over the whole 16-state, as written;
        there the clock must stay in: its variance, in m^2 and growing, is what holds omega
        near 1. Without it the trace, dominated by the position's m^2, does not see the
        attitude's rad^2, and omega inflates the attitude covariance at every fusion until the
        heading is lost (measured: an 85 deg attitude error, a 270 deg std after 120 s).
        """
        P = self.filter.P
        if self.criterion == "trace":
            return fusion.ci_update(np.zeros(DIM), P, dz, Pz, H_POSITION, "trace")
        keep = coupled(P, H_POSITION)
        sub = np.ix_(keep, keep)
        dx_k, P_k, omega = fusion.ci_update(np.zeros(len(keep)), P[sub], dz, Pz, H_POSITION[:, keep],
                                            self.criterion)
        dx, P_new = np.zeros(DIM), P.copy()
        dx[keep], P_new[sub] = dx_k, P_k
        return dx, P_new, omega


def coupled(P: np.ndarray, H: np.ndarray) -> np.ndarray:
    """Indices of the state components the fusion involves: every one except those neither
    measured (H column zero) nor correlated with any other (P row zero off the diagonal)."""
    off = P.copy()
    np.fill_diagonal(off, 0.0)
    alone = ~np.any(off != 0.0, axis=1) & ~np.any(H != 0.0, axis=0)
    return np.flatnonzero(~alone)


class NaiveNode(CiNode):
    """EKF-CI without the CI: the neighbour's implied position is fused by a plain Kalman
    update, as if it were independent of this node's estimate. It is not (the neighbour's
    estimate already holds this node's earlier ones), so the covariance shrinks faster than the
    error does."""

    algorithm = "ekf-naive"

    def fuse(self, dz, Pz):
        dx, P = fusion.naive_fusion(np.zeros(DIM), self.filter.P, dz, Pz, H_POSITION)
        return dx, P, float("nan")
