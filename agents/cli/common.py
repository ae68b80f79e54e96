"""What every `swarmloc` command shares: one-line errors, option checks, the common options
(--swarm, --connect, --out, --seed, ...) and the scenario a command line names."""

from __future__ import annotations

import math
import sys
from typing import TYPE_CHECKING

import typer
from typer.core import TyperGroup

from agents.control import DEFAULT_ENDPOINT, ENDPOINT, Failure
from swarmloc import wire

if TYPE_CHECKING:
    from swarmloc.experiment.scenario import Scenario


def scenarios_module():
    """swarmloc.experiment.scenario, imported when a command needs it: an agent built from --spec never
    parses a scenario, and pydantic would cost it about 17 MB."""
    from swarmloc.experiment import scenario

    return scenario


class SwarmlocGroup(TyperGroup):
    """Every error is one line on stderr, `error: ...` (typer frames usage errors in a box)."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        try:
            code = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except typer.TyperException as exc:  # usage errors and Failure
            message = _plain(exc.format_message())
            if message:  # empty for a group called without a command: its help is already out
                error(message)
            sys.exit(exc.exit_code)
        sys.exit(code if isinstance(code, int) else 0)


# typer converts option values with pydantic, whose messages are not a command line's words.
PYDANTIC_WORDS = {"Input should be a valid integer, unable to parse string as an integer": "must be a whole number",
                  "Input should be a valid number, unable to parse string as a number": "must be a number",
                  "Input should be a valid boolean, unable to interpret input": "must be true or false"}


def _plain(message: str) -> str:
    for theirs, ours in PYDANTIC_WORDS.items():
        message = message.replace(theirs, ours)
    return message


def error(message: str) -> None:
    """One `error: ...` line on stderr."""
    typer.echo(f"{typer.style('error:', fg='red', bold=True)} {message}", err=True)


# Negative numbers are arguments here (`inject loss -0.1`, `inject jammer -40 10`), not options;
# the fault validation then says what is out of range.
NUMBERS = {"ignore_unknown_options": True}


def console(stderr: bool = False):
    """What commands print on: complete in a pipe or a file (swarmloc.process.console)."""
    from swarmloc.process import console

    return console(stderr)


def in_range(lo: float, hi: float | None = None, *, above: bool = False):
    """Option callback: the number, if given, must be finite and at least lo (above: more than lo), at most hi."""
    bounds = f"{lo}..{hi}" if hi is not None else f"{'>' if above else '>='} {lo}"

    def check(value):
        if value is not None and not (math.isfinite(value) and (value > lo if above else value >= lo)
                                      and (hi is None or value <= hi)):
            raise typer.BadParameter(f"must be {bounds}, got {value}")
        return value

    return check


def swarm_name(value: str) -> str:
    try:
        wire.Keys(value)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None
    return value


"""A Zenoh endpoint, protocol/address[?metadata][#config]: what --connect, --listen and an agent
configuration's `zenoh` accept."""


def check_endpoints(values: list[str] | None) -> list[str] | None:
    for v in values or ():
        if not ENDPOINT.fullmatch(v):
            raise typer.BadParameter(f"{v!r} is not a Zenoh endpoint like {DEFAULT_ENDPOINT}")
    return values


def parse_numbers(text: str, option: str, count: int) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != count or not all(map(math.isfinite, values)):
        raise typer.BadParameter(f"expected {count} comma-separated finite numbers, got {text!r}", param_hint=[option])
    return values


def parse_ids(text: str, what: str) -> list[int]:
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise typer.BadParameter(f"expected comma-separated agent ids, got {text!r}", param_hint=[what]) from None


# The scenario fields the command line sets, by the option that sets them: an error in one
# names the option the user typed, not the field.
OPTION_FIELDS = {"seed": "--seed", "estimator": "--estimator", "estimator.name": "--estimator",
                 "clock.mode": "--realtime", "clock.speed": "--speed", "clock.duration": "--duration"}


def load_scenario(name: str, seed: int | None = None, estimator: str | None = None, realtime: bool | None = None,
                  speed: float | None = None, duration: float | None = None) -> "Scenario":
    """A scenario with the command line's overrides (--seed, --estimator, --realtime/--lockstep,
    --speed, --duration)."""
    S = scenarios_module()
    try:
        sc = S.load(name)
    except S.ScenarioError as exc:
        raise Failure(str(exc), 2) from None
    changes: dict = {"seed": seed} if seed is not None else {}
    if estimator is not None and estimator != sc.estimator.name:
        from swarmloc.estimators import REGISTRY

        models = sorted({a.model for a in sc.world.agents if a.localized})
        if not set(models) <= set(REGISTRY[estimator].models):
            raise Failure(f"--estimator {estimator} runs on models {list(REGISTRY[estimator].models)}; "
                          f"{sc.name} has {models}", 2)
        # Another estimator's parameters are not this one's: start from its defaults.
        changes["estimator"] = {"name": estimator, "params": {}}
    if realtime is not None:
        changes["clock.mode"] = "realtime" if realtime else "lockstep"
    if speed is not None:
        if changes.get("clock.mode", sc.clock.mode) != "realtime":
            raise typer.BadParameter(f"a lockstep run waits for the swarm every tick and has no speed; add --realtime "
                                     f"({sc.name} runs in {sc.clock.mode})", param_hint=["--speed"])
        changes["clock.speed"] = speed
    if duration is not None:
        changes["clock.duration"] = duration
    try:
        return sc.with_overrides(**changes) if changes else sc
    except S.ScenarioError as exc:
        raise Failure(str(exc.renamed(sc.name, OPTION_FIELDS)), 2) from None


def estimator_name(value: str | None) -> str | None:
    from swarmloc.estimators import REGISTRY

    if value is not None and value not in REGISTRY.running():
        raise typer.BadParameter(f"unknown estimator {value!r}; agents run one of: {', '.join(REGISTRY.running())}")
    return value


EstimatorOpt = typer.Option(None, "--estimator", callback=estimator_name,
                            help="the estimator the agents run, instead of the scenario's (`swarmloc estimators`)")


SwarmOpt = typer.Option("default", "--swarm", callback=swarm_name, help="swarm name: the key prefix swarmloc/<swarm>/")
RunSwarmOpt = typer.Option(None, "--swarm", callback=lambda v: None if v is None else swarm_name(v),
                           help="swarm name: the key prefix swarmloc/<swarm>/ (default: default, or default-2, -3, ... "
                                "while another run holds it; printed at the start)")
RealtimeOpt = typer.Option(None, "--realtime/--lockstep", help="tick in real time (times --speed), waiting for nobody; "
                           "--lockstep: wait for the swarm every tick, deterministic for a seed (default: the "
                           "scenario's clock.mode)")
SpeedOpt = typer.Option(None, "--speed", callback=in_range(0, above=True), help="with --realtime: simulated seconds per "
                        "wall second (default: the scenario's clock.speed)")
DurationOpt = typer.Option(None, "--duration", callback=in_range(0, above=True),
                           help="simulated seconds to run (default: the scenario's clock.duration)")
ConnectOpt = typer.Option(None, "--connect", callback=check_endpoints,
                          help=f"Zenoh endpoint of netsim or a router (default: the one `swarmloc run` registered for "
                               f"--swarm, else {DEFAULT_ENDPOINT})")


OutOpt = typer.Option(None, "--out", "-o", help="run directory; must be new or empty unless --force (default: a new runs/<name>-<time>)")
SeedOpt = typer.Option(None, "--seed", callback=in_range(0), help="override the scenario's seed (>= 0)")
PortOpt = typer.Option(None, "--port", callback=in_range(0, 65535),
                       help="netsim's Zenoh port on 127.0.0.1 (default: 7447, or a free one if busy; 0: any free)")
PlotsOpt = typer.Option(True, "--plots/--no-plots", help="write plots/*.png into the run directory")
ForceOpt = typer.Option(False, "--force", help="empty an existing, non-empty --out run directory first")
RestartOpt = typer.Option(False, "--restart-crashed",
                          help="restart an agent that crashes (up to 3 times); it resumes from its checkpoint")
