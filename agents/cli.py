"""The `swarmloc` command line: run a swarm, start one agent, inject faults, show status.

It lives beside the agent daemon because, like the daemon, it speaks Zenoh; it starts netsim
only as a separate process (`python -m netsim`), so agents and netsim still never import each
other.
"""

from __future__ import annotations

import json
import logging
import signal
import socket
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from swarmloc import scenario as scenarios
from swarmloc import wire

app = typer.Typer(add_completion=False, no_args_is_help=True, help="swarmloc: cooperative localization over a real (or emulated) network.")
inject_app = typer.Typer(no_args_is_help=True, help="Inject a fault into a running swarm (applies from the next tick).")
app.add_typer(inject_app, name="inject")
console = Console()
err = Console(stderr=True)

DEFAULT_PORT = 7447
SwarmOpt = typer.Option("default", "--swarm", help="swarm name: the key prefix swarmloc/<swarm>/")
ConnectOpt = typer.Option(None, "--connect", help=f"Zenoh endpoint of netsim or a router [default: tcp/127.0.0.1:{DEFAULT_PORT}]")


def fail(msg: str, code: int = 2) -> typer.Exit:
    err.print(f"[bold red]error:[/] {msg}")
    return typer.Exit(code)


def load_scenario(name: str) -> scenarios.Scenario:
    try:
        return scenarios.load(name)
    except scenarios.ScenarioError as exc:
        raise fail(str(exc))


# ------------------------------------------------------------------------------------ scenarios


@app.command("scenarios")
def list_scenarios():
    """List the built-in scenarios."""
    t = Table("name", "agents", "duration", "radio", "description")
    for name in scenarios.builtin_names():
        sc = scenarios.load(name)
        t.add_row(name, str(len(sc.world.agents)), f"{sc.clock.duration:g} s @ {sc.clock.dt:g} s",
                  " ".join([sc.radio["model"], *([f"{sc.radio['range_m']:g} m"] if "range_m" in sc.radio else [])]),
                  sc.description)
    console.print(t)


# ------------------------------------------------------------------------------------ run


def _port_free(port: int) -> bool:
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
            return True
        except OSError:
            return False


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_listening(port: int, proc: subprocess.Popen, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            return
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.05)


class Swarm:
    """The processes of one run: netsim and one agent each; stopped together, whatever happens."""

    def __init__(self, logs: Path):
        self.logs = logs
        self.procs: dict[str, subprocess.Popen] = {}
        self.agent_args: dict[int, list[str]] = {}
        self.killed: set[str] = set()  # killed on purpose (a kill fault), not crashed

    def spawn(self, name: str, args: list[str]) -> subprocess.Popen:
        f = open(self.logs / f"{name}.log", "ab")
        p = subprocess.Popen([sys.executable, *args], stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                             start_new_session=True)
        self.procs[name] = p
        return p

    def crashed(self) -> list[tuple[str, int]]:
        return [(n, p.returncode) for n, p in self.procs.items() if p.poll() not in (None, 0) and n not in self.killed]

    def on_event(self, kind: str, aid: int) -> None:
        """netsim's kill/restart faults: the launcher owns the processes, so it carries them out."""
        name = f"agent-{aid}"
        if kind == "kill" and name in self.procs:
            self.killed.add(name)
            self.procs[name].kill()
            self.procs[name].wait()
            console.print(f"[yellow]killed {name} (fault)[/]")
        elif kind == "restart" and aid in self.agent_args:
            self.killed.discard(name)
            self.spawn(name, self.agent_args[aid])
            console.print(f"[yellow]restarted {name} (fault); it resumes from its checkpoint[/]")

    def tail(self, name: str, lines: int = 15) -> str:
        text = (self.logs / f"{name}.log").read_text(errors="replace").splitlines()
        return "\n".join(text[-lines:])

    def stop(self, grace: float = 3.0) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace
        for p in self.procs.values():
            try:
                p.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def run_swarm(sc_arg: str, out: Path | None, seed: int | None, swarm: str, port: int | None, plots: bool) -> Path:
    sc = load_scenario(sc_arg)
    if seed is not None:
        sc = sc.with_overrides(seed=seed)
    if port is None:
        port = DEFAULT_PORT if _port_free(DEFAULT_PORT) else _free_port()
    elif port == 0:
        port = _free_port()
    elif not _port_free(port):
        raise fail(f"port {port} on 127.0.0.1 is in use (another swarm running?); pass --port 0 for any free port")
    endpoint = f"tcp/127.0.0.1:{port}"
    out = out or Path("runs") / f"{sc.name}-{datetime.now():%Y%m%d-%H%M%S}"
    out.mkdir(parents=True, exist_ok=True)
    (out / "logs").mkdir(exist_ok=True)
    for old in [*(out / "logs").glob("*.log"), *(out / "logs").glob("*.state.npy")]:
        old.unlink()  # a reused run directory must not resume agents from an older run
    scenario_file = out / "logs" / "scenario.input.yaml"
    scenario_file.write_text(sc.to_yaml())

    console.print(f"[bold]swarmloc run[/] {sc.name}: {len(sc.world.agents)} agents, {sc.clock.steps + 1} ticks (0..{sc.clock.steps}) of "
                  f"{sc.clock.dt:g} s, {sc.clock.mode}, seed {sc.seed}, Zenoh router {endpoint}, swarm '{swarm}'")
    procs = Swarm(out / "logs")
    # Ctrl-C (and a plain kill) must stop the whole swarm, even when we were started with
    # SIGINT ignored (a background job of a non-interactive shell, as under CI).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        net = procs.spawn("netsim", ["-m", "netsim", str(scenario_file), "--swarm", swarm, "--listen", endpoint,
                                     "--out", str(out), *([] if plots else ["--no-plots"])])
        _wait_listening(port, net)
        if net.poll() is not None:
            # netsim exits 2 for a bad scenario (e.g. a radio parameter), like our own checks.
            raise fail(f"netsim failed to start (exit code {net.returncode}):\n{procs.tail('netsim')}",
                       2 if net.returncode == 2 else 1)
        for a in sc.agent_ids:
            procs.agent_args[a] = ["-m", "agents", "agent", "--id", str(a), "--scenario", str(scenario_file), "--swarm", swarm,
                                   "--connect", endpoint, "--state-file", str(out / "logs" / f"agent-{a}.state.npy")]
            procs.spawn(f"agent-{a}", procs.agent_args[a])
        _watch(procs, net, sc, swarm, endpoint)
    except KeyboardInterrupt:
        procs.stop()
        err.print(f"[yellow]interrupted: stopped {len(procs.procs)} processes; logs in {out / 'logs'}[/]")
        raise typer.Exit(130)
    finally:
        procs.stop()
    if net.returncode != 0:
        raise fail(f"netsim exited with code {net.returncode}:\n{procs.tail('netsim')}")
    _print_summary(out)
    return out


def _watch(procs: Swarm, net: subprocess.Popen, sc, swarm: str, endpoint: str) -> None:
    """Progress from netsim's clock; stop at once if any process dies."""
    import queue as _queue

    import zenoh

    ticks: _queue.SimpleQueue = _queue.SimpleQueue()
    events: _queue.SimpleQueue = _queue.SimpleQueue()
    session = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("client", connect=[endpoint])))
    sub = session.declare_subscriber(wire.Keys(swarm).clock, lambda s: ticks.put(s.payload.to_bytes()))
    sub_events = session.declare_subscriber(wire.Keys(swarm).events, lambda s: events.put(s.payload.to_bytes()))
    try:
        with Progress(TextColumn("[progress.description]{task.description}"), BarColumn(), MofNCompleteColumn(),
                      TextColumn("ticks"), TimeElapsedColumn(), TimeRemainingColumn(), console=console, transient=False) as bar:
            task = bar.add_task("waiting for agents", total=sc.clock.steps + 1)
            while net.poll() is None:
                while not events.empty():
                    try:
                        ev = wire.decode(events.get_nowait()).body
                        procs.on_event(ev.kind, ev.node)
                    except wire.WireError:
                        pass
                crashed = [(n, c) for n, c in procs.crashed() if n != "netsim"]
                if crashed:
                    name, code = crashed[0]
                    raise fail(f"{name} crashed (exit code {code}); its last log lines:\n{procs.tail(name)}", 1)
                latest = None
                try:
                    latest = ticks.get(timeout=0.1)
                    while True:
                        latest = ticks.get_nowait()
                except _queue.Empty:
                    pass
                if latest is not None:
                    try:
                        c = wire.decode(latest).body
                        bar.update(task, completed=c.k + 1, description=f"t = {c.t:7.1f} s")
                    except wire.WireError:
                        pass
    finally:
        sub.undeclare()
        sub_events.undeclare()
        session.close()


def _print_summary(out: Path) -> None:
    m = json.loads((out / "metrics.json").read_text())
    algs = [a for a in ("il", "ukf-dcl", "ukf-ccl") if a in m["estimators"]]
    t = Table(title=f"Position error (m), {m['scenario']} seed {m['seed']}")
    t.add_column("agent")
    for a in algs:
        t.add_column(f"{a} mean", justify="right")
        t.add_column(f"{a} final", justify="right")

    def fmt(v):
        return "-" if v is None else f"{v:.2f}"

    for aid in map(str, m["agents"]):
        row = [f"A{aid}"]
        for a in algs:
            e = m["estimators"][a]["agents"][aid]
            row += [fmt(e["mean_error_m"]), fmt(e["final_error_m"])]
        t.add_row(*row)
    t.add_row("all", *sum(([fmt(m["estimators"][a]["mean_error_m"]), ""] for a in algs), []), style="bold")
    console.print(t)
    r = m.get("radio", {})
    console.print(f"{m['ticks']} ticks in {m['wall_time_s']:.1f} s ({m['ticks_per_s']:.0f} ticks/s); radio: "
                  f"{r.get('delivered', 0)} frames delivered, dropped {r.get('dropped', {}) or 'none'}")
    plots = ", plots/*.png" if (out / "plots").is_dir() else ""
    console.print(f"run directory: [bold]{out}[/] (metrics.json, estimates/*.npz{plots})")


@app.command()
def run(
    scenario: str = typer.Argument(..., help="built-in scenario name (see `swarmloc scenarios`) or a YAML file"),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="run directory [default: runs/<name>-<time>]"),
    seed: Optional[int] = typer.Option(None, "--seed", help="override the scenario's seed"),
    swarm: str = SwarmOpt,
    port: Optional[int] = typer.Option(None, "--port", help=f"netsim's Zenoh port on 127.0.0.1 [default: {DEFAULT_PORT}, or a free one if busy; 0: any free]"),
    plots: bool = typer.Option(True, "--plots/--no-plots"),
):
    """Run a scenario: netsim plus one agent process per platform, over Zenoh on loopback."""
    run_swarm(scenario, out, seed, swarm, port, plots)


@app.command()
def demo(out: Optional[Path] = typer.Option(None, "--out", "-o")):
    """Run the built-in wang2019 scenario (UKF-DCL paper, 4 platforms, 800 ticks)."""
    run_swarm("wang2019", out, None, "default", None, True)


# ------------------------------------------------------------------------------------ agent


@app.command()
def agent(
    id: int = typer.Option(..., "--id", help="this agent's id"),
    scenario: Optional[str] = typer.Option(None, "--scenario", help="take start point, model and filter settings from a scenario"),
    start: Optional[str] = typer.Option(None, "--start", help="known start position, e.g. '0,0' (without --scenario)"),
    initial_std: float = typer.Option(0.1, "--initial-std", help="std of the start position (m), without --scenario"),
    algorithm: str = typer.Option("ukf-dcl", "--algorithm", help="ukf-dcl or il"),
    swarm: str = SwarmOpt,
    connect: Optional[list[str]] = ConnectOpt,
    listen: Optional[list[str]] = typer.Option(None, "--listen", help="Zenoh endpoint to listen on (peer mode)"),
    mode: str = typer.Option("client", "--mode", help="Zenoh mode: client (of netsim) or peer"),
    direct: bool = typer.Option(False, "--direct", help="no netsim: publish radio frames straight to peers"),
    state_file: Optional[Path] = typer.Option(None, "--state-file", help="checkpoint every tick here; resume from it at start"),
    verbose: bool = typer.Option(False, "--verbose", "-v"),
):
    """Start one agent daemon (used by `run`; on a companion computer, run it by hand)."""
    import numpy as np

    from agents.daemon import AgentConfig, run_agent
    from swarmloc.estimators import NODE_TYPES
    from swarmloc.runner import make_nodes

    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING,
                        format=f"%(asctime)s agent-{id} %(levelname)s %(message)s")
    if algorithm not in NODE_TYPES:
        raise fail(f"unknown algorithm {algorithm!r}; choose from {sorted(NODE_TYPES)}")
    if scenario:
        sc = load_scenario(scenario)
        if id not in sc.agent_ids:
            raise fail(f"agent {id} is not in scenario {sc.name} (agents {sc.agent_ids})")
        node = make_nodes(algorithm, sc, [id])[id]
    elif start:
        try:
            x0 = np.array([float(v) for v in start.split(",")])
        except ValueError:
            raise fail(f"--start {start!r}: expected comma-separated numbers like 0,0")
        if x0.shape != (2,) or not np.isfinite(x0).all():
            raise fail("--start needs two finite numbers (planar-speed-heading model)")
        node = NODE_TYPES[algorithm](id, x0, np.eye(2) * initial_std**2)
    else:
        raise fail("give --scenario or --start")
    cfg = AgentConfig(swarm=swarm, connect=tuple(connect or [f"tcp/127.0.0.1:{DEFAULT_PORT}"]),
                      listen=tuple(listen or ()), mode=mode, direct=direct, state_file=state_file)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    try:
        run_agent(node, cfg)
    except KeyboardInterrupt:
        pass
    except Exception as exc:  # zenoh raises ZError when it cannot connect
        raise fail(f"agent {id}: {exc}", 1)


# ------------------------------------------------------------------------------------ control


def control(op: str, args: dict, swarm: str, connect: list[str] | None, timeout: float = 3.0) -> dict:
    import zenoh

    from swarmloc.messages import Control, Reply

    endpoint = list(connect or [f"tcp/127.0.0.1:{DEFAULT_PORT}"])
    try:
        session = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("client", connect=endpoint)))
    except Exception as exc:
        raise fail(f"cannot reach netsim at {', '.join(endpoint)}: {exc}")
    try:
        replies = list(session.get(wire.Keys(swarm).control, payload=wire.encode(Control(op, args), 0, 0), timeout=timeout))
    finally:
        session.close()
    for r in replies:
        if r.ok is not None:
            try:
                body = wire.decode(r.ok.payload.to_bytes(), expect=(Reply,)).body
            except wire.WireError as exc:
                raise fail(f"unreadable reply from netsim: {exc}")
            if not body.ok:
                raise fail(f"netsim refused {op}: {body.error}")
            return body.data
    raise fail(f"no netsim answered on swarm '{swarm}' at {', '.join(endpoint)} (is `swarmloc run` running?)")


ForOpt = typer.Option(None, "--for", help="clear the fault automatically after this many seconds (simulated)")


def inject(fault: dict, swarm: str, connect: list[str] | None, duration: float | None) -> None:
    from swarmloc.faults import FaultError, parse_fault

    if duration is not None:
        fault["duration"] = duration
    try:
        parse_fault(fault)  # same schema netsim uses: fail here, with the field named
    except FaultError as exc:
        raise fail(f"bad fault: {exc}")
    data = control("inject", {"fault": fault}, swarm, connect)
    shown = {k: v for k, v in data["fault"].items() if k != "action"}
    console.print(f"{fault['action']} {shown}: applies from tick {data['applies_at_tick']}")


def _ids(text: str) -> list[int]:
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise fail(f"expected comma-separated agent ids, got {text!r}")


A = typer.Argument(..., help="agent id")
B = typer.Argument(..., help="agent id")
N = typer.Argument(..., help="agent id")


@inject_app.command("cut")
def inject_cut(a: int = A, b: int = B, forward: bool = typer.Option(False, "--forward", help="only frames from A to B"),
               duration: Optional[float] = ForOpt, swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt):
    """Cut the radio link A-B (both directions unless --forward)."""
    inject({"action": "cut", "link": [a, b], "direction": "forward" if forward else "both"}, swarm, connect, duration)


@inject_app.command("restore")
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
    inject_app.command(action)(cmd)


_node_fault("radio-off", "Switch a node's radio off: it neither sends nor receives.", clears=False)
_node_fault("radio-on", "Switch a node's radio back on.", clears=True)
_node_fault("gnss-off", "GNSS outage on a node: its fixes stop.", clears=False)
_node_fault("gnss-on", "End a GNSS outage.", clears=True)
_node_fault("kill", "Kill an agent process (with --for, `swarmloc run` restarts it afterwards).", clears=False)
_node_fault("restart", "Restart a killed agent process.", clears=True)


@inject_app.command("partition")
def inject_partition(groups: list[str] = typer.Argument(..., help="groups of ids, e.g. 1,2 3,4 (unlisted agents: one more group)"),
                     duration: Optional[float] = ForOpt, swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt):
    """Partition the swarm into groups that cannot hear each other."""
    inject({"action": "partition", "groups": [_ids(g) for g in groups]}, swarm, connect, duration)


@inject_app.command("heal")
def inject_heal(swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt):
    """Heal a partition."""
    inject({"action": "heal"}, swarm, connect, None)


def _loss_target(node: int | None, link: str | None) -> dict:
    if node is not None and link is not None:
        raise fail("give --node or --link, not both")
    if link is not None:
        ids = _ids(link)
        if len(ids) != 2:
            raise fail(f"--link takes two ids like 1,2, got {link!r}")
        return {"link": ids}
    return {"node": node} if node is not None else {}


@inject_app.command("loss")
def inject_loss(probability: float = typer.Argument(..., help="extra loss probability per frame, 0..1"),
                node: Optional[int] = typer.Option(None, "--node", help="only frames sent or received by this agent"),
                link: Optional[str] = typer.Option(None, "--link", help="only frames on this link, e.g. 1,2"),
                duration: Optional[float] = ForOpt, swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt):
    """Add random frame loss everywhere, on one node, or on one link."""
    inject({"action": "loss", "probability": probability, **_loss_target(node, link)}, swarm, connect, duration)


@inject_app.command("clear-loss")
def inject_clear_loss(node: Optional[int] = typer.Option(None, "--node"), link: Optional[str] = typer.Option(None, "--link"),
                      swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt):
    """Remove extra loss added with the same target."""
    inject({"action": "clear-loss", **_loss_target(node, link)}, swarm, connect, None)


@inject_app.command("jammer")
def inject_jammer(x: float = typer.Argument(..., help="position x (m)"), y: float = typer.Argument(..., help="position y (m)"),
                  power: float = typer.Option(30.0, "--power", help="dBm"),
                  band: Optional[float] = typer.Option(None, "--band", help="jammed bandwidth (Hz); default the whole channel"),
                  velocity: str = typer.Option("0,0", "--velocity", help="vx,vy in m/s for a moving jammer"),
                  radius: float = typer.Option(50.0, "--radius", help="unit-disk radio: receivers within this many m are silenced"),
                  name: str = typer.Option("j1", "--name"),
                  duration: Optional[float] = ForOpt, swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt):
    """Switch a jammer on at (X, Y)."""
    try:
        vel = [float(v) for v in velocity.split(",")]
    except ValueError:
        raise fail(f"--velocity takes vx,vy, got {velocity!r}")
    inject({"action": "jammer", "name": name, "position": [x, y], "power_dbm": power, "band_hz": band,
            "velocity": vel, "radius_m": radius}, swarm, connect, duration)


@inject_app.command("jammer-off")
def inject_jammer_off(name: str = typer.Option("j1", "--name"), swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt):
    """Switch a jammer off."""
    inject({"action": "jammer-off", "name": name}, swarm, connect, None)


@app.command()
def clear(fault_id: int = typer.Argument(..., help="fault id from `swarmloc faults`"), swarm: str = SwarmOpt,
          connect: Optional[list[str]] = ConnectOpt):
    """Clear an active fault by its id."""
    data = control("clear", {"id": fault_id}, swarm, connect)
    console.print(f"fault {fault_id} clears from tick {data['applies_at_tick']}")


@app.command()
def faults(swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt,
           as_json: bool = typer.Option(False, "--json")):
    """List the faults in force in a running swarm."""
    data = control("faults", {}, swarm, connect)
    if as_json:
        print(json.dumps(data))
        return
    if not data["active"]:
        console.print(f"no active faults (t = {data['t']:.1f} s)")
        return
    t = Table("id", "fault", "arguments", "since (s)", "until (s)")
    for f in data["active"]:
        t.add_row(str(f["id"]), f["action"], json.dumps(f["args"]), f"{f['since']:.1f}",
                  "-" if f["until"] is None else f"{f['until']:.1f}")
    console.print(t)


def _status_view(s: dict):
    from rich.console import Group

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
    active = ", ".join(f"#{f['id']} {f['action']} {json.dumps(f['args'])}" for f in s["faults"]) or "none"
    return Group(head, agents, links, f"faults: {active}")


@app.command()
def status(swarm: str = SwarmOpt, connect: Optional[list[str]] = ConnectOpt,
           as_json: bool = typer.Option(False, "--json", help="print the raw status as JSON"),
           watch: bool = typer.Option(False, "--watch", "-w", help="refresh until Ctrl-C or the run ends"),
           interval: float = typer.Option(0.5, "--interval", help="seconds between refreshes with --watch")):
    """Show a running swarm: tick, agents alive, link table (SNR, delivery ratio, last heard), faults."""
    if not watch:
        s = control("status", {}, swarm, connect)
        if as_json:
            print(json.dumps(s))
        else:
            console.print(_status_view(s))
        return
    from rich.live import Live

    seen = False
    with Live(console=console, refresh_per_second=4) as live:
        try:
            while True:
                try:
                    live.update(_status_view(control("status", {}, swarm, connect)))
                    seen = True
                except typer.Exit:
                    if seen:  # the run ended under our eyes: that is the normal way out
                        console.print("netsim is gone: the run has ended")
                        return
                    raise
                time.sleep(interval)
        except KeyboardInterrupt:
            pass


def main():
    app()
