"""Scenario files: one versioned YAML document describes a whole experiment.

The pydantic models below are the schema; their field descriptions are the documentation
(docs/scenarios.md is generated from the same words). Unknown fields are errors, so a typo
never silently falls back to a default.
"""

from __future__ import annotations

import math
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal, Union

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from swarmloc.faults import ACTIONS, Fault, nodes_named
from swarmloc.models import MOTION_MODELS

PRIOR_STREAM = 0x9A10  # keeps the prior's draws apart from netsim's world streams

SCENARIO_VERSION = 1


class ScenarioError(ValueError):
    """A scenario that cannot be used; the message names every offending field."""


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


Motion = Annotated[Union[CircleMotion, RandomMotion], Field(discriminator="kind")]


class AgentSpec(_Strict):
    id: int = Field(ge=0, description="agent id, unique in the swarm")
    model: str = Field("planar-speed-heading", description="motion model name (swarmloc.models.MOTION_MODELS)")
    start: list[float] = Field(description="initial position (m), known to the agent")
    heading: float = Field(0.0, description="initial heading (rad), known to the agent")
    motion: Motion = Field(default_factory=CircleMotion)

    @field_validator("model")
    @classmethod
    def _known_model(cls, v):
        if v not in MOTION_MODELS:
            raise ValueError(f"unknown model {v!r}; known: {sorted(MOTION_MODELS)}")
        return v

    @model_validator(mode="after")
    def _start_dim(self):
        want = MOTION_MODELS[self.model].state_dim
        if len(self.start) != want or not all(math.isfinite(v) for v in self.start):
            raise ValueError(f"start must be {want} finite numbers for model {self.model}")
        return self


class World(_Strict):
    agents: list[AgentSpec] = Field(min_length=1)

    @field_validator("agents")
    @classmethod
    def _unique_ids(cls, v):
        ids = [a.id for a in v]
        if len(set(ids)) != len(ids):
            raise ValueError(f"agent ids must be unique, got {ids}")
        return v


class OdometrySensor(_Strict):
    speed_noise: float = Field(0.5, ge=0, description="std of measured speed (m/s)")
    turn_rate_noise: float = Field(1e-3, ge=0, description="std of measured turn rate (rad/s); heading is its integral")


class RangeSensor(_Strict):
    noise: float = Field(1.0, gt=0, description="std of a range measurement (m)")
    probability: float = Field(0.5, ge=0, le=1, description="chance per step and per slot that a measurement happens")
    max_per_step: int = Field(1, ge=0, description="measurement slots per step in the whole swarm")
    max_range: float = Field(math.inf, gt=0, description="sensing range (m): pairs farther apart are never measured")


class GnssSensor(_Strict):
    enabled: bool = Field(False, description="publish a GNSS position fix every step")
    noise: float = Field(2.0, gt=0, description="std of each horizontal coordinate (m)")


class Sensors(_Strict):
    odometry: OdometrySensor = Field(default_factory=OdometrySensor)
    range: RangeSensor = Field(default_factory=RangeSensor)
    gnss: GnssSensor = Field(default_factory=GnssSensor)


RADIO_MODELS = ("unit-disk", "log-distance")


class Estimation(_Strict):
    initial_std: float = Field(0.1, gt=0, description="std of the known initial position (m)")
    initial_error: bool = Field(True, description="draw each platform's initial estimate from N(start, "
                                "initial_std^2), as the prior claims (false: start exactly at the truth, "
                                "which makes NEES read low until the process noise dominates)")
    spread: float | None = Field(None, gt=0, description="unscented transform spread n + lambda; default: "
                                 "twice the state dimension (no negative sigma weight)")
    rejoin_std: float | None = Field(15.0, gt=0, description="UKF-DCL: a node whose position std (largest axis, m) "
                                     "exceeds this is lost (a restart, a long isolation): it takes no range into its "
                                     "filter until a window of ranges pins its position down by multilateration; "
                                     "null: never")


ESTIMATORS = ("il", "ukf-dcl", "ukf-ccl")


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
    estimators: list[Literal["il", "ukf-dcl", "ukf-ccl"]] = Field(default_factory=lambda: list(ESTIMATORS))
    faults: list[Fault] = Field(default_factory=list, description="fault timeline: each fault with `at` (docs/faults.md)")

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

    @property
    def agent_ids(self) -> list[int]:
        return sorted(a.id for a in self.world.agents)

    def agent(self, aid: int) -> AgentSpec:
        return next(a for a in self.world.agents if a.id == aid)

    def prior(self, aid: int) -> tuple[np.ndarray, np.ndarray]:
        """Platform aid's initial estimate and covariance. The error is drawn from its own
        seeded stream, so every process (agent, in-process runner, references) gets the same."""
        est, start = self.estimation, np.array(self.agent(aid).start, float)
        P0 = np.eye(len(start)) * est.initial_std**2
        if not est.initial_error:
            return start, P0
        rng = np.random.default_rng([self.seed, PRIOR_STREAM, aid])
        return start + est.initial_std * rng.standard_normal(len(start)), P0

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


def parse(data, source: str = "<scenario>") -> Scenario:
    if not isinstance(data, dict):
        raise ScenarioError(f"{source}: a scenario is a YAML mapping, got {type(data).__name__}")
    try:
        return Scenario.model_validate(data)
    except ValidationError as exc:
        lines = []
        for err in exc.errors():
            loc = ".".join(str(p) for p in err["loc"] if not (isinstance(p, str) and (p in ("circle", "random") or p in ACTIONS)))
            lines.append(f"  {loc or '(top level)'}: {err['msg']}")
        raise ScenarioError(f"{source}: invalid scenario\n" + "\n".join(lines)) from None


def builtin_names() -> list[str]:
    return sorted(p.name[:-5] for p in resources.files("swarmloc.scenarios").iterdir() if p.name.endswith(".yaml"))


def load(name_or_path: str | Path) -> Scenario:
    """A built-in scenario by name, or a YAML file by path."""
    text: str
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists():
        if not p.is_file():
            raise ScenarioError(f"{p}: no such scenario file")
        text, source = p.read_text(), str(p)
    elif str(name_or_path) in builtin_names():
        text = resources.files("swarmloc.scenarios").joinpath(f"{name_or_path}.yaml").read_text()
        source = f"built-in {name_or_path}"
    else:
        raise ScenarioError(f"{name_or_path!r} is neither a scenario file nor a built-in ({', '.join(builtin_names())})")
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ScenarioError(f"{source}: not valid YAML: {exc}") from None
    return parse(data, source)
