"""Scenario files: one versioned YAML document describes a whole experiment.

The pydantic models below are the schema; their field descriptions are the documentation
(docs/scenarios.md is generated from the same words). Unknown fields are errors, so a typo
never silently falls back to a default. The scenario of an MR.CLAM replay, built from the
recording, is replay.py's.
"""

from __future__ import annotations

import functools
import math
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal, Union

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_serializer, model_validator

from swarmloc.datasets.calibrate import CalibrationError, NoiseModel
from swarmloc.errors import problems_of, schema_fields, yaml_type
from swarmloc.experiment.faults import Fault, nodes_named
from swarmloc.models.motion import MOTION_MODELS

PRIOR_STREAM = 0x9A10  # keeps the prior's draws apart from netsim's world streams

SCENARIO_VERSION = 1


class ScenarioError(ValueError):
    """A scenario that cannot be used; the message names every offending field.

    problems: (field path, message) pairs, the path dotted ("world.offset") or "" for a rule
    across fields whose message names them; a command line that set a field from an option
    names the option instead (`swarmloc replay --offset`)."""

    def __init__(self, message: str, problems: list[tuple[str, str]] | None = None):
        super().__init__(message)
        self.problems = problems or []

    def renamed(self, source: str, names: dict[str, str]) -> "ScenarioError":
        """The same problems, each field the caller set from an option named as that option."""
        if not self.problems:
            return self
        lines = [f"{names.get(loc, loc)}: {msg}" if loc else msg for loc, msg in self.problems]
        return ScenarioError(f"{source}: {lines[0]}" if len(lines) == 1 else f"{source}:\n  " + "\n  ".join(lines),
                             self.problems)


def _field_error(loc: str, message: str) -> ScenarioError:
    return ScenarioError(f"{loc}: {message}", [(loc, message)])


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Clock(_Strict):
    mode: Literal["lockstep", "realtime"] = Field("lockstep", description="lockstep: deterministic, waits for the swarm each tick; realtime: wall clock times `speed`")
    dt: float = Field(0.5, gt=0, description="sample interval (s)")
    duration: float = Field(400.0, gt=0, description="simulated time (s)")
    speed: float = Field(1.0, gt=0, description="realtime only: simulated seconds per wall second")

    @property
    def steps(self) -> int:
        return int(round(self.duration / self.dt))


class CircleMotion(_Strict):
    kind: Literal["circle"] = "circle"
    speed: float = Field(1.0, ge=0, description="m/s")
    turn_rate: float = Field(0.015, description="rad/s, positive counter-clockwise")


class RandomMotion(_Strict):
    kind: Literal["random"] = "random"
    speed: float = Field(1.0, ge=0, description="m/s")
    turn_rate_std: float = Field(0.05, ge=0, description="std of the turn rate (rad/s), an Ornstein-Uhlenbeck process")
    turn_rate_tau: float = Field(10.0, gt=0, description="correlation time of the turn rate (s)")


class Figure8Motion(_Strict):
    kind: Literal["figure8"] = "figure8"
    width: float = Field(200.0, gt=0, description="m, along the figure's axis")
    height: float | None = Field(None, gt=0, description="m, across the axis; default width/2")
    period: float = Field(60.0, gt=0, description="s for one figure")
    heading: float = Field(0.0, description="rad, the axis counter-clockwise from east")
    climb: float = Field(0.0, ge=0, description="m, amplitude of an altitude wave with the figure's period")
    phase: float = Field(0.0, description="rad, where on the figure the flight starts")


class OrbitMotion(_Strict):
    kind: Literal["orbit"] = "orbit"
    radius: float = Field(50.0, gt=0, description="m")
    speed: float = Field(10.0, gt=0, description="m/s")
    phase: float = Field(0.0, description="rad: the start point's angle around the orbit's centre, counter-clockwise from east")
    clockwise: bool = False


class Random3dMotion(_Strict):
    kind: Literal["random3d"] = "random3d"
    radius: float = Field(100.0, gt=0, description="m, of the loiter circle the flight wanders around")
    speed: float = Field(12.0, gt=0, description="m/s, mean")
    wander: float = Field(0.4, ge=0, lt=1, description="speed varies within (1 +- wander) speed")
    vertical: float = Field(0.2, ge=0, description="scale of the vertical wander")


class StaticMotion(_Strict):
    kind: Literal["static"] = "static"


class TrackMotion(_Strict):
    """A quadrotor or ground robot following a circle under its tracking controller
    (swarmloc/models/vehicles.py); the vehicle starts at rest at the agent's `start`, yaw `heading`."""

    kind: Literal["track"] = "track"
    center: list[float] | None = Field(None, description="the circle's centre (m, 3 numbers; z is the height flown "
                                       "or driven at); null: the agent's start")
    radius: float = Field(0.0, ge=0, description="m; 0: hold the centre")
    period: float = Field(30.0, description="s per lap; negative: clockwise")
    phase: float = Field(0.0, description="rad: the reference's angle around the centre at t = 0, counter-clockwise "
                         "from east")
    yaw: float | None = Field(None, description="a constant yaw to hold (rad); null: face along the circle")

    @model_validator(mode="after")
    def _shape(self):
        if self.center is not None and (len(self.center) != 3 or not all(math.isfinite(v) for v in self.center)):
            raise ValueError("center must be 3 finite numbers")
        if self.period == 0 or not math.isfinite(self.period):
            raise ValueError("period must be a finite non-zero number of seconds")
        return self


Motion = Annotated[Union[CircleMotion, RandomMotion, Figure8Motion, OrbitMotion, Random3dMotion, StaticMotion, TrackMotion],
                   Field(discriminator="kind")]
# Which motions each model's world can fly: planar robots drive, UAS fly 3D trajectories placed
# so that they pass through `start` at t = 0, a ground station stays where it is.
MOTIONS_OF_MODEL = {"planar-speed-heading": ("circle", "random"), "planar-pose": ("circle", "random"), "uas-ins": ("figure8", "orbit", "random3d"),
                    "ground-station": ("static",), "quadrotor": ("track",), "ground-robot": ("track",)}


class AgentSpec(_Strict):
    id: int = Field(ge=0, description="agent id, unique in the swarm")
    model: str = Field("planar-speed-heading", description="motion model name (swarmloc.models.motion.MOTION_MODELS)")
    start: list[float] = Field(description="initial position (m), known to the agent: 2 numbers for a planar model, "
                               "3 (east, north, up) for uas-ins, ground-station, quadrotor and ground-robot")
    heading: float = Field(0.0, description="planar, quadrotor, ground-robot: initial heading (yaw, rad), known to the "
                           "agent")
    motion: Motion | None = Field(None, description="how the platform moves; default: circle (planar), figure8 (uas-ins), "
                                  "static (ground-station)")

    @field_validator("model")
    @classmethod
    def _known_model(cls, v):
        if v not in MOTION_MODELS:
            raise ValueError(f"unknown model {v!r}; known: {sorted(MOTION_MODELS)}")
        return v

    @model_validator(mode="after")
    def _start_dim(self):
        want = MOTION_MODELS[self.model].position_dim
        if len(self.start) != want or not all(math.isfinite(v) for v in self.start):
            raise ValueError(f"start must be {want} finite numbers for model {self.model}")
        kinds = MOTIONS_OF_MODEL[self.model]
        if self.motion is None:
            default = {"circle": CircleMotion, "figure8": Figure8Motion, "static": StaticMotion,
                       "track": TrackMotion}[kinds[0]]
            object.__setattr__(self, "motion", default())
        elif self.motion.kind not in kinds:
            raise ValueError(f"motion {self.motion.kind!r} does not fit model {self.model} (one of {list(kinds)})")
        return self

    @property
    def localized(self) -> bool:
        """Whether the platform is one the swarm localizes (a ground station is not)."""
        return MOTION_MODELS[self.model].state_dim > 0

    def reference_params(self) -> dict:
        """The CircleReference (swarmloc/models/vehicles.py) of a vehicle's `track` motion, as plain values."""
        m = self.motion
        center = [float(v) for v in (m.center if m.center is not None else self.start)]
        return {"center": center, "radius": float(m.radius), "period": float(m.period), "phase": float(m.phase),
                "yaw": m.yaw}


class TargetSpec(_Strict):
    """Something the swarm localizes besides itself: it carries no agent, sends nothing and is
    only ever ranged (`sensors.target_range`)."""

    id: int = Field(ge=0, description="target id, unique among the targets (its own id space, not the agents')")
    position: list[float] = Field(description="position at t = 0 (m), 2 numbers")
    velocity: list[float] = Field([0.0, 0.0], description="constant velocity (m/s), 2 numbers; [0, 0]: static")

    @model_validator(mode="after")
    def _planar(self):
        for name in ("position", "velocity"):
            v = getattr(self, name)
            if len(v) != 2 or not all(math.isfinite(x) for x in v):
                raise ValueError(f"{name} must be 2 finite numbers (targets are planar)")
        return self


class LandmarkSpec(_Strict):
    """A fixed, known point the platforms observe by range and bearing (`sensors.range_bearing`)."""

    id: int = Field(ge=0, description="landmark id, unique among the landmarks (its own id space, not the agents')")
    position: list[float] = Field(description="position (m), 2 numbers")

    @field_validator("position")
    @classmethod
    def _planar(cls, v):
        if len(v) != 2 or not all(math.isfinite(x) for x in v):
            raise ValueError("position must be 2 finite numbers (landmarks are planar)")
        return v


class ArcFormation(_Strict):
    """Planar agents on an arc around a point, each driving straight at it: the start of a
    target-localization run, written as the few numbers a study sweeps (start distance and
    angular spread) instead of every agent's coordinates."""

    kind: Literal["arc"] = "arc"
    count: int = Field(ge=1, le=64, description="number of agents")
    first_id: int = Field(1, ge=0, description="the first agent's id; the others follow in order")
    center: list[float] = Field(description="the point the agents drive at (m, 2 numbers)")
    radius: float = Field(gt=0, description="every agent's start distance from `center` (m)")
    bearing_deg: float = Field(180.0, description="the arc's middle, seen from `center` (deg, counter-clockwise from "
                               "east); 180: the agents start west of it")
    spread_deg: float = Field(0.0, ge=0, le=360, description="angle between the first and the last agent, seen from "
                              "`center` (deg); the agents are evenly spaced over it")
    speed: float = Field(1.0, ge=0, description="m/s, straight at `center` (circle motion with turn rate 0)")
    model: Literal["planar-speed-heading", "planar-pose"] = "planar-pose"

    @field_validator("center")
    @classmethod
    def _planar(cls, v):
        if len(v) != 2 or not all(math.isfinite(x) for x in v):
            raise ValueError("center must be 2 finite numbers")
        return v

    def agents(self) -> list[dict]:
        out = []
        for i in range(self.count):
            frac = i / (self.count - 1) - 0.5 if self.count > 1 else 0.0
            b = math.radians(self.bearing_deg + self.spread_deg * frac)
            x, y = self.center[0] + self.radius * math.cos(b), self.center[1] + self.radius * math.sin(b)
            out.append({"id": self.first_id + i, "model": self.model, "start": [x, y],
                        "heading": math.atan2(self.center[1] - y, self.center[0] - x),
                        "motion": {"kind": "circle", "speed": self.speed, "turn_rate": 0.0}})
        return out


class World(_Strict):
    source: Literal["simulated", "mrclam", "mcap"] = Field("simulated", description="simulated: netsim simulates "
                                                           "the agents' motion and sensors; mrclam: it replays a "
                                                           "recorded MR.CLAM dataset (docs/replay.md), and agents and "
                                                           "landmarks default to the recording's; mcap: it plays the "
                                                           "sensor frames and truth of a run's run.mcap again "
                                                           "(`swarmloc rerun`, docs/run-format.md#runmcap)")
    path: str | None = Field(None, description="mrclam: the dataset directory; mcap: the recording (relative to the "
                             "scenario file's directory, or absolute)")
    robots: list[int] | None = Field(None, description="mrclam: the recorded robots to replay as agents; null: all")
    offset: float = Field(0.0, ge=0, description="mrclam: seconds into the recording at which the run starts")
    odometry_lag: float | None = Field(None, description="mrclam: seconds by which the recorded odometry leads the "
                                       "motion it causes; null: estimated per robot from the recording (0.22-0.25 s "
                                       "on Dataset6)")
    noise: NoiseModel | None = Field(None, description="mrclam: the recording's noise model (`swarmloc calibrate`, "
                                     "the mapping of a noise.yaml, or its path relative to the scenario file): the "
                                     "replay corrects each reading by it and states its stds in the frames, per robot "
                                     "(its lags replace odometry_lag); null: the readings as recorded, with "
                                     "`sensors`' noise")
    agents: list[AgentSpec] = Field(min_length=1)
    formation: ArcFormation | None = Field(None, description="instead of `agents`: the agents generated on an arc "
                                           "around a point, each driving at it (scenario files give one or the other)")
    landmarks: list[LandmarkSpec] = Field(default_factory=list, description="the landmark map: known to the "
                                          "estimators, observed by range and bearing (`sensors.range_bearing`)")
    targets: list[TargetSpec] = Field(default_factory=list, description="targets to localize (CSL-CTL, IL-CTL)")
    stop_distance: float | None = Field(None, gt=0, description="the run ends at the first tick at which an agent is "
                                        "within this distance of a target (m); null: it runs `clock.duration`")
    control: Literal["netsim", "agents"] = Field("netsim", description="quadrotors and ground robots: who closes each "
                                                 "vehicle's loop. netsim: its autopilot is fed the true state (the "
                                                 "paper's validation runs, motion capture in the loop); agents: each "
                                                 "agent computes the command from its own estimate and publishes it "
                                                 "(docs/wire.md, `command`)")

    @model_validator(mode="before")
    @classmethod
    def _expand_formation(cls, data):
        if isinstance(data, dict) and data.get("formation") is not None:
            if data.get("agents"):
                raise ValueError("give `agents` or `formation`, not both")
            try:
                f = ArcFormation.model_validate(data["formation"])
            except ValidationError:
                return data  # validated again as the field, so the error names world.formation
            data = {**data, "formation": f, "agents": f.agents()}
        return data

    @model_serializer(mode="wrap")
    def _dump(self, handler):
        # A formation's agents are generated: what is dumped (and parsed again after an
        # override of the formation) is the formation alone.
        out = handler(self)
        if self.formation is not None:
            out.pop("agents", None)
        return out

    @field_validator("agents")
    @classmethod
    def _unique_ids(cls, v):
        ids = [a.id for a in v]
        if len(set(ids)) != len(ids):
            raise ValueError(f"agent ids must be unique, got {ids}")
        return v

    @model_validator(mode="after")
    def _targets(self):
        lm = [m.id for m in self.landmarks]
        if len(set(lm)) != len(lm):
            raise ValueError(f"landmark ids must be unique, got {lm}")
        if self.source == "mrclam" and not self.path:
            raise ValueError("source mrclam needs `path`, the dataset directory")
        if self.source == "mcap" and (not self.path or self.robots is not None or self.offset
                                      or self.odometry_lag is not None or self.stop_distance is not None
                                      or self.noise is not None):
            raise ValueError("source mcap needs `path`, the recording, and takes no robots, offset, odometry_lag, "
                             "noise or stop_distance (the recording has its own)")
        if self.source == "mrclam" and self.robots is not None:
            ids = sorted(a.id for a in self.agents)
            if ids != sorted(self.robots) or any(a.model != "planar-pose" for a in self.agents):
                raise ValueError(f"a replay's agents are its robots {sorted(self.robots)}, each planar-pose; got "
                                 f"{[(a.id, a.model) for a in self.agents]}")
        if self.source == "simulated" and (self.path is not None or self.robots is not None or self.offset
                                           or self.odometry_lag is not None or self.noise is not None):
            raise ValueError("path, robots, offset, odometry_lag and noise are for a recorded source (source: mrclam)")
        if self.source == "mrclam" and self.noise is not None:
            missing = sorted(set(a.id for a in self.agents) - set(self.noise.robots))
            if missing:
                raise ValueError(f"noise: the noise model has no robot {missing[0]} (it has {sorted(self.noise.robots)})")
        ids = [t.id for t in self.targets]
        if len(set(ids)) != len(ids):
            raise ValueError(f"target ids must be unique, got {ids}")
        if self.targets and any(a.model not in ("planar-speed-heading", "planar-pose") for a in self.agents):
            raise ValueError("targets: only a swarm of planar agents (planar-speed-heading, planar-pose) ranges targets")
        if self.stop_distance is not None and not self.targets:
            raise ValueError("stop_distance needs targets")
        return self


class OdometrySensor(_Strict):
    speed_noise: float = Field(0.5, ge=0, description="std of measured speed (m/s)")
    turn_rate_noise: float = Field(1e-3, ge=0, description="std of measured turn rate (rad/s); heading is its integral")


class RangeSensor(_Strict):
    noise: float = Field(1.0, gt=0, description="std of a range measurement (m)")
    probability: float = Field(0.5, ge=0, le=1, description="chance per step and per slot that a measurement happens")
    max_per_step: int = Field(1, ge=0, description="measurement slots per step in the whole swarm")
    max_range: float = Field(math.inf, gt=0, description="sensing range (m): pairs farther apart are never measured")
    all_pairs: bool = Field(False, description="instead of random slots, every platform ranges every other platform "
                            "within max_range (planar: every tick; UAS: once per `sensors.relative_epoch`)")
    both_ends: bool = Field(True, description="UAS, all_pairs: each pair is ranged from both ends, with independent "
                            "noise; false: once per pair, by the lower id (the N(N-1)/2 ranges of Goel et al.)")


class TargetRangeSensor(_Strict):
    noise: float = Field(10.0, gt=0, description="std of a range to a target (m)")
    max_range: float = Field(math.inf, gt=0, description="detection range (m): a target farther away is not seen")
    probability: float = Field(1.0, ge=0, le=1, description="chance per tick that an agent within max_range detects "
                               "a target (and ranges it)")


class GnssSensor(_Strict):
    enabled: bool = Field(False, description="a GNSS receiver on the platforms (planar: a position fix every step; "
                          "UAS: one epoch every `sensors.epoch` s)")
    kind: Literal["position", "pseudorange"] = Field("position", description="UAS: what the receiver reports, a 3D "
                                                     "position fix or the pseudoranges of the simulated constellation")
    noise: float = Field(2.0, gt=0, description="std of each horizontal coordinate of a position fix (m)")
    noise_vertical: float | None = Field(None, gt=0, description="UAS: std of the vertical coordinate of a fix (m); "
                                         "default: `noise`")
    pseudorange_noise: float = Field(1.0, gt=0, description="UAS: std of a pseudorange (m)")
    mask_deg: float = Field(10.0, ge=0, lt=90, description="UAS: elevation mask of the constellation (deg)")
    agents: list[int] | None = Field(None, description="agents with a receiver; null: all")
    to_fault: float = Field(0.0, ge=0, le=1, description="planar: chance per tick that a receiver that has a fix "
                            "loses it (a Markov chain of normal and fault states; 0 with to_normal 0: no switching)")
    to_normal: float = Field(0.0, ge=0, le=1, description="planar: chance per tick that a receiver without a fix gets "
                             "it back. With switching, each receiver starts normal with the chain's stationary "
                             "probability to_normal / (to_fault + to_normal)")
    normal_share: float | None = Field(None, ge=0, le=1, description="planar, without switching: the share of the "
                                       "receivers that have a fix (a seeded random subset of round(share * n) of them, "
                                       "fixed for the run); null: all")


class ImuSensor(_Strict):
    """UAS: a strapdown IMU; the defaults are an industrial MEMS unit (docs/uas.md)."""

    rate_hz: float = Field(100.0, gt=0, description="IMU samples per second; a tick carries dt * rate_hz of them "
                           "(clock.dt must be a whole number of IMU intervals)")
    gyro_arw: float = Field(8.73e-5, ge=0, description="angle random walk (rad/s/sqrt(Hz)); 8.73e-5 = 0.3 deg/sqrt(h)")
    accel_vrw: float = Field(1.0e-3, ge=0, description="velocity random walk (m/s^2/sqrt(Hz))")
    gyro_bias_rw: float = Field(8.08e-7, ge=0, description="gyro bias random walk (rad/s/sqrt(s))")
    accel_bias_rw: float = Field(1.63e-5, ge=0, description="accelerometer bias random walk (m/s^2/sqrt(s))")
    gyro_bias_sigma0: float = Field(4.85e-4, ge=0, description="turn-on gyro bias std (rad/s); 4.85e-4 = 100 deg/h")
    accel_bias_sigma0: float = Field(2.94e-2, ge=0, description="turn-on accelerometer bias std (m/s^2); 2.94e-2 = 3 mg")

    def spec(self):
        """The IMU as swarmloc.models.ins.ImuSpec: the world draws its errors from it, the filters
        and the bound model them with it."""
        from swarmloc.models.ins import ImuSpec

        return ImuSpec(gyro_arw=self.gyro_arw, accel_vrw=self.accel_vrw, gyro_bias_rw=self.gyro_bias_rw,
                       accel_bias_rw=self.accel_bias_rw, bias_tau=math.inf, gyro_bias_sigma0=self.gyro_bias_sigma0,
                       accel_bias_sigma0=self.accel_bias_sigma0)


class RelPosSensor(_Strict):
    enabled: bool = Field(False, description="UAS: every platform measures the relative position (ENU) of every "
                          "other platform within max_range, once per `sensors.relative_epoch`")
    noise: float = Field(0.05, gt=0, description="std of each component (m)")
    max_range: float = Field(math.inf, gt=0, description="sensing range (m)")


class RangeBearingSensor(_Strict):
    """Range and bearing in the measuring platform's body frame (a camera reading barcodes, as on
    the MR.CLAM robots): a replayed recording delivers what it recorded; a simulated planar-pose
    swarm measures them when `enabled`."""

    enabled: bool = Field(False, description="simulated world: every planar-pose agent measures every other agent and "
                          "landmark within max_range, every tick (a replay ignores this: it has its recording)")
    max_range: float = Field(math.inf, gt=0, description="simulated world: sensing range (m)")
    robots: bool = Field(True, description="observations of other agents are delivered")
    landmarks: bool = Field(True, description="observations of the landmarks of `world.landmarks` are delivered "
                            "(the map is known); false: the swarm has only its odometry and each other")
    range_noise: float = Field(0.1, gt=0, description="std of a range (m), as the estimators assume it")
    bearing_noise: float = Field(0.05, gt=0, description="std of a bearing (rad), as the estimators assume it")


class GpsSchedule(_Strict):
    """When the vehicles' GPS has a fix: none before `start`, then `on_for` seconds with a fix,
    `off_for` seconds without, repeating (`off_for: 0`: always from `start` on)."""

    start: float = Field(0.0, ge=0, description="s")
    on_for: float = Field(math.inf, gt=0, description="s")
    off_for: float = Field(0.0, ge=0, description="s")

    def active(self, t: float) -> bool:
        if t < self.start:
            return False
        if self.off_for == 0 or not math.isfinite(self.on_for):
            return True
        return (t - self.start) % (self.on_for + self.off_for) < self.on_for


class VehicleSensors(_Strict):
    """Quadrotors and ground robots (Oliveros & Ashrafiuon 2023, section 6.1): an IMU's
    orientation every tick, relative positions in the measurer's body frame along the measurement
    graph within the proximity of the pair's types, GPS on a schedule. The world perturbs every
    actuator input with white noise held over the tick: the process noise of the estimators."""

    attitude_noise: float = Field(0.01, gt=0, description="std of each IMU orientation component (quaternion "
                                  "components for a quadrotor; yaw, rad, for a ground robot)")
    relpos_noise: float = Field(0.005, gt=0, description="std of each component of a relative position (m)")
    gps_noise: float = Field(0.005, gt=0, description="std of each coordinate of a GPS fix (m)")
    gps: list[int] = Field(default_factory=list, description="vehicles with GPS")
    gps_schedule: GpsSchedule = Field(default_factory=GpsSchedule)
    graph: list[tuple[int, int]] | None = Field(None, description="the measurement graph: [base, target] pairs, the "
                                                "base measuring the target; null: every ordered pair")
    proximity: dict[str, float] = Field(default_factory=dict, description="sensing range (m) by the pair's types, "
                                        "e.g. {quadrotor/quadrotor: 4, quadrotor/ground-robot: 2} (either order); "
                                        "a pair of types not listed: unlimited")
    force_noise: float = Field(0.02, ge=0, description="std of the noise on a thrust or surge force (N)")
    moment_noise: float = Field(2e-4, ge=0, description="std of the noise on a moment (N m)")

    def range_of(self, a: str, b: str) -> float:
        return self.proximity.get(f"{a}/{b}", self.proximity.get(f"{b}/{a}", math.inf))

    @field_validator("proximity")
    @classmethod
    def _pair_names(cls, v):
        from swarmloc.models.motion import VEHICLES

        for key, r in v.items():
            parts = key.split("/")
            if len(parts) != 2 or not set(parts) <= set(VEHICLES):
                raise ValueError(f"proximity key {key!r} is not '<type>/<type>' of {list(VEHICLES)}")
            if not r > 0:
                raise ValueError(f"proximity[{key}] must be > 0, got {r}")
        return v


class Sensors(_Strict):
    range_bearing: RangeBearingSensor = Field(default_factory=RangeBearingSensor)
    odometry: OdometrySensor = Field(default_factory=OdometrySensor)
    range: RangeSensor = Field(default_factory=RangeSensor)
    gnss: GnssSensor = Field(default_factory=GnssSensor)
    imu: ImuSensor = Field(default_factory=ImuSensor)
    relpos: RelPosSensor = Field(default_factory=RelPosSensor)
    target_range: TargetRangeSensor = Field(default_factory=TargetRangeSensor)
    vehicle: VehicleSensors = Field(default_factory=VehicleSensors)
    epoch: float = Field(1.0, gt=0, description="UAS: seconds between GNSS epochs (a whole number of ticks)")
    relative_epoch: float | None = Field(None, gt=0, description="UAS: seconds between relative measurements (ranges, "
                                         "relative positions; a whole number of ticks); null: `epoch`, with the GNSS")


RADIO_MODELS = ("unit-disk", "log-distance")


class Security(_Strict):
    keys: str | None = Field(None, description="the swarm's key directory (`swarmloc keys new`) whose swarm.key "
                             "seals every frame of the run; null: the run makes throwaway keys of its own")


class Estimation(_Strict):
    initial_std: float = Field(0.1, gt=0, description="std of the known initial position (m)")
    initial_heading_std: float = Field(1e-3, gt=0, description="planar-pose: std of the known initial heading (rad)")
    initial_error: bool = Field(True, description="draw each platform's initial estimate from N(start, "
                                "initial_std^2), as the prior claims (false: start exactly at the truth, "
                                "which makes NEES read low until the process noise dominates)")
    spread: float | None = Field(None, gt=0, description="unscented transform spread n + lambda; default: "
                                 "twice the state dimension (no negative sigma weight)")
    gate: float | None = Field(None, gt=0, lt=1, description="chi-square innovation gate: a measurement whose NIS "
                               "exceeds this quantile of the chi-square distribution of its dimension is rejected "
                               "(counted); null: no gate. Estimators with a gate: ekf, ekf-ci and ekf-ccl on "
                               "planar-pose, ukf-dcl, ukf-ccl (docs/replay.md)")
    gate_open_after: int = Field(10, ge=1, description="after this many consecutive rejections of one platform's (or "
                                 "pair's) measurements the gate stands open for it until a measurement passes again, "
                                 "so a bad stretch of odometry cannot lock a platform out for good")
    attitude_std: float | None = Field(None, gt=0, description="quadrotors and ground robots: the orientation std the "
                                       "filters assume for the IMU's reading (Oliveros & Ashrafiuon: 0.1); null: the "
                                       "std the IMU reports, its true one (sensors.vehicle.attitude_noise)")
    process_noise: float | None = Field(None, gt=0, description="quadrotors and ground robots: the filters' process "
                                        "noise as a constant Q = process_noise * I per tick (Oliveros & Ashrafiuon: "
                                        "0.1); null: matched to the world's actuator noise, dt^2 g diag(std^2) g^T")
    rejoin_std: float | None = Field(15.0, gt=0, description="UKF-DCL: a node whose position std (largest axis, m) "
                                     "exceeds this is lost (a restart, a long isolation): it takes no range into its "
                                     "filter until a window of ranges pins its position down by multilateration; "
                                     "null: never")


class EstimatorChoice(_Strict):
    name: str = Field("ukf-dcl", description="the estimator the agent processes run (`swarmloc estimators` lists them)")
    params: dict = Field(default_factory=dict, description="its settings; each estimator documents and validates its own")

    @model_validator(mode="after")
    def _known(self):
        from swarmloc.estimators import REGISTRY

        info = REGISTRY.get(self.name)
        if info is None or not info.runs_on_agents:
            raise ValueError(f"unknown estimator {self.name!r}; agents run one of {sorted(REGISTRY.running())}")
        info.settings(self.params)  # raises ValueError naming the bad parameter
        return self


class Scenario(_Strict):
    version: int = Field(description=f"scenario format version; this swarmloc reads {SCENARIO_VERSION}")
    name: str = Field(pattern=r"^[A-Za-z0-9_.-]+$")
    description: str = ""
    seed: int = Field(0, ge=0, description="the one seed every random draw derives from")
    clock: Clock = Field(default_factory=Clock)
    world: World
    sensors: Sensors = Field(default_factory=Sensors)
    radio: dict = Field(default_factory=lambda: {"model": "unit-disk"},
                        description="channel model and its parameters (docs/radio.md); netsim validates the parameters")
    estimation: Estimation = Field(default_factory=Estimation)
    estimator: EstimatorChoice = Field(default_factory=EstimatorChoice)
    references: list[str] | None = Field(None, description="estimators computed offline from the recorded sensor stream "
                                         "after the run; null: every reference that fits the swarm's models")
    reference_params: dict[str, dict] = Field(default_factory=dict, description="settings of offline references, by "
                                              "name, each validated by its estimator as estimator.params is (e.g. "
                                              "{ekf-ccl: {odometry_bias: true}}); a reference not named runs with its "
                                              "defaults")
    bound: bool = Field(True, description="compute the run's posterior Cramér-Rao bound after the run, beside the "
                        "references (docs/estimators.md); false: skip it")
    faults: list[Fault] = Field(default_factory=list, description="fault timeline: each fault with `at` (docs/faults.md)")
    security: Security = Field(default_factory=Security, description="frame authentication (docs/security.md)")

    @model_validator(mode="before")
    @classmethod
    def _migrate_and_default_estimator(cls, data):
        # Before `estimator` and `references`, one list named the estimators to report; the
        # agents always ran ukf-dcl, the others were offline references.
        if isinstance(data, dict) and "estimators" in data:
            data = dict(data)
            old = data.pop("estimators")
            if not isinstance(old, list):
                raise ValueError(f"estimators (the old form of references) must be a list, got {old!r}")
            data.setdefault("references", [e for e in old if e != "ukf-dcl"])
        # No estimator named: ukf-dcl if it runs on the swarm's models, else the first in the
        # registry that does (ekf for UAS).
        if isinstance(data, dict) and "estimator" not in data:
            from swarmloc.estimators import REGISTRY
            from swarmloc.models.motion import MOTION_MODELS

            agents = (data.get("world") or {}).get("agents") or []
            models = {a.get("model", "planar-speed-heading") for a in agents if isinstance(a, dict)}
            models = {m for m in models if m in MOTION_MODELS and MOTION_MODELS[m].state_dim > 0}
            fits = [e.name for e in REGISTRY if e.runs_on_agents and models <= set(e.models)]
            fits.sort(key=lambda name: name != EstimatorChoice.model_fields["name"].default)
            if fits:
                data = {**data, "estimator": {"name": fits[0]}}
        return data

    @field_validator("estimator")
    @classmethod
    def _has_what_it_needs(cls, v, info):
        # An estimator of targets on a swarm without any would run as dead reckoning, silently.
        from swarmloc.estimators import REGISTRY

        world, sensors = info.data.get("world"), info.data.get("sensors")
        if world is None or sensors is None:
            return v  # they failed their own validation
        has = _has(world, sensors)
        missing = [need for need in REGISTRY[v.name].requires if not has[need]]
        if missing:
            what = {"targets": "targets (world.targets)", "gnss": "GNSS fixes (sensors.gnss)"}
            raise ValueError(f"{v.name} needs {' and '.join(what[m] for m in missing)}, and this scenario has none: "
                             "its agents would run dead reckoning alone")
        return v

    @field_validator("references")
    @classmethod
    def _known_references(cls, v):
        from swarmloc.estimators import REGISTRY

        if v is not None:
            bad = [r for r in v if r not in REGISTRY.references()]
            if bad:
                raise ValueError(f"unknown references {bad}; known: {sorted(REGISTRY.references())}")
        return v

    @field_validator("reference_params")
    @classmethod
    def _known_reference_params(cls, v):
        from swarmloc.estimators import REGISTRY

        for name, params in v.items():
            if name not in REGISTRY.references():
                raise ValueError(f"unknown reference {name!r}; known: {sorted(REGISTRY.references())}")
            try:
                REGISTRY[name].settings(params)
            except ValueError as exc:
                raise ValueError(f"{name}: {exc}") from None
        return v

    def reference_settings(self, name: str):
        """The settings the offline reference `name` runs with (reference_params, else its defaults)."""
        from swarmloc.estimators import REGISTRY

        return REGISTRY[name].settings(self.reference_params.get(name, {}))

    @field_validator("version")
    @classmethod
    def _version(cls, v):
        if v != SCENARIO_VERSION:
            raise ValueError(f"unsupported version {v}; this swarmloc reads version {SCENARIO_VERSION}")
        return v

    @field_validator("radio")
    @classmethod
    def _radio_model(cls, v):
        if v.get("model") not in RADIO_MODELS:
            raise ValueError(f"radio.model must be one of {list(RADIO_MODELS)}, got {v.get('model')!r}")
        return v

    @model_validator(mode="after")
    def _faults_name_agents(self):
        ids = {a.id for a in self.world.agents}
        for i, f in enumerate(self.faults):
            if f.at is None:
                raise ValueError(f"faults[{i}] needs `at` (simulated time in s)")
            bad = [a for a in nodes_named(f) if a not in ids]
            if bad:
                raise ValueError(f"faults[{i}] ({f.action}) names unknown agents {bad}")
        return self

    @model_validator(mode="after")
    def _models_fit(self):
        ids = {a.id for a in self.world.agents}
        g = self.sensors.gnss.agents
        if g is not None and set(g) - ids:
            raise ValueError(f"sensors.gnss.agents names unknown agents {sorted(set(g) - ids)}")
        uas = [a for a in self.world.agents if a.model == "uas-ins"]
        if uas:
            rel = self.sensors.relative_epoch
            for what, x in (("clock.dt * sensors.imu.rate_hz", self.clock.dt * self.sensors.imu.rate_hz),
                            ("sensors.epoch / clock.dt", self.sensors.epoch / self.clock.dt),
                            ("sensors.relative_epoch / clock.dt", (rel or self.sensors.epoch) / self.clock.dt)):
                if round(x) < 1 or abs(x - round(x)) > 1e-9 * max(1.0, x):
                    raise ValueError(f"{what} must be a whole number >= 1 for uas-ins agents, got {x:.6g}")
            # What one sensor frame can carry (docs/wire.md): 4096 rows of an array, 64 list entries.
            if self.clock.dt * self.sensors.imu.rate_hz > 4096:
                raise ValueError("clock.dt * sensors.imu.rate_hz: a tick carries at most 4096 IMU samples")
            if len(uas) > 65 and (self.sensors.relpos.enabled or self.sensors.range.all_pairs):
                raise ValueError("sensors.relpos / sensors.range.all_pairs: a frame carries at most 64 relative "
                                 f"measurements, and {len(uas)} UAS would measure {len(uas) - 1}")
        self._vehicles_fit(ids)
        from swarmloc.estimators import REGISTRY

        info = REGISTRY[self.estimator.name]
        models = {a.model for a in self.world.agents if a.localized}
        if not models <= set(info.models):
            raise ValueError(f"estimator {info.name} runs on models {list(info.models)}, the swarm has {sorted(models)}")
        if "ground-station" in info.models and not any(a.model == "ground-station" for a in self.world.agents):
            raise ValueError(f"estimator {info.name} needs a ground-station agent (its fusion centre)")
        for r in self.references or ():
            if not models <= set(REGISTRY[r].models):
                raise ValueError(f"reference {r} runs on models {list(REGISTRY[r].models)}, the swarm has {sorted(models)}")
        return self

    def _vehicles_fit(self, ids: set[int]) -> None:
        from swarmloc.models.motion import VEHICLES

        vehicles = {a.id for a in self.world.agents if a.model in VEHICLES}
        v = self.sensors.vehicle
        if set(v.gps) - vehicles:
            raise ValueError(f"sensors.vehicle.gps names agents that are not vehicles {sorted(set(v.gps) - vehicles)}")
        for b, t in v.graph or ():
            if b not in vehicles or t not in vehicles or b == t:
                raise ValueError(f"sensors.vehicle.graph: [{b}, {t}] must name two different vehicles "
                                 f"(the vehicles: {sorted(vehicles)})")
        if vehicles and any(a.model not in VEHICLES + ("ground-station",) for a in self.world.agents):
            raise ValueError("quadrotor and ground-robot agents fly with other vehicles and ground stations only, got "
                             f"{sorted({a.model for a in self.world.agents})}")
        if vehicles and self.clock.dt > VEHICLE_MAX_DT:
            raise ValueError(f"clock.dt = {self.clock.dt} s: quadrotor and ground-robot agents need clock.dt <= "
                             f"{VEHICLE_MAX_DT} s (their dynamics are integrated and their controllers sample once a "
                             "tick; the paper runs at 50 Hz)")
        if self.world.control == "agents" and not vehicles:
            raise ValueError("world.control: agents needs quadrotor or ground-robot agents")

    @property
    def agent_ids(self) -> list[int]:
        return sorted(a.id for a in self.world.agents)

    @property
    def localized_ids(self) -> list[int]:
        """The platforms the swarm localizes (every agent but ground stations)."""
        return sorted(a.id for a in self.world.agents if a.localized)

    @property
    def reference_names(self) -> list[str]:
        """The offline references of this run: those the scenario names, or every one that fits."""
        from swarmloc.estimators import REGISTRY

        mine = self.estimator.name  # the agents' results are never replaced by an offline run
        if self.references is not None:
            return [r for r in self.references if r != mine]
        models = {a.model for a in self.world.agents if a.localized}
        return [r for r in REGISTRY.references() if models <= set(REGISTRY[r].models) and r != mine
                and all(self.has[need] for need in REGISTRY[r].requires)]

    @property
    def has(self) -> dict[str, bool]:
        """What an estimator may require of the scenario (EstimatorInfo.requires): targets, GNSS fixes."""
        return _has(self.world, self.sensors)

    def agent(self, aid: int) -> AgentSpec:
        return next(a for a in self.world.agents if a.id == aid)

    def prior(self, aid: int) -> tuple[np.ndarray, np.ndarray]:
        """Platform aid's initial estimate and covariance. The error is drawn from its own
        seeded stream, so every process (agent, in-process runner, references) gets the same."""
        est, spec = self.estimation, self.agent(aid)
        start = np.array(spec.start, float)
        std = np.full(len(start), est.initial_std)
        if spec.model == "planar-pose":  # the heading is known too
            start, std = np.r_[start, spec.heading], np.r_[std, est.initial_heading_std]
        rng = np.random.default_rng([self.seed, PRIOR_STREAM, aid])
        if spec.model in ("quadrotor", "ground-robot"):
            return _vehicle_prior(spec, est, rng)
        P0 = np.diag(std**2)
        if not est.initial_error:
            return start, P0
        return start + std * rng.standard_normal(len(start)), P0

    def with_overrides(self, **changes) -> "Scenario":
        """A validated copy with dotted-path overrides, e.g. {"sensors.range.probability": 0.05}."""
        data = self.model_dump()
        for path, value in changes.items():
            node = data
            *head, last = path.split(".")
            for part in head:
                node = node[part]
            node[last] = value
        return parse(data, source=f"{self.name} (overridden)")

    def to_yaml(self) -> str:
        def plain(v):  # python-mode dump keeps inf (json mode would turn the radio's inf to null)
            if isinstance(v, dict):
                return {k: plain(x) for k, x in v.items()}
            if isinstance(v, (list, tuple)):
                return [plain(x) for x in v]
            return v

        return yaml.safe_dump(plain(self.model_dump(exclude_none=False)), sort_keys=False)


VEHICLE_MAX_DT = 0.05
"""Longest tick (s) with quadrotors and ground robots: at 20 Hz their tracking controllers are
still stable; at 10 Hz the quadrotor's attitude loop is not."""


VEHICLE_RATE_STD = 1e-3
"""Prior std of a vehicle's velocities and rates (m/s, rad/s): it starts at rest, and knows it."""


def _vehicle_prior(spec: AgentSpec, est: Estimation, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A vehicle at rest at its start: position within initial_std, yaw within initial_heading_std
    (a quadrotor's quaternion components then within half that), level."""
    from swarmloc.models.vehicles import MODELS

    model = MODELS[spec.model]
    e = rng.standard_normal(4) if est.initial_error else np.zeros(4)
    x = model.initial_state(np.array(spec.start, float) + est.initial_std * e[:3],
                            spec.heading + est.initial_heading_std * e[3])
    std = np.full(model.state_dim, VEHICLE_RATE_STD)
    std[:3] = est.initial_std
    if spec.model == "quadrotor":
        std[3:7] = max(est.initial_heading_std / 2, VEHICLE_RATE_STD)
    else:
        std[3] = est.initial_heading_std
    return x, np.diag(std**2)


def recording(path: str):
    """A loaded MR.CLAM directory, cached while its files are unchanged (the scenario, netsim's
    world and the noise fit all read it)."""
    try:
        stamp = max((f.stat().st_mtime_ns for f in Path(path).iterdir()), default=0)
    except OSError:
        stamp = 0  # not a directory: the loader says what is wrong
    return _recording(path, stamp)


@functools.lru_cache(maxsize=4)
def _recording(path: str, stamp: int):
    from swarmloc.datasets import mrclam

    return mrclam.load(path)


def _expand_recorded(data: dict, base: Path | None) -> dict:
    """A world with `source: mrclam`: the path made absolute, and what the scenario leaves out
    taken from the recording: the agents (every recorded robot, planar-pose, starting at its
    Vicon pose at the run's start), the landmark map and the duration (to the recording's end)."""
    from swarmloc.datasets import mrclam

    world = data.get("world")
    if isinstance(world, dict) and world.get("source") == "mcap" and isinstance(world.get("path"), str) \
            and not world["path"].startswith("["):  # a JSON list: agents' own recordings, absolute paths
        path = Path(world["path"]).expanduser()
        if not path.is_absolute() and base is not None:
            return {**data, "world": {**world, "path": str((base / path).resolve())}}
        return data
    if not isinstance(world, dict) or world.get("source") != "mrclam":
        return data
    if not isinstance(world.get("path"), str):
        raise _field_error("world.path", "source mrclam needs `path`, the dataset directory")
    path = Path(world["path"]).expanduser()
    if not path.is_absolute() and base is not None:
        path = base / path
    try:
        rec = recording(str(path.resolve()))
    except mrclam.MrclamError as exc:
        raise _field_error("world.path", f"{exc}") from None
    world = {**world, "path": str(path.resolve()), "robots": world.get("robots") or list(rec.robots)}
    if isinstance(world.get("noise"), str):
        noise = Path(world["noise"]).expanduser()
        try:
            world["noise"] = NoiseModel.load(noise if noise.is_absolute() or base is None else base / noise)
        except CalibrationError as exc:
            raise _field_error("world.noise", f"{exc}") from None
    robots = world.get("robots") or list(rec.robots)
    if not isinstance(robots, list) or set(robots) - set(rec.robots):
        raise _field_error("world.robots", f"the recording has robots {list(rec.robots)}, got {robots!r}")
    offset = world.get("offset", 0.0)
    offset = offset if isinstance(offset, (int, float)) else 0.0
    if "agents" not in world:
        agents = []
        for r in robots:
            g = rec.groundtruth[r]
            # The Vicon pose at the start; a robot not yet tracked then starts at its first pose.
            pose = rec.truth_at(r, rec.t0 + offset)
            if not np.isfinite(pose).all():
                i = min(int(np.searchsorted(g.t, rec.t0 + offset)), len(g) - 1)
                pose = np.array([g.x[i], g.y[i], g.heading[i]])
            agents.append({"id": r, "model": "planar-pose", "start": [float(pose[0]), float(pose[1])],
                           "heading": float(pose[2])})
        world["agents"] = agents
    world.setdefault("landmarks", [{"id": s, "position": list(m.xy)} for s, m in sorted(rec.landmarks.items())])
    clock = dict(data.get("clock") or {})
    dt = clock.get("dt", Clock.model_fields["dt"].default)
    left = rec.duration - offset
    if left <= 0:
        raise _field_error("world.offset", f"the recording spans {rec.duration:.3f} s, got an offset of {offset:g} s")
    if "duration" not in clock and isinstance(dt, (int, float)) and dt > 0:
        clock["duration"] = math.floor(left / dt + 1e-9) * dt
    elif isinstance(clock.get("duration"), (int, float)) and clock["duration"] > left + 1e-9:
        raise _field_error("clock.duration", f"the recording has {left:.3f} s after the offset, got {clock['duration']:g} s")
    return {**data, "world": world, "clock": clock}


SCENARIO_FIELDS = schema_fields(Scenario)


def parse(data, source: str = "<scenario>", base: Path | None = None) -> Scenario:
    """A validated scenario; `base`: the directory relative paths in it are taken from."""
    if not isinstance(data, dict):
        got = "an empty file (null)" if data is None else yaml_type(data)
        raise ScenarioError(f"{source}: a scenario is a YAML mapping of fields, got {got}")
    try:
        data = _expand_recorded(data, base)
        return Scenario.model_validate(data)
    except ScenarioError as exc:
        problems = exc.problems or [("", str(exc))]
    except ValidationError as exc:
        problems = problems_of(exc, SCENARIO_FIELDS)
    lines = [f"  {loc}: {msg}" if loc else f"  {msg}" for loc, msg in problems]
    raise ScenarioError(f"{source}: invalid scenario\n" + "\n".join(lines), problems) from None


def _has(world: World, sensors: Sensors) -> dict[str, bool]:
    return {"targets": bool(world.targets), "gnss": sensors.gnss.enabled}


def builtin_names() -> list[str]:
    return sorted(p.name[:-5] for p in resources.files("swarmloc.experiment.scenarios").iterdir() if p.name.endswith(".yaml"))


def load(name_or_path: str | Path) -> Scenario:
    """A built-in scenario by name, or a YAML file by path."""
    text: str
    base = None
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists():
        if not p.is_file():
            raise ScenarioError(f"{p}: no such scenario file")
        text, source, base = p.read_text(), str(p), p.resolve().parent
    elif str(name_or_path) in builtin_names():
        text = resources.files("swarmloc.experiment.scenarios").joinpath(f"{name_or_path}.yaml").read_text()
        source = f"built-in {name_or_path}"
    else:
        raise ScenarioError(f"{name_or_path!r} is neither a scenario file nor a built-in ({', '.join(builtin_names())})")
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ScenarioError(f"{source}: not valid YAML: {exc}") from None
    return parse(data, source, base)
