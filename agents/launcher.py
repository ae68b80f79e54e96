"""`swarmloc run`: netsim plus one agent process per platform (or K agents to a process,
agents/host.py), watched until netsim ends.

The launcher owns the processes it starts. Ctrl-C, SIGTERM and SIGHUP stop them all; if the
launcher itself dies (kill -9), a parent-death signal stops them. An agent that crashes is
reported and the run goes on without it (netsim stops waiting for an agent whose liveliness
token is gone), or, with --restart-crashed, it is started again and resumes from its
checkpoint. Only netsim failing fails the run. The summary printed at the end is
agents/summary.py's.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import queue
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass
from datetime import datetime
from pathlib import Path

import typer

from agents.control import DEFAULT_PORT, Failure, Registration
from agents.summary import DROP_WARN, print_summary
from swarmloc import wire
from swarmloc.experiment.scenario import Scenario
from swarmloc.process import console as process_console
from swarmloc.process import die_with_parent

console = process_console()
err = process_console(stderr=True)
MAX_RESTARTS = 3  # per agent: an agent that keeps crashing is left out after this
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


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


@dataclass
class HostProc:
    """Agents sharing one process (agents/host.py), started, killed and restarted one by one
    through the commands on its stdin; its stdout says which of them crashed."""

    name: str
    ids: list[int]
    args: list[str]
    proc: subprocess.Popen | None = None
    crashed: queue.SimpleQueue | None = None  # agents whose loop failed, as the host reported them
    over: bool = False  # its process died and none of its agents is to be restarted

    def command(self, line: str) -> None:
        try:
            self.proc.stdin.write(line + "\n")
            self.proc.stdin.flush()
        except (BrokenPipeError, OSError, ValueError):
            pass  # the host is gone: check_agents reports it


class Swarm:
    """The processes of one run: netsim and the agents (one process each, or K to a host);
    stopped together, whatever happens."""

    def __init__(self, logs: Path, ui=console):
        self.logs, self.ui = logs, ui
        self.netsim: subprocess.Popen | None = None
        self.agents: dict[int, subprocess.Popen] = {}
        self.agent_args: dict[int, list[str]] = {}
        self.hosts: dict[int, HostProc] = {}  # by agent id, for agents that share a process
        self.gone: set[int] = set()  # crashed and left out
        self.killed: set[int] = set()  # killed on purpose (a kill fault), not crashed
        self.crashes: list[Crash] = []
        self.left: dict[int, int | None] = {}  # agents that exited cleanly while netsim ran -> tick noticed
        self._preexec = die_with_parent()  # children are only ever spawned from the main thread

    def _spawn(self, name: str, args: list[str], commands: bool = False) -> subprocess.Popen:
        with open(self.logs / f"{name}.log", "ab") as log:
            return subprocess.Popen([sys.executable, *args], stdout=subprocess.PIPE if commands else log,
                                    stderr=log, stdin=subprocess.PIPE if commands else subprocess.DEVNULL,
                                    text=commands or None, start_new_session=True, preexec_fn=self._preexec)

    def start_netsim(self, args: list[str]) -> subprocess.Popen:
        self.netsim = self._spawn("netsim", args)
        return self.netsim

    def add_host(self, host: HostProc) -> None:
        for aid in host.ids:
            self.hosts[aid] = host
        self.start_host(host)

    def start_host(self, host: HostProc) -> None:
        """(Re)start a host's process: its agents killed by a fault or left out stay down."""
        hold = [x for aid in host.ids if aid in self.killed | self.gone for x in ("--hold", str(aid))]
        host.proc = self._spawn(host.name, [*host.args, *hold], commands=True)
        host.crashed = queue.SimpleQueue()

        def read(proc, crashed):
            for line in proc.stdout:
                verb, _, aid = line.strip().partition(" ")
                if verb == "crashed" and aid.isdigit():
                    crashed.put(int(aid))

        threading.Thread(target=read, args=(host.proc, host.crashed), daemon=True).start()

    def start_agent(self, aid: int) -> None:
        if aid in self.hosts:
            self.hosts[aid].command(f"start {aid}")
        else:
            self.agents[aid] = self._spawn(f"agent-{aid}", self.agent_args[aid])

    def _crashed(self, aid: int, returncode: int, tick: int | None, restart: bool, log: str) -> bool:
        """Report agent aid's crash; True if it is to be started again."""
        again = restart and sum(c.agent == aid and c.restarted for c in self.crashes) < MAX_RESTARTS
        crash = Crash(aid, returncode, again, tick)
        self.crashes.append(crash)
        tail = self.tail(log)
        err.print(f"[yellow]{crash.describe()}; "
                  f"{'restarting it from its checkpoint' if again else 'the run goes on without it'}[/]")
        if tail:
            err.print(tail, markup=False, highlight=False)
        if not again:
            self.gone.add(aid)
        return again

    def check_agents(self, tick: int | None, restart: bool) -> None:
        """Report agents that died on their own since the last check; restart them if asked."""
        for aid, p in list(self.agents.items()):
            if aid in self.killed or p.poll() is None:
                continue
            if p.returncode == 0:  # a clean exit: netsim's stop at the end, or a stop clock before it
                # Said once netsim is done (_ended_early), when it is known which: every normal
                # run's agents exit while netsim writes its results.
                if self.netsim is not None and self.netsim.poll() is None and aid not in self.left:
                    self.left[aid] = tick
                continue
            if self._crashed(aid, p.returncode, tick, restart, f"agent-{aid}"):
                self.start_agent(aid)
            else:
                del self.agents[aid]
        for host in {id(h): h for h in self.hosts.values()}.values():
            while not host.crashed.empty():  # one agent's loop failed; its hostmates go on
                aid = host.crashed.get()
                if aid not in self.killed and self._crashed(aid, 1, tick, restart, host.name):
                    host.command(f"start {aid}")
            if host.over or host.proc.poll() in (None, 0):
                continue
            # The whole process died: each of its agents crashed.
            down = [aid for aid in host.ids if aid not in self.killed | self.gone]
            again = [aid for aid in down if self._crashed(aid, host.proc.returncode, tick, restart, host.name)]
            if again:
                self.start_host(host)
            else:
                host.over = True

    def on_event(self, kind: str, aid: int, gate: Gate | None = None) -> None:
        """netsim's kill/restart faults: the launcher owns the processes, so it carries them out.
        A restart of an agent that is running is refused: a second process of one agent stalls
        the run (issue 26, finding 1)."""
        if aid in self.hosts:
            host = self.hosts[aid]
            if kind == "kill" and aid not in self.killed | self.gone and host.proc.poll() is None:
                self.killed.add(aid)
                host.command(f"kill {aid}")
                self.ui.print(f"[yellow]killed agent-{aid} (fault)[/]")
            elif kind == "restart" and aid in self.killed:
                self.killed.discard(aid)
                host.command(f"start {aid}")
                self.ui.print(f"[yellow]restarted agent-{aid} (fault); it resumes from its checkpoint[/]")
            elif kind == "restart" and gate is not None:
                gate.refuse("events", "agent-running", f"restart of agent-{aid}")
            return
        p = self.agents.get(aid)
        if kind == "restart" and p is not None and p.poll() is None:
            if gate is not None:
                gate.refuse("events", "agent-running", f"restart of agent-{aid}")
            return
        if kind == "kill" and p is not None and p.poll() is None:
            self.killed.add(aid)
            p.kill()
            p.wait()
            self.ui.print(f"[yellow]killed agent-{aid} (fault)[/]")
        elif kind == "restart" and aid in self.agent_args:
            self.killed.discard(aid)
            self.start_agent(aid)
            self.ui.print(f"[yellow]restarted agent-{aid} (fault); it resumes from its checkpoint[/]")

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
            hosts = [h.proc for h in {id(h): h for h in self.hosts.values()}.values()]
            procs = [p for p in (self.netsim, *self.agents.values(), *hosts) if p is not None]
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


class Gate:
    """What the launcher believes of what it hears: a frame netsim sealed (docs/security.md),
    of the type its key carries; everything else refused and counted by key and reason
    (metrics.json `launcher.rejected`). Anyone on the router can publish on the swarm's keys."""

    TYPES = {"events": "event", "clock": "clock"}

    def __init__(self, keys: Path | None):
        from collections import Counter

        from swarmloc.wire import auth

        # Frames for everyone only (me=None), signed by netsim: no member's key can seal them.
        self.opener = None if keys is None else auth.Opener(auth.Keyring.load(keys))
        self.key = None if self.opener is None else {k: getattr(wire.Keys(self.opener.keyring.swarm), k) for k in self.TYPES}
        self.rejected: dict[str, Counter] = {k: Counter() for k in self.TYPES}

    def refuse(self, kind: str, reason: str, detail: str = "") -> None:
        self.rejected[kind][reason] += 1
        if self.rejected[kind][reason] <= 3:
            err.print(f"[yellow]refused a frame on {kind} ({reason}{': ' + detail if detail else ''})[/]", highlight=False)

    def open(self, kind: str, data: bytes | None):
        """The body of an authentic frame of netsim's on `kind`, or None (refused and counted)."""
        from agents.daemon import NETSIM_ID
        from swarmloc.wire import auth

        # Cheap refusals first: size, envelope, type and sender before any MAC, so that a frame
        # on the wrong key neither costs a MAC nor marks its counter as seen (its original, on
        # its own key, must still open).
        if data is None:  # wire.bounded: above the ceiling, never copied out of Zenoh
            return self.refuse(kind, "oversize")
        try:
            env = wire.decode(data, body=False)
        except wire.WireError as exc:
            return self.refuse(kind, "malformed", str(exc))
        if env.type != self.TYPES[kind]:
            return self.refuse(kind, "wrong-type", env.type)
        if env.src != NETSIM_ID:
            return self.refuse(kind, "src-mismatch", f"src {env.src}")
        if self.opener is not None:
            try:
                data, _ = self.opener.open(data, self.key[kind], NETSIM_ID)
            except auth.AuthError as exc:
                return self.refuse(kind, f"auth-{exc.reason}", str(exc))
        try:
            return wire.decode(data).body
        except wire.WireError as exc:
            return self.refuse(kind, "malformed", str(exc))

    def record(self) -> dict:
        return {"rejected": {k: dict(c) for k, c in self.rejected.items() if c}}


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


def run_swarm(sc: Scenario, out: Path | None, swarm: str | None, port: int | None, plots: bool, force: bool,
              restart_crashed: bool, as_json: bool = False, netsim_args: tuple[str, ...] = (),
              per_process: int = 1) -> Path:
    """Run the swarm; swarm None: `default`, or the first of default-2, default-3, ... that no
    other run holds. as_json: metrics.json on stdout at the end, everything else on stderr.
    `netsim_args`: netsim's own options (--no-record, --view, --ros2-...). per_process: agents
    that share one process (agents/host.py); 1: a process each."""
    ui = err if as_json else console
    check_out(out, force)
    port = pick_port(port)
    endpoint = f"tcp/127.0.0.1:{port}"
    # Ctrl-C, a plain kill and a closed terminal must stop the whole swarm, even when we were
    # started with SIGINT ignored (a background job of a non-interactive shell, as under CI).
    for s in STOP_SIGNALS:
        signal.signal(s, _interrupt)
    if swarm is not None:
        registration = Registration(swarm, endpoint=endpoint, scenario=sc.name)
    else:
        registration, taken = Registration.first_free("default", endpoint=endpoint, scenario=sc.name)
        swarm = registration.swarm
        if taken:
            held = ", ".join(f"'{t['swarm']}' (launcher pid {t['pid']})" for t in taken)
            ui.print(f"[yellow]{held} already running: this run is swarm '{swarm}' on {endpoint}; give `--swarm "
                     f"{swarm}` to status, inject, faults, clear and stop[/]")
    try:
        out = make_out(out, sc.name)
        keys = _run_keys(sc, swarm, out)
        registration.update(out=str(out.resolve()), keys=str(keys.resolve()))
        procs = Swarm(out / "logs", ui)
        gate = Gate(keys)
        failure = None
        try:
            _start(procs, sc, out, swarm, endpoint, plots, restart_crashed, keys, ui, netsim_args, per_process)
            _watch(procs, sc, swarm, endpoint, restart_crashed, ui, gate)
        except Interrupted as exc:
            failure = Failure(f"interrupted ({signal.Signals(exc.signum).name}): stopped every process of the swarm; "
                              f"logs in {out / 'logs'}", 128 + exc.signum)
        finally:
            procs.stop()  # before the error above is shown
    finally:
        registration.remove()
    if failure is None and procs.netsim.returncode != 0:
        failure = procs.netsim_failed("netsim failed")
    if failure is not None:
        raise _salvage(out, procs, gate, failure, plots, ui)
    _record_launcher(out, procs.crashes, gate)
    if as_json:
        typer.echo((out / "metrics.json").read_text())
    print_summary(out, procs.crashes, ui)
    early = _ended_early(out, sc, procs)
    if early:
        raise Failure(early, 1)
    return out


def _salvage(out: Path, procs: Swarm, gate: Gate, failure: Failure, plots: bool, ui) -> Failure:
    """A run that netsim did not finish: its results rebuilt from the recording, up to the last
    finished tick, so that nothing computed is lost; the failure, saying how far the run got."""
    from swarmloc.experiment.recording import RecordingError
    from swarmloc.experiment.rundir import RECORDING, rebuild_run

    if (out / "metrics.json").is_file() or not (out / RECORDING).is_file():
        return failure
    previous = {s: signal.signal(s, signal.SIG_IGN) for s in STOP_SIGNALS}  # a second Ctrl-C must not cut it
    try:
        m = rebuild_run(out, plots, why=str(failure).split(";")[0])
        _record_launcher(out, procs.crashes, gate)
    except (RecordingError, ValueError) as exc:
        return Failure(f"{failure}; nothing to rebuild the results from ({exc})", failure.exit_code)
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    last = m.get("ended_early", {}).get("last_tick", m["ticks"] - 1)
    return Failure(f"{failure}; the run ended after tick {last}: metrics.json, estimates and plots rebuilt from "
                   f"{out / RECORDING} up to that tick", failure.exit_code)


def _ended_early(out: Path, sc: Scenario, procs: Swarm) -> str | None:
    """Why a run that netsim finished is not whole, or None: it stopped short of its last tick
    though nobody asked it to, or agents stopped on a stop clock while netsim went on."""
    m = json.loads((out / "metrics.json").read_text())
    said = []
    if m["ticks"] < sc.clock.steps + 1 and "stopped_at_tick" not in m:
        said.append(f"netsim ended after tick {m['ticks'] - 1} of {sc.clock.steps}")
    for aid, k in sorted(procs.left.items()):
        if k is not None and k >= m["ticks"] - 1:  # at the run's last tick: netsim's own stop
            continue
        said.append(f"agent-{aid} exited on its own" + ("" if k is None else f" at tick {k}") +
                    " while netsim went on (a stop it was sent?)")
    return "the run ended early: " + "; ".join(said) if said else None


def _run_keys(sc: Scenario, swarm: str, out: Path) -> Path:
    """The key directory that seals the run's frames: the scenario's (its swarm must be this
    run's), or throwaway keys made for the run in logs/keys (docs/security.md)."""
    from swarmloc.wire.auth import Keyring

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
    # Per-member identity: the hub's file (netsim's), the directory, and each member's own keys.
    Keyring.generate(swarm, sc.agent_ids).save_directory(keys)
    return keys


def _start(procs: Swarm, sc: Scenario, out: Path, swarm: str, endpoint: str, plots: bool, restart_crashed: bool,
           keys: Path, ui=console, netsim_args: tuple[str, ...] = (), per_process: int = 1) -> None:
    scenario_file = out / "logs" / "scenario.input.yaml"
    scenario_file.write_text(sc.to_yaml())
    stop = "" if sc.world.stop_distance is None else \
        f" at most, stopping when an agent is within {sc.world.stop_distance:g} m of a target,"
    ground = [a.id for a in sc.world.agents if not a.localized]
    agents = f"{len(sc.world.agents)} agents" + (f" ({len(sc.localized_ids)} localized and ground station "
                                                 f"{', '.join(map(str, ground))})" if ground else "")
    ui.print(f"[bold]swarmloc run[/] {sc.name}: {agents}, {sc.clock.steps + 1} ticks (0..{sc.clock.steps}){stop} "
                  f"of {sc.clock.dt:g} s, {sc.clock.mode}, seed {sc.seed}, Zenoh router {endpoint}, swarm '{swarm}'")
    net = procs.start_netsim(["-m", "netsim", str(scenario_file), "--swarm", swarm, "--listen", endpoint, "--out", str(out),
                              "--keys", str(keys),
                              *([] if plots else ["--no-plots"]), *(["--await-rejoin"] if restart_crashed else []),
                              *netsim_args])
    if not _wait_listening(int(endpoint.rsplit(":", 1)[1]), net):
        if net.poll() is not None:
            raise procs.netsim_failed("netsim failed to start")
        tail = procs.tail("netsim")
        raise Failure(f"netsim did not open its Zenoh port {endpoint} within {NETSIM_START_S:.0f} s"
                      + (f"; its last log lines:\n{tail}" if tail else ""), 1)
    from swarmloc.estimators import REGISTRY

    info = REGISTRY[sc.estimator.name]
    settings = info.settings(sc.estimator.params)
    specs = {}
    for a in sc.agent_ids:
        # The agent gets its node as plain values, not the scenario: it never parses one.
        specs[a] = out / "logs" / f"agent-{a}.node.json"
        specs[a].write_text(info.node_spec(sc, a, settings).dumps())
    if per_process == 1:
        for a in sc.agent_ids:
            procs.agent_args[a] = ["-m", "agents.daemon", "--id", str(a), "--spec", str(specs[a]), "--swarm", swarm,
                                   "--connect", endpoint, "--state-file", str(out / "logs" / f"agent-{a}.state.npy"),
                                   "--keys", str(keys)]
            procs.start_agent(a)
        return
    ids = list(sc.agent_ids)
    for first in range(0, len(ids), per_process):
        group = ids[first:first + per_process]
        procs.add_host(HostProc(f"host-{group[0]}-{group[-1]}", group, [
            "-m", "agents.host", *(x for a in group for x in ("--agent", f"{a}={specs[a]}")), "--swarm", swarm,
            "--connect", endpoint, "--state-dir", str(out / "logs"), "--keys", str(keys)]))


NETSIM_START_S = 120.0
"""How long netsim may take to open its Zenoh port. It needs 1-2 s on an idle machine, but its
imports alone took 19 s beside a load of 25; slow is not dead, so this is generous."""


def _wait_listening(port: int, proc: subprocess.Popen, timeout: float = NETSIM_START_S) -> bool:
    """True once netsim listens on port; False if it ended or did not listen within timeout."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            return False
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return True
        time.sleep(0.05)
    return False


def _watch(procs: Swarm, sc: Scenario, swarm: str, endpoint: str, restart_crashed: bool, ui=console,
           gate: Gate | None = None) -> None:
    """Progress from netsim's clock, kill/restart faults carried out, crashes reported; until netsim ends.
    Only frames netsim sealed count (`gate`): anyone can publish on the swarm's keys."""
    import queue

    import zenoh
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    ticks: queue.SimpleQueue = queue.SimpleQueue()
    events: queue.SimpleQueue = queue.SimpleQueue()
    session = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("client", connect=[endpoint])))
    # Each key carries one type: a payload longer than it can be is refused by its length alone.
    clock_max, event_max = wire.key_limit("clock"), wire.key_limit("event")
    sub = session.declare_subscriber(wire.Keys(swarm).clock, lambda s: ticks.put(wire.bounded(s.payload, clock_max)))
    sub_events = session.declare_subscriber(wire.Keys(swarm).events,
                                            lambda s: events.put(wire.bounded(s.payload, event_max)))
    gate = gate or Gate(None)
    tick, now_t = None, 0.0
    drops = _DropWatch(swarm, endpoint) if sc.clock.mode == "realtime" else None
    plain = _PlainProgress(ui, sc.clock.steps + 1)
    try:
        with Progress(TextColumn("[progress.description]{task.description}"), BarColumn(), MofNCompleteColumn(),
                      TextColumn("ticks"), TimeElapsedColumn(), TimeRemainingColumn(), console=ui, transient=False) as bar:
            task = bar.add_task("waiting for agents", total=sc.clock.steps + 1)
            while procs.netsim.poll() is None:
                if drops is not None:
                    warning = drops.check()
                    if warning:
                        bar.console.print(f"[yellow]t = {now_t:.1f} s: {warning}[/]")
                while not events.empty():
                    ev = gate.open("events", events.get_nowait())
                    if ev is not None:
                        procs.on_event(ev.kind, ev.node, gate)
                procs.check_agents(tick, restart_crashed)
                c = None
                try:
                    c = gate.open("clock", ticks.get(timeout=0.1)) or c
                    while True:
                        c = gate.open("clock", ticks.get_nowait()) or c
                except queue.Empty:
                    pass
                if c is not None:
                    tick, now_t = c.k, c.t
                    bar.update(task, completed=c.k + 1, description=f"t = {c.t:7.1f} s")
                    plain.update(c.k + 1, c.t)
        procs.check_agents(tick, restart=False)  # the run is over: a crash now is recorded, not undone
    finally:
        if drops is not None:
            drops.close()
        sub.undeclare()
        sub_events.undeclare()
        session.close()


class _PlainProgress:
    """Off a terminal rich draws no bar until the end: a plain line now and then instead."""

    EVERY_S = 10.0

    def __init__(self, ui, total: int):
        self.ui, self.total = ui, total
        self.start = self.last = time.monotonic()

    def update(self, done: int, t: float) -> None:
        now = time.monotonic()
        if self.ui.is_terminal or now - self.last < self.EVERY_S:
            return
        self.last = now
        self.ui.print(f"t = {t:.1f} s: {done}/{self.total} ticks, {now - self.start:.0f} s elapsed", highlight=False)


class _DropWatch:
    """Real time waits for nobody: when the machine cannot keep up, UKF-DCL's chains do not
    finish within their tick and their measurements are dropped. This asks the agents for their
    counters every few seconds (a thread of its own: each round waits up to a second) and says
    so while the run goes, when the share dropped since the last round is large."""

    EVERY_S = 5.0
    QUIET_S = 30.0  # one warning at most this often

    def __init__(self, swarm: str, endpoint: str):
        import queue
        import threading

        self.rounds: queue.SimpleQueue = queue.SimpleQueue()
        self.stop = threading.Event()
        self.last = (0, 0)  # dropped, used over the swarm at the last round
        self.warned = -math.inf
        self.thread = threading.Thread(target=self._poll, args=(swarm, endpoint), name="drop-watch", daemon=True)
        self.thread.start()

    def _poll(self, swarm: str, endpoint: str) -> None:
        from agents.control import ControlClient

        try:
            with ControlClient(swarm, [endpoint]) as ctl:
                while not self.stop.wait(self.EVERY_S):
                    self.rounds.put(ctl.agents().stats)
        except Exception:  # a warning is a courtesy: the run must not depend on it
            return

    def check(self) -> str | None:
        import queue

        latest = None
        try:
            while True:
                latest = self.rounds.get_nowait()
        except queue.Empty:
            pass
        stats = [s for s in (latest or {}).values() if "measurements_dropped" in s]
        if not stats:
            return None
        now = (sum(s["measurements_dropped"] for s in stats), sum(s.get("measurements_used", 0) for s in stats))
        dropped, used = now[0] - self.last[0], now[1] - self.last[1]
        self.last = now
        if dropped + used < 20 or dropped / (dropped + used) <= DROP_WARN or time.monotonic() - self.warned < self.QUIET_S:
            return None
        self.warned = time.monotonic()
        return (f"the agents dropped {dropped / (dropped + used):.0%} of their measurements in the last "
                f"{self.EVERY_S:g} s (chains that did not finish within their tick): this machine is not keeping up "
                "with real time. Lower --speed, or run in lockstep (run --lockstep, replay without --realtime), which waits")

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=3.0)


# ------------------------------------------------------------------------------------ results


def _record_launcher(out: Path, crashes: list[Crash], gate: Gate) -> None:
    path = out / "metrics.json"
    m = json.loads(path.read_text())
    m["crashes"] = [{k: v for k, v in asdict(c).items() if k != "tick"} for c in crashes]
    m["launcher"] = gate.record()
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(m, indent=2))
    os.replace(tmp, path)
