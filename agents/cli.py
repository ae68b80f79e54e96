"""The `swarmloc` command line: run a swarm, start one agent, inject faults, show status.

Only the commands live here: agents/launcher.py runs a swarm (netsim is started as a separate
process, `python -m netsim`, so agents and netsim still never import each other) and
agents/control.py talks to a running one. The launcher, rich and Zenoh are imported inside
the commands that need them, so `swarmloc agent` starts without the first two.
"""

from __future__ import annotations

import json
import logging
import math
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Literal, Optional

import typer
from typer.core import TyperGroup

from agents.control import DEFAULT_ENDPOINT, ENDPOINT, ControlClient, Failure, NobodyAnswers, NotRunning
from agents import service
from swarmloc import wire


def _scenarios():
    """swarmloc.scenario, imported when a command needs it: an agent built from --spec never
    parses a scenario, and pydantic would cost it about 17 MB."""
    from swarmloc import scenario

    return scenario


class _Swarmloc(TyperGroup):
    """Every error is one line on stderr, `error: ...` (typer frames usage errors in a box)."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        try:
            code = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except typer.TyperException as exc:  # usage errors and Failure
            message = exc.format_message()
            if message:  # empty for a group called without a command: its help is already out
                error(message)
            sys.exit(exc.exit_code)
        sys.exit(code if isinstance(code, int) else 0)


def error(message: str) -> None:
    """One `error: ...` line on stderr."""
    typer.echo(f"{typer.style('error:', fg='red', bold=True)} {message}", err=True)


app = typer.Typer(cls=_Swarmloc, add_completion=False, no_args_is_help=True,
                  help="swarmloc: cooperative localization over a real (or emulated) network.")
inject_app = typer.Typer(no_args_is_help=True, help="Inject a fault into a running swarm (applies from the next tick).")
app.add_typer(inject_app, name="inject")
keys_app = typer.Typer(no_args_is_help=True, help="The swarm's keys: the frame key and the certificates of its "
                       "members (docs/security.md).")
app.add_typer(keys_app, name="keys")
# Negative numbers are arguments here (`inject loss -0.1`, `inject jammer -40 10`), not options;
# the fault validation then says what is out of range.
NUMBERS = {"ignore_unknown_options": True}


def _console():
    from rich.console import Console

    return Console()


# ------------------------------------------------------------------------------------ checks


def _in_range(lo: float, hi: float | None = None, *, above: bool = False):
    """Option callback: the number, if given, must be finite and at least lo (above: more than lo), at most hi."""
    bounds = f"{lo}..{hi}" if hi is not None else f"{'>' if above else '>='} {lo}"

    def check(value):
        if value is not None and not (math.isfinite(value) and (value > lo if above else value >= lo)
                                      and (hi is None or value <= hi)):
            raise typer.BadParameter(f"must be {bounds}, got {value}")
        return value

    return check


def _swarm_name(value: str) -> str:
    try:
        wire.Keys(value)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None
    return value


"""A Zenoh endpoint, protocol/address[?metadata][#config]: what --connect, --listen and an agent
configuration's `zenoh` accept."""


def _endpoints(values: list[str] | None) -> list[str] | None:
    for v in values or ():
        if not ENDPOINT.fullmatch(v):
            raise typer.BadParameter(f"{v!r} is not a Zenoh endpoint like {DEFAULT_ENDPOINT}")
    return values


def _numbers(text: str, option: str, count: int) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != count or not all(map(math.isfinite, values)):
        raise typer.BadParameter(f"expected {count} comma-separated finite numbers, got {text!r}", param_hint=[option])
    return values


def _ids(text: str, what: str) -> list[int]:
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise typer.BadParameter(f"expected comma-separated agent ids, got {text!r}", param_hint=[what]) from None


def load_scenario(name: str, seed: int | None = None, estimator: str | None = None) -> "Scenario":
    """A scenario with the command line's overrides (--seed, --estimator)."""
    try:
        sc = _scenarios().load(name)
        changes = {"seed": seed} if seed is not None else {}
        if estimator is not None and estimator != sc.estimator.name:
            from swarmloc.estimators import REGISTRY

            models = sorted({a.model for a in sc.world.agents if a.localized})
            if not set(models) <= set(REGISTRY[estimator].models):
                raise Failure(f"--estimator {estimator} runs on models {list(REGISTRY[estimator].models)}; "
                              f"{sc.name} has {models}", 2)
            # Another estimator's parameters are not this one's: start from its defaults.
            changes["estimator"] = {"name": estimator, "params": {}}
        return sc.with_overrides(**changes) if changes else sc
    except _scenarios().ScenarioError as exc:
        raise Failure(str(exc), 2) from None


def _estimator_name(value: str | None) -> str | None:
    from swarmloc.estimators import REGISTRY

    if value is not None and value not in REGISTRY.running():
        raise typer.BadParameter(f"unknown estimator {value!r}; agents run one of: {', '.join(REGISTRY.running())}")
    return value


EstimatorOpt = typer.Option(None, "--estimator", callback=_estimator_name,
                            help="the estimator the agents run, instead of the scenario's (`swarmloc estimators`)")


SwarmOpt = typer.Option("default", "--swarm", callback=_swarm_name, help="swarm name: the key prefix swarmloc/<swarm>/")
ConnectOpt = typer.Option(None, "--connect", callback=_endpoints,
                          help=f"Zenoh endpoint of netsim or a router (default: the one `swarmloc run` registered for "
                               f"--swarm, else {DEFAULT_ENDPOINT})")


# ------------------------------------------------------------------------------------ scenarios


@app.command("estimators")
def list_estimators():
    """List the estimators: what agents can run (scenario `estimator`, --estimator) and the
    references computed offline from a run's sensor stream (scenario `references`)."""
    from rich.table import Table

    from swarmloc.estimators import REGISTRY

    t = Table("name", "agents", "reference", "models", "paper", "what it does")
    for e in REGISTRY:
        t.add_row(e.name, "yes" if e.runs_on_agents else "", "yes" if e.reference else "", ", ".join(e.models),
                  e.paper, e.description)
    _console().print(t)



@app.command("scenarios")
def list_scenarios(name: Optional[str] = typer.Argument(None, help="print this built-in scenario's YAML, to copy and edit")):
    """List the built-in scenarios, or print one as YAML (swarmloc scenarios goel10 > mine.yaml)."""
    from importlib import resources

    from rich.table import Table

    if name is not None:
        if name not in _scenarios().builtin_names():
            raise typer.BadParameter(f"no built-in scenario {name!r}; built-in: {', '.join(_scenarios().builtin_names())}",
                                     param_hint=["NAME"])
        typer.echo(resources.files("swarmloc.scenarios").joinpath(f"{name}.yaml").read_text(), nl=False)
        return
    t = Table("name", "agents", "duration", "radio", "estimator", "description")
    for name in _scenarios().builtin_names():
        sc = _scenarios().load(name)
        t.add_row(name, str(len(sc.world.agents)), f"{sc.clock.duration:g} s @ {sc.clock.dt:g} s",
                  " ".join([sc.radio["model"], *([f"{sc.radio['range_m']:g} m"] if "range_m" in sc.radio else [])]),
                  sc.estimator.name, sc.description)
    _console().print(t)


# ------------------------------------------------------------------------------------ run

OutOpt = typer.Option(None, "--out", "-o", help="run directory; must be new or empty unless --force (default: a new runs/<name>-<time>)")
SeedOpt = typer.Option(None, "--seed", callback=_in_range(0), help="override the scenario's seed (>= 0)")
PortOpt = typer.Option(None, "--port", callback=_in_range(0, 65535),
                       help="netsim's Zenoh port on 127.0.0.1 (default: 7447, or a free one if busy; 0: any free)")
PlotsOpt = typer.Option(True, "--plots/--no-plots", help="write plots/*.png into the run directory")
ForceOpt = typer.Option(False, "--force", help="empty an existing, non-empty --out run directory first")
RestartOpt = typer.Option(False, "--restart-crashed",
                          help="restart an agent that crashes (up to 3 times); it resumes from its checkpoint")


def _run(scenario: str, out: Path | None, seed: int | None, swarm: str, port: int | None, plots: bool, force: bool,
         restart_crashed: bool, estimator: str | None = None) -> None:
    from agents.launcher import run_swarm

    run_swarm(load_scenario(scenario, seed, estimator), out, swarm, port, plots, force, restart_crashed)


@app.command()
def run(
    scenario: str = typer.Argument(..., help="built-in scenario name (see `swarmloc scenarios`) or a YAML file"),
    out: Optional[Path] = OutOpt, seed: Optional[int] = SeedOpt, swarm: str = SwarmOpt, port: Optional[int] = PortOpt,
    plots: bool = PlotsOpt, force: bool = ForceOpt, restart_crashed: bool = RestartOpt,
    estimator: Optional[str] = EstimatorOpt,
):
    """Run a scenario: netsim plus one agent process per platform, over Zenoh on loopback.

    A crashed agent is reported and the run goes on without it; only a failing netsim fails the run."""
    _run(scenario, out, seed, swarm, port, plots, force, restart_crashed, estimator)


@app.command()
def demo(out: Optional[Path] = OutOpt, seed: Optional[int] = SeedOpt, swarm: str = SwarmOpt, port: Optional[int] = PortOpt,
         plots: bool = PlotsOpt, force: bool = ForceOpt, restart_crashed: bool = RestartOpt):
    """Run the built-in wang2019 scenario (UKF-DCL paper, 4 platforms, 801 ticks)."""
    _run("wang2019", out, seed, swarm, port, plots, force, restart_crashed)


@app.command()
def replay(
    path: Path = typer.Argument(..., help="an MR.CLAM dataset directory (e.g. MRCLAM_Dataset6)"),
    estimator: str = typer.Option("ukf-dcl", "--estimator", callback=_estimator_name, help="what the agents run"),
    dt: float = typer.Option(0.1, "--dt", callback=_in_range(0, above=True), help="tick (s)"),
    duration: Optional[float] = typer.Option(None, "--duration", callback=_in_range(0, above=True),
                                             help="seconds to replay (default: to the recording's end)"),
    offset: float = typer.Option(0.0, "--offset", callback=_in_range(0), help="start this many seconds in"),
    robots: Optional[str] = typer.Option(None, "--robots", help="replay only these robots, e.g. 1,2,3"),
    landmarks: bool = typer.Option(True, "--landmarks/--no-landmarks", help="deliver landmark observations (known map)"),
    observations: bool = typer.Option(True, "--observations/--no-observations",
                                      help="deliver the robots' observations of each other"),
    gate: Optional[float] = typer.Option(0.999, "--gate", callback=_in_range(0),
                                         help="chi-square gate probability; 0 turns the gate off"),
    odometry_horizon: Optional[float] = typer.Option(None, "--odometry-horizon", callback=_in_range(0, above=True),
                                                     help="fit the odometry noise to its drift over this many seconds "
                                                     "instead of tick by tick (docs/replay.md)"),
    realtime: bool = typer.Option(False, "--realtime", help="tick at the recording's pace (times --speed) "
                                  "instead of as fast as the agents go"),
    speed: float = typer.Option(1.0, "--speed", callback=_in_range(0, above=True), help="--realtime: recorded seconds "
                                "per wall second"),
    out: Optional[Path] = OutOpt, seed: Optional[int] = SeedOpt, swarm: str = SwarmOpt, port: Optional[int] = PortOpt,
    plots: bool = PlotsOpt, force: bool = ForceOpt,
):
    """Replay a recorded MR.CLAM dataset through the agent processes (Leung et al., IJRR 2011):
    netsim plays each robot's odometry and range-bearing observations on the sensor keys, its
    Vicon poses drive the radio and score the estimates. Prints position and heading RMSE and
    NEES per robot and estimator; writes the usual run directory."""
    from agents.launcher import run_swarm

    sc = _scenarios()
    try:
        scenario = sc.replay_scenario(path, estimator=estimator or "ukf-dcl", dt=dt, duration=duration, offset=offset,
                                      robots=_ids(robots, "--robots") if robots else None, landmarks=landmarks,
                                      observations=observations, gate=gate or None,
                                      mode="realtime" if realtime else "lockstep", speed=speed, seed=seed or 0,
                                      odometry_horizon=odometry_horizon)
    except sc.ScenarioError as exc:
        raise Failure(str(exc), 2) from None
    n = scenario.sensors
    _console().print(f"noise fitted against Vicon: speed {n.odometry.speed_noise:.4f} m/s, turn rate "
                     f"{n.odometry.turn_rate_noise:.4f} rad/s, range {n.range_bearing.range_noise:.4f} m, bearing "
                     f"{n.range_bearing.bearing_noise:.4f} rad")
    run_swarm(scenario, out, swarm, port, plots, force, False)


@app.command()
def study(
    spec: Path = typer.Argument(..., help="study spec (YAML, docs/study.md)"),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="study directory; rerun with the same one to resume "
                                       "(default: studies/<name>)"),
    runs: Optional[int] = typer.Option(None, "--runs", callback=_in_range(1), help="runs per point, instead of the spec's"),
    workers: Optional[int] = typer.Option(None, "--workers", callback=_in_range(1),
                                          help="local worker processes, instead of the spec's (default: CPU count)"),
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="run on this Dask distributed scheduler, e.g. "
                                            "tcp://10.0.0.5:8786, instead of the local process pool"),
    plots: bool = typer.Option(True, "--plots/--no-plots", help="write plots/*.png into the study directory"),
    force: bool = typer.Option(False, "--force", help="discard the runs of a different study in --out"),
):
    """Monte Carlo study: sweep scenario parameters, many seeded in-process runs per point, in
    parallel; resumable after Ctrl-C; writes results.csv, summary.csv and plots."""
    import signal
    import subprocess

    # The study drives netsim's world and radio, so it runs as netsim's process, as `run` does.
    args = [str(spec), *(["--out", str(out)] if out else []), *(["--runs", str(runs)] if runs else []),
            *(["--workers", str(workers)] if workers else []), *(["--scheduler", scheduler] if scheduler else []),
            *([] if plots else ["--no-plots"]), *(["--force"] if force else [])]
    child = subprocess.Popen([sys.executable, "-m", "netsim.study", *args])
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the study; it stops and says how to resume
    try:
        code = child.wait()
    finally:
        signal.signal(signal.SIGINT, previous)
    raise typer.Exit(code)


# ------------------------------------------------------------------------------------ agent


def _configured_agent(ctx: typer.Context, path: Path, check: bool):
    """The node and daemon settings of an agent configuration file; (None, None) once
    --check-config has printed its summary. A bad file is one `error:` line per field, exit 2."""
    from agents.config import ConfigError, daemon_config, load, node_spec, summary

    # By the source's name: typer vendors its own click, whose ParameterSource is not click's.
    given = [p.opts[0] for p in ctx.command.params if p.name not in ("config", "check_config", "verbose")
             and getattr(ctx.get_parameter_source(p.name), "name", "DEFAULT") != "DEFAULT"]
    if given:
        raise Failure(f"--config is the whole agent: give it without {', '.join(given)}", 2)
    try:
        cfg = load(path)
        spec = node_spec(cfg)
    except ConfigError as exc:
        for line in exc.lines:
            error(f"{path}: {line}")
        raise typer.Exit(2) from None
    if check:
        typer.echo(f"{path}: a valid agent configuration")
        for line in summary(cfg, spec):
            typer.echo(f"  {line}")
        return None, None
    if cfg.state_dir is not None:
        try:
            cfg.state_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise Failure(f"{path}: state_dir: cannot create {cfg.state_dir}: {exc.strerror or exc}", 2) from None
    return spec.build(), daemon_config(cfg)


@app.command()
def agent(
    ctx: typer.Context,
    id: Optional[int] = typer.Option(None, "--id", help="this agent's id (required without --config)"),
    config: Optional[Path] = typer.Option(None, "--config", help="the whole agent from a configuration file (YAML, "
                                          "docs/deploy.md#configuration): no scenario, no other option but -v"),
    check_config: bool = typer.Option(False, "--check-config", help="with --config: validate the file, print a "
                                      "summary of the agent and exit"),
    scenario: Optional[str] = typer.Option(None, "--scenario", help="take start point, model and filter settings from a scenario"),
    spec: Optional[Path] = typer.Option(None, "--spec", help="build the node from a node spec file (JSON, what `run` "
                                        "writes to logs/agent-ID.node.json): no scenario is parsed in this process"),
    start: Optional[str] = typer.Option(None, "--start", help="known start position, e.g. '0,0' (without --scenario)"),
    initial_std: float = typer.Option(0.1, "--initial-std", callback=_in_range(0, above=True),
                                      help="std of the start position (m), without --scenario"),
    estimator: Optional[str] = typer.Option(None, "--estimator", callback=_estimator_name,
                                            help="the estimator to run (default: the scenario's; without --scenario, ukf-dcl)"),
    swarm: str = SwarmOpt,
    connect: Optional[list[str]] = typer.Option(None, "--connect", callback=_endpoints,
                                                help=f"Zenoh endpoint to connect to (repeatable; default: {DEFAULT_ENDPOINT}, none for a peer with --listen)"),
    listen: Optional[list[str]] = typer.Option(None, "--listen", callback=_endpoints,
                                               help="Zenoh endpoint to listen on (peer mode; repeatable)"),
    mode: Literal["client", "peer"] = typer.Option("client", "--mode", help="Zenoh mode: client (of netsim) or peer"),
    direct: bool = typer.Option(False, "--direct", help="no netsim: publish radio frames straight to peers"),
    state_file: Optional[Path] = typer.Option(None, "--state-file", help="checkpoint here (after a sensor frame, at most every 0.2 s); resume from it at start"),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="log at INFO: what the agent waits for, what it does"),
):
    """Start one agent daemon (used by `run`; on a companion computer, run it by hand)."""
    from agents.daemon import AgentConfig, OpenError, load_node, serve

    if check_config and config is None:
        raise Failure("--check-config needs --config FILE", 2)
    if config is None and id is None:
        raise typer.BadParameter("required without --config", param_hint=["--id"])
    if config is not None:
        node, cfg = _configured_agent(ctx, config, check_config)
        if node is None:  # --check-config: the summary is out
            return
    elif spec is not None:
        if scenario or start or estimator:
            raise Failure("--spec is the whole node: give it without --scenario, --start or --estimator", 2)
        try:
            node = load_node(spec, id)
        except ValueError as exc:
            raise Failure(str(exc), 2) from None
    elif scenario:
        from swarmloc.estimators import make_nodes

        sc = load_scenario(scenario, estimator=estimator)
        if id not in sc.agent_ids:
            raise typer.BadParameter(f"agent {id} is not in scenario {sc.name} (agents {sc.agent_ids})", param_hint=["--id"])
        node = make_nodes(sc.estimator.name, sc, [id])[id]
    elif start:
        from swarmloc.estimators import REGISTRY, make_nodes

        estimator = estimator or "ukf-dcl"
        if "planar-speed-heading" not in REGISTRY[estimator].models:
            raise typer.BadParameter(f"{estimator} needs --scenario (--start is a planar robot's position)",
                                     param_hint=["--estimator"])
        # A one-platform scenario: the node is built exactly as from a scenario file.
        sc = _scenarios().parse({"version": _scenarios().SCENARIO_VERSION, "name": f"agent-{id}",
                              "world": {"agents": [{"id": id, "start": _numbers(start, "--start", 2)}]},
                              "estimation": {"initial_std": initial_std, "initial_error": False},
                              "estimator": {"name": estimator}})
        node = make_nodes(estimator, sc, [id])[id]
    else:
        raise Failure("give --config, --scenario, --start or --spec", 2)
    if config is None:
        cfg = AgentConfig(swarm=swarm, connect=tuple(connect or ([] if mode == "peer" and listen else [DEFAULT_ENDPOINT])), listen=tuple(listen or ()), mode=mode,
                          direct=direct, state_file=state_file)
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING,
                        format=f"%(asctime)s agent-{node.id} %(levelname)s %(message)s")
    try:
        serve(node, cfg)
    except OpenError as exc:
        raise Failure(str(exc)) from None


@app.command()
def router(
    listen: list[str] = typer.Option(..., "--listen", callback=_endpoints,
                                     help="Zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)"),
    connect: Optional[list[str]] = typer.Option(None, "--connect", callback=_endpoints,
                                                help="another router to join (repeatable)"),
    keys: Optional[Path] = typer.Option(None, "--keys", help="the swarm's key directory: mutual TLS with its "
                                        "router.pem, and access control (docs/security.md#transport)"),
    agents: Optional[str] = typer.Option(None, "--agents", help="with --keys: the agent ids access control lets in, "
                                         "e.g. 1,2,3 (revoked ones never)"),
    direct: bool = typer.Option(False, "--direct", help="with --keys: agents talk to each other (no netsim)"),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="log at INFO"),
):
    """Run a Zenoh router for a swarm of agents in client mode (docs/deploy.md#peers-and-routers)."""
    import zenoh

    from agents.daemon import zenoh_message
    from swarmloc import exit_on_sigterm

    conf = wire.zenoh_config("router", listen, connect or ())
    if keys is not None:
        from agents import tls

        swarm = _keyring(keys).swarm
        if agents is None:
            raise Failure("--keys needs --agents: the ids access control lets in", 2)
        ids = sorted(set(_ids(agents, "--agents")) - {int(m[6:]) for m in _revoked(keys) if m.startswith("agent-")})
        try:
            conf = json.dumps(tls.zenoh_acl(tls.zenoh_tls(conf, keys, "router"), swarm, ids, direct=direct))
        except (ValueError, FileNotFoundError) as exc:
            raise Failure(f"{keys}: {exc} (swarmloc keys add {keys} router --host ADDRESS)", 2) from None
    elif agents is not None or direct:
        raise Failure("--agents and --direct are for access control: give --keys", 2)
    exit_on_sigterm()
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING,
                        format="%(asctime)s router %(levelname)s %(message)s")
    try:
        session = zenoh.open(zenoh.Config.from_json5(conf))
    except zenoh.ZError as exc:
        raise Failure(f"cannot start a Zenoh router on {', '.join(listen)}: {zenoh_message(exc)}") from None
    secured = "" if keys is None else f" (mutual TLS, access control for swarm {swarm}: agents {ids or 'none'})"
    typer.echo(f"router up on {', '.join(json.loads(conf)['listen']['endpoints'])}{secured}"
               + (f", joined to {', '.join(connect)}" if connect else "") + "; Ctrl-C or SIGTERM stops it", err=True)
    try:
        while True:  # timed: the exit SIGTERM raises needs the main thread awake
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        session.close()


KeyDir = typer.Argument(..., help="the swarm's key directory")
from swarmloc.auth import KEY_FILE  # noqa: E402  (the frame key's file in a key directory)


def _keyring(directory: Path):
    from swarmloc.auth import Keyring

    try:
        return Keyring.load(directory / KEY_FILE)
    except ValueError as exc:
        raise Failure(str(exc), 2) from None


def _fingerprint(data: bytes) -> str:
    import hashlib

    return hashlib.sha256(data).hexdigest()[:16]


def _member(name: str) -> str:
    """A member's certificate name: `3` and `agent-3` are agent 3's."""
    return f"agent-{name}" if name.isdigit() else name


@keys_app.command("new")
def keys_new(directory: Path = KeyDir, swarm: str = SwarmOpt):
    """Create a swarm's key directory (mode 0700): the frame key (swarm.key) and the swarm's
    certificate authority (ca.pem, ca.key) that `keys add` signs members' certificates with."""
    from agents import tls
    from swarmloc.auth import Keyring

    if (directory / KEY_FILE).exists() or (directory / tls.CA_KEY).exists():
        raise Failure(f"{directory} already holds a swarm's keys; `keys rotate` replaces the frame key", 2)
    try:
        directory.mkdir(mode=0o700, parents=True, exist_ok=True)
        ring = Keyring.generate(swarm)
        ring.save(directory / KEY_FILE)
        tls.new_ca(directory, swarm)
    except OSError as exc:
        raise Failure(f"cannot write {directory}: {exc.strerror or exc}") from None
    typer.echo(f"{directory}: swarm {swarm}; frame key {ring.current} ({_fingerprint(ring.keys[ring.current])}) in "
               f"{KEY_FILE}; certificate authority ca.pem, ca.key (keep ca.key here, give members ca.pem)")


@keys_app.command("add")
def keys_add(directory: Path = KeyDir,
             name: str = typer.Argument(..., help="an agent id (3 or agent-3), netsim, operator or router"),
             host: Optional[list[str]] = typer.Option(None, "--host", help="an address or DNS name the member "
                                                      "listens on, put in its certificate (repeatable)")):
    """Issue a member's certificate (NAME.pem, NAME.key, signed by the swarm's CA) for Zenoh TLS."""
    from agents import tls

    _keyring(directory)
    member = _member(name)
    try:
        cert, key = tls.issue(directory, member, host or [])
    except (ValueError, FileNotFoundError) as exc:
        raise Failure(f"{directory}: {exc}", 2) from None
    revoked = _revoked(directory)
    if member in revoked:
        revoked.remove(member)
        (directory / "revoked.json").write_text(json.dumps(sorted(revoked)))
    typer.echo(f"{cert}, {key}: give the member these, ca.pem and {KEY_FILE}")


def _revoked(directory: Path) -> set[str]:
    path = directory / "revoked.json"
    return set(json.loads(path.read_text())) if path.exists() else set()


@keys_app.command("revoke")
def keys_revoke(directory: Path = KeyDir, name: str = typer.Argument(..., help="an agent id, netsim, operator or router")):
    """Revoke a member: its certificate is deleted and listed as revoked (access control grants it
    nothing), and the frame key is rotated, so what it holds opens nothing new."""
    member = _member(name)
    ring = _keyring(directory)
    for suffix in (".pem", ".key"):
        (directory / f"{member}{suffix}").unlink(missing_ok=True)
    revoked = _revoked(directory) | {member}
    (directory / "revoked.json").write_text(json.dumps(sorted(revoked)))
    old, kid = ring.current, ring.rotate()
    ring.save(directory / KEY_FILE)
    typer.echo(f"{member} revoked; frame key {old} dropped, key {kid} ({_fingerprint(ring.keys[kid])}) current: copy "
               f"{KEY_FILE} to every other member and restart it")


@keys_app.command("rotate")
def keys_rotate(directory: Path = KeyDir):
    """Replace the frame key with a new one (a copy of swarm.key was lost): frames sealed with the old
    key are refused from then on, so every member needs the new file."""
    ring = _keyring(directory)
    old, kid = ring.current, ring.rotate()
    ring.save(directory / KEY_FILE)
    typer.echo(f"{directory / KEY_FILE}: key {old} dropped, key {kid} ({_fingerprint(ring.keys[kid])}) current; copy "
               "it to every member and restart it")


@keys_app.command("show")
def keys_show(directory: Path = KeyDir):
    """A key directory's swarm, key fingerprints, members and revocations (never a key)."""
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding

    ring = _keyring(directory)
    typer.echo(f"{directory}: swarm {ring.swarm}")
    for kid, key in sorted(ring.keys.items()):
        typer.echo(f"  frame key {kid}  sha256 {_fingerprint(key)}" + ("  (current)" if kid == ring.current else ""))
    for pem in sorted(directory.glob("*.pem")):
        cert = x509.load_pem_x509_certificate(pem.read_bytes())
        cn = cert.subject.get_attributes_for_oid(x509.NameOID.COMMON_NAME)[0].value
        typer.echo(f"  {pem.name:<16} {cn:<28} until {cert.not_valid_after_utc:%Y-%m-%d}  "
                   f"sha256 {_fingerprint(cert.public_bytes(Encoding.DER))}")
    revoked = _revoked(directory)
    typer.echo(f"  revoked: {', '.join(sorted(revoked)) or 'none'}")


# A command of its own, not `agent install-service`: `agent` takes options, not subcommands.
@app.command("install-service")
def install_service(
    config: Path = typer.Option(..., "--config", help="the agent's configuration file (docs/deploy.md#configuration)"),
    name: Optional[str] = typer.Option(None, "--name", help="the unit's name (default: swarmloc-agent-<id>)"),
    unit_dir: Path = typer.Option(service.SYSTEM_UNIT_DIR, "--unit-dir",
                                  help="where to write the unit; ~/.config/systemd/user for a user unit"),
    user: Optional[str] = typer.Option(None, "--user", help="system unit: run the agent as this user, who then "
                                       "owns a new state_dir"),
    dry_run: bool = typer.Option(False, "--dry-run", help="print the unit instead of writing it; create nothing"),
):
    """Install an agent as a systemd service: check its configuration, write the unit
    (restart on failure, logs to the journal), create its state_dir; print what to run next."""
    from agents.config import ConfigError, load, node_spec

    try:
        cfg = load(config)
        node_spec(cfg)  # what --check-config builds: a file that passes here starts
    except ConfigError as exc:
        for line in exc.lines:
            error(f"{config}: {line}")
        raise typer.Exit(2) from None
    try:
        plan = service.plan(config, cfg, name, unit_dir, user)
    except ValueError as exc:
        raise Failure(str(exc), 2) from None
    if dry_run:
        typer.echo(plan.text, nl=False)
        return
    try:
        note = service.prepare_state_dir(plan)
        replaced = service.write_unit(plan)
    except OSError as exc:
        raise Failure(f"{exc.strerror or exc}{f': {exc.filename}' if exc.filename else ''}"
                      f"{' (a system unit needs root: sudo)' if isinstance(exc, PermissionError) else ''}") from None
    typer.echo(f"{'replaced' if replaced else 'wrote'} {plan.path}")
    if plan.state_dir is not None:
        typer.echo(f"checkpoints in {plan.state_dir}")
    if note:
        typer.echo(f"{typer.style('warning:', fg='yellow', bold=True)} {note}", err=True)
    typer.echo("next:")
    for command in service.next_commands(plan):
        typer.echo(f"  {command}")
    absent = service.systemd_absent()
    if absent is not None:
        typer.echo(f"note: {absent}; run them where systemd runs")


# ------------------------------------------------------------------------------------ control

ForOpt = typer.Option(None, "--for", help="clear the fault automatically after this many seconds (simulated)")


def inject(fault: dict, swarm: str, connect: list[str] | None, duration: float | None) -> None:
    from swarmloc.faults import FaultError, parse_fault

    if duration is not None:
        fault["duration"] = duration
    try:
        parse_fault(fault)  # same schema netsim uses: fail here, with the field named
    except FaultError as exc:
        raise Failure(f"bad fault: {exc}", 2) from None
    with ControlClient(swarm, connect) as ctl:
        data = ctl.request("inject", {"fault": fault})
    shown = {k: v for k, v in data["fault"].items() if k != "action"}
    typer.echo(f"{fault['action']} {shown}: applies from tick {data['applies_at_tick']}")


A = typer.Argument(..., help="agent id")
B = typer.Argument(..., help="agent id")
N = typer.Argument(..., help="agent id")


@inject_app.command("cut", context_settings=NUMBERS)
def inject_cut(a: int = A, b: int = B, forward: bool = typer.Option(False, "--forward", help="only frames from A to B"),
               duration: Optional[float] = ForOpt, swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt):
    """Cut the radio link A-B (both directions unless --forward)."""
    inject({"action": "cut", "link": [a, b], "direction": "forward" if forward else "both"}, swarm, connect, duration)


@inject_app.command("restore", context_settings=NUMBERS)
def inject_restore(a: int = A, b: int = B, swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt):
    """Restore the radio link A-B."""
    inject({"action": "restore", "link": [a, b]}, swarm, connect, None)


def _node_fault(action: str, doc: str, clears: bool):
    """An `inject ACTION NODE` command; faults that clear something take no --for."""
    if clears:
        def cmd(node: int = N, swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt):
            inject({"action": action, "node": node}, swarm, connect, None)
    else:
        def cmd(node: int = N, duration: Optional[float] = ForOpt, swarm: str = SwarmOpt,
                connect: Optional[list[str]] = ConnectOpt):
            inject({"action": action, "node": node}, swarm, connect, duration)
    cmd.__doc__ = doc
    inject_app.command(action, context_settings=NUMBERS)(cmd)


_node_fault("radio-off", "Switch a node's radio off: it neither sends nor receives.", clears=False)
_node_fault("radio-on", "Switch a node's radio back on.", clears=True)
_node_fault("gnss-off", "GNSS outage on a node: its fixes stop.", clears=False)
_node_fault("gnss-on", "End a GNSS outage.", clears=True)
_node_fault("command-off", "Lose a vehicle's command stream: it keeps its last command.", clears=False)
_node_fault("command-on", "End a command-stream outage.", clears=True)
_node_fault("kill", "Kill an agent process (with --for, `swarmloc run` restarts it afterwards).", clears=False)
_node_fault("restart", "Restart a killed agent process.", clears=True)


@inject_app.command("partition", context_settings=NUMBERS)
def inject_partition(groups: list[str] = typer.Argument(..., help="groups of ids, e.g. 1,2 3,4 (unlisted agents: one more group)"),
                     duration: Optional[float] = ForOpt, swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt):
    """Partition the swarm into groups that cannot hear each other."""
    inject({"action": "partition", "groups": [_ids(g, "GROUPS") for g in groups]}, swarm, connect, duration)


@inject_app.command("heal")
def inject_heal(swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt):
    """Heal a partition."""
    inject({"action": "heal"}, swarm, connect, None)


NodeOpt = typer.Option(None, "--node", help="only frames sent or received by this agent")
LinkOpt = typer.Option(None, "--link", help="only frames on this link, e.g. 1,2")


def _loss_target(node: int | None, link: str | None) -> dict:
    if node is not None and link is not None:
        raise Failure("give --node or --link, not both", 2)
    if link is not None:
        ids = _ids(link, "--link")
        if len(ids) != 2:
            raise typer.BadParameter(f"takes two ids like 1,2, got {link!r}", param_hint=["--link"])
        return {"link": ids}
    return {"node": node} if node is not None else {}


@inject_app.command("loss", context_settings=NUMBERS)
def inject_loss(probability: float = typer.Argument(..., help="extra loss probability per frame, 0..1"),
                node: Optional[int] = NodeOpt, link: Optional[str] = LinkOpt,
                duration: Optional[float] = ForOpt, swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt):
    """Add random frame loss everywhere, on one node, or on one link."""
    inject({"action": "loss", "probability": probability, **_loss_target(node, link)}, swarm, connect, duration)


@inject_app.command("clear-loss")
def inject_clear_loss(node: Optional[int] = NodeOpt, link: Optional[str] = LinkOpt, swarm: str = SwarmOpt,
                      connect: Optional[list[str]] = ConnectOpt):
    """Remove extra loss added with the same target (no target: the loss on every frame)."""
    inject({"action": "clear-loss", **_loss_target(node, link)}, swarm, connect, None)


JammerName = typer.Option("j1", "--name", help="the jammer's name, to switch it off again (several may run at once)")


@inject_app.command("jammer", context_settings=NUMBERS)
def inject_jammer(x: float = typer.Argument(..., help="position x (m)"), y: float = typer.Argument(..., help="position y (m)"),
                  power: float = typer.Option(30.0, "--power", help="transmit power (dBm)"),
                  band: Optional[float] = typer.Option(None, "--band", help="jammed bandwidth (Hz); default the whole channel"),
                  velocity: str = typer.Option("0,0", "--velocity", help="vx,vy in m/s for a moving jammer"),
                  radius: float = typer.Option(50.0, "--radius", help="unit-disk radio: receivers within this many m are silenced"),
                  name: str = JammerName,
                  duration: Optional[float] = ForOpt, swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt):
    """Switch a jammer on at (X, Y)."""
    inject({"action": "jammer", "name": name, "position": [x, y], "power_dbm": power, "band_hz": band,
            "velocity": _numbers(velocity, "--velocity", 2), "radius_m": radius}, swarm, connect, duration)


@inject_app.command("jammer-off")
def inject_jammer_off(name: str = JammerName, swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt):
    """Switch a jammer off."""
    inject({"action": "jammer-off", "name": name}, swarm, connect, None)


@app.command(context_settings=NUMBERS)
def clear(fault_id: int = typer.Argument(..., help="fault id from `swarmloc faults`"), swarm: str = SwarmOpt,
          connect: Optional[list[str]] = ConnectOpt):
    """Clear an active fault by its id."""
    with ControlClient(swarm, connect) as ctl:
        data = ctl.request("clear", {"id": fault_id})
    typer.echo(f"fault {fault_id} clears from tick {data['applies_at_tick']}")


@app.command()
def stop(swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt):
    """End a running swarm after its current tick; the run directory is written as at a normal end."""
    with ControlClient(swarm, connect) as ctl:
        data = ctl.request("stop")
    typer.echo(f"stopping after tick {data['k']} of {data['steps']} (t = {data['t']:.1f} s)")


@app.command()
def faults(swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt,
           as_json: bool = typer.Option(False, "--json", help="print the faults in force as JSON")):
    """List the faults in force in a running swarm."""
    with ControlClient(swarm, connect) as ctl:
        data = ctl.request("faults")
    if as_json:
        typer.echo(json.dumps(data))
        return
    if not data["active"]:
        typer.echo(f"no active faults (t = {data['t']:.1f} s)")
        return
    from rich.table import Table

    t = Table("id", "fault", "arguments", "since (s)", "until (s)")
    for f in data["active"]:
        t.add_row(str(f["id"]), f["action"], json.dumps(f["args"]), f"{f['since']:.1f}",
                  "-" if f["until"] is None else f"{f['until']:.1f}")
    _console().print(t)


def _faults_text(s: dict) -> str:
    return ", ".join(f"#{f['id']} {f['action']} {json.dumps(f['args'])}" for f in s["faults"]) or "none"


def _status_view(s: dict):
    from rich.console import Group
    from rich.table import Table

    head = f"scenario {s['scenario']} ({s['mode']}, {s['radio']} radio): tick {s['k']}/{s['steps']}, t = {s['t']:.1f} s"
    agents = Table("agent", "alive", "responsive", "last tick done", title="agents")
    for aid, a in s["agents"].items():
        agents.add_row(aid, "yes" if a["alive"] else "[red]no[/]", "yes" if a["responsive"] else "[red]no[/]", str(a["done_k"]))
    links = Table("link", "up", "distance (m)", "SNR (dB)", "last SINR (dB)", "model PDR", "delivered", "dropped",
                  "delivery ratio", "last heard (s)", title="links")
    for l in s["links"]:
        fmt = lambda v, f="{:.2f}": "-" if v is None or v != v else f.format(v)
        links.add_row(f"{l['a']}-{l['b']}", "up" if l["up"] else f"[red]down ({l['reason']})[/]", f"{l['distance']:.1f}",
                      fmt(l["snr_db"], "{:.1f}"), fmt(l.get("sinr_db"), "{:.1f}"), fmt(l["pdr_model"]),
                      str(l["delivered"]), str(l["dropped"]),
                      fmt(l["delivery_ratio"]), fmt(l["last_heard"], "{:.1f}"))
    return Group(head, agents, links, f"faults: {_faults_text(s)}")


def _status_line(s: dict) -> str:
    alive = sum(a["alive"] for a in s["agents"].values())
    up = sum(l["up"] for l in s["links"])
    return (f"tick {s['k']}/{s['steps']} t={s['t']:.1f}s agents alive {alive}/{len(s['agents'])} "
            f"links up {up} down {len(s['links']) - up} faults {_faults_text(s)}")


def _sources_text(sources: dict) -> str:
    """A daemon's polled sources in a few words: a flight controller's link, a recording's progress."""
    def one(name: str, st: dict) -> str:
        if "link" in st:
            return f"{name}: {st['link']}, tick {st['tick']}"
        if "of" in st:
            more = [f", {v} {k}" for k, v in st.items() if k not in ("frames", "of") and isinstance(v, int) and v]
            return f"{name}: {st['frames']}/{st['of']} frames{''.join(more)}"
        return f"{name}: {json.dumps(st)}"

    return "\n".join(one(n, st) for n, st in sources.items()) or "-"


def _agents_view(a: dict):
    from rich.console import Group
    from rich.table import Column, Table

    rows = a["rows"]
    answering = sum(r["reply_ms"] is not None for r in rows)
    head = f"swarm {a['swarm']}: {answering}/{len(rows)} agents answer on swarmloc/{a['swarm']}/agent/*/stats"
    # `peers` is shown once the daemons report it; today's stats do not.
    peers = any("peers" in r["data"] for r in rows if r["data"])
    t = Table("agent", "estimator", "tick", "ticks", "skipped", *(["peers"] if peers else []), "rejected",
              "node drops", Column("sources", overflow="fold"), "alive", "heard", title="agents")
    for r in rows:
        d = r["data"]
        alive = "yes" if r["alive"] else "[red]no[/]"
        # Answering now: how long its answer took (its loop's latency); silent: since when.
        if r["reply_ms"] is not None:
            heard = f"{r['reply_ms']:.0f} ms"
        else:
            heard = "[red]never[/]" if r["heard_s"] is None else f"[red]{r['heard_s']:.1f} s ago[/]"
        if d is None:  # a token, but never an answer: its loop is stuck, or it is not a swarmloc daemon
            t.add_row(str(r["id"]), "-", "-", "-", "-", *(["-"] if peers else []), "-", "-", "-", alive, heard)
            continue
        t.add_row(str(r["id"]), d["algorithm"], str(d["k"]), str(d["ticks"]), str(d["ticks_skipped"]),
                  *([", ".join(map(str, d.get("peers", []))) or "none"] if peers else []),
                  str(sum(d["rejected"].values())), str(sum(d["node_drops"].values())),
                  _sources_text(d.get("sources", {})), alive, heard)
    extra = [f"unreadable reply on {key}: {why}" for key, why in a["unreadable"].items()]
    return Group(head, t, *extra)


def _agents_line(a: dict) -> str:
    rows = a["rows"]

    def one(r: dict) -> str:
        if r["reply_ms"] is not None:
            return f"{r['id']} {r['data']['algorithm']} tick {r['data']['k']}"
        return f"{r['id']} silent" + ("" if r["heard_s"] is None else f" for {r['heard_s']:.1f}s")

    shown = [one(r) for r in rows]
    return f"agents answer {sum(r['reply_ms'] is not None for r in rows)}/{len(rows)}: {', '.join(shown)}"


def _agents_rounds(ctl: ControlClient, watch: bool, interval: float):
    """The agents' answers, round after round with --watch; an agent that stops answering keeps
    its last row, with how long ago it was last heard."""
    last: dict[int, tuple[dict, float]] = {}  # agent id: its last stats, and when they came
    first = True
    while True:
        ans = ctl.agents()
        if first and not (ans.stats or ans.alive or ans.unreadable):
            raise NobodyAnswers(ctl.swarm, ctl.endpoints)
        first = False
        now = time.monotonic()
        last.update((aid, (data, now)) for aid, data in ans.stats.items())
        rows = []
        for aid in sorted(set(last) | ans.alive):
            data, heard = last.get(aid, (None, None))
            rows.append({"id": aid, "data": data, "alive": aid in ans.alive,
                         "reply_ms": ans.reply_s[aid] * 1e3 if aid in ans.reply_s else None,
                         "heard_s": None if heard is None else now - heard})
        yield {str(aid): data for aid, data in sorted(ans.stats.items())}, \
            {"swarm": ctl.swarm, "rows": rows, "unreadable": ans.unreadable}
        if not watch:
            return
        time.sleep(interval)


def _show(rounds, view, line, as_json: bool, watch: bool) -> bool:
    """Print each (raw, shown) round: the raw answer as JSON, a rich view, or with --watch off a
    terminal one plain line; on a terminal --watch redraws in place. False after Ctrl-C."""
    try:
        if watch and not as_json and sys.stdout.isatty():
            from rich.live import Live

            with Live(console=_console(), refresh_per_second=4) as live:
                for _, shown in rounds:
                    live.update(view(shown))
        else:
            for raw, shown in rounds:
                if as_json:
                    typer.echo(json.dumps(raw))
                elif watch:
                    typer.echo(line(shown))
                else:
                    _console().print(view(shown))
    except KeyboardInterrupt:
        # Ctrl-C is the way out of --watch: if closing the Zenoh session then hangs (a query in
        # flight), the process still ends, cleanly, 2 s later, as exit_on_sigterm does for SIGTERM.
        watchdog = threading.Timer(2.0, os._exit, args=(0,))
        watchdog.daemon = True
        watchdog.start()
        return False
    return True


@app.command()
def status(swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt,
           as_json: bool = typer.Option(False, "--json", help="print the raw status as JSON (from the agents: "
                                        "their stats, keyed by agent id)"),
           watch: bool = typer.Option(False, "--watch", "-w", help="refresh until Ctrl-C or the run ends "
                                      "(not on a terminal: one plain line per refresh)"),
           interval: float = typer.Option(0.5, "--interval", callback=_in_range(0, above=True),
                                          help="seconds between refreshes with --watch"),
           agents: bool = typer.Option(False, "--agents", help="ask the agents for their own counters, not netsim "
                                       "(what status does when no netsim answers)")):
    """Show a running swarm: tick, agents alive, link table (SNR, delivery ratio, last heard), faults.
    Without netsim (agents on a direct radio), each agent's own counters."""
    if watch:
        # Ctrl-C ends --watch even when we were started with SIGINT ignored (a background job
        # of a non-interactive shell, as the launcher also handles).
        signal.signal(signal.SIGINT, signal.default_int_handler)
    client = ControlClient(swarm, connect)
    try:
        with client as ctl:
            first = None
            if not agents:
                try:
                    first = ctl.request("status")
                except NotRunning:
                    pass  # no netsim: the agents may still answer for themselves
            if first is None:
                _show(_agents_rounds(ctl, watch, interval), _agents_view, _agents_line, as_json, watch)
                return

            def statuses():
                yield first, first
                while watch:
                    time.sleep(interval)
                    try:
                        s = ctl.request("status")
                    except NotRunning:  # the run ended under our eyes: the normal way out
                        return
                    yield s, s

            ended = _show(statuses(), _status_view, _status_line, as_json, watch)
    except NotRunning:  # no session at all: nothing listens there
        raise NobodyAnswers(swarm, client.endpoints) from None
    if watch and ended:
        typer.echo("netsim is gone: the run has ended")
