"""The commands of a companion computer: `swarmloc agent` (one agent daemon), `router` (a Zenoh
router for agents in client mode) and `install-service` (the agent as a systemd service)."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Literal, Optional

import typer

from agents.cli.common import (
    SwarmOpt,
    check_endpoints,
    error,
    estimator_name,
    in_range,
    load_scenario,
    parse_ids,
    parse_numbers,
    scenarios_module,
)
from agents.cli.keys import load_keyring, revoked_members
from agents.companion import service
from agents.control import DEFAULT_ENDPOINT, Failure
from swarmloc import wire

app = typer.Typer()


def _configured_agents(ctx: typer.Context, paths: list[Path], check: bool):
    """The agents of configuration files, to host in this process; None once --check-config has
    printed their summaries. A bad file is one `error:` line per field, and files that cannot
    share a process one per clash, exit 2."""
    from agents.config import (
        ConfigError,
        daemon_config,
        hostmates,
        load,
        node_spec,
        summary,
    )
    from agents.host import Hosted

    # By the source's name: typer vendors its own click, whose ParameterSource is not click's.
    given = [p.opts[0] for p in ctx.command.params if p.name not in ("config", "check_config", "verbose")
             and getattr(ctx.get_parameter_source(p.name), "name", "DEFAULT") != "DEFAULT"]
    if given:
        raise Failure(f"--config is the whole agent: give it without {', '.join(given)}", 2)
    agents, bad = [], False
    for path in paths:
        try:
            cfg = load(path)
            agents.append((path, cfg, node_spec(cfg)))
        except ConfigError as exc:
            for line in exc.lines:
                error(f"{path}: {line}")
            bad = True
    clashes = [] if bad else hostmates([(path, cfg) for path, cfg, _ in agents])
    for line in clashes:
        error(line)
    if bad or clashes:
        raise typer.Exit(2)
    if check:
        for path, cfg, spec in agents:
            typer.echo(f"{path}: a valid agent configuration")
            for line in summary(cfg, spec):
                typer.echo(f"  {line}")
        return None
    for path, cfg, _ in agents:
        if cfg.state_dir is not None:
            try:
                cfg.state_dir.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise Failure(f"{path}: state_dir: cannot create {cfg.state_dir}: {exc.strerror or exc}", 2) from None
    return [Hosted(cfg.id, spec, daemon_config(cfg)) for _, cfg, spec in agents]


def _host(agents: list, verbose: bool) -> None:
    """The configured agents until every one has stopped: one as `serve` runs it, several each on
    a thread of this process (agents/host.py). One of several that cannot start or whose loop
    fails is an `error:` line, and its hostmates go on; the exit code is 1 if any did."""
    from agents.daemon import OpenError, serve
    from agents.host import Host, serve_host
    from swarmloc.process import exit_on_sigterm

    # One agent: every line is its own, whichever thread says it (Zenoh's callbacks too).
    who = f"agent-{agents[0].aid}" if len(agents) == 1 else "%(threadName)s"
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING,
                        format=f"%(asctime)s {who} %(levelname)s %(message)s")
    if len(agents) == 1:
        # In the main thread, as every agent alone: SIGTERM ends its loop at once, before it
        # hears its peers go (a host's threads hear them while the main thread stops them).
        try:
            return serve(agents[0].spec.build(), agents[0].cfg)
        except OpenError as exc:
            raise Failure(str(exc)) from None
    exit_on_sigterm()
    failed = []

    def report(line: str, why: str) -> None:
        failed.append(why)
        error(why)

    serve_host(Host(agents, report))
    if failed:
        raise typer.Exit(1)


@app.command()
def agent(
    ctx: typer.Context,
    id: Optional[int] = typer.Option(None, "--id", help="this agent's id (required without --config)"),
    config: Optional[list[Path]] = typer.Option(None, "--config", help="the whole agent from a configuration file "
                                                "(YAML, docs/deploy.md#configuration): no scenario, no other option "
                                                "but -v; repeatable: several agents in this process, served by one loop"),
    check_config: bool = typer.Option(False, "--check-config", help="with --config: validate the files, print a "
                                      "summary of each agent and exit"),
    scenario: Optional[str] = typer.Option(None, "--scenario", help="take start point, model and filter settings from a scenario"),
    spec: Optional[Path] = typer.Option(None, "--spec", help="build the node from a node spec file (JSON, what `run` "
                                        "writes to logs/agent-ID.node.json): no scenario is parsed in this process"),
    start: Optional[str] = typer.Option(None, "--start", help="known start position, e.g. '0,0' (without --scenario)"),
    initial_std: float = typer.Option(0.1, "--initial-std", callback=in_range(0, above=True),
                                      help="std of the start position (m), without --scenario"),
    estimator: Optional[str] = typer.Option(None, "--estimator", callback=estimator_name,
                                            help="the estimator to run (default: the scenario's; without --scenario, ukf-dcl)"),
    swarm: str = SwarmOpt,
    connect: Optional[list[str]] = typer.Option(None, "--connect", callback=check_endpoints,
                                                help=f"Zenoh endpoint to connect to (repeatable; default: {DEFAULT_ENDPOINT}, none for a peer with --listen)"),
    listen: Optional[list[str]] = typer.Option(None, "--listen", callback=check_endpoints,
                                               help="Zenoh endpoint to listen on (peer mode; repeatable)"),
    mode: Literal["client", "peer"] = typer.Option("client", "--mode", help="Zenoh mode: client (of netsim) or peer"),
    direct: bool = typer.Option(False, "--direct", help="no netsim: publish radio frames straight to peers"),
    state_file: Optional[Path] = typer.Option(None, "--state-file", help="checkpoint here (after a sensor frame, at most every 0.2 s); resume from it at start"),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="log at INFO: what the agent waits for, what it does"),
):
    """Start an agent daemon (used by `run`; on a companion computer, run it by hand), or several
    from configuration files."""
    from agents.daemon import AgentConfig, OpenError, load_node, serve

    if check_config and not config:
        raise Failure("--check-config needs --config FILE", 2)
    if config:
        agents = _configured_agents(ctx, config, check_config)
        if agents is not None:  # None: --check-config printed the summaries
            _host(agents, verbose)
        return
    if id is None:
        raise typer.BadParameter("required without --config", param_hint=["--id"])
    if spec is not None:
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
        sc = scenarios_module().parse({"version": scenarios_module().SCENARIO_VERSION, "name": f"agent-{id}",
                              "world": {"agents": [{"id": id, "start": parse_numbers(start, "--start", 2)}]},
                              "estimation": {"initial_std": initial_std, "initial_error": False},
                              "estimator": {"name": estimator}})
        node = make_nodes(estimator, sc, [id])[id]
    else:
        raise Failure("give --config, --scenario, --start or --spec", 2)
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
    listen: list[str] = typer.Option(..., "--listen", callback=check_endpoints,
                                     help="Zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)"),
    connect: Optional[list[str]] = typer.Option(None, "--connect", callback=check_endpoints,
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
    from swarmloc.process import exit_on_sigterm

    conf = wire.zenoh_config("router", listen, connect or ())
    if keys is not None:
        from agents import tls

        swarm = load_keyring(keys).swarm
        if agents is None:
            raise Failure("--keys needs --agents: the ids access control lets in", 2)
        ids = sorted(set(parse_ids(agents, "--agents")) - {int(m[6:]) for m in revoked_members(keys) if m.startswith("agent-")})
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
