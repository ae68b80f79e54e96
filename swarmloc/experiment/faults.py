"""Faults as data: what can go wrong, in a scenario timeline or injected live.

Every fault is a pydantic model, validated with errors that name the field; the same schema
serves YAML timelines (with `at`) and `swarmloc inject`. netsim.faults.FaultState holds the
active ones and answers the radio's questions.
"""

from __future__ import annotations

from typing import Annotated, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError, model_validator

from swarmloc.errors import readable, yaml_type


class _Fault(BaseModel):
    # NaN or infinity in a fault would reach metrics.json, which JSON cannot hold.
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    at: float | None = Field(None, ge=0, description="scenario timelines: simulated time (s) the fault happens")
    duration: float | None = Field(None, gt=0, description="clear automatically after this many seconds (CLI: --for)")


class Cut(_Fault):
    """Cut a radio link: both directions, or only a -> b."""

    action: Literal["cut"] = "cut"
    link: tuple[int, int] = Field(description="the two agent ids [a, b]")
    direction: Literal["both", "forward"] = Field("both", description="forward: only frames from a to b are lost")

    @model_validator(mode="after")
    def _two(self):
        if self.link[0] == self.link[1]:
            raise ValueError(f"link must name two different agents, got {list(self.link)}")
        return self


class Restore(_Fault):
    action: Literal["restore"] = "restore"
    link: tuple[int, int] = Field(description="the link to restore (both directions)")


class RadioOff(_Fault):
    """The node's radio neither sends nor receives."""

    action: Literal["radio-off"] = "radio-off"
    node: int


class RadioOn(_Fault):
    action: Literal["radio-on"] = "radio-on"
    node: int


class Partition(_Fault):
    """Split the swarm into groups that cannot hear each other (nodes not listed form one more group)."""

    action: Literal["partition"] = "partition"
    groups: list[list[int]] = Field(min_length=1)

    @model_validator(mode="after")
    def _disjoint(self):
        flat = [a for g in self.groups for a in g]
        if len(flat) != len(set(flat)):
            raise ValueError("partition groups must not share agents")
        return self


class Heal(_Fault):
    action: Literal["heal"] = "heal"


class Loss(_Fault):
    """Extra loss probability on every frame of a link, of a node (sent or received), or everywhere."""

    action: Literal["loss"] = "loss"
    probability: float = Field(ge=0.0, le=1.0)
    node: int | None = None
    link: tuple[int, int] | None = None

    @model_validator(mode="after")
    def _target(self):
        if self.node is not None and self.link is not None:
            raise ValueError("give node or link (or neither, for every frame), not both")
        return self


class ClearLoss(_Fault):
    action: Literal["clear-loss"] = "clear-loss"
    node: int | None = None
    link: tuple[int, int] | None = None


class JammerOn(_Fault):
    """A jammer: adds power at receivers (log-distance radio) or blocks receivers within radius_m (unit disk)."""

    action: Literal["jammer"] = "jammer"
    name: str = Field("j1", pattern=r"^[A-Za-z0-9_.-]{1,32}$")
    position: tuple[float, float] = Field(description="(m)")
    power_dbm: float = Field(30.0, description="transmit power (dBm)")
    band_hz: float | None = Field(None, gt=0, description="jammed bandwidth; None: the whole channel")
    velocity: tuple[float, float] = Field((0.0, 0.0), description="m/s, for a moving jammer")
    radius_m: float = Field(50.0, gt=0, description="unit-disk radio only: receivers within this distance lose every frame")


class JammerOff(_Fault):
    action: Literal["jammer-off"] = "jammer-off"
    name: str = "j1"


class GnssOff(_Fault):
    """GNSS outage: the node's GNSS sensor stops reporting."""

    action: Literal["gnss-off"] = "gnss-off"
    node: int


class GnssOn(_Fault):
    action: Literal["gnss-on"] = "gnss-on"
    node: int


class CommandOff(_Fault):
    """The vehicle's command stream is lost: commands the agent publishes never reach the vehicle,
    which keeps the last one that did (closed loop, `world.control: agents`)."""

    action: Literal["command-off"] = "command-off"
    node: int


class CommandOn(_Fault):
    action: Literal["command-on"] = "command-on"
    node: int


class Kill(_Fault):
    """Kill the agent process (the launcher does it); with duration, restart it afterwards."""

    action: Literal["kill"] = "kill"
    node: int


class Restart(_Fault):
    action: Literal["restart"] = "restart"
    node: int


Fault = Annotated[Union[Cut, Restore, RadioOff, RadioOn, Partition, Heal, Loss, ClearLoss, JammerOn, JammerOff,
                        GnssOff, GnssOn, CommandOff, CommandOn, Kill, Restart], Field(discriminator="action")]
FAULT_ADAPTER = TypeAdapter(Fault)
FAULT_TYPES = (Cut, Restore, RadioOff, RadioOn, Partition, Heal, Loss, ClearLoss, JammerOn, JammerOff, GnssOff, GnssOn,
               CommandOff, CommandOn, Kill, Restart)
ACTIONS = [t.model_fields["action"].default for t in FAULT_TYPES]

# What clears what: the inverse of each activating fault, used by `duration` and by `clear`.
INVERSE = {"cut": "restore", "radio-off": "radio-on", "partition": "heal", "loss": "clear-loss",
           "jammer": "jammer-off", "gnss-off": "gnss-on", "command-off": "command-on", "kill": "restart"}


class FaultError(ValueError):
    pass


def parse_fault(data: dict) -> _Fault:
    try:
        return FAULT_ADAPTER.validate_python(data)
    except ValidationError as exc:
        if not isinstance(data, dict):
            raise FaultError(f"a fault is a mapping of fields (action: ...), got {yaml_type(data)}") from None
        lines = [f"{'.'.join(str(p) for p in e['loc'][1:]) or 'action'}: {readable(e)}" for e in exc.errors()]
        raise FaultError("; ".join(lines)) from None


def nodes_named(f: _Fault) -> list[int]:
    out = [f.node] if getattr(f, "node", None) is not None else []
    if getattr(f, "link", None) is not None:
        out += list(f.link)
    for g in getattr(f, "groups", None) or []:
        out += g
    return out


def inverse_of(f: _Fault) -> _Fault | None:
    """The fault that clears f (for `duration` / --for)."""
    match f:
        case Cut():
            return Restore(link=f.link)
        case RadioOff():
            return RadioOn(node=f.node)
        case Partition():
            return Heal()
        case Loss():
            return ClearLoss(node=f.node, link=f.link)
        case JammerOn():
            return JammerOff(name=f.name)
        case GnssOff():
            return GnssOn(node=f.node)
        case CommandOff():
            return CommandOn(node=f.node)
        case Kill():
            return Restart(node=f.node)
    return None
