"""Agent configuration files: one versioned YAML document describes one agent on its own
computer (`swarmloc agent --config FILE`), where there is no scenario.

The pydantic models below are the schema; their field descriptions are the documentation
(docs/deploy.md#configuration follows the same words). Unknown fields are errors, and every
error names its field.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Annotated, Literal, Union

import numpy as np
import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    FiniteFloat,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from agents.control import DEFAULT_ENDPOINT, ENDPOINT
from agents.daemon import AgentConfig
from swarmloc import wire
from swarmloc.errors import readable, schema_fields, yaml_type
from swarmloc.estimators import REGISTRY
from swarmloc.experiment.scenario import (
    SCENARIO_VERSION,
    VEHICLE_MAX_DT,
    Estimation,
    LandmarkSpec,
    ScenarioError,
    parse,
)
from swarmloc.models.motion import MOTION_MODELS, VEHICLES
from swarmloc.node import NodeSpec

CONFIG_VERSION = 1

# Their nodes are built from the whole swarm's roster (every agent's id, model and prior), which
# one agent's file does not have; the registry has no flag for that yet.
NEEDS_ROSTER = {"csl-ctl": "every agent's prior", "il-ctl": "every agent's id",
                "ekf-centre": "the ground station and its UAS"}

MAVLINK_URL = re.compile(r"(udpin|udpout|tcp):[^:\s]+:(\d{1,5})|/\S+")


class ConfigError(ValueError):
    """A configuration that cannot be used; one line per problem, `field: message`."""

    def __init__(self, lines: list[str]):
        super().__init__("\n".join(lines))
        self.lines = lines


class _FieldError(ValueError):
    """Raised in a validator to name a field below (or beside) the one being validated: pydantic
    alone would name the model, or `(top level)`, for a rule that spans fields."""

    def __init__(self, path: tuple, message: str):
        super().__init__(message)
        self.path, self.message = path, message


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


def _base(info: ValidationInfo) -> Path:
    """The directory relative paths are taken from: the configuration file's."""
    return (info.context or {}).get("base", Path.cwd())


class EstimatorChoice(_Strict):
    name: str = Field("ukf-dcl", description="the estimator the agent runs (`swarmloc estimators`, column `agents`)")
    params: dict = Field(default_factory=dict, description="its settings; each estimator documents and validates its "
                         "own (docs/estimators.md)")

    @model_validator(mode="after")
    def _runs_here(self):
        info = REGISTRY.get(self.name)
        if info is None or not info.runs_on_agents:
            raise _FieldError(("name",), f"unknown estimator {self.name!r}; agents run one of: "
                              f"{', '.join(REGISTRY.running())}")
        if self.name in NEEDS_ROSTER:
            raise _FieldError(("name",), f"{self.name} needs {NEEDS_ROSTER[self.name]}, which an agent configuration "
                              "does not have: start it from a scenario (--scenario)")
        try:
            info.settings(self.params)
        except ValueError as exc:  # "estimator NAME params: field: message"; the path says the first part
            raise _FieldError(("params",), str(exc).removeprefix(f"estimator {self.name} params: ")) from None
        return self


class Prior(_Strict):
    position: list[FiniteFloat] = Field(description="known start position (m): 2 numbers (x, y) for a planar model, "
                                        "3 (east, north, up) for uas-ins")
    heading: FiniteFloat | None = Field(None, description="planar-pose: known start heading (rad, counter-clockwise "
                                        "from x), required there; quadrotor, ground-robot: the start yaw (default 0); "
                                        "refused for other models")
    std: float = Field(0.1, gt=0, allow_inf_nan=False, description="std of each coordinate of the start position (m)")
    heading_std: float = Field(1e-3, gt=0, allow_inf_nan=False, description="planar-pose, quadrotor, ground-robot: "
                               "std of the start heading (rad)")


class ZenohSession(_Strict):
    mode: Literal["peer", "client"] = Field("peer", description="peer: one of the swarm's mesh; client: of a Zenoh "
                                            "router")
    listen: list[str] = Field(default_factory=list, description=f"endpoints to listen on, like {DEFAULT_ENDPOINT}")
    connect: list[str] = Field(default_factory=list, description=f"endpoints to connect to (peers or a router); "
                               f"default: [{DEFAULT_ENDPOINT}], or none for a peer that listens (the rule of --connect)")
    gossip: bool = Field(False, description="peer: also dial the peers that the connected ones know of (Zenoh "
                         "gossip). Off: two peers that dial each other can be left in a split session by a link "
                         "outage close to Zenoh's lease (docs/deploy.md#peers-and-routers); each pair of peers "
                         "must then be joined by one side's connect")

    @model_validator(mode="before")
    @classmethod
    def _default_connect(cls, data):
        # As `swarmloc agent` without --connect: the local router (or netsim) on the default
        # port, unless the agent is a peer that others dial.
        if isinstance(data, dict) and "connect" not in data:
            listens = data.get("mode", "peer") == "peer" and data.get("listen")
            data = {**data, "connect": [] if listens else [DEFAULT_ENDPOINT]}
        return data

    @field_validator("listen", "connect")
    @classmethod
    def _endpoints(cls, v):
        for i, e in enumerate(v):
            if not ENDPOINT.fullmatch(e):
                raise _FieldError((i,), f"{e!r} is not a Zenoh endpoint like {DEFAULT_ENDPOINT}")
        return v

    @model_validator(mode="after")
    def _reachable(self):
        # Multicast scouting is off (wire.zenoh_config): without endpoints nobody is ever found.
        if self.mode == "client" and not self.connect:
            raise _FieldError(("connect",), "a client needs an endpoint to connect to (its router)")
        if self.mode == "peer" and not (self.listen or self.connect):
            raise _FieldError(("listen",), "a peer needs endpoints to listen on or connect to (no scouting)")
        if self.mode == "client" and self.gossip:
            raise _FieldError(("gossip",), "gossip is for peers; a client reaches the swarm through its router")
        return self


class ZenohSource(_Strict):
    kind: Literal["zenoh"]
    key: str | None = Field(None, description="key expression the sensor frames (docs/wire.md) arrive on; null: "
                            "swarmloc/<swarm>/agent/<id>/sensors")
    role: Literal["frames", "measurements"] = Field("frames", description="frames: whole ticks the node steps on; "
                                                    "measurements: their ranges, range-bearings, relative positions, "
                                                    "target ranges, fix and pseudoranges join the next frame of "
                                                    "another source (docs/deploy.md#measurements-from-another-source)")

    @field_validator("key")
    @classmethod
    def _key(cls, v):
        if v is not None and (not all(v.split("/")) or re.search(r"[\s?#$]", v)):
            raise ValueError(f"{v!r} is not a Zenoh key expression like swarmloc/default/agent/1/sensors")
        return v


class MavlinkSource(_Strict):
    kind: Literal["mavlink"]
    url: str = Field(description="the flight controller's link: udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, "
                     "or a serial device such as /dev/ttyACM0 (docs/deploy.md#connection-strings)")
    baud: int | None = Field(None, gt=0, description="serial device only: line rate; null: 921600")
    tick: float = Field(0.1, gt=0, allow_inf_nan=False, description="estimator tick (s of the flight controller's "
                        "clock): one sensor frame per tick")
    speed_std: float = Field(0.1, gt=0, allow_inf_nan=False, description="planar models: std of the speed the "
                             "flight controller reports (m/s)")
    heading_std: float = Field(0.02, gt=0, allow_inf_nan=False, description="planar-speed-heading: std of its "
                               "heading (rad)")
    turn_rate_std: float = Field(0.01, gt=0, allow_inf_nan=False, description="planar-pose: std of its yaw rate "
                                 "(rad/s)")
    attitude_std: float = Field(0.01, gt=0, allow_inf_nan=False, description="quadrotor, ground-robot: std of each "
                                "component of the attitude the flight controller reports (quaternion components, or "
                                "the yaw in rad)")
    origin: list[FiniteFloat] | None = Field(None, min_length=3, max_length=3, description="GNSS fixes are ENU "
                                             "metres from this [lat, lon, alt MSL] (the swarm frame's origin); null: "
                                             "the first 3D fix")

    @model_validator(mode="after")
    def _url(self):
        m = MAVLINK_URL.fullmatch(self.url)
        if m is None or (m[2] is not None and not 0 < int(m[2]) < 65536):
            raise _FieldError(("url",), f"{self.url!r} is not udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT or a "
                              "serial device path")
        if self.baud is not None and m[1] is not None:
            raise _FieldError(("baud",), f"a baud rate is for a serial device, not {self.url}")
        return self


class FileSource(_Strict):
    kind: Literal["file"]
    path: Path = Field(description="recorded sensor frames to play back (a run directory's sensors.npz), relative "
                       "to this file's directory")
    speed: float | Literal["as_fast_as_possible"] = Field(1.0, description="recorded seconds per wall second, or "
                                                          "as_fast_as_possible")

    @field_validator("speed", mode="before")
    @classmethod
    def _speed(cls, v):
        # One rule and one message, not one per member of the union.
        if v == "as_fast_as_possible" or (isinstance(v, (int, float)) and not isinstance(v, bool)
                                          and math.isfinite(v) and v > 0):
            return v
        raise ValueError(f"must be a number > 0 (recorded seconds per wall second) or as_fast_as_possible, got "
                         f"{yaml_type(v)}")

    @field_validator("path")
    @classmethod
    def _exists(cls, v, info: ValidationInfo):
        v = _base(info) / v.expanduser()
        if not v.is_file():
            raise ValueError(f"no such file: {v}")
        return v

    def agents(self) -> list[int]:
        """The agent ids the recording holds (ValueError when it is no sensors.npz)."""
        try:
            with np.load(self.path, allow_pickle=False) as f:
                return [int(i) for i in f["ids"]]
        except (OSError, ValueError, KeyError) as exc:
            raise ValueError(f"{self.path} is not a run's sensors.npz: {exc}") from None


class Ros2Source(_Strict):
    kind: Literal["ros2"]
    topic: str = Field("odom", description="a nav_msgs/msg/Odometry topic of the ros2 section's domain (relative "
                       "names are in its namespace), as an rmw_zenoh node publishes it on the same Zenoh network; its "
                       "twist drives a planar model (docs/ros2.md#odometry-from-ros-2)")
    tick: float = MavlinkSource.model_fields["tick"]
    speed_std: float = MavlinkSource.model_fields["speed_std"]
    heading_std: float = MavlinkSource.model_fields["heading_std"]
    turn_rate_std: float = MavlinkSource.model_fields["turn_rate_std"]

    @field_validator("topic")
    @classmethod
    def _topic(cls, v):
        parts = v.strip("/").split("/")
        if not v or v.endswith("/") or not all(re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", p) for p in parts):
            raise ValueError(f"{v!r} is not a ROS 2 topic name like odom or /robot1/odom")
        return v

    @property
    def url(self) -> str:  # what FlightControllerTicks names its source by
        return f"ros2:{self.topic}"


Source = Annotated[Union[ZenohSource, MavlinkSource, FileSource, Ros2Source], Field(discriminator="kind")]
SOURCE_KINDS = ("zenoh", "mavlink", "file", "ros2")


class Ros2(_Strict):
    domain_id: int = Field(0, ge=0, le=232, description="ROS_DOMAIN_ID of the ROS 2 nodes to talk to")
    namespace: str = Field("/swarmloc", description="namespace of the topics: the estimate goes to "
                           "<namespace>/agent<id>/pose and .../odom")
    distro: Literal["jazzy", "humble"] = Field("jazzy", description="jazzy: type hashes in the keys (Jazzy and later); "
                                               "humble: none (TypeHashNotSupported)")
    publish: bool = Field(True, description="publish the estimate on ROS 2 topics (false: only read ros2 sources)")

    @field_validator("namespace")
    @classmethod
    def _namespace(cls, v):
        from swarmloc.wire.ros2 import check_namespace

        return check_namespace(v)

    def topics(self):
        from swarmloc.wire.ros2 import Topics

        return Topics(self.domain_id, self.namespace, self.distro)


class MavlinkOutput(_Strict):
    rate_hz: float = Field(30.0, gt=0, allow_inf_nan=False, description="most estimates sent a second")
    message: Literal["odometry", "vision_position_estimate"] = Field("odometry", description="ODOMETRY (position, "
                                                                     "velocity, attitude) or VISION_POSITION_ESTIMATE "
                                                                     "(position and attitude)")
    frame: Literal["local_ned", "local_frd"] = Field("local_ned", description="ODOMETRY's frame_id: local_ned for "
                                                     "PX4, local_frd for ArduPilot")
    reset_gate: float = Field(5.0, gt=0, allow_inf_nan=False, description="a new swarm estimate that moves the one "
                              "sent by more than this many of its standard deviations changes the reset counter, so "
                              "the autopilot resets to it instead of gating it out (5: PX4's EKF2_EVP_GATE default)")

    @model_validator(mode="after")
    def _frame_is_odometry(self):
        if self.message == "vision_position_estimate" and "frame" in self.model_fields_set:
            raise _FieldError(("frame",), "only ODOMETRY carries a frame (message: odometry)")
        return self


class SetpointOutput(_Strict):
    enabled: bool = Field(False, description="send the vehicle's commands to the flight controller as setpoints; "
                          "nothing moves the vehicle unless this is true")
    rate_hz: float = Field(20.0, gt=2.0, le=100.0, allow_inf_nan=False, description="setpoints sent a second "
                           "(PX4 offboard leaves the mode below 2 Hz)")
    stale_after: float = Field(0.5, gt=0, allow_inf_nan=False, description="s without a new estimate after which "
                               "the setpoint becomes a hold (also while the flight controller's heartbeat is lost)")


class Outputs(_Strict):
    swarm: bool = Field(True, description="publish the estimate on swarmloc/<swarm>/agent/<id>/estimate")
    mavlink: MavlinkOutput | None = Field(None, description="send the estimate to the flight controller of the "
                                          "mavlink source; null: not")
    setpoints: SetpointOutput | None = Field(None, description="a closed-loop vehicle's commands to the flight "
                                             "controller as SET_POSITION_TARGET_LOCAL_NED (docs/deploy.md#setpoints); "
                                             "null: none")
    log: Path | None = Field(None, description="append every estimate to this file as a JSON line (relative to this "
                             "file's directory; docs/deploy.md#the-estimate-log); null: not")
    record: Path | None = Field(None, description="record every frame the agent receives and sends, its sensor frames "
                                "and estimates, as MCAP to this file, written as it goes (relative to this file's "
                                "directory; docs/run-format.md#runmcap; `swarmloc rerun` plays it); null: not")

    @field_validator("log", "record")
    @classmethod
    def _relative_to_file(cls, v, info: ValidationInfo):
        return None if v is None else _base(info) / v.expanduser()


class Security(_Strict):
    keys: Path | None = Field(None, description="the swarm's key directory (`swarmloc keys new`, or a copy holding "
                              "swarm.key, ca.pem and this agent's agent-<id>.pem and .key): every frame sealed and "
                              "opened with its swarm.key (docs/security.md); relative to this file's directory. "
                              "null: frames are not authenticated, which the agent warns about at start")
    tls: bool = Field(False, description="Zenoh over TLS with mutual authentication: the endpoints become tls/, "
                      "the agent shows its certificate agent-<id>.pem and trusts the swarm's ca.pem (needs keys)")

    @field_validator("keys")
    @classmethod
    def _readable(cls, v, info: ValidationInfo):
        if v is None:
            return None
        v = _base(info) / v.expanduser()
        if not v.exists():  # its files are read with the agent's id (below): agent-<id>.secret, members.json
            raise ValueError(f"{v}: no such key directory")
        return v


class SwarmClock(_Strict):
    epoch: FiniteFloat | None = Field(None, description="UNIX time (s, the system clock: keep it NTP- or "
                                      "GPS-disciplined) of the swarm's tick 0: mavlink ticks end at epoch + k * tick "
                                      "and a recording plays from it, on every agent alike; null: each agent counts "
                                      "ticks from its own first sample")
    offset_bound_ms: float = Field(10.0, gt=0, allow_inf_nan=False, description="a peer whose clock is estimated "
                                   "further than this from ours is logged and counted (docs/deploy.md#clock-offsets)")


class VehicleReference(_Strict):
    """The circle a closed-loop vehicle's controller tracks (a scenario's `motion: {kind: track}`)."""

    center: list[FiniteFloat] = Field(min_length=3, max_length=3, description="the circle's centre (m, east, north, "
                                      "up; up is the height flown or driven at)")
    radius: float = Field(0.0, ge=0, allow_inf_nan=False, description="m; 0: hold the centre")
    period: FiniteFloat = Field(30.0, description="s per lap; negative: clockwise")
    phase: FiniteFloat = Field(0.0, description="rad: the reference's angle around the centre at the swarm's t = 0, "
                               "counter-clockwise from east")
    yaw: FiniteFloat | None = Field(None, description="a constant yaw to hold (rad); null: face along the circle")

    @field_validator("period")
    @classmethod
    def _nonzero(cls, v):
        if v == 0:
            raise ValueError("must not be 0")
        return v


class RosterEntry(_Strict):
    id: int = Field(ge=0, description="another vehicle's agent id")
    model: Literal["quadrotor", "ground-robot"] = Field(description="its model")


class VehicleConfig(_Strict):
    reference: VehicleReference | None = Field(None, description="closed loop: the circle the vehicle's controller "
                                               "tracks, whose commands outputs.setpoints sends; null: estimation only")
    roster: list[RosterEntry] = Field(default_factory=list, description="the swarm's other vehicles, whose relative "
                                      "positions (a camera's, on a measurements source) and poses this one fuses")
    force_noise: float = Field(0.02, ge=0, allow_inf_nan=False, description="std of the model's thrust or surge force "
                               "error (N): the filter's process noise")
    moment_noise: float = Field(2e-4, ge=0, allow_inf_nan=False, description="std of its moment error (N m)")


class AgentFileConfig(_Strict):
    version: int = Field(description=f"configuration format version; this swarmloc reads {CONFIG_VERSION}")
    id: int = Field(ge=0, description="this agent's id, unique in the swarm")
    swarm: str = Field("default", description="swarm name: the key prefix swarmloc/<swarm>/")
    estimator: EstimatorChoice = Field(default_factory=EstimatorChoice)
    model: str = Field(description="the platform's motion model (swarmloc.models.motion.MOTION_MODELS); one the estimator "
                       "runs on")
    prior: Prior
    landmarks: list[LandmarkSpec] = Field(default_factory=list, description="the known landmark map, observed by "
                                          "range and bearing")
    # The same rules, words and defaults as a scenario's `estimation`.
    gate: float | None = Estimation.model_fields["gate"]
    gate_open_after: int = Estimation.model_fields["gate_open_after"]
    zenoh: ZenohSession = Field(default_factory=lambda: ZenohSession.model_validate({}),
                                description="the agent's Zenoh session; default: a peer connecting to "
                                            f"{DEFAULT_ENDPOINT}")
    sensors: list[Source] = Field(default_factory=lambda: [ZenohSource(kind="zenoh")], min_length=1,
                                  description="where sensor data comes from; default: the swarm's sensor key")
    outputs: Outputs = Field(default_factory=Outputs)
    clock: SwarmClock = Field(default_factory=SwarmClock, description="the swarm clock ticks are numbered from")
    vehicle: VehicleConfig | None = Field(None, description="quadrotor, ground-robot: closed loop and the swarm's other "
                                          "vehicles; null: estimation only, alone")
    security: Security = Field(default_factory=Security, description="frame authentication")
    state_dir: Path | None = Field(None, description="directory of the checkpoint agent-<id>.state.npy (relative to "
                                   "this file's directory; created at start); null: no checkpoint")
    ros2: Ros2 | None = Field(None, description="ROS 2 over Zenoh, as rmw_zenoh speaks it, with no ROS install "
                              "(docs/ros2.md): the estimate on ROS 2 topics, odometry from one; null: none")
    radio: Literal["direct", "netsim"] = Field("direct", description="direct: radio frames straight to the peers' "
                                               "radio/rx keys, the network decides (a real swarm); netsim: through a "
                                               "netsim, which decides who hears them and drives the clock (a rehearsal "
                                               "of these files against an emulated swarm, lockstep included)")

    @field_validator("version")
    @classmethod
    def _version(cls, v):
        if v != CONFIG_VERSION:
            raise ValueError(f"unsupported version {v}; this swarmloc reads version {CONFIG_VERSION}")
        return v

    @field_validator("swarm")
    @classmethod
    def _swarm(cls, v):
        wire.Keys(v)  # the CLI's rule (--swarm): a ValueError names the bad name
        return v

    @field_validator("model")
    @classmethod
    def _model(cls, v, info: ValidationInfo):
        if v not in MOTION_MODELS:
            raise ValueError(f"unknown model {v!r}; known: {', '.join(MOTION_MODELS)}")
        est = info.data.get("estimator")  # absent when it failed its own validation
        if est is not None and v not in REGISTRY[est.name].models:
            raise ValueError(f"estimator {est.name} runs on {', '.join(REGISTRY[est.name].models)}, not {v}")
        return v

    @field_validator("prior")
    @classmethod
    def _prior_fits(cls, v, info: ValidationInfo):
        model = info.data.get("model")
        if model is None:
            return v
        want = MOTION_MODELS[model].position_dim
        if len(v.position) != want:
            raise _FieldError(("position",), f"{len(v.position)} numbers; model {model} needs {want}")
        if model == "planar-pose" and v.heading is None:
            raise _FieldError(("heading",), "required for model planar-pose (its state holds the heading)")
        if model not in ("planar-pose", *VEHICLES) and v.heading is not None:
            raise _FieldError(("heading",), f"only planar-pose and the vehicles have a heading in their state, not {model}")
        return v

    @field_validator("landmarks")
    @classmethod
    def _unique_landmarks(cls, v):
        ids = [m.id for m in v]
        if len(set(ids)) != len(ids):
            raise ValueError(f"landmark ids must be unique, got {ids}")
        return v

    @field_validator("sensors")
    @classmethod
    def _one_flight_controller(cls, v):
        if sum(s.kind == "mavlink" for s in v) > 1:
            raise ValueError("at most one mavlink source (one flight controller)")
        return v

    @field_validator("sensors")
    @classmethod
    def _frames_to_merge_into(cls, v):
        measurements = [i for i, s in enumerate(v) if s.kind == "zenoh" and s.role == "measurements"]
        if measurements and len(measurements) == len(v):
            raise _FieldError((measurements[0], "role"), "measurements join the frames of another source, and no "
                              "source gives frames (a mavlink or file source, or a zenoh one with role: frames)")
        return v

    @model_validator(mode="after")
    def _netsim_frames(self):
        # Under netsim a sensor frame from anyone but netsim is refused (src-mismatch), so
        # frames on a driver's key would all be dropped.
        if self.radio == "netsim":
            for i, s in enumerate(self.sensors):
                if s.kind == "zenoh" and s.role == "frames" and s.key not in (None, self.sensor_key):
                    raise _FieldError(("sensors", i, "key"), f"radio netsim: sensor frames come from netsim, on "
                                      f"{self.sensor_key} (null), not {s.key}")
        return self

    @model_validator(mode="after")
    def _ros2_sources(self):
        for i, s in enumerate(self.sensors):
            if s.kind == "ros2" and self.ros2 is None:
                raise _FieldError(("sensors", i, "topic"), "a ros2 source needs the ros2 section (its domain)")
            if s.kind == "ros2" and self.model not in ("planar-speed-heading", "planar-pose"):
                raise _FieldError(("sensors", i, "kind"), f"odometry from ROS 2 drives a planar model, not {self.model}")
        return self

    @field_validator("sensors")
    @classmethod
    def _recorded_agent(cls, v, info: ValidationInfo):
        aid = info.data.get("id")
        for i, s in enumerate(v):
            if s.kind == "file" and aid is not None and aid not in (ids := s.agents()):
                raise _FieldError((i, "path"), f"{s.path} holds agents {ids}, not {aid}")
        return v

    @field_validator("state_dir")
    @classmethod
    def _relative_to_file(cls, v, info: ValidationInfo):
        return None if v is None else _base(info) / v.expanduser()

    @field_validator("outputs")
    @classmethod
    def _fc_for_output(cls, v, info: ValidationInfo):
        sensors = info.data.get("sensors")
        if v.mavlink is not None and sensors is not None and not any(s.kind == "mavlink" for s in sensors):
            raise _FieldError(("mavlink",), "needs a sensors entry of kind mavlink: the flight controller link it is "
                              "sent on")
        return v

    @field_validator("vehicle")
    @classmethod
    def _vehicle_fits(cls, v, info: ValidationInfo):
        model, aid = info.data.get("model"), info.data.get("id")
        if v is None or model is None:
            return v
        if model not in VEHICLES:
            raise ValueError(f"only for {' and '.join(VEHICLES)}, not {model}")
        ids = [r.id for r in v.roster]
        if len(set(ids)) != len(ids) or aid in ids:
            raise _FieldError(("roster",), f"ids must be unique and not this agent's ({aid}), got {ids}")
        return v

    @model_validator(mode="after")
    def _vehicle_ticks(self):
        # After every field: sensors, outputs and vehicle are checked against each other here.
        if self.model in VEHICLES:
            for i, s in enumerate(self.sensors):
                if s.kind == "mavlink" and s.tick > VEHICLE_MAX_DT:
                    raise _FieldError(("sensors", i, "tick"), f"{s.tick:g} s: a {self.model}'s dynamics and controller "
                                      f"need a tick of at most {VEHICLE_MAX_DT:g} s")
        sp = self.outputs.setpoints
        if sp is not None and sp.enabled:
            if not any(s.kind == "mavlink" for s in self.sensors):
                raise _FieldError(("outputs", "setpoints"), "needs a sensors entry of kind mavlink: the flight "
                                  "controller the setpoints go to")
            if self.model not in VEHICLES or self.vehicle is None or self.vehicle.reference is None:
                raise _FieldError(("outputs", "setpoints"), "only a closed-loop vehicle has commands: model quadrotor "
                                  "or ground-robot with vehicle.reference")
        return self

    @field_validator("security")
    @classmethod
    def _keys_of_this_swarm(cls, v, info: ValidationInfo):
        swarm, aid = info.data.get("swarm"), info.data.get("id")
        if v.tls and v.keys is None:
            raise _FieldError(("tls",), "needs keys: the directory with ca.pem and this agent's certificate")
        if v.keys is not None and swarm is not None:
            from swarmloc.wire.auth import Keyring, member_of

            try:  # the agent's own keys (per-member identity) and the swarm's directory
                ring = Keyring.load(v.keys, None if aid is None else member_of(aid))
            except ValueError as exc:
                raise _FieldError(("keys",), str(exc)) from None
            if ring.swarm != swarm:
                raise _FieldError(("keys",), f"{v.keys} holds the keys of swarm {ring.swarm!r}, not {swarm!r}")
            missing = [f for f in ("ca.pem", f"agent-{aid}.pem", f"agent-{aid}.key") if not (v.keys / f).is_file()]
            if v.tls and aid is not None and missing:
                raise _FieldError(("tls",), f"{v.keys} has no {', '.join(missing)} (swarmloc keys add {v.keys} {aid})")
        return v

    @property
    def sensor_key(self) -> str:
        return wire.Keys(self.swarm).sensors(self.id)

    @property
    def keyring(self):
        from swarmloc.wire.auth import Keyring, member_of

        return None if self.security.keys is None else Keyring.load(self.security.keys, member_of(self.id))

    @property
    def state_file(self) -> Path | None:
        return None if self.state_dir is None else self.state_dir / f"agent-{self.id}.state.npy"


def _vehicle_text(v: VehicleConfig) -> str:
    ref = "estimation only" if v.reference is None else (
        f"closed loop on a circle about {v.reference.center}, radius {v.reference.radius:g} m, "
        f"{v.reference.period:g} s a lap")
    roster = ", ".join(f"{r.id} {r.model}" for r in v.roster) or "none"
    return f"{ref}; other vehicles: {roster}"


def _utc(unix: float) -> str:
    import datetime

    return datetime.datetime.fromtimestamp(unix, datetime.timezone.utc).isoformat(timespec="milliseconds")


def _problems(exc: ValidationError) -> list[str]:
    lines = []
    for err in exc.errors():
        loc = list(err["loc"])
        # A sensor's loc carries its union tag after the index: sensors.0.mavlink.url.
        loc = [p for i, p in enumerate(loc) if not (p in SOURCE_KINDS and i and isinstance(loc[i - 1], int))]
        cause = (err.get("ctx") or {}).get("error")
        if isinstance(cause, _FieldError):
            loc, msg = loc + list(cause.path), cause.message
        else:
            msg = readable(err)
            if err["type"] in ("union_tag_invalid", "union_tag_not_found"):
                loc.append("kind")
        loc = [p for i, p in enumerate(loc) if isinstance(p, int) or p in CONFIG_FIELDS
               or (err["type"] == "extra_forbidden" and i == len(loc) - 1)]
        line = f"{'.'.join(map(str, loc)) or '(top level)'}: {msg}"
        if line not in lines:
            lines.append(line)
    return lines


CONFIG_FIELDS = schema_fields(AgentFileConfig) | {"kind"}


def parse_config(data, base: Path | None = None) -> AgentFileConfig:
    """A validated configuration from its YAML's data; `base`: the directory of relative paths."""
    if not isinstance(data, dict):
        got = "an empty file (null)" if data is None else yaml_type(data)
        raise ConfigError([f"(top level): an agent configuration is a YAML mapping of fields, got {got}"])
    try:
        return AgentFileConfig.model_validate(data, context={"base": base or Path.cwd()})
    except ValidationError as exc:
        raise ConfigError(_problems(exc)) from None


def load(path: str | Path) -> AgentFileConfig:
    """The configuration in the YAML file at `path` (ConfigError listing every bad field)."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ConfigError([f"cannot read it: {exc.strerror or exc}"]) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        raise ConfigError([f"not valid YAML: {where}{getattr(exc, 'problem', None) or exc}"]) from None
    return parse_config(data, path.resolve().parent)


def scenario(cfg: AgentFileConfig):
    """The one-agent scenario whose agent `cfg.id` is this configuration's node."""
    p = cfg.prior
    me = {"id": cfg.id, "model": cfg.model, "start": p.position, "heading": p.heading or 0.0}
    extra = {}
    if cfg.model in VEHICLES:
        # A vehicle's node reads the swarm's vehicles (their models: relative positions name
        # them), its controller's circle (closed loop) and the tick its controller samples at.
        v = cfg.vehicle or VehicleConfig()
        agents = [me, *({"id": r.id, "model": r.model, "start": [0.0, 0.0, 0.0], "motion": {"kind": "track"}}
                        for r in v.roster)]
        if v.reference is not None:
            me["motion"] = {"kind": "track", **v.reference.model_dump()}
        ticks = [s.tick for s in cfg.sensors if s.kind == "mavlink"]
        extra = {"world": {"agents": agents, "control": "agents" if v.reference is not None else "netsim"},
                 "clock": {"dt": ticks[0] if ticks else VEHICLE_MAX_DT / 2.5},
                 "sensors": {"vehicle": {"force_noise": v.force_noise, "moment_noise": v.moment_noise}}}
    data = {
        "version": SCENARIO_VERSION, "name": f"agent-{cfg.id}",
        "world": {"agents": [me], "landmarks": [m.model_dump() for m in cfg.landmarks]},
        # On a real platform the prior is what the file says: no drawn error.
        "estimation": {"initial_std": p.std, "initial_heading_std": p.heading_std, "initial_error": False,
                       "gate": cfg.gate, "gate_open_after": cfg.gate_open_after},
        "estimator": {"name": cfg.estimator.name, "params": cfg.estimator.params},
    }
    for key, value in extra.items():
        data[key] = {**data.get(key, {}), **value}
    return parse(data, source=f"agent {cfg.id}'s configuration")


def node_spec(cfg: AgentFileConfig) -> NodeSpec:
    """The agent's node, built by the estimator's registered factory as in a run.

    Through a one-agent scenario (as `--start` does): each factory reads its own part of a
    scenario (prior, gate, landmarks, IMU model, seed), so one construction path serves every
    estimator, a new one included, and a file and a scenario saying the same build the same node."""
    info = REGISTRY[cfg.estimator.name]
    try:
        return info.node_spec(scenario(cfg), cfg.id, info.settings(cfg.estimator.params))
    except (ScenarioError, ValueError) as exc:
        raise ConfigError([f"estimator: {' '.join(str(exc).split())}"]) from None


def daemon_config(cfg: AgentFileConfig) -> AgentConfig:
    """The daemon's settings: the file's Zenoh session and radio, its sources and outputs."""
    z = cfg.zenoh
    return AgentConfig(swarm=cfg.swarm, connect=tuple(z.connect), listen=tuple(z.listen), mode=z.mode,
                       direct=cfg.radio == "direct",
                       gossip=z.gossip and z.mode == "peer",
                       state_file=cfg.state_file,
                       sensor_keys=tuple(s.key or cfg.sensor_key for s in cfg.sensors
                                         if s.kind == "zenoh" and s.role == "frames"),
                       measurement_keys=tuple(s.key or cfg.sensor_key for s in cfg.sensors
                                              if s.kind == "zenoh" and s.role == "measurements"),
                       sources=tuple(s for s in cfg.sensors if s.kind != "zenoh"),
                       publish_swarm=cfg.outputs.swarm, mavlink_output=cfg.outputs.mavlink,
                       setpoints=cfg.outputs.setpoints if cfg.outputs.setpoints and cfg.outputs.setpoints.enabled
                       else None, clock_bound=cfg.clock.offset_bound_ms * 1e-3,
                       estimate_log=cfg.outputs.log, epoch=cfg.clock.epoch, keyring=cfg.keyring,
                       tls_dir=cfg.security.keys if cfg.security.tls else None,
                       ros2=cfg.ros2.topics() if cfg.ros2 is not None else None,
                       ros2_publish=cfg.ros2 is not None and cfg.ros2.publish, record=cfg.outputs.record,
                       record_meta={"config": cfg.model_dump(mode="json")} if cfg.outputs.record is not None else None)


WILDCARDS = ("0.0.0.0", "[::]", "::")
BINDING = re.compile(r"(\w+)[/:](.*):(\d+)")  # tcp/HOST:PORT (Zenoh), udpin:HOST:PORT (MAVLink)


def _same_port(a: str, b: str) -> bool:
    """Two bindings one port cannot take both: the same protocol and port on the same address,
    or on every address (0.0.0.0) and one of them; anything else (a serial device) when equal."""
    (pa, ha, na), (pb, hb, nb) = ((m.groups() if (m := BINDING.fullmatch(re.split(r"[?#]", x)[0])) else (x, "", ""))
                                  for x in (a, b))
    return (pa, na) == (pb, nb) and (ha == hb or ha in WILDCARDS or hb in WILDCARDS)


def hostmates(configs: list[tuple[Path, AgentFileConfig]]) -> list[str]:
    """Why these agents cannot share one process, one `FILE: field: message` line each; empty
    when they can. No field has to be equal across them (each agent has its own Zenoh session,
    keys, sources and outputs): what is refused is what one process cannot hold twice."""
    lines = []
    ids, listens, links, files = [], [], [], []

    def clash(path, field, value, taken, same, why):
        for opath, ofield, ovalue in taken:
            if same(value, ovalue):
                other = "" if ovalue == value else f" ({ovalue})"
                lines.append(f"{path}: {field}: {value} is {opath}'s {ofield} too{other}: {why}")
                return
        taken.append((path, field, value))

    for path, cfg in configs:
        clash(path, "id", cfg.id, ids, int.__eq__, "the agents of one process are told apart by their ids (their "
              "threads, log lines and checkpoints agent-<id>.state.npy)")
        for i, e in enumerate(cfg.zenoh.listen):
            clash(path, f"zenoh.listen.{i}", e, listens, _same_port, "two Zenoh sessions cannot listen on one port")
        for i, src in enumerate(cfg.sensors):
            if src.kind == "mavlink":
                clash(path, f"sensors.{i}.url", src.url, links, _same_port,
                      "a flight controller link is one agent's (a serial device or a UDP port opens once, and a "
                      "flight controller follows one companion's estimate)")
        for name in ("log", "record"):
            out = getattr(cfg.outputs, name)
            if out is not None:
                clash(path, f"outputs.{name}", out.resolve(), files, Path.__eq__, "two agents cannot write one file")
    return lines


def summary(cfg: AgentFileConfig, spec: NodeSpec) -> list[str]:
    """What `--check-config` prints: the agent as it would start."""
    p, z, o = cfg.prior, cfg.zenoh, cfg.outputs
    params = cfg.estimator.params
    prior = f"position {p.position} +- {p.std:g} m"
    if p.heading is not None:
        prior += f", heading {p.heading:g} +- {p.heading_std:g} rad"

    def source(s) -> str:
        if s.kind == "zenoh":
            return f"zenoh {s.key or cfg.sensor_key}" + (" (measurements)" if s.role == "measurements" else "")
        if s.kind == "mavlink":
            return f"mavlink {s.url}" + (f" at {s.baud} baud" if s.baud else "")
        if s.kind == "ros2":
            return f"ros2 {s.topic} (nav_msgs/msg/Odometry, domain {cfg.ros2.domain_id})"
        return f"file {s.path} " + ("as fast as possible" if s.speed == "as_fast_as_possible" else f"at {s.speed:g}x")

    outputs = [f"swarm {wire.Keys(cfg.swarm).estimate(cfg.id)}"] if o.swarm else []
    if o.mavlink is not None:
        m = o.mavlink
        outputs.append(f"mavlink {m.message}" + (f" {m.frame}" if m.message == "odometry" else "") + f" at {m.rate_hz:g} Hz")
    if o.setpoints is not None:
        sp = o.setpoints
        outputs.append(f"setpoints at {sp.rate_hz:g} Hz, hold after {sp.stale_after:g} s" if sp.enabled else
                       "setpoints off (enabled: false)")
    if o.log is not None:
        outputs.append(f"log {o.log}")
    if o.record is not None:
        outputs.append(f"record {o.record}")
    if cfg.ros2 is not None and cfg.ros2.publish:
        t = cfg.ros2.topics()
        outputs.append(f"ros2 {t.pose(cfg.id)}, {t.odom(cfg.id)} (domain {t.domain_id}, {t.distro})")
    gate = "off" if cfg.gate is None else f"{cfg.gate:g}, open after {cfg.gate_open_after}"
    rows = [
        ("id", str(cfg.id)), ("swarm", cfg.swarm),
        ("estimator", cfg.estimator.name + (f" ({', '.join(f'{k}: {v}' for k, v in params.items())})" if params else "")),
        ("model", cfg.model),
        ("prior", prior), ("landmarks", ", ".join(f"{m.id} {m.position}" for m in cfg.landmarks) or "none"),
        ("gate", gate), ("radio", "direct: frames straight to the peers" if cfg.radio == "direct" else
                         "netsim: frames and clock through a netsim"),
        ("zenoh", f"{z.mode}; listen {', '.join(z.listen) or '-'}; connect {', '.join(z.connect) or '-'}"
                  + ("; gossip" if z.gossip else "")),
        ("sensors", "; ".join(map(source, cfg.sensors))), ("outputs", "; ".join(outputs) or "none"),
        ("clock", ("own: ticks from the first sample" if cfg.clock.epoch is None else
                   f"swarm: tick 0 at UNIX {cfg.clock.epoch:.3f} ({_utc(cfg.clock.epoch)})")
         + f"; peers' offsets logged beyond {cfg.clock.offset_bound_ms:g} ms"),
        *([("vehicle", _vehicle_text(cfg.vehicle))] if cfg.vehicle is not None else []),
        ("checkpoint", str(cfg.state_file) if cfg.state_file else "none"),
        ("security", (f"frames authenticated with {cfg.security.keys}" + ("; Zenoh over mutual TLS" if
                      cfg.security.tls else "")) if cfg.security.keys else "none: frames are not authenticated"),
        ("node", spec.factory),
    ]
    return [f"{k:<11}{v}" for k, v in rows]
