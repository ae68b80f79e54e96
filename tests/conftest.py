import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from swarmloc.process import pin_blas

pin_blas()  # before numpy loads

ROOT = Path(__file__).resolve().parent.parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Cli:
    """The real `swarmloc` command in a subprocess, on its own port and swarm name."""

    def __init__(self, tmp_path: Path):
        self.port = free_port()
        self.swarm = "t" + uuid.uuid4().hex[:8]
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.tmp = tmp_path
        self.procs: list[subprocess.Popen] = []

    def cmd(self, *args) -> list[str]:
        return [sys.executable, "-m", "agents", *args]

    def run(self, *args, timeout=120, check=False) -> subprocess.CompletedProcess:
        p = subprocess.run(self.cmd(*args), capture_output=True, text=True, timeout=timeout, cwd=self.tmp)
        if check and p.returncode != 0:
            raise AssertionError(f"swarmloc {' '.join(args)} failed ({p.returncode}):\n{p.stdout}\n{p.stderr}")
        return p

    def start_run(self, scenario: str, out: Path, *extra) -> subprocess.Popen:
        p = subprocess.Popen(self.cmd("run", scenario, "--out", str(out), "--port", str(self.port), "--swarm", self.swarm,
                                      "--no-plots", *extra),
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=self.tmp)
        self.procs.append(p)
        return p

    def control(self, *args, timeout=30) -> subprocess.CompletedProcess:
        return self.run(*args, "--swarm", self.swarm, "--connect", self.endpoint, timeout=timeout)

    def wait_tick(self, k: int, proc: subprocess.Popen, timeout=60.0) -> dict:
        """netsim's status once it has reached tick k. Polled over an in-process Zenoh client: a
        `swarmloc status` process per poll costs a second of CPU, which real-time runs beside
        it would lose (the CLI's own status is tested in test_cli and test_processes)."""
        import zenoh

        deadline = time.monotonic() + timeout
        ns = None
        try:
            while True:
                assert proc.poll() is None, f"run ended early: {proc.communicate()}"
                if ns is None:
                    try:
                        ns = NetsimClient(self.endpoint, self.swarm)
                    except zenoh.ZError:  # netsim listens once the launcher has started it
                        ns = None
                if ns is not None:
                    try:
                        s = ns.request("status", timeout=1.0)
                        if s["k"] >= k:
                            return s
                    except AssertionError:  # no reply yet: netsim is starting
                        pass
                if time.monotonic() > deadline:
                    raise AssertionError(f"tick {k} not reached in {timeout} s")
                time.sleep(0.05)
        finally:
            if ns is not None:
                ns.close()

    def cleanup(self):
        for p in self.procs:
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()


@pytest.fixture
def cli(tmp_path):
    c = Cli(tmp_path)
    yield c
    c.cleanup()


def swarm_pids(swarm: str) -> list[int]:
    """Processes whose command line names this swarm (netsim and agents of one run)."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                cmdline = (d / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if swarm.encode() in cmdline and any(b"agents" in c or b"netsim" in c for c in cmdline):
                out.append(int(d.name))
    return out


def agent_pid(swarm: str, agent_id: int) -> int:
    """The process of one agent of a run."""
    for pid in swarm_pids(swarm):
        try:
            cmd = (Path("/proc") / str(pid) / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"--id" in cmd and cmd[cmd.index(b"--id") + 1] == str(agent_id).encode():
            return pid
    raise AssertionError(f"agent {agent_id} not running")


def netsim_pid(swarm: str) -> int:
    (pid,) = [p for p in swarm_pids(swarm) if b"netsim" in (Path("/proc") / str(p) / "cmdline").read_bytes().split(b"\0")]
    return pid


class NetsimClient:
    """A Zenoh client of a running netsim's control queryable (fast polling for tests)."""

    def __init__(self, endpoint: str, swarm: str):
        import zenoh

        from agents.control import lookup
        from swarmloc import wire
        from swarmloc.wire import auth

        self.wire, self.keys = wire, wire.Keys(swarm)
        # A run seals its frames (docs/security.md): control requests need its key.
        found = lookup(swarm)
        self.sealer = (auth.Sealer(auth.Keyring.load(found["keys"], "operator"), auth.operator())
                       if found and found.get("keys") else None)
        self.session = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("client", connect=[endpoint])))

    def request(self, op: str, args: dict | None = None, timeout: float = 5.0) -> dict:
        from swarmloc.wire.messages import Control, Reply

        payload = self.wire.encode(Control(op, args or {}), 0, 1)
        if self.sealer is not None:
            payload = self.sealer.seal(payload, self.keys.control, 0)
        for r in self.session.get(self.keys.control, payload=payload, timeout=timeout):
            if r.ok is not None:
                body = self.wire.decode(r.ok.payload.to_bytes(), expect=(Reply,)).body
                assert body.ok, body.error
                return body.data
        raise AssertionError(f"no reply to {op}")

    def wait(self, predicate, timeout: float = 30.0, what: str = "condition"):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                s = self.request("status")
            except AssertionError:
                s = None
            if s is not None and predicate(s):
                return s
            time.sleep(0.05)
        raise AssertionError(f"timed out waiting for {what}")

    def close(self):
        self.session.close()


_SPIN = """
import time
p0, t0 = time.process_time(), time.monotonic()
while time.monotonic() - t0 < {seconds}:
    sum(range(1000))
print((time.process_time() - p0) / (time.monotonic() - t0))
"""


def spare_cores(processes: int = 2, seconds: float = 1.0) -> float:
    """How many cores this machine can give us right now: `processes` spinning processes run for
    `seconds` of wall time and report the CPU share each got (2.0 on a quiet 2-core machine,
    about 1.0 beside two processes burning a core each)."""
    procs = [subprocess.Popen([sys.executable, "-c", _SPIN.format(seconds=seconds)], stdout=subprocess.PIPE, text=True)
             for _ in range(processes)]
    return sum(float(p.communicate(timeout=seconds + 60)[0]) for p in procs)


def require_spare_cores(need: float, why: str) -> float:
    """Skip, saying so, unless the machine has `need` cores to spare: for a property that only
    means something with spare CPU (keeping up in real time), never for one the protocol
    guarantees."""
    have = spare_cores()
    if have < need:
        pytest.skip(f"needs {need:.1f} spare cores, the machine gives {have:.2f} now: {why}")
    return have


def camera_view(cam: dict):
    """The half-width and half-height (m) a layout's top-down 3D camera sees: its half-height at
    its distance, and LAYOUT_ASPECT times that across."""
    import math

    import numpy as np

    from swarmloc.experiment.recording import LAYOUT_ASPECT

    half_h = cam["distance"] * math.tan(math.radians(cam["fovy"] / 2))
    return np.array([LAYOUT_ASPECT * half_h, half_h])


def framed(cam: dict, xy) -> bool:
    """Every point of `xy` inside what a layout's top-down 3D camera sees."""
    import numpy as np

    d = np.abs(np.asarray(xy, float) - np.asarray(cam["targetOffset"][:2]))
    return bool((d <= camera_view(cam)).all())
