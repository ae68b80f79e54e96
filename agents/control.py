"""Talk to a running swarm: find it by name, query its netsim's control queryable, or ask
its agents themselves for their counters (a swarm without netsim has nothing else to ask).

Each `swarmloc run` registers its swarm in a runtime file (endpoint, launcher pid, scenario,
run directory), so `status`, `inject`, `faults` and `clear` reach it by its --swarm name
even when it took a free port. Zenoh is imported only when a session is opened.
"""

from __future__ import annotations

import itertools
import json
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import typer

from swarmloc import wire

DEFAULT_PORT = 7447
DEFAULT_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"
ENDPOINT = re.compile(r"[a-z0-9-]+/[^?#\s]+(\?[^#\s]*)?(#\S*)?")  # a Zenoh endpoint: proto/address[?metadata][#config]


class Failure(typer.TyperException):
    """An error the user can act on: shown as `error: <message>` (no traceback), exit code `code`."""

    def __init__(self, message: str, code: int = 1):
        super().__init__(message)
        self.exit_code = code


class NotRunning(Failure):
    def __init__(self, swarm: str, endpoints: list[str]):
        super().__init__(f"no swarm '{swarm}' is running on {', '.join(endpoints)} (start one with `swarmloc run`)")


class NobodyAnswers(Failure):
    """`status` asked netsim and then the agents, and heard from neither."""

    def __init__(self, swarm: str, endpoints: list[str]):
        super().__init__(f"no swarm '{swarm}' answers on {', '.join(endpoints)}: neither netsim nor any agent")


# ------------------------------------------------------------------------------------ registry


def runtime_dir() -> Path:
    base = os.environ.get("XDG_RUNTIME_DIR")
    d = Path(base) / "swarmloc" if base else Path("/tmp") / f"swarmloc-{os.getuid()}"
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    st = d.lstat()
    # /tmp is shared: a directory planted there by another user must not be trusted.
    if st.st_uid != os.getuid() or not d.is_dir() or d.is_symlink():
        raise Failure(f"runtime directory {d} is not a directory owned by you; remove it or set XDG_RUNTIME_DIR")
    return d


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:  # a killed launcher its parent has not reaped yet is gone all the same
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


def lookup(swarm: str) -> dict | None:
    """The runtime entry of a live launcher of this swarm; a stale entry is removed."""
    path = runtime_dir() / f"{swarm}.json"
    try:
        info = json.loads(path.read_text())
        if _alive(int(info["pid"])):
            return info
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError):
        pass
    path.unlink(missing_ok=True)
    return None


class SwarmTaken(Failure):
    """Another live launcher holds this swarm name (`running`: its runtime entry)."""

    def __init__(self, swarm: str, running: dict):
        super().__init__(f"swarm '{swarm}' is already running (launcher pid {running['pid']}, {running['endpoint']}); "
                         "give this run another --swarm name", 2)
        self.running = running


class Registration:
    """A launcher's runtime entry for its swarm: claimed exclusively, removed when the run ends."""

    @classmethod
    def first_free(cls, base: str, **info) -> tuple["Registration", list[dict]]:
        """The first of base, base-2, base-3, ... that no live launcher holds, claimed; and the
        entries of the launchers that hold the names before it."""
        taken = []
        for n in itertools.count(1):
            try:
                return cls(base if n == 1 else f"{base}-{n}", **info), taken
            except SwarmTaken as exc:
                taken.append(exc.running)

    def __init__(self, swarm: str, **info):
        self.swarm = swarm
        self.path = runtime_dir() / f"{swarm}.json"
        self.info = {"swarm": swarm, "pid": os.getpid(), **info}
        tmp = self._write()
        try:
            while True:
                try:
                    os.link(tmp, self.path)  # exclusive, and never seen half written
                    return
                except FileExistsError:
                    running = lookup(swarm)  # removes a stale entry, then we try again
                    if running is not None:
                        raise SwarmTaken(swarm, running) from None
        finally:
            tmp.unlink()

    def _write(self) -> Path:
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}")
        with os.fdopen(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600), "w") as f:
            json.dump(self.info, f)
        return tmp

    def update(self, **info) -> None:
        self.info.update(info)
        os.replace(self._write(), self.path)

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)


# ------------------------------------------------------------------------------------ control


KEYS_ENV = "SWARMLOC_KEYS"
"""The swarm's key directory for the control commands when no `swarmloc run` on this machine
registered one (a swarm reached with --connect)."""

AGENTS_TIMEOUT = 1.0
"""s an agents round waits for answers. It ends sooner when every agent Zenoh knows of has
answered; an agent's loop answers between two inputs, within a tick when it is healthy."""


@dataclass
class AgentAnswers:
    stats: dict[int, dict] = field(default_factory=dict)  # agent id: its stats
    reply_s: dict[int, float] = field(default_factory=dict)  # agent id: s from asking to its answer
    alive: set[int] = field(default_factory=set)  # agents whose liveliness token is there
    unreadable: dict[str, str] = field(default_factory=dict)  # key: why its reply could not be decoded


class ControlClient:
    """A Zenoh client session to a swarm: requests on its netsim's control queryable, and the
    agents' own stats (a client of any one peer of the swarm, or of its router, reaches them all)."""

    def __init__(self, swarm: str, connect: list[str] | None = None):
        self.swarm = swarm
        found = lookup(swarm)
        self.endpoints = list(connect) if connect else [found["endpoint"] if found else DEFAULT_ENDPOINT]
        self.sealer = self.opener = None
        keys = os.environ.get(KEYS_ENV) or (found or {}).get("keys")
        if keys:
            from swarmloc.wire import auth

            try:  # the operator's own keys; the hub's file (the admin's directory) can speak as it too
                path = Path(keys)
                ring = auth.Keyring.load(path, "operator" if (path / f"operator{auth.SECRET_SUFFIX}").exists() else None)
            except ValueError as exc:
                raise Failure(str(exc), 2) from None
            me = auth.operator()
            self.sealer, self.opener = auth.Sealer(ring, me), auth.Opener(ring, me)

    def __enter__(self) -> "ControlClient":
        import zenoh

        try:
            self.session = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("client", connect=self.endpoints)))
        except zenoh.ZError:
            raise NotRunning(self.swarm, self.endpoints) from None
        return self

    def __exit__(self, *exc) -> None:
        self.session.close()

    def request(self, op: str, args: dict | None = None, timeout: float = 3.0) -> dict:
        from swarmloc.wire import auth
        from swarmloc.wire.messages import Control

        key = wire.Keys(self.swarm).control
        # A nonce netsim's answer must hold, under netsim's seal for this operator: a captured
        # answer (to another request, or another operator) is not this request's (issue 26).
        nonce = auth.query_nonce()
        payload = wire.encode(Control(op, {**(args or {}), "nonce": nonce}), 0, 0)
        if self.sealer is not None:
            payload = self.sealer.seal(payload, key, auth.NETSIM)
        unreadable = None
        for r in self.session.get(key, payload=payload, timeout=timeout):
            if r.ok is None:
                continue
            try:  # netsim's, sealed by netsim: anyone can answer a query, the first is not the answer
                body = auth.open_control_reply(self.opener, str(r.ok.key_expr), r.ok.payload.to_bytes(), nonce)
            except (wire.WireError, auth.AuthError) as exc:
                unreadable = exc
                continue
            if not body.ok:
                raise Failure(f"netsim refused {op}: {body.error}", 2)
            return body.data
        if unreadable is not None:
            raise Failure(f"unreadable reply from netsim: {unreadable}")
        raise NotRunning(self.swarm, self.endpoints)

    def agents(self, timeout: float = AGENTS_TIMEOUT) -> AgentAnswers:
        """One round of asking every agent of the swarm: its stats (docs/wire.md, section 8) and
        whether its liveliness token is there."""
        import zenoh

        from swarmloc.wire import auth

        keys = wire.Keys(self.swarm)
        start = time.monotonic()
        # Both queries go out before either is read: the round costs one timeout, not two.
        nonce = auth.query_nonce()
        # No consolidation: Zenoh would keep one answer per key, a stranger's as readily as the agent's.
        stats = self.session.get(keys.stats("*"), payload=nonce.encode(), timeout=timeout,
                                 consolidation=zenoh.ConsolidationMode.NONE)
        tokens = self.session.liveliness().get(keys.alive("*"), timeout=timeout)
        out = AgentAnswers()
        for r in stats:
            if r.ok is None:
                continue
            try:  # only an agent's own answer to this query counts (issue 26, finding 3)
                aid, data = auth.open_stats_reply(self.opener, str(r.ok.key_expr), r.ok.payload.to_bytes(), nonce)
            except ValueError as exc:  # auth.AuthError is a ValueError
                out.unreadable[str(r.ok.key_expr)] = str(exc)
                continue
            if aid not in out.stats:
                out.stats[aid] = data
                out.reply_s[aid] = time.monotonic() - start
        for r in tokens:
            try:
                out.alive.add(wire.Keys.agent_of(str(r.ok.key_expr)))
            except (AttributeError, ValueError):  # an error reply, or a token that names no agent
                continue
        return out

