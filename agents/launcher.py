"""`swarmloc run`: netsim plus one agent process per platform, watched until netsim ends.

The launcher owns the processes it starts. Ctrl-C, SIGTERM and SIGHUP stop them all; if the
launcher itself dies (kill -9), a parent-death signal stops them. An agent that crashes is
reported and the run goes on without it (netsim stops waiting for an agent whose liveliness
token is gone), or, with --restart-crashed, it is started again and resumes from its
checkpoint. Only netsim failing fails the run.
"""

from __future__ import annotations

import ctypes
import functools
import itertools
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from datetime import datetime
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from agents.control import DEFAULT_PORT, Failure, Registration
from swarmloc import wire
from swarmloc.estimators import REGISTRY
from swarmloc.scenario import Scenario

console = Console()
err = Console(stderr=True, soft_wrap=True)
MAX_RESTARTS = 3  # per agent: an agent that keeps crashing is left out after this
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
PR_SET_PDEATHSIG = 1
# Resolved here, not in the forked child, where only the call itself should run.
_prctl = ctypes.CDLL(None, use_errno=True).prctl if sys.platform.startswith("linux") else None


def _die_with(launcher: int) -> None:
    """preexec_fn: SIGTERM this child when the launcher dies, however it dies.

    The kernel sends it when the thread that forked the child exits, so children are only
    ever spawned from the main thread."""
    _prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM))
    if os.getppid() != launcher:  # the launcher died before prctl took effect
        os._exit(1)


def exit_status(code: int) -> str:
    if code >= 0:
        return f"exit code {code}"
    try:
        return f"exit code {code}: {signal.Signals(-code).name}"
    except ValueError:
        return f"exit code {code}: signal {-code}"


@dataclass
class Crash:
    agent: int
    returncode: int
    restarted: bool
    tick: int | None  # the last tick the launcher saw before it noticed; None: before the first

    def describe(self) -> str:
        when = "" if self.tick is None else f", noticed at tick {self.tick}"
        return f"agent-{self.agent} crashed ({exit_status(self.returncode)}{when})"


class Swarm:
    """The processes of one run: netsim and one agent each; stopped together, whatever happens."""

    def __init__(self, logs: Path):
        self.logs = logs
        self.netsim: subprocess.Popen | None = None
        self.agents: dict[int, subprocess.Popen] = {}
        self.agent_args: dict[int, list[str]] = {}
        self.killed: set[int] = set()  # killed on purpose (a kill fault), not crashed
        self.crashes: list[Crash] = []
        self._preexec = functools.partial(_die_with, os.getpid()) if _prctl is not None else None

    def _spawn(self, name: str, args: list[str]) -> subprocess.Popen:
        with open(self.logs / f"{name}.log", "ab") as log:
            return subprocess.Popen([sys.executable, *args], stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                    start_new_session=True, preexec_fn=self._preexec)

    def start_netsim(self, args: list[str]) -> subprocess.Popen:
        self.netsim = self._spawn("netsim", args)
        return self.netsim

    def start_agent(self, aid: int) -> None:
        self.agents[aid] = self._spawn(f"agent-{aid}", self.agent_args[aid])

    def check_agents(self, tick: int | None, restart: bool) -> None:
        """Report agents that died on their own since the last check; restart them if asked."""
        for aid, p in list(self.agents.items()):
            if aid in self.killed or p.poll() in (None, 0):
                continue
            again = restart and sum(c.agent == aid and c.restarted for c in self.crashes) < MAX_RESTARTS
            crash = Crash(aid, p.returncode, again, tick)
            self.crashes.append(crash)
            tail = self.tail(f"agent-{aid}")
            err.print(f"[yellow]{crash.describe()}; "
                      f"{'restarting it from its checkpoint' if again else 'the run goes on without it'}[/]")
            if tail:
                err.print(tail, markup=False, highlight=False)
            if again:
                self.start_agent(aid)
            else:
                del self.agents[aid]

    def on_event(self, kind: str, aid: int) -> None:
        """netsim's kill/restart faults: the launcher owns the processes, so it carries them out."""
        p = self.agents.get(aid)
        if kind == "kill" and p is not None and p.poll() is None:
            self.killed.add(aid)
            p.kill()
            p.wait()
            console.print(f"[yellow]killed agent-{aid} (fault)[/]")
        elif kind == "restart" and aid in self.agent_args:
            self.killed.discard(aid)
            self.start_agent(aid)
            console.print(f"[yellow]restarted agent-{aid} (fault); it resumes from its checkpoint[/]")

    def netsim_failed(self, what: str) -> Failure:
        code = self.netsim.returncode
        tail = self.tail("netsim")
        # netsim exits 2 for a bad scenario (e.g. a radio parameter), like our own checks.
        return Failure(f"{what} ({exit_status(code)})" + (f"; its last log lines:\n{tail}" if tail else ""), 2 if code == 2 else 1)

    def tail(self, name: str, lines: int = 15) -> str:
        text = (self.logs / f"{name}.log").read_text(errors="replace").splitlines()
        return "\n".join(text[-lines:])

    def stop(self, grace: float = 3.0) -> None:
        """Stop every process; signals are ignored meanwhile, so a second Ctrl-C leaves no orphans."""
        previous = {s: signal.signal(s, signal.SIG_IGN) for s in STOP_SIGNALS}
        try:
            procs = [p for p in (self.netsim, *self.agents.values()) if p is not None]
            for p in procs:
                if p.poll() is None:
                    p.send_signal(signal.SIGTERM)
            deadline = time.monotonic() + grace
            for p in procs:
                try:
                    p.wait(max(0.0, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
        finally:
            for s, handler in previous.items():
                signal.signal(s, handler)


class Interrupted(KeyboardInterrupt):
    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _interrupt(signum, frame):
    raise Interrupted(signum)


# ------------------------------------------------------------------------------------ setup


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


def pick_port(port: int | None) -> int:
    if port is None:
        return DEFAULT_PORT if _port_free(DEFAULT_PORT) else _free_port()
    if port == 0:
        return _free_port()
    if not _port_free(port):
        raise typer.BadParameter(f"{port} is in use on 127.0.0.1 (another swarm running?); pass --port 0 for any free port",
                                 param_hint=["--port"])
    return port


def _is_run_dir(d: Path) -> bool:
    return (d / "logs").is_dir() or (d / "metrics.json").is_file()


def check_out(out: Path | None, force: bool) -> None:
    """Refuse an --out that is not a directory, or holds files, before anything is started."""
    if out is None or not out.exists():
        return
    if not out.is_dir():
        raise typer.BadParameter(f"{out} exists and is not a directory", param_hint=["--out"])
    if any(out.iterdir()):
        if not force:
            raise typer.BadParameter(f"{out} is not empty; pass --force to empty it first", param_hint=["--out"])
        if not _is_run_dir(out):  # --force must never wipe a directory that is not ours
            raise typer.BadParameter(f"{out} is not empty and not a swarmloc run directory; refusing to empty it",
                                     param_hint=["--out"])


def make_out(out: Path | None, name: str) -> Path:
    """Create the run directory (emptied, if check_out allowed a non-empty one) with logs/."""
    try:
        if out is None:
            base = Path("runs") / f"{name}-{datetime.now():%Y%m%d-%H%M%S}"
            for n in itertools.count(1):
                out = base if n == 1 else base.with_name(f"{base.name}-{n}")
                try:
                    out.mkdir(parents=True)
                    break
                except FileExistsError:
                    continue
        else:
            out.mkdir(parents=True, exist_ok=True)
            for child in out.iterdir():
                if child.is_dir() and not child.is_symlink():
                    shutil.rmtree(child)
                else:
                    child.unlink()
        (out / "logs").mkdir()
    except OSError as exc:
        raise typer.BadParameter(f"cannot create {exc.filename or out}: {exc.strerror}", param_hint=["--out"]) from None
    return out


# ------------------------------------------------------------------------------------ run


def run_swarm(sc: Scenario, out: Path | None, swarm: str, port: int | None, plots: bool, force: bool,
              restart_crashed: bool) -> Path:
    check_out(out, force)
    port = pick_port(port)
    endpoint = f"tcp/127.0.0.1:{port}"
    # Ctrl-C, a plain kill and a closed terminal must stop the whole swarm, even when we were
    # started with SIGINT ignored (a background job of a non-interactive shell, as under CI).
    for s in STOP_SIGNALS:
        signal.signal(s, _interrupt)
    registration = Registration(swarm, endpoint=endpoint, scenario=sc.name)
    try:
        out = make_out(out, sc.name)
        keys = _run_keys(sc, swarm, out)
        registration.update(out=str(out.resolve()), keys=str(keys.resolve()))
        procs = Swarm(out / "logs")
        try:
            _start(procs, sc, out, swarm, endpoint, plots, restart_crashed, keys)
            _watch(procs, sc, swarm, endpoint, restart_crashed)
        except Interrupted as exc:
            raise Failure(f"interrupted ({signal.Signals(exc.signum).name}): stopped every process of the swarm; "
                          f"logs in {out / 'logs'}", 128 + exc.signum) from None
        finally:
            procs.stop()  # before the error above is shown
    finally:
        registration.remove()
    if procs.netsim.returncode != 0:
        raise procs.netsim_failed("netsim failed")
    _record_crashes(out, procs.crashes)
    print_summary(out, procs.crashes)
    return out


def _run_keys(sc: Scenario, swarm: str, out: Path) -> Path:
    """The key directory that seals the run's frames: the scenario's (its swarm must be this
    run's), or throwaway keys made for the run in logs/keys (docs/security.md)."""
    from swarmloc.auth import KEY_FILE, Keyring

    if sc.security.keys is not None:
        path = Path(sc.security.keys).expanduser()
        try:
            ring = Keyring.load(path)
        except ValueError as exc:
            raise Failure(f"security.keys: {exc}", 2) from None
        if ring.swarm != swarm:
            raise Failure(f"security.keys: {path} holds the keys of swarm {ring.swarm!r}; run it with --swarm {ring.swarm}",
                          2)
        return path
    keys = out / "logs" / "keys"
    keys.mkdir(mode=0o700, parents=True, exist_ok=True)
    Keyring.generate(swarm).save(keys / KEY_FILE)
    return keys


def _start(procs: Swarm, sc: Scenario, out: Path, swarm: str, endpoint: str, plots: bool, restart_crashed: bool,
           keys: Path) -> None:
    scenario_file = out / "logs" / "scenario.input.yaml"
    scenario_file.write_text(sc.to_yaml())
    stop = "" if sc.world.stop_distance is None else \
        f" at most, stopping when an agent is within {sc.world.stop_distance:g} m of a target,"
    console.print(f"[bold]swarmloc run[/] {sc.name}: {len(sc.world.agents)} agents, {sc.clock.steps + 1} ticks (0..{sc.clock.steps}){stop} "
                  f"of {sc.clock.dt:g} s, {sc.clock.mode}, seed {sc.seed}, Zenoh router {endpoint}, swarm '{swarm}'")
    net = procs.start_netsim(["-m", "netsim", str(scenario_file), "--swarm", swarm, "--listen", endpoint, "--out", str(out),
                              "--keys", str(keys),
                              *([] if plots else ["--no-plots"]), *(["--await-rejoin"] if restart_crashed else [])])
    _wait_listening(int(endpoint.rsplit(":", 1)[1]), net)
    if net.poll() is not None:
        raise procs.netsim_failed("netsim failed to start")
    from swarmloc.estimators import REGISTRY

    info = REGISTRY[sc.estimator.name]
    settings = info.settings(sc.estimator.params)
    for a in sc.agent_ids:
        # The agent gets its node as plain values, not the scenario: it never parses one.
        spec = out / "logs" / f"agent-{a}.node.json"
        spec.write_text(info.node_spec(sc, a, settings).dumps())
        procs.agent_args[a] = ["-m", "agents.daemon", "--id", str(a), "--spec", str(spec), "--swarm", swarm,
                               "--connect", endpoint, "--state-file", str(out / "logs" / f"agent-{a}.state.npy"),
                               "--keys", str(keys)]
        procs.start_agent(a)


def _wait_listening(port: int, proc: subprocess.Popen, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            return
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.05)


def _watch(procs: Swarm, sc: Scenario, swarm: str, endpoint: str, restart_crashed: bool) -> None:
    """Progress from netsim's clock, kill/restart faults carried out, crashes reported; until netsim ends."""
    import queue

    import zenoh
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    ticks: queue.SimpleQueue = queue.SimpleQueue()
    events: queue.SimpleQueue = queue.SimpleQueue()
    session = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("client", connect=[endpoint])))
    sub = session.declare_subscriber(wire.Keys(swarm).clock, lambda s: ticks.put(s.payload.to_bytes()))
    sub_events = session.declare_subscriber(wire.Keys(swarm).events, lambda s: events.put(s.payload.to_bytes()))
    tick = None
    try:
        with Progress(TextColumn("[progress.description]{task.description}"), BarColumn(), MofNCompleteColumn(),
                      TextColumn("ticks"), TimeElapsedColumn(), TimeRemainingColumn(), console=console, transient=False) as bar:
            task = bar.add_task("waiting for agents", total=sc.clock.steps + 1)
            while procs.netsim.poll() is None:
                while not events.empty():
                    try:
                        ev = wire.decode(events.get_nowait()).body
                        procs.on_event(ev.kind, ev.node)
                    except wire.WireError:
                        pass
                procs.check_agents(tick, restart_crashed)
                latest = None
                try:
                    latest = ticks.get(timeout=0.1)
                    while True:
                        latest = ticks.get_nowait()
                except queue.Empty:
                    pass
                if latest is not None:
                    try:
                        c = wire.decode(latest).body
                    except wire.WireError:
                        continue
                    tick = c.k
                    bar.update(task, completed=c.k + 1, description=f"t = {c.t:7.1f} s")
        procs.check_agents(tick, restart=False)  # the run is over: a crash now is recorded, not undone
    finally:
        sub.undeclare()
        sub_events.undeclare()
        session.close()


# ------------------------------------------------------------------------------------ results


def _record_crashes(out: Path, crashes: list[Crash]) -> None:
    path = out / "metrics.json"
    m = json.loads(path.read_text())
    m["crashes"] = [{k: v for k, v in asdict(c).items() if k != "tick"} for c in crashes]
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(m, indent=2))
    os.replace(tmp, path)


def consistency_table(m: dict, algs: list[str]) -> Table:
    """Average NEES (and NIS) of each estimator over agents and ticks, with the two-sided 95%
    chi-square bounds a consistent filter's average falls in."""
    t = Table(title="Consistency: average NEES and NIS (95% bounds)")
    for col in ("estimator", "NEES", "bounds", "", "NIS", "bounds", ""):
        t.add_column(col, justify="left" if col == "estimator" else "right")

    def cells(c):
        if not c:
            return ["-", "", ""]
        lo, hi = c["bounds"]
        return [f"{c['mean']:.2f}", f"[{lo:.2f}, {hi:.2f}]", "[green]inside[/]" if c["inside"] else "[red]outside[/]"]

    for a in algs:
        e = m["estimators"][a]
        t.add_row(a, *cells(e.get("nees")), *cells(e.get("nis")))
    return t


def target_table(m: dict, algs: list[str]) -> Table:
    """Each target-localizing estimator's target error (m): averaged over the agents and the
    ticks they had an estimate, and over the agents at the last tick; and its NEES."""
    t = Table(title="Target error (m), over agents")
    for col in ("estimator", "target", "mean", "final", "NEES", "bounds"):
        t.add_column(col, justify="left" if col in ("estimator", "target") else "right")
    for a in algs:
        for o, e in m["estimators"][a].get("targets", {}).items():
            n = e.get("nees")
            t.add_row(a, o, *("-" if v is None else f"{v:.2f}" for v in (e["mean_error_m"], e["final_error_m"])),
                      "-" if not n else f"{n['mean']:.2f}", "" if not n else f"[{n['bounds'][0]:.2f}, {n['bounds'][1]:.2f}]")
    return t


def pose_table(m: dict, algs: list[str]) -> Table:
    """Per agent and estimator: position RMSE (m), heading RMSE (rad) and average NEES, for a
    swarm whose states carry a heading (a replay's robots)."""
    t = Table(title="Per agent: position RMSE (m), heading RMSE (rad), NEES (3 dof when consistent)", show_lines=True)
    t.add_column("estimator")
    for aid in m["agents"]:
        t.add_column(f"A{aid}", justify="right")
    t.add_column("all", justify="right")

    def cell(e):
        nees = e.get("nees")
        parts = [f"{e['rmse_m']:.3f}" if e.get("rmse_m") is not None else "-",
                 f"{e['heading_rmse_rad']:.3f}" if e.get("heading_rmse_rad") is not None else "-",
                 f"{nees['mean']:.1f}" if nees else "-"]
        return "\n".join(parts)

    for a in algs:
        e = m["estimators"][a]
        t.add_row(a, *(cell(e["agents"][str(aid)]) for aid in m["agents"]), cell(e))
    return t


def print_summary(out: Path, crashes: list[Crash]) -> None:
    m = json.loads((out / "metrics.json").read_text())
    algs = REGISTRY.order(m["estimators"])
    t = Table(title=f"Position error (m), {m['scenario']} seed {m['seed']}")
    t.add_column("agent")
    for a in algs:  # two-line headers: a long estimator name does not widen two columns
        t.add_column(f"{a}\nmean", justify="right")
        t.add_column(f"{a}\nfinal", justify="right")

    def fmt(v):
        return "-" if v is None else f"{v:.3f}" if abs(v) < 1 else f"{v:.2f}"

    for aid in map(str, m["agents"]):
        row = [f"A{aid}"]
        for a in algs:
            e = m["estimators"][a]["agents"][aid]
            row += [fmt(e["mean_error_m"]), fmt(e["final_error_m"])]
        t.add_row(*row)
    t.add_row("all", *sum(([fmt(m["estimators"][a]["mean_error_m"]), ""] for a in algs), []), style="bold")
    console.print(t)
    console.print(consistency_table(m, algs))
    if any(m["estimators"][a].get("heading_rmse_rad") is not None for a in algs):
        console.print(pose_table(m, algs))
    if any("targets" in m["estimators"][a] for a in algs):
        console.print(target_table(m, algs))
    r = m.get("radio", {})
    console.print(f"{m['ticks']} ticks in {m['wall_time_s']:.1f} s ({m['ticks_per_s']:.0f} ticks/s); radio: "
                  f"{r.get('delivered', 0)} frames delivered, dropped {r.get('dropped', {}) or 'none'}")
    for c in crashes:
        then = "restarted from its checkpoint" if c.restarted else "left out from then on (its estimates stop there)"
        console.print(f"[yellow]{c.describe()}; {then}[/]", soft_wrap=True)
    plots = ", plots/*.png" if (out / "plots").is_dir() else ""
    console.print(f"run directory: [bold]{out}[/] (metrics.json, estimates/*.npz{plots})")
