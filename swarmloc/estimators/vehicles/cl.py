"""Cooperative localization of quadrotors and ground robots in closed loop (Oliveros &
Ashrafiuon 2023), as radio roles.

Four estimators, all on the vehicle filters of swarmloc/estimators/vehicles/filters.py:

* ``ekf-cl``, the paper's centralized EKF (section 5) in the fusion-centre role. Every vehicle
  runs a `VehicleClient`: its own EKF (propagation with the command in force, IMU orientation,
  GPS), the fallback whenever the centre's answer does not come, and each tick it unicasts
  `fc.data` (its frame; its own x, P when the centre may not hold it) to the centre. The
  `VehicleCentre` on a ground station runs the joint EKF over every member's state, of mixed
  sizes (propagation eq. 44, the relative positions of section 4 with their cross-covariances,
  eqs. 45-47), and unicasts each member its marginal (`fc.estimate`). Membership follows
  swarmloc/estimators/ekf/centre.py: a vehicle is taken in from its own x, P, uncorrelated; a
  member leaves (marginalised) unless the previous tick ran with its data; the centre runs a tick when every
  expected vehicle's data came, on a later tick's datum, or on its timer.
* ``ekf-local``, cooperative localization without CL (the paper's "without CL" runs): each vehicle
  alone, and a relative position measured to a target is fused against the target's own estimate
  of the tick, which every vehicle broadcasts (`veh.pose`) after its own sensors and before any
  relative measurement of the tick; the target's covariance enters the innovation, the
  correlation between the two estimates is ignored.
* ``ekf-ci`` on vehicles (`CiVehicleNode`): the same exchange, each relative position fused by
  covariance intersection instead, consistent whatever the two estimates share.
* ``raw`` (`RawNode`), the paper's closed loop "without CL": each controller fed the raw
  measurements of the pose (GPS, or a relative position chained from the target's raw position;
  the IMU's orientation), its own EKF only for the velocities and rates.

Closed loop (`world.control: agents`): every vehicle node holds the controller of
swarmloc/models/vehicles.py and `command()` gives the command from its current estimate. Asked again in
the same tick (the daemon publishes after each batch of inputs) it starts again from the
controller's state after the previous tick, so the last command of a tick depends only on the
final estimate, as the in-process runner computes it.

Nothing a peer sends makes a node raise: malformed or implausible data are dropped and counted.
"""

from __future__ import annotations

import copy
import math

import numpy as np

from swarmloc.estimators.ekf.common import (
    GROUND_STATION,
    RUN,
    RejectedInput,
    beacon_timing,
    bounded,
    centre_id,
    checked,
    checked_covariance,
    plausible_std,
    release_held,
)
from swarmloc.estimators.vehicles.filters import JointVehicleEkf, VehicleEkf
from swarmloc.filters import plausibility
from swarmloc.models.motion import VEHICLES
from swarmloc.models.vehicles import MODELS, CircleReference, actuator_std, controller_for
from swarmloc.node import Idle, Node, NodeSpec, Send, Timer
from swarmloc.wire.messages import CentreData, CentreEstimate, Command, Sensors, VehiclePose


def check_frame(s: Sensors, model, models: dict[int, object]) -> None:
    """Everything of a vehicle's frame a filter reads, checked (RejectedInput otherwise):
    shapes for its model, finite and bounded numbers, relative positions of known vehicles."""
    v = s.vehicle
    if v is None:
        raise RejectedInput("malformed", "a vehicle frame without its `vehicle` readings")
    if not (math.isfinite(v.dt) and 0.0 <= v.dt <= 1.0):
        raise RejectedInput("malformed", f"vehicle dt {v.dt!r}")
    bounded(checked(v.u, (model.input_dim,), "command u"), "command u")
    bounded(checked(v.attitude, (model.orientation_dim,), "attitude"), "attitude")
    plausible_std(v.attitude_std, "attitude std")
    for r in v.seen:
        if r.target not in models:
            raise RejectedInput("unknown-target", f"relative position of {r.target}, not a vehicle of the swarm")
        bounded(checked(r.z, (3,), "relpos z"), "relpos z")
        plausible_std(r.std, "relpos std")
    if s.gnss is not None:
        bounded(checked(s.gnss.position, (3,), "gps position"), "gps position")
        plausible_std(s.gnss.std, "gps std")


def check_state(x, P, n: int) -> tuple[np.ndarray, np.ndarray]:
    return bounded(checked(x, (n,), "x"), "x"), bounded(checked_covariance(P, n, "P"), "P")


class VehicleNode(Node):
    """A vehicle's own EKF and, in closed loop, its controller: what both estimators share."""

    algorithm = ""

    def __init__(self, aid, x0, P0, model: str, actuator_std, roster=(), reference: CircleReference | None = None,
                 dt: float = 0.02, process_q: float | None = None, attitude_std: float | None = None):
        super().__init__(aid, x0, P0, model)
        # The orientation std the filter assumes; None: the one the IMU reports with its reading.
        self.attitude_std = attitude_std
        self.dyn = MODELS[model]
        self.actuator_std = np.asarray(actuator_std, float)
        self.filter = VehicleEkf(self.dyn, self.x, self.P, self.actuator_std, q=process_q)
        # Every vehicle of the swarm by id: a relative position names its target's model.
        self.models = {int(a): MODELS[m] for a, m in roster}
        self.models.setdefault(self.id, self.dyn)
        self.dt = float(dt)
        self.t = 0.0
        self.nis: list[tuple[float, int]] = []
        self.stats = {"gps_updates": 0, "attitude_updates": 0, "relpos_updates": 0, "coasted_ticks": 0}
        self.reference = reference
        self._ctrl_base = None if reference is None else controller_for(self.dyn, reference)
        self._ctrl_last = None
        self._ctrl_k: int | None = None

    @classmethod
    def spec(cls, scenario, aid, settings=None) -> NodeSpec:
        return vehicle_spec(cls, scenario, aid)

    def _sync(self) -> None:
        self.x, self.P = self.filter.x.copy(), self.filter.P.copy()

    def resume(self, k, x, P) -> None:
        self.filter.x, self.filter.P = np.array(x, float), np.array(P, float)
        self.k = int(k)
        self._sync()

    def _guard(self, what: str, update, *args):
        """One filter input: its NIS, or None if refused (counted); the filter is unchanged then."""
        x, P = self.filter.x.copy(), self.filter.P.copy()
        try:
            nis = update(*args)
        except RejectedInput as exc:
            self.drop(exc.reason, f"{what}: {exc.detail}")
            return None
        except (np.linalg.LinAlgError, ValueError, FloatingPointError) as exc:
            self.filter.x, self.filter.P = x, P
            self.drop("numerical", f"{what}: {exc}")
            return None
        if not (np.isfinite(self.filter.x).all() and np.isfinite(self.filter.P).all()):
            self.filter.x, self.filter.P = x, P
            self.drop("numerical", f"{what}: non-finite result")
            return None
        return nis

    def own_step(self, s: Sensors) -> bool:
        """Time update with the command in force (coasting over missed ticks on it), then the
        IMU's orientation and a GPS fix. False if the frame was refused (nothing changed)."""
        if s.k <= self.k:
            self.drop("stale-tick", f"sensors k={s.k} at k={self.k}")
            return False
        try:
            check_frame(s, self.dyn, self.models)
        except RejectedInput as exc:
            self.drop(exc.reason, exc.detail)
            return False
        self.nis = []
        v = s.vehicle
        missed = s.k - self.k - 1 if self.k >= 0 else 0
        self.k, self.t = s.k, float(s.t)
        if v.dt > 0:
            steps = [v.dt] * (1 + missed)
            self.stats["coasted_ticks"] += missed
            for dt in steps:
                self._guard("predict", self.filter.predict, v.u, dt)
        att_std = v.attitude_std if self.attitude_std is None else self.attitude_std
        if (nis := self._guard("attitude", self.filter.update_attitude, v.attitude, att_std)) is not None:
            self.nis.append((nis, self.dyn.orientation_dim))
            self.stats["attitude_updates"] += 1
        if s.gnss is not None and (nis := self._guard("gps", self.filter.update_gps, s.gnss.position, s.gnss.std)) is not None:
            self.nis.append((nis, 3))
            self.stats["gps_updates"] += 1
        self._sync()
        return True

    def command(self):
        if self._ctrl_base is None or self.k < 0:
            return None
        if self.k != self._ctrl_k:
            if self._ctrl_last is not None:
                self._ctrl_base = self._ctrl_last
            self._ctrl_k = self.k
        ctrl = copy.deepcopy(self._ctrl_base)
        u = ctrl.command(self.x, self.t, self.dt)
        self._ctrl_last = ctrl
        return Command(self.k, np.asarray(u, float))

    def estimate(self):
        from swarmloc.node import Estimate

        return Estimate(self.k, self.x.copy(), self.P.copy(), tuple(self.nis))


def roster_of(scenario) -> list[tuple[int, str]]:
    """Every vehicle of the swarm as (id, model): a node spec holds no maps."""
    return sorted((a.id, a.model) for a in scenario.world.agents if a.model in VEHICLES)


def vehicle_spec(cls, scenario, aid: int, **extra) -> NodeSpec:
    """The node spec of vehicle aid: prior, model, actuator noise, the roster, and in closed
    loop (`world.control: agents`) the reference its controller tracks."""
    spec = scenario.agent(aid)
    if spec.model not in VEHICLES:
        raise ValueError(f"{cls.algorithm} runs on {list(VEHICLES)}; agent {aid} is {spec.model}")
    x0, P0 = scenario.prior(aid)
    cfg = scenario.sensors.vehicle
    dyn = MODELS[spec.model]
    noise = actuator_std(dyn, cfg.force_noise, cfg.moment_noise)
    reference = CircleReference(**spec.reference_params()) if scenario.world.control == "agents" else None
    return NodeSpec.of(cls, aid=aid, x0=x0, P0=P0, model=spec.model, actuator_std=noise, roster=roster_of(scenario),
                       reference=reference, dt=scenario.clock.dt, process_q=scenario.estimation.process_noise,
                       attitude_std=scenario.estimation.attitude_std, **extra)


# ------------------------------------------------------------------------ ekf-local (no CL)


class LocalNode(VehicleNode):
    """``ekf-local``: each vehicle alone; relative positions fused against the targets' broadcast
    estimates of the tick (module docstring)."""

    algorithm = "ekf-local"
    ci = False  # CiVehicleNode: fuse by covariance intersection instead

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.pending: list = []  # this tick's relative positions whose target's pose has not come
        # Poses of ticks this node has not reached: held until it steps there. In lockstep a
        # pose only comes within its tick; in real time (a companion computer on the swarm
        # clock) a peer whose flight controller's samples come a little earlier steps first.
        self.held: list = []
        self.stats.update({"no_anchor": 0, "held": 0})

    def resume(self, k, x, P) -> None:
        super().resume(k, x, P)
        self.held = [(src, m) for src, m in self.held if m.k > self.k]

    def step(self, sensors: Sensors) -> list[Send]:
        for _ in self.pending:
            self.stats["no_anchor"] += 1  # the target's pose of that tick never came
        self.pending = []
        if not self.own_step(sensors):
            return []
        self.pending = list(sensors.vehicle.seen)
        # The pose goes out before this tick's relative measurements, so what a vehicle fuses
        # never includes anything derived from itself in the same tick.
        return [Send(VehiclePose(self.k, self.x.copy(), self.P.copy()))] + release_held(self)

    def _sender_state(self, src: int, msg: VehiclePose):
        """A neighbour's vehicle model, and its pose's state and covariance checked against it."""
        model = self.models.get(src)
        if model is None:
            raise RejectedInput("unknown-sender", str(src))
        return (model, *check_state(msg.x, msg.P, model.state_dim))

    def receive(self, src, msg) -> list[Send]:
        if not isinstance(msg, VehiclePose):
            return self.drop("unexpected", type(msg).__name__)
        early = beacon_timing(self, src, msg)  # stale: dropped; of a later tick: held
        if early is not None:
            return early
        try:
            model, xt, Pt = self._sender_state(src, msg)
        except RejectedInput as exc:
            return self.drop(exc.reason, exc.detail)
        for r in [r for r in self.pending if r.target == src]:
            self.pending.remove(r)
            if self.ci:
                got = self._guard("relpos", self.filter.update_relpos_ci, r.z, r.std, model, xt, Pt, self.criterion)
                nis = None if got is None or got[1] >= 1.0 else got[0]
            else:
                nis = self._guard("relpos", self.filter.update_relpos_anchor, r.z, r.std, model, xt, Pt)
            if nis is not None:
                self.nis.append((nis, 3))
                self.stats["relpos_updates"] += 1
        self._sync()
        return []


class CiVehicleNode(LocalNode):
    """``ekf-ci`` on quadrotors and ground robots: as ``ekf-local``, but a relative position is
    fused against the target's pose by covariance intersection (VehicleEkf.update_relpos_ci),
    which stays consistent whatever the two estimates share."""

    algorithm = "ekf-ci"
    ci = True

    def __init__(self, *args, criterion: str = "det", **kwargs):
        super().__init__(*args, **kwargs)
        if criterion not in ("trace", "det"):
            raise ValueError(f"criterion {criterion!r}: trace or det")
        self.criterion = criterion


class RawNode(LocalNode):
    """``raw``: the paper's closed loop "without CL" (section 6.3): each controller fed the raw
    measurements of its vehicle's pose, not a cooperative estimate.

    * Orientation: the IMU's reading, as it comes (a quaternion normalised, a yaw).
    * Position: the vehicle's GPS fix when it has one; otherwise the position its relative
      measurement gives from its target's raw position, r_b = r_t - R(q_b) z, with q_b the raw
      orientation (section 6.3.1: vehicles without GPS "exclusively receive relative position
      measurements"); otherwise, measuring nobody with a raw position this tick, its own EKF's
      (dead reckoning on its commands: what a leader does in a GPS outage).
    * Velocities and rates, which no sensor gives: its own EKF, which takes the GPS fix and each
      relative position against the target's raw pose (as ``ekf-local`` does against the
      target's estimate).

    A vehicle broadcasts its raw pose (`veh.pose`) once per tick, as soon as it has it: at once
    with a fix or measuring nobody, else when its first target's pose arrives, so a chain
    1 -> 2 -> 3 -> 4 resolves within the tick (a round of the radio per link). A vehicle in a
    measurement cycle without a fix never hears a raw pose and reports its own EKF's position.

    Covariance reported (for NEES, and for a base's update): the raw position's, first order and
    uncorrelated with the rest: a fix's std^2 I; from a target, its raw position covariance plus
    R Sz R^T plus J So J^T (J the derivative of R(q) z in the orientation, So the IMU's); the raw
    orientation's std^2 I; the EKF's blocks for the rest."""

    algorithm = "raw"

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.raw: tuple[np.ndarray, np.ndarray] | None = None  # this tick's raw (position, its covariance)
        self.attitude: tuple[np.ndarray, float] | None = None  # this tick's IMU reading and its std
        self.sent = False
        self.stats.update({"raw_gps": 0, "raw_chain": 0, "raw_none": 0})

    def step(self, sensors: Sensors) -> list[Send]:
        for _ in self.pending:
            self.stats["no_anchor"] += 1
        self.pending, self.raw, self.sent, self.attitude = [], None, False, None
        if not self.own_step(sensors):
            return []
        v = sensors.vehicle
        z = np.asarray(v.attitude, float)
        if self.dyn.orientation_dim == 4:
            z = z / np.linalg.norm(z) if np.linalg.norm(z) > 0 else self.dyn.orientation(self.filter.x)
        self.attitude = (z, float(np.max(np.atleast_1d(v.attitude_std))))
        if sensors.gnss is not None:
            std = float(np.max(np.atleast_1d(sensors.gnss.std)))
            self.raw = (np.asarray(sensors.gnss.position, float).copy(), std * std * np.eye(3))
            self.stats["raw_gps"] += 1
        self.pending = list(v.seen)
        self._compose()
        if self.raw is not None or not self.pending:
            return self._announce()
        return []

    def _announce(self) -> list[Send]:
        if self.sent:
            return []
        self.sent = True
        if self.raw is None:
            self.stats["raw_none"] += 1
        return [Send(VehiclePose(self.k, self.x.copy(), self.P.copy()))]

    def _compose(self) -> None:
        """x, P: the EKF's, with the raw orientation and (if any) raw position put in their place."""
        x, P = self.filter.x.copy(), self.filter.P.copy()
        o = self.dyn._orientation_slice
        z, std = self.attitude
        x[o] = z
        P[o, :], P[:, o] = 0.0, 0.0
        P[o, o] = std * std * np.eye(self.dyn.orientation_dim)
        if self.raw is not None:
            r, C = self.raw
            x[:3] = r
            P[:3, :], P[:, :3] = 0.0, 0.0
            P[:3, :3] = C
        self.x, self.P = x, P

    def receive(self, src, msg) -> list[Send]:
        if not isinstance(msg, VehiclePose):
            return self.drop("unexpected", type(msg).__name__)
        if msg.k != self.k:
            return self.drop("stale", f"pose of tick {msg.k} at {self.k}")
        try:
            model, xt, Pt = self._sender_state(src, msg)
        except RejectedInput as exc:
            return self.drop(exc.reason, exc.detail)
        if self.attitude is None:
            return []  # no frame of this tick taken yet: nothing to anchor
        mine = [r for r in self.pending if r.target == src]
        for r in mine:
            self.pending.remove(r)
            if (nis := self._guard("relpos", self.filter.update_relpos_anchor, r.z, r.std, model, xt, Pt)) is not None:
                self.nis.append((nis, 3))
                self.stats["relpos_updates"] += 1
            if self.raw is None:
                self.raw = self._from_target(r, xt, Pt)
                self.stats["raw_chain"] += 1
        self._compose()
        return self._announce() if mine and self.raw is not None else []

    def _from_target(self, r, xt, Pt) -> tuple[np.ndarray, np.ndarray]:
        """r_b = r_t - R(q_b) z and its first-order covariance (class docstring)."""
        xb = self.filter.x.copy()
        z, std = self.attitude
        xb[self.dyn._orientation_slice] = z
        R = self.dyn.rotation(xb)
        zr = np.asarray(r.z, float)
        J = self.dyn.rot_jacobian(xb, zr)
        s = float(np.max(np.atleast_1d(r.std)))
        C = Pt[:3, :3] + s * s * (R @ R.T) + std * std * (J @ J.T)
        return xt[:3] - R @ zr, 0.5 * (C + C.T)


# ------------------------------------------------------------------------ ekf-cl (fusion centre)


def node_spec(scenario, aid: int, settings) -> NodeSpec:
    """ekf-cl: the centre on its ground station, a VehicleClient on every vehicle, an idle node
    on any other ground station. settings: swarmloc.estimators.settings.CentreSettings."""
    centre = centre_id(scenario, settings)
    model = scenario.agent(aid).model
    if aid == centre:
        cfg = scenario.sensors.vehicle
        return NodeSpec.of(VehicleCentre, aid=aid, roster=roster_of(scenario),
                           actuator_noise=[cfg.force_noise, cfg.moment_noise], wait=settings.wait,
                           forget_after=settings.forget_after, process_q=scenario.estimation.process_noise,
                           attitude_std=scenario.estimation.attitude_std)
    if model in VEHICLES:
        return vehicle_spec(VehicleClient, scenario, aid, centre=centre)
    if model == GROUND_STATION:
        return NodeSpec.of(Idle, aid=aid, algorithm=VehicleClient.algorithm)
    raise ValueError(f"ekf-cl runs on {list(VEHICLES)} and a ground station; agent {aid} is {model}")


class VehicleClient(VehicleNode):
    """A vehicle of ``ekf-cl``: its own EKF, replaced by the centre's marginal when that comes
    within the tick (module docstring). `stats`: centre_ticks, own_ticks, stale,
    centre_unreachable, state_sent."""

    algorithm = "ekf-cl"

    def __init__(self, *args, centre: int = 0, **kwargs):
        super().__init__(*args, **kwargs)
        self.centre = int(centre)
        self.adopted: int | None = None
        self.stats.update({"centre_ticks": 0, "own_ticks": 0, "stale": 0, "centre_unreachable": 0, "state_sent": 0})

    def step(self, sensors: Sensors) -> list[Send]:
        if not self.own_step(sensors):
            return []
        self.stats["own_ticks"] += 1
        # The centre holds our state only if we hold its answer for the previous tick.
        fresh = self.adopted != self.k - 1
        self.stats["state_sent"] += fresh
        return [Send(CentreData(self.k, sensors, self.x.copy() if fresh else None,
                                  self.P.copy() if fresh else None), self.centre)]

    def receive(self, src, msg) -> list[Send]:
        if not isinstance(msg, CentreEstimate) or src != self.centre:
            return self.drop("unexpected", f"{type(msg).__name__} from {src}")
        if msg.k != self.k:
            self.stats["stale"] += 1
            return []
        try:
            x, P = check_state(msg.x, msg.P, self.dyn.state_dim)
        except RejectedInput as exc:
            return self.drop(exc.reason, exc.detail)
        # The centre is a member too (issue 26, finding 7): its marginal for us must not move our
        # position further than plausibility's bound in our own and its metric together.
        S = self.P[:3, :3] + P[:3, :3]
        if (why := plausibility.shift(x[:3] - self.x[:3], 0.5 * (S + S.T))) is not None:
            return self.drop(why, f"the centre's estimate is {np.linalg.norm(x[:3] - self.x[:3]):.3g} m off ours")
        self.filter.x, self.filter.P = x, P
        self._sync()
        if self.adopted != self.k:
            self.stats["centre_ticks"] += 1
            self.stats["own_ticks"] -= 1
        self.adopted = self.k
        return []

    def link_failed(self, dst, msg) -> list[Send]:
        if isinstance(msg, CentreData):
            self.stats["centre_unreachable"] += 1
        return []


class VehicleCentre(Node):
    """The fusion centre of ``ekf-cl`` on a ground station: the joint EKF of the vehicles."""

    algorithm = "ekf-cl"

    def __init__(self, aid, roster, actuator_noise, wait: float = 0.05, forget_after: int = 20,
                 process_q: float | None = None, attitude_std: float | None = None):
        super().__init__(aid, np.zeros(0), np.zeros((0, 0)), GROUND_STATION)
        self.models = {int(a): MODELS[m] for a, m in roster}
        self.noise = {a: actuator_std(m, *actuator_noise) for a, m in self.models.items()}
        self.process_q = process_q
        self.attitude_std = attitude_std  # the filters' assumed orientation std; None: the IMU's own
        self.wait, self.forget_after = float(wait), int(forget_after)
        self.joint = JointVehicleEkf()
        self.data: dict[int, dict[int, CentreData]] = {}  # tick -> vehicle -> its datum
        self.heard: dict[int, int] = {}  # vehicle -> last tick it sent data for
        self.unreachable: set[int] = set()
        self.first: int | None = None
        self.member_tick: dict[int, int] = {}  # member -> last tick run with its data
        self.ran = -1  # last tick run (or skipped)
        self.stats = {"ticks_run": 0, "late": 0, "no_state": 0, "joined": 0, "left": 0, "numerical": 0,
                      "relpos_updates": 0, "timer_runs": 0}

    def step(self, sensors) -> list[Send]:
        self.k = max(self.k, sensors.k)
        return []

    def receive(self, src, msg) -> list[Send]:
        if not isinstance(msg, CentreData):
            return self.drop("unexpected", type(msg).__name__)
        model = self.models.get(src)
        if model is None:
            return self.drop("unknown-sender", str(src))
        try:
            if msg.sensors.k != msg.k:
                raise RejectedInput("malformed", f"datum of tick {msg.k} carries the frame of {msg.sensors.k}")
            check_frame(msg.sensors, model, self.models)
            if (msg.x is None) != (msg.P is None):
                raise RejectedInput("malformed", "x without P or P without x")
            if msg.x is not None:
                check_state(msg.x, msg.P, model.state_dim)
        except RejectedInput as exc:
            return self.drop(exc.reason, exc.detail)
        self.heard[src] = max(self.heard.get(src, -1), msg.k)
        self.unreachable.discard(src)
        if msg.k <= self.ran:
            self.stats["late"] += 1
            return []
        out: list = []
        for k in sorted(k for k in self.data if k < msg.k):  # a later tick's datum: run what is pending
            out += self._run(k)
        if self.first is None:
            self.first = msg.k
        first_of_tick = msg.k not in self.data
        self.data.setdefault(msg.k, {}).setdefault(src, msg)
        if all(a in self.data[msg.k] for a in self._expected(msg.k)):
            return out + self._run(msg.k)
        return out + ([Timer(self.wait, RUN)] if first_of_tick else [])

    def on_timer(self, tag, t) -> list:
        if tag != RUN or not self.data:
            return []
        self.stats["timer_runs"] += 1
        return [x for k in sorted(self.data) for x in self._run(k)]

    def link_failed(self, dst, msg) -> list[Send]:
        self.unreachable.add(dst)
        return []

    def _expected(self, k: int) -> list[int]:
        if self.first is not None and k - self.first < self.forget_after:
            return [a for a in self.models if a not in self.unreachable]
        return [a for a, last in self.heard.items() if last >= k - self.forget_after and a not in self.unreachable]

    def _run(self, k: int) -> list[Send]:
        data = self.data.pop(k, {})
        self.ran = max(self.ran, k)
        # A member stays only if the centre ran the previous tick with its data: without its
        # command it cannot be propagated, and an older state cannot be propagated by one tick.
        for a in [a for a in self.joint.members if a not in data or self.member_tick.get(a) != k - 1]:
            self.joint.remove(a)
            self.stats["left"] += 1
        before = copy.deepcopy(self.joint)
        try:
            self._tick(data)
            if not (np.isfinite(self.joint.x).all() and np.isfinite(self.joint.P).all()):
                raise FloatingPointError("non-finite joint state")
        except (np.linalg.LinAlgError, ValueError, FloatingPointError) as exc:
            # The joint state as before the tick; no answers, so the vehicles use their own.
            self.joint = before
            self.stats["numerical"] += 1
            self.drop("numerical", f"tick {k}: {exc}")
            return []
        self.stats["ticks_run"] += 1
        for a in self.joint.members:
            self.member_tick[a] = k
        out = []
        for a in self.joint.members:
            x, P = self.joint.marginal(a)
            out.append(Send(CentreEstimate(k, x, P), a))
        return out

    def _tick(self, data: dict[int, CentreData]) -> None:
        members = set(self.joint.members)
        joined = []
        for a in sorted(data):
            if a not in members:
                d = data[a]
                if d.x is None:
                    self.stats["no_state"] += 1
                    continue
                joined.append(a)
        # Members: propagated with the command in force over the tick, then their own sensors.
        inputs = {a: (data[a].sensors.vehicle.u, data[a].sensors.vehicle.dt) for a in self.joint.members}
        if inputs and any(dt > 0 for _, dt in inputs.values()):
            self.joint.predict({a: (u, dt) for a, (u, dt) in inputs.items()})
        for a in list(self.joint.members):
            s = data[a].sensors
            self._datum(a, "attitude", self.joint.update_attitude, a, s.vehicle.attitude,
                        s.vehicle.attitude_std if self.attitude_std is None else self.attitude_std)
            if s.gnss is not None:
                self._datum(a, "gps", self.joint.update_gps, a, s.gnss.position, s.gnss.std)
        # Newcomers join with their own estimate of the tick (their own sensors applied).
        for a in joined:
            self.joint.add(a, self.models[a], np.asarray(data[a].x, float), np.asarray(data[a].P, float), self.noise[a],
                           q=self.process_q)
            self.stats["joined"] += 1
        # Relative positions among members, in (base, order taken) order.
        members = set(self.joint.members)
        for b in sorted(data):
            if b not in members:
                continue
            for r in data[b].sensors.vehicle.seen:
                if r.target in members and self._datum(b, f"relpos to {r.target}", self.joint.update_relpos, b,
                                                       r.target, r.z, r.std):
                    self.stats["relpos_updates"] += 1

    def _datum(self, a: int, what: str, update, *args) -> bool:
        """One member's datum into the joint filter; a lie past plausibility's bound (issue 26,
        finding 7; JointVehicleEkf refuses it before touching anything) is counted and skipped,
        the rest of the tick runs."""
        try:
            update(*args)
        except RejectedInput as exc:
            if not exc.reason.startswith("implausible"):
                raise
            self.drop(exc.reason, f"{what} of {a}: {exc.detail}")
            return False
        return True
