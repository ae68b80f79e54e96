"""`swarmloc inject ...`, `clear` and `faults`: faults injected into a running swarm, and the
faults in force (the schema is swarmloc/experiment/faults.py, the same netsim applies)."""

from __future__ import annotations

import json
from typing import Optional

import typer

from agents.cli.common import (
    NUMBERS,
    ConnectOpt,
    SwarmOpt,
    console,
    parse_ids,
    parse_numbers,
)
from agents.control import ControlClient, Failure

app = typer.Typer()
inject_app = typer.Typer(no_args_is_help=True, help="Inject a fault into a running swarm (applies from the next tick).")


ForOpt = typer.Option(None, "--for", help="clear the fault automatically after this many seconds (simulated)")


def inject(fault: dict, swarm: str, connect: list[str] | None, duration: float | None) -> None:
    from swarmloc.experiment.faults import FaultError, parse_fault

    if duration is not None:
        fault["duration"] = duration
    try:
        parse_fault(fault)  # same schema netsim uses: fail here, with the field named
    except FaultError as exc:
        raise Failure(f"bad fault: {exc}", 2) from None
    with ControlClient(swarm, connect) as ctl:
        data = ctl.request("inject", {"fault": fault})
    typer.echo(f"{describe_fault(data['fault'])}: applies from tick {data['applies_at_tick']}")


def describe_fault(fault: dict) -> str:
    """A fault in words, as the user typed it: `kill node 3, for 10 s`, `cut link 3-4, direction forward`."""
    def value(v) -> str:
        if isinstance(v, (list, tuple)):
            return "-".join(map(value, v)) if all(isinstance(x, int) for x in v) else f"({', '.join(map(value, v))})"
        return f"{v:g}" if isinstance(v, float) else str(v)

    def field(k: str, v) -> str:
        for suffix, unit in (("_dbm", "dBm"), ("_m", "m"), ("_s", "s")):
            if k.endswith(suffix):
                return f"{k[:-len(suffix)].replace('_', ' ')} {value(v)} {unit}"
        return f"{k.replace('_', ' ')} {value(v)}"

    parts = [field(k, v) for k, v in fault.items() if k not in ("action", "duration")]
    if fault.get("duration") is not None:
        parts.append(f"for {value(fault['duration'])} s")
    return f"{fault['action']} {', '.join(parts)}".rstrip()


A = typer.Argument(..., metavar="A", help="agent id")
B = typer.Argument(..., metavar="B", help="agent id")
N = typer.Argument(..., metavar="NODE", help="agent id")


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
def inject_partition(groups: list[str] = typer.Argument(..., metavar="GROUPS...", help="groups of ids, e.g. 1,2 3,4 (unlisted agents: one more group)"),
                     duration: Optional[float] = ForOpt, swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt):
    """Partition the swarm into groups that cannot hear each other."""
    inject({"action": "partition", "groups": [parse_ids(g, "GROUPS") for g in groups]}, swarm, connect, duration)


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
        ids = parse_ids(link, "--link")
        if len(ids) != 2:
            raise typer.BadParameter(f"takes two ids like 1,2, got {link!r}", param_hint=["--link"])
        return {"link": ids}
    return {"node": node} if node is not None else {}


@inject_app.command("loss", context_settings=NUMBERS)
def inject_loss(probability: float = typer.Argument(..., metavar="PROBABILITY", help="extra loss probability per frame, 0..1"),
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
def inject_jammer(x: float = typer.Argument(..., metavar="X", help="position x (m)"), y: float = typer.Argument(..., metavar="Y", help="position y (m)"),
                  power: float = typer.Option(30.0, "--power", help="transmit power (dBm)"),
                  band: Optional[float] = typer.Option(None, "--band", help="jammed bandwidth (Hz); default the whole channel"),
                  velocity: str = typer.Option("0,0", "--velocity", help="vx,vy in m/s for a moving jammer"),
                  radius: float = typer.Option(50.0, "--radius", help="unit-disk radio: receivers within this many m are silenced"),
                  name: str = JammerName,
                  duration: Optional[float] = ForOpt, swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt):
    """Switch a jammer on at (X, Y)."""
    inject({"action": "jammer", "name": name, "position": [x, y], "power_dbm": power, "band_hz": band,
            "velocity": parse_numbers(velocity, "--velocity", 2), "radius_m": radius}, swarm, connect, duration)


@inject_app.command("jammer-off")
def inject_jammer_off(name: str = JammerName, swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt):
    """Switch a jammer off."""
    inject({"action": "jammer-off", "name": name}, swarm, connect, None)


@app.command(context_settings=NUMBERS)
def clear(fault_id: int = typer.Argument(..., metavar="FAULT_ID", help="fault id from `swarmloc faults`"), swarm: str = SwarmOpt,
          connect: Optional[list[str]] = ConnectOpt):
    """Clear an active fault by its id."""
    with ControlClient(swarm, connect) as ctl:
        data = ctl.request("clear", {"id": fault_id})
    typer.echo(f"fault {fault_id} clears from tick {data['applies_at_tick']}")



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
    console().print(t)
