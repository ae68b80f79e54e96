"""The fusion centre of Goel, Kealy, Lohani 2016, section 3.3, as radio roles ("ekf-centre").

"The centralized Kalman filter runs at a central processing center where all the measurements
and observations from all the nodes (UASs) are received. After processing, the fusion center
transmits back the states of each of the UASs." Here the centre is a process on a ground station
(`FusionCentre`, running swarmloc.estimators.ekf.ccl.JointEkf) and every UAS runs a
`CentreClient`: its own INS/GNSS EKF (EkfNode), the fallback whenever the centre's answer does
not come, plus the exchange with the centre. The paper's weakness, the single point of failure
(its section 6), is what the fallback is for.

One tick k, seen from a UAS:

1. It steps its own filter on its frame (IMU, GNSS), then unicasts `CentreData(k, frame, x, P)`
   to the centre. x, P is its estimate *after* that step (its own estimate of tick k), sent only
   when its estimate did not come from the centre's answer for tick k-1, i.e. when the centre
   may not hold it: at the start, after a restart, after a tick without the centre's answer.
   Otherwise x = P = None. After the step, not before: its filter has then coasted over any
   ticks it missed and applied its own GNSS, so the centre can take it in at tick k without
   its history, and without propagating it.
2. The centre's `CentreEstimate(k, x, P)` for its current tick: adopted, the filter takes the
   centre's marginal. The answer for the previous tick, come after this tick's frame, is
   adopted late: taken as tick k-1's estimate, with this tick's own step done again on top
   (`late_adopted`). Anything older is counted `stale` and ignored. A NACK of its CentreData is
   counted `centre_unreachable`; the UAS carries on on its own.

`stats`: `centre_ticks` (ticks whose estimate is the centre's), `own_ticks` (ticks on its own
filter; a tick counts as its own until the centre's answer for it is adopted), `stale`, `late_adopted`,
`centre_unreachable`, `state_sent` (CentreData that carried x, P), plus EkfNode's counters.

The centre, for a tick k:

* Collects the tick's CentreData (the first valid one from each UAS). It runs the tick when data
  of tick k came from every UAS it expects, when its `wait` timer (set at the tick's first datum)
  fires, or when a datum of a later tick arrives (and, in lockstep, at the start of the next
  tick). Expected: the scenario's UAS during the first `forget_after` ticks after the centre's
  first datum, afterwards those it had a datum from in the last `forget_after` ticks; a UAS
  whose estimate the radio could not deliver (NACK) is not waited for until heard from again.
  Data of a tick already run, or skipped, are `late`: counted and dropped, but their UAS counts
  as heard from, so the centre waits for it next tick (else a UAS whose data always arrive
  after the others' would never be taken back in).
* Membership of the joint state: a member keeps its joint state only if the centre ran tick k-1
  with its data, so the joint state holds, for every member, every datum it sent, in a row. A
  member without data of tick k is removed (marginalised out) before the tick runs: without its
  IMU it cannot be propagated. A UAS that is not a member (new, restarted centre, back after
  missing ticks) is taken in from the x, P of its datum, uncorrelated with the members; without
  x, P it cannot be (counted `no_state`) and it gets no answer, so its next datum carries them.
  A member whose datum carries x, P anyway (the centre's answer for k-1 was lost on the way) is
  not replaced: the centre's state is the better one, built from the same data plus everyone
  else's, and keeps the cross-covariances.
* Runs the tick: members taken in this tick joined with their own estimate of tick k, so they
  are neither propagated nor updated with their own GNSS again; every other member is
  propagated with its IMU; then the joint update with every member's own GNSS and the relative
  measurements among members (ekf_ccl's order). Then each member gets its marginal,
  `CentreEstimate(k, x_i, P_i)`, unicast.

So with the centre up and every datum delivered in time, a UAS's estimates are those of the
offline reference (CentralizedEkf) on the same frames; the centre lost, they are its own EKF's;
the centre back (a new process with an empty state), it takes every UAS in from its x, P.

Lockstep: a timer fires at the start of the next tick, before the UAS step, so the answers of
a tick run on the timer reach every UAS after it has moved on: each adopts it late (above).
That happens while a UAS the centre expects is silent, i.e. for forget_after ticks after a UAS
goes out of the centre's reach (tests/test_fusion_centre.py shows it).

Determinism: the centre reads no clock; time reaches it only through its timer and the ticks of
the data. Given the same deliveries in the same order, it sends the same messages.

Robustness: nothing a peer sends makes a role raise. Malformed or implausible data (shapes,
non-finite values, stds outside [MIN_STD, MAX_ABS], magnitudes beyond `MAX_ABS`, IMU intervals
beyond `MAX_IMU_DT`, a covariance that is not symmetric positive semi-definite, a tick that
disagrees with its frame's) is dropped whole and counted in `drops`, so the centre never runs
on it; a tick whose arithmetic fails anyway leaves the joint state as it was before the tick,
counts `numerical` and sends nothing (its UAS fall back, and are taken in again next tick).
"""

from __future__ import annotations

import math

import numpy as np
from msgspec.structs import replace

from swarmloc.estimators.ekf.ccl import UAS, JointEkf
from swarmloc.estimators.ekf.common import (
    GROUND_STATION,
    RUN,
    RejectedInput,
    bounded,
    centre_id,
    checked,
    checked_covariance,
    plausible_std,
)
from swarmloc.estimators.ekf.local import EkfNode, imu_spec
from swarmloc.models import ins
from swarmloc.node import Idle, Node, NodeSpec, Send, Timer
from swarmloc.wire.messages import CentreData, CentreEstimate, Sensors

MAX_IMU_DT = 1.0
"""Longest IMU interval accepted (s): an IMU that samples less often than this is not one."""


def node_spec(scenario, aid: int, settings) -> NodeSpec:
    """The ekf-centre node of agent aid: the FusionCentre on the centre's ground station, a
    CentreClient on every uas-ins agent, an idle node (swarmloc.node.Idle) on any other ground station.
    settings: swarmloc.estimators.settings.CentreSettings."""
    centre = centre_id(scenario, settings)
    model = scenario.agent(aid).model
    if aid == centre:
        roster = [a.id for a in scenario.world.agents if a.model == UAS.name]
        return NodeSpec.of(FusionCentre, aid=aid, roster=roster, imu=imu_spec(scenario), wait=settings.wait,
                           forget_after=settings.forget_after)
    if model == UAS.name:
        return CentreClient.spec(scenario, aid).with_(centre=centre)
    if model == GROUND_STATION:
        return NodeSpec.of(Idle, aid=aid, algorithm=CentreClient.algorithm)
    raise ValueError(f"ekf-centre runs on {UAS.name} platforms; agent {aid} is {model}")


def check_state(x, P) -> tuple[np.ndarray, np.ndarray]:
    """A UAS estimate as it may enter a filter: x (16,), P its symmetric PSD error covariance,
    finite and bounded; RejectedInput otherwise."""
    x = bounded(checked(x, (ins.ERROR_DIM,), "x"), "x")
    P = bounded(checked_covariance(P, ins.ERROR_DIM, "P"), "P")
    return x, P


def check_frame(s: Sensors) -> None:
    """Everything of a UAS's frame the joint filter reads, checked as EkfNode checks its own
    inputs (swarmloc.estimators.ekf.local), plus the bounds above: one UAS's frame must not be able to
    break the arithmetic of the whole swarm's tick. RejectedInput otherwise."""
    if s.imu is not None:
        dt = float(s.imu.dt)
        if not (math.isfinite(dt) and 0.0 < dt <= MAX_IMU_DT):
            raise RejectedInput("malformed", f"imu dt {dt!r}")
        bounded(checked(s.imu.samples, (None, 6), "imu samples"), "imu samples")
    if s.gnss is not None:
        bounded(checked(s.gnss.position, (3,), "gnss position"), "gnss position")
        plausible_std(s.gnss.std, "gnss std")
        plausible_std(s.gnss.std_vertical, "gnss std_vertical", optional=True)
    if s.pseudoranges is not None:
        sats = bounded(checked(s.pseudoranges.sats, (None, 3), "pseudorange satellites"), "satellites")
        bounded(checked(s.pseudoranges.rho, (sats.shape[0],), "pseudoranges"), "pseudoranges")
        plausible_std(s.pseudoranges.std, "pseudorange std")
    for r in s.relpos:
        bounded(checked(r.z, (3,), "relpos z"), "relpos z")
        plausible_std(r.std, "relpos std")
    for r in s.ranges:
        bounded(checked(r.range, (), "range"), "range")
        plausible_std(r.std, "range std")


def _malformed(node: Node, exc: Exception, what: str) -> list:
    reason = exc.reason if isinstance(exc, RejectedInput) else "malformed"
    return node.drop(reason, f"{what}: {exc}")


class CentreClient(EkfNode):
    """A UAS of the fusion-centre estimator (module docstring): its own EkfNode, the centre's
    answer adopted when it comes in time."""

    algorithm = "ekf-centre"

    def __init__(self, aid, x0, P0, imu: ins.ImuSpec = ins.ImuSpec(), clock: ins.ClockSpec = ins.ClockSpec(),
                 centre: int | None = None):
        super().__init__(aid, x0, P0, imu, clock)
        self.centre = centre
        self.adopted: int | None = None  # tick of the centre's answer the filter holds, None: its own
        self.frame: Sensors | None = None  # this tick's frame: a late answer is adopted under it
        self.stats.update({"centre_ticks": 0, "own_ticks": 0, "stale": 0, "centre_unreachable": 0, "state_sent": 0,
                           "late_adopted": 0})

    def resume(self, k, x, P) -> None:
        super().resume(k, x, P)
        self.adopted = None

    def step(self, sensors: Sensors) -> list:
        before, adopted = self.k, self.adopted
        out = super().step(sensors)
        if self.k != sensors.k:  # refused as stale by EkfNode: nothing to tell the centre
            return out
        self.adopted, self.frame = None, sensors
        self.stats["own_ticks"] += 1
        if self.centre is None:
            return out
        # The centre holds our estimate of k-1 iff we hold its answer for k-1, unchanged since.
        held = adopted is not None and adopted == before == sensors.k - 1 and sensors.align is None
        x, P = (None, None) if held else (self.x.copy(), self.P.copy())
        self.stats["state_sent"] += x is not None
        return out + [Send(CentreData(sensors.k, sensors, x, P), dst=self.centre)]

    def receive(self, src: int, msg) -> list:
        if not isinstance(msg, CentreEstimate):
            return self.drop("unexpected", type(msg).__name__)
        if src != self.centre:
            return self.drop("not-centre", f"fc.estimate from {src}")
        try:
            x, P = check_state(msg.x, msg.P)
        except (RejectedInput, ValueError, TypeError) as exc:
            return _malformed(self, exc, "fc.estimate")
        if msg.k == self.k - 1 and self.adopted is None and self.frame is not None and self.frame.k == self.k:
            return self._adopt_late(msg.k, x, P)
        if msg.k < self.k or (msg.k == self.k and self.adopted == msg.k):
            self.stats["stale"] += 1
            return []
        if msg.k > self.k:
            return self.drop("future", f"fc.estimate k={msg.k} at k={self.k}")
        try:
            self.filter.set(x, P)
        except (RejectedInput, ValueError, TypeError) as exc:
            return _malformed(self, exc, "fc.estimate")
        self._sync()
        self.adopted = msg.k
        self.stats["centre_ticks"] += 1
        self.stats["own_ticks"] -= 1
        return []

    def _adopt_late(self, k: int, x, P) -> list:
        """The centre's answer for the previous tick, come after this tick's frame (in lockstep,
        a tick the centre ran on its timer while it waited for a silent UAS): take it as tick
        k-1's estimate and do this tick's own step again on top of it. The centre's solution one
        tick late is better than none; the centre keeps our state, so the next datum need not
        carry it, but sends it anyway (the centre ignores it: `state_ignored`)."""
        try:
            self.filter.set(x, P)
        except (RejectedInput, ValueError, TypeError) as exc:
            return _malformed(self, exc, "fc.estimate")
        self.k = k
        self._sync()
        EkfNode.step(self, self.frame)
        self.stats["late_adopted"] += 1
        return []

    def link_failed(self, dst: int, msg) -> list:
        if isinstance(msg, CentreData):
            self.stats["centre_unreachable"] += 1
        return []


class FusionCentre(Node):
    """The fusion centre on a ground station (module docstring). Its own estimate is empty
    (state_dim 0); `joint` is the joint filter, `joint_nis` its last tick's aid -> [(nis, dof)]
    (not `nis`: the drivers read a node's `nis` as its own estimate's),
    `stats` its counters: ticks_run, estimates_sent, joined, left, late, no_state,
    state_ignored, numerical, unreachable."""

    algorithm = "ekf-centre"

    def __init__(self, aid: int, roster, imu: ins.ImuSpec = ins.ImuSpec(), clock: ins.ClockSpec = ins.ClockSpec(),
                 wait: float = 0.05, forget_after: int = 20):
        super().__init__(aid, np.zeros(0), np.zeros((0, 0)), GROUND_STATION)
        self.roster = frozenset(int(a) for a in roster)
        self.wait, self.forget_after = float(wait), int(forget_after)
        self.joint = JointEkf(imu, clock)
        self.member_tick: dict[int, int] = {}  # tick of each member's joint state
        self.heard: dict[int, int] = {}  # tick of each UAS's last valid datum
        self.unreachable: set[int] = set()
        self.first: int | None = None  # tick of the first datum: the roster is expected from there
        self.pending: int | None = None
        self.data: dict[int, CentreData] = {}
        self.last_run = -1
        self.joint_nis: dict[int, list[tuple[float, int]]] = {}
        self.stats = {key: 0 for key in ("ticks_run", "estimates_sent", "joined", "left", "late", "no_state",
                                         "state_ignored", "numerical", "unreachable")}

    # ------------------------------------------------------------------ inputs

    def step(self, sensors) -> list:
        self.k = max(self.k, int(sensors.k))
        # Lockstep: a tick is over for everyone when the next starts, so nothing more will come.
        if self.synchronous and self.pending is not None and self.pending < sensors.k:
            return self._run()
        return []

    def on_timer(self, tag: str, t: float) -> list:
        return self._run() if tag == RUN and self.pending is not None else []

    def link_failed(self, dst: int, msg) -> list:
        if isinstance(msg, CentreEstimate):
            self.stats["unreachable"] += 1
            self.unreachable.add(dst)
        return []

    def receive(self, src: int, msg) -> list:
        if not isinstance(msg, CentreData):
            return self.drop("unexpected", type(msg).__name__)
        if src not in self.roster:
            return self.drop("unknown-sender", f"fc.data from {src}")
        try:
            if msg.sensors.k != msg.k:
                raise RejectedInput("malformed", f"frame of tick {msg.sensors.k} in data of tick {msg.k}")
            check_frame(msg.sensors)
            if (msg.x is None) != (msg.P is None):
                raise RejectedInput("malformed", "x without P or P without x")
            if msg.x is not None:
                check_state(msg.x, msg.P)
        except (RejectedInput, ValueError, TypeError) as exc:
            return _malformed(self, exc, f"fc.data from {src}")
        k = msg.k
        # Heard even if late: a UAS whose data came after its tick ran is waited for next tick,
        # or a UAS whose data always arrive last would never be taken back in.
        self.heard[src] = max(k, self.heard.get(src, k))
        self.unreachable.discard(src)
        if self.first is None:
            self.first = k
        if k <= self.last_run or (self.pending is not None and k < self.pending):
            self.stats["late"] += 1
            return []
        out = self._run() if self.pending is not None and k > self.pending else []
        if src in self.data:
            return out + self.drop("duplicate", f"fc.data k={k} from {src}")
        first_of_tick = self.pending is None
        self.pending = k
        self.data[src] = msg
        if self.expected(k) <= set(self.data):
            return out + self._run()
        return out + ([Timer(self.wait, RUN)] if first_of_tick else [])

    def expected(self, k: int) -> set[int]:
        """The UAS whose data of tick k the centre waits for (module docstring)."""
        start = self.first if self.first is not None else k
        return {a for a in self.roster
                if a not in self.unreachable and k - self.heard.get(a, start) <= self.forget_after}

    # ------------------------------------------------------------------ the tick

    def _run(self) -> list:
        k, data = self.pending, self.data
        self.pending, self.data = None, {}
        self.last_run = k
        j = self.joint
        saved = (list(j.ids), dict(j.states), j.P.copy(), dict(self.member_tick))
        try:
            # Overflow and the like are caught by the check below, not warned about.
            with np.errstate(all="ignore"):
                joined = self._members(k, data)
                j.predict({a: data[a].sensors.imu for a in j.ids if a not in joined})
                # A joiner's own GNSS of tick k is in the estimate it joined with already.
                frames = {a: replace(data[a].sensors, gnss=None, pseudoranges=None) if a in joined
                          else data[a].sensors for a in j.ids}
                self.joint_nis = j.update(frames)
            if not (np.isfinite(j.P).all() and all(np.isfinite(UAS.pack(s)).all() for s in j.states.values())):
                raise FloatingPointError("non-finite joint state")
        except (np.linalg.LinAlgError, FloatingPointError, ValueError) as exc:
            j.ids, j.states, j.P, self.member_tick = saved
            self.stats["numerical"] += 1
            self.joint_nis = {}
            return self.drop("numerical", f"tick {k}: {exc}")
        self.stats["ticks_run"] += 1
        out = []
        for a in j.ids:
            self.member_tick[a] = k
            x, P = j.estimate(a)
            out.append(Send(CentreEstimate(k, x, P), dst=a))
        self.stats["estimates_sent"] += len(out)
        return out

    def _members(self, k: int, data: dict[int, CentreData]) -> list[int]:
        """Membership for tick k (module docstring): members without data of k, or whose state
        is not of tick k-1, leave; UAS with data that are not members join from their x, P.
        Returns the joiners."""
        j = self.joint
        for a in list(j.ids):
            if a not in data or self.member_tick.get(a) != k - 1:
                j.remove(a)
                del self.member_tick[a]
                self.stats["left"] += 1
        joined = []
        for a in sorted(data):
            d = data[a]
            if a in j:
                self.stats["state_ignored"] += d.x is not None
            elif d.x is None:
                self.stats["no_state"] += 1
            else:
                j.add(a, d.x, d.P)
                joined.append(a)
        self.stats["joined"] += len(joined)
        return joined


__all__ = ["CentreClient", "FusionCentre", "node_spec", "check_state", "check_frame"]
