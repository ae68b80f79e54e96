"""An agent host: several agents in one OS process, each exactly the agent a process of its
own would be (its node, id, keys, Zenoh session and Zenoh keys, its checkpoint), all served by
one loop. On the wire nothing tells them apart from one agent per process.

Why: an agent process is about 50 MB, nearly all of it the interpreter, numpy, scipy and
Zenoh's runtime, which agents in one process share (a Zenoh session costs well under a
megabyte: docs/benchmarks.md#agents-per-process). 256 agents in 256 processes would not fit
the 6 GB a swarm of 256 may take on one host.

Isolation: a node's exception is caught by its daemon (counted `node-error`, as in a process of
its own); an error that ends an agent's loop ends that agent only, reported on stdout as
`crashed ID`, and its hostmates go on. What they share is the loop's time: an agent's long
turn (a slow step of its node) delays its hostmates' turns. A whole-process death (a segfault,
an out-of-memory kill) takes every agent of the host, as it would take a companion computer.

Two front ends: `swarmloc run --agents-per-process K` (below) and, on a companion computer,
`swarmloc agent --config A --config B` (agents/cli/deploy.py), whose agents are built from their
configuration files and run until each has stopped (SIGTERM, or netsim's stop under radio netsim).

The launcher (agents/launcher.py) drives a host over stdin, one command a line, because it
carries out kill and restart faults itself: `kill ID` stops agent ID at once (its session
closed: the swarm sees it gone, as after kill -9), `start ID` starts it again from its
checkpoint. The host exits when stdin closes, on SIGTERM, or when every agent it runs has
stopped with the swarm's clock and none waits for a restart.

    python -m agents.host --swarm S --connect tcp/127.0.0.1:7447 --keys K \\
        --agent 1=logs/agent-1.node.json --agent 2=logs/agent-2.node.json --state-dir logs
"""

from __future__ import annotations

import argparse
import logging
import queue
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from agents.daemon import AgentConfig, AgentDaemon, OpenError, announce, load_node, open_daemon
from swarmloc.node import NodeSpec
from swarmloc.process import exit_on_sigterm
from swarmloc.wire import auth

log = logging.getLogger("swarmloc.host")


@dataclass
class Hosted:
    """One agent of the host: how to build it, and its daemon while it runs."""

    aid: int
    spec: Path | NodeSpec  # a file as `swarmloc run` writes it, or the node of an agent configuration
    cfg: AgentConfig
    daemon: AgentDaemon | None = None
    killed: bool = False  # stopped by `kill`, waiting for `start`
    ended: threading.Event = field(default_factory=threading.Event)  # its daemon closed (by itself, a kill, a crash)

    @property
    def name(self) -> str:
        return f"agent-{self.aid}"


class Host:
    """The agents of one process, served by one loop: an agent's turn (AgentDaemon.service)
    comes when its inbox has something or a timer or polled source of its is due. One loop and
    not a thread each: with a thread each, every frame woke its agent's thread, which then had
    to win the GIL from its hostmates; one loop takes what arrived together in one wake-up, for
    about a seventh less CPU in swarm256's hosts (docs/benchmarks.md#one-loop-per-host-2026-12-08)."""

    def __init__(self, agents: list[Hosted], report):
        self.agents = {a.aid: a for a in agents}
        self.report = report  # report(line, why): one line to the launcher per event, and the reason in words
        self.changed = threading.Event()  # an agent ended or was killed: the main loop looks again
        self._lock = threading.Lock()
        self.stdin_closed = False  # the launcher is gone: so is the reason to wait for a restart
        # What the loop is told: an agent with something queued (a Hosted), one to take on
        # ("add", Hosted), the end (None).
        self._ready: queue.SimpleQueue = queue.SimpleQueue()
        self._loop: threading.Thread | None = None

    def start(self, aid: int) -> None:
        a = self.agents[aid]
        with self._lock:
            if a.daemon is not None and not a.ended.is_set():
                return
            a.killed = False
            a.ended.clear()
            # Afresh: a restarted agent is a new one that resumes its checkpoint.
            node = load_node(a.spec, aid) if isinstance(a.spec, Path) else a.spec.build()
            a.daemon = open_daemon(node, a.cfg)
            if self._loop is None:
                self._loop = threading.Thread(target=self._serve, name="agents", daemon=True)
                self._loop.start()
            self._ready.put(("add", a))

    def _serve(self) -> None:
        live: dict[int, Hosted] = {}
        while True:
            now = time.monotonic()
            wake = min((a.daemon.wake_at for a in live.values()), default=now + 0.5)
            turn: dict[int, Hosted] = {}
            try:
                item = self._ready.get(timeout=min(0.5, max(0.0, wake - now)))
                while True:  # everything told so far goes in this round, each agent once
                    if item is None:
                        return
                    if isinstance(item, tuple):  # ("add", a): its inbox may hold frames already
                        a = item[1]
                        live[a.aid] = a
                        a.daemon.inbox.wake = lambda a=a: self._ready.put(a)
                        threading.current_thread().name = a.name
                        announce(a.daemon)
                        turn[a.aid] = a
                    elif live.get(item.aid) is item:
                        turn[item.aid] = item
                    item = self._ready.get_nowait()
            except queue.Empty:
                pass
            now = time.monotonic()
            for a in live.values():
                if a.daemon.wake_at <= now:
                    turn[a.aid] = a
            for a in turn.values():
                self._turn(a, live)

    def _turn(self, a: Hosted, live: dict[int, Hosted]) -> None:
        daemon = a.daemon
        # The log's thread name says whose turn it is (`-v` lines read agent-ID, as they did
        # when each agent had a thread).
        threading.current_thread().name = a.name
        try:
            going = daemon.service()
        except Exception as exc:
            log.exception("agent %s: its loop failed; the host's other agents go on", a.aid)
            if not a.killed:
                self.report(f"crashed {a.aid}", f"agent {a.aid}: its loop failed ({type(exc).__name__}: {exc}); the "
                            "other agents of this process go on")
            going = False
        if going:
            return
        del live[a.aid]
        try:
            daemon.close()
        except Exception:
            log.exception("agent %s: closing it failed", a.aid)
        a.ended.set()
        self.changed.set()

    def kill(self, aid: int) -> None:
        a = self.agents[aid]
        a.killed = True
        if a.daemon is not None:
            a.daemon.stop()
            a.ended.wait(5.0)
        log.info("agent %s killed", aid)
        self.changed.set()

    def command(self, line: str) -> None:
        """One of the launcher's lines: `kill ID` or `start ID`; anything else is logged and ignored."""
        verb, _, arg = line.strip().partition(" ")
        try:
            aid = int(arg)
            if aid not in self.agents or verb not in ("kill", "start"):
                raise ValueError
        except ValueError:
            log.warning("host: not a command: %r", line.strip())
            return
        if verb == "kill":
            self.kill(aid)
        else:
            try:
                self.start(aid)
            except (OpenError, ValueError) as exc:
                self.agents[aid].ended.set()
                self.report(f"crashed {aid}", str(exc))

    def done(self) -> bool:
        """Every agent has stopped with the swarm's clock, none waits for a restart."""
        return all(a.ended.is_set() and not a.killed for a in self.agents.values())

    def stop(self) -> None:
        for a in self.agents.values():
            if a.daemon is not None:
                a.daemon.stop()
        deadline = time.monotonic() + 2.0
        for a in self.agents.values():
            if a.daemon is not None:
                a.ended.wait(max(0.0, deadline - time.monotonic()))
        if self._loop is not None:
            self._ready.put(None)
            self._loop.join(2.0)


def _read_commands(host: Host, stream) -> None:
    for line in stream:
        host.command(line)
    host.stdin_closed = True
    host.changed.set()


def serve_host(host: Host, held: tuple[int, ...] = (), commands=None) -> None:
    """Start the host's agents (but the `held` ones) and wait until every one has stopped, or
    `commands` (the launcher's stdin) closes; every agent stopped after. Call exit_on_sigterm
    first: SIGTERM ends the wait here, in the main thread."""
    for aid in host.agents:
        if aid in held:
            host.agents[aid].killed = True
        else:
            host.command(f"start {aid}")  # one agent that cannot start is reported; the others start
    if commands is not None:
        threading.Thread(target=_read_commands, args=(host, commands), name="commands", daemon=True).start()
    try:
        while not (host.done() or host.stdin_closed):
            host.changed.wait(0.5)
            host.changed.clear()
    except KeyboardInterrupt:
        pass
    finally:
        host.stop()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m agents.host", description="Several agents in one process.")
    p.add_argument("--agent", action="append", required=True, metavar="ID=SPEC",
                   help="an agent and its node spec (JSON, as `swarmloc run` writes it); repeatable")
    p.add_argument("--hold", action="append", type=int, default=[], metavar="ID",
                   help="an agent known but not started (killed by a fault): `start ID` on stdin starts it")
    p.add_argument("--swarm", default="default")
    p.add_argument("--connect", action="append", required=True, help="Zenoh endpoint (repeatable)")
    p.add_argument("--state-dir", type=Path, help="checkpoints: agent-ID.state.npy in this directory")
    p.add_argument("--keys", type=Path, help="the swarm's key directory: each agent seals with its own keys (agent-<id>.secret)")
    p.add_argument("-v", "--verbose", action="store_true")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO if a.verbose else logging.WARNING,
                        format="%(asctime)s %(threadName)s %(levelname)s %(message)s")
    exit_on_sigterm()
    try:
        agents = []
        for item in a.agent:
            aid, sep, spec = item.partition("=")
            if not sep or not aid.strip().isdigit():
                raise ValueError(f"--agent {item}: expected ID=SPEC")
            state = None if a.state_dir is None else a.state_dir / f"agent-{int(aid)}.state.npy"
            # Each agent its own keys (per-member identity): agent-<id>.secret of the directory.
            keyring = None if a.keys is None else auth.Keyring.load(a.keys, auth.member_of(int(aid)))
            agents.append(Hosted(int(aid), Path(spec), AgentConfig(swarm=a.swarm, connect=tuple(a.connect),
                                                                   state_file=state, keyring=keyring)))
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2

    def report(line: str, why: str) -> None:
        log.error("%s", why)
        print(line, flush=True)

    serve_host(Host(agents, report), tuple(a.hold), sys.stdin)
    return 0


if __name__ == "__main__":
    sys.exit(main())
