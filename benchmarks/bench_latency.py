"""Benchmark: the latency netsim adds to a radio hop, against a direct Zenoh hop, in one run.

Every path is measured the way the agent daemon measures a hop: the sender attaches
time.perf_counter() (CLOCK_MONOTONIC, comparable between processes on one Linux machine) to
its put (congestion control BLOCK, reliability RELIABLE); the receiver's Zenoh callback only
enqueues, and the latency is taken when the receiver's loop picks the frame up.

Paths, each a set of separate OS processes on 127.0.0.1, measured in turn in every repetition:

- netsim, real time: `python -m agents run` of an N-agent scenario with `clock.mode: realtime`
  and a unit-disk radio with latency_s 0 (modelled latency zero); hop statistics from
  metrics.json `agent_stats`.
- netsim, lockstep: the same scenario with `clock.mode: lockstep`; without interference (unit
  disk) netsim routes each frame as soon as it arrives.
- Zenoh peer to peer: a publisher process and a subscriber process in peer mode.
- Zenoh via a router: publisher and subscriber in client mode through a third process that
  opens a Zenoh session in router mode (as netsim does), without netsim's Python relay.

The direct paths send frames of the size the agents send (median of the first netsim run's
radio.npz), paced two ways: one every --interval s (processes kept busy, as in lockstep) and
one every dt (processes idle between frames, as in real time at speed 1).

Usage: .venv/bin/python benchmarks/bench_latency.py [--repeat 3] [--agents 2] [--duration 30] [--dt 0.1]
Timing only; nothing here is a pass/fail test.
"""

from __future__ import annotations

import os

from swarmloc.process import pin_blas

pin_blas()  # before numpy loads

import argparse
import json
import platform
import queue
import signal
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

from machine import code_version, cpu_model  # benchmarks/machine.py

HERE = Path(__file__).resolve()
PY = sys.executable
HOST = "127.0.0.1"
KEY = "bench/latency/hop"

# --------------------------------------------------------------------------- process bookkeeping


def _start_time(pid: int) -> str | None:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def _children(pid: int) -> list[int]:
    out = []
    try:
        for task in Path(f"/proc/{pid}/task").iterdir():
            try:
                out += [int(c) for c in (task / "children").read_text().split()]
            except OSError:
                pass
    except OSError:
        pass
    return out


class Procs:
    """Every process this script starts, directly or through `agents run`; all stopped in stop()."""

    def __init__(self) -> None:
        self.popens: list[subprocess.Popen] = []
        self.seen: dict[int, str] = {}  # pid -> /proc start time, so a recycled pid is never signalled

    def start(self, args: list[str], log: Path, **kw) -> subprocess.Popen:
        f = open(log, "ab")
        p = subprocess.Popen(args, stdout=kw.pop("stdout", f), stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                             start_new_session=True, **kw)
        f.close()
        self.popens.append(p)
        self.track(p.pid)
        return p

    def track(self, pid: int) -> None:
        """Remember pid and all its current descendants (`agents run` starts netsim and agents itself)."""
        todo = [pid]
        while todo:
            q = todo.pop()
            st = _start_time(q)
            if st is None:
                continue
            self.seen.setdefault(q, st)
            todo += _children(q)

    def _alive(self, pid: int) -> bool:
        st = _start_time(pid)
        if st is None or st != self.seen.get(pid):
            return False
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            return False
        return state != "Z"

    def wait(self, p: subprocess.Popen, timeout: float) -> int | None:
        """Wait for p (tracking its descendants meanwhile); None if it is still running at the timeout."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.track(p.pid)
            try:
                return p.wait(0.2)
            except subprocess.TimeoutExpired:
                pass
        return None

    def stop(self, p: subprocess.Popen, first=signal.SIGTERM, grace: float = 5.0) -> None:
        self.track(p.pid)
        if p.poll() is None:
            p.send_signal(first)
            try:
                p.wait(grace)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)

    def stop_all(self) -> None:
        for p in self.popens:
            if p.poll() is None:
                self.stop(p)
        # Whatever is left of the descendants (e.g. agents of an `agents run` that was killed).
        left = [pid for pid in self.seen if self._alive(pid)]
        for pid in left:
            try:
                os.kill(pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and any(self._alive(pid) for pid in left):
            time.sleep(0.1)
        for pid in left:
            if self._alive(pid):
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
        for p in self.popens:
            try:
                p.wait(2)
            except subprocess.TimeoutExpired:
                pass

    def leftovers(self) -> list[int]:
        return [pid for pid in self.seen if self._alive(pid)]


def free_port() -> int:
    with socket.socket() as s:
        s.bind((HOST, 0))
        return s.getsockname()[1]


def wait_listening(port: int, proc: subprocess.Popen, timeout: float = 20.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            return False
        with socket.socket() as s:
            if s.connect_ex((HOST, port)) == 0:
                return True
        time.sleep(0.05)
    return False


def wait_line(path: Path, text: str, proc: subprocess.Popen, timeout: float = 20.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists() and text in path.read_text(errors="replace"):
            return True
        if proc.poll() is not None:
            return False
        time.sleep(0.05)
    return False


def pct(lat_sorted: list[float], q: float) -> float:
    """The agent daemon's percentile (agents/daemon.py stats()), so both sides are computed alike."""
    return lat_sorted[min(len(lat_sorted) - 1, int(q * len(lat_sorted)))]


# --------------------------------------------------------------------------- child roles


def zconfig(mode: str, listen=(), connect=()) -> "object":
    import zenoh

    from swarmloc import wire

    return zenoh.Config.from_json5(wire.zenoh_config(mode, list(listen), list(connect)))


def role_router(a) -> None:
    """A bare Zenoh router (what netsim's session is, minus netsim). Ends on SIGTERM or after --timeout."""
    import zenoh

    session = zenoh.open(zconfig("router", listen=[a.listen]))
    print("ready", flush=True)
    try:
        time.sleep(a.timeout)
    finally:
        session.close()


def role_relay(a) -> None:
    """A bare Python relay: a router session (as netsim's) that subscribes to <KEY>/in and, from
    its main loop, puts every frame on <KEY>/out with its attachment: netsim's hop minus netsim."""
    import zenoh

    q: queue.SimpleQueue = queue.SimpleQueue()
    session = zenoh.open(zconfig("router", listen=[a.listen]))
    pub = session.declare_publisher(f"{KEY}/out", congestion_control=zenoh.CongestionControl.BLOCK,
                                    reliability=zenoh.Reliability.RELIABLE)
    session.declare_subscriber(f"{KEY}/in", lambda s: q.put((s.payload.to_bytes(), s.attachment)))
    print("ready", flush=True)
    deadline = time.monotonic() + a.timeout
    try:
        while time.monotonic() < deadline:
            try:
                data, att = q.get(timeout=0.5)
            except queue.Empty:
                continue
            pub.put(data, attachment=att.to_bytes() if att is not None else None)
    finally:
        session.close()


def role_agent_pub(a) -> None:
    """Agent 1 of a netsim swarm, reduced to its radio: alive token, then --count unicast frames
    to agent 2 on radio/tx/1, numbered as the daemon numbers them, with its send-time attachment."""
    import numpy as np
    import zenoh

    from swarmloc import wire
    from swarmloc.wire.messages import Beacon

    keys = wire.Keys(a.swarm)
    session = zenoh.open(zconfig("client", connect=[a.connect]))
    clock = queue.SimpleQueue()
    session.declare_subscriber(keys.clock, lambda s: clock.put(1))
    pub = session.declare_publisher(keys.radio_tx(1), **wire.publisher_options(zenoh))
    token = session.liveliness().declare_token(keys.alive(1))
    try:
        clock.get(timeout=30)  # netsim ticks once both agents are alive
        pad = max(0, a.size - len(wire.encode(Beacon(0, np.zeros(2), np.eye(2), {}), 1, 1, 2)))
        seq = 0

        def send(k: int) -> None:
            nonlocal seq
            seq += 1
            msg = Beacon(k, np.zeros(2), np.eye(2), {i: 0 for i in range(pad // 3)})
            pub.put(wire.encode(msg, 1, seq, 2), attachment=wire.encode_send_time(time.perf_counter()))

        for _ in range(20):  # warm-up, dropped by the receiver (k = 0)
            send(0)
            time.sleep(0.01)
        time.sleep(0.2)
        nxt = time.perf_counter()
        for i in range(a.count):
            send(i + 1)
            nxt += a.interval
            delay = nxt - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        time.sleep(0.5)
    finally:
        token.undeclare()
        session.close()


def role_agent_sub(a) -> None:
    """Agent 2 of a netsim swarm, reduced to its radio: alive token, and the hop latency of every
    frame on radio/rx/2 (delivery attachment) taken when its loop picks the frame up."""
    import zenoh

    from swarmloc import wire

    keys = wire.Keys(a.swarm)
    q: queue.SimpleQueue = queue.SimpleQueue()
    session = zenoh.open(zconfig("client", connect=[a.connect]))
    session.declare_subscriber(keys.radio_rx(2), lambda s: q.put((s.payload.to_bytes(), s.attachment)))
    token = session.liveliness().declare_token(keys.alive(2))
    print("ready", flush=True)
    lat: list[float] = []
    deadline = time.monotonic() + a.timeout
    try:
        while len(lat) < a.count and time.monotonic() < deadline:
            try:
                data, att = q.get(timeout=0.5)
            except queue.Empty:
                continue
            now = time.perf_counter()
            got = wire.decode_delivery(att.to_bytes() if att is not None else None)
            if got is None or got[1] is None:
                continue
            if wire.decode(data).body.k >= 1:
                lat.append(now - got[1])
    finally:
        token.undeclare()
        session.close()
    Path(a.out).write_text(json.dumps({"lat_s": lat}))


def role_sub(a) -> None:
    """Subscriber: callback enqueues; the loop takes the latency on pick-up; results to --out as JSON."""
    import zenoh

    q: queue.SimpleQueue = queue.SimpleQueue()
    session = zenoh.open(zconfig(a.mode, listen=[a.listen] if a.listen else [], connect=[a.connect] if a.connect else []))
    sub = session.declare_subscriber(a.key, lambda s: q.put((s.payload.to_bytes(), s.attachment)))
    print("ready", flush=True)
    lat: list[float] = []
    deadline = time.monotonic() + a.timeout
    try:
        while len(lat) < a.count and time.monotonic() < deadline:
            try:
                data, att = q.get(timeout=min(1.0, max(0.01, deadline - time.monotonic())))
            except queue.Empty:
                continue
            sent = struct.unpack("<d", att.to_bytes())[0] if att is not None else None
            now = time.perf_counter()
            seq = struct.unpack_from("<q", data)[0]
            if seq == -2:
                break  # end marker
            if seq >= 0 and sent is not None:
                lat.append(now - sent)
    finally:
        sub.undeclare()
        session.close()
    Path(a.out).write_text(json.dumps({"lat_s": lat}))


def role_pub(a) -> None:
    """Publisher: waits for a matching subscriber, warms up, then --count frames every --interval s."""
    import zenoh

    session = zenoh.open(zconfig(a.mode, listen=[a.listen] if a.listen else [], connect=[a.connect] if a.connect else []))
    pub = session.declare_publisher(a.key, congestion_control=zenoh.CongestionControl.BLOCK,
                                    reliability=zenoh.Reliability.RELIABLE)
    try:
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline:
            ms = pub.matching_status
            if getattr(ms, "matching", ms):
                break
            time.sleep(0.02)
        pad = bytes(max(0, a.size - 8))

        def send(seq: int) -> None:
            pub.put(struct.pack("<q", seq) + pad, attachment=struct.pack("<d", time.perf_counter()))

        for _ in range(20):  # warm-up, not measured
            send(-1)
            time.sleep(0.01)
        time.sleep(0.2)
        stop_at = time.monotonic() + a.timeout
        nxt = time.perf_counter()
        for seq in range(a.count):
            if time.monotonic() > stop_at:
                break
            send(seq)
            nxt += a.interval
            delay = nxt - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        send(-2)
        time.sleep(0.5)  # let the end marker out before the session closes
    finally:
        pub.undeclare()
        session.close()


# --------------------------------------------------------------------------- measurements


def scenario_yaml(n: int, mode: str, dt: float, duration: float) -> str:
    # Agents on the corners of a 100 m square, circling; unit disk with infinite range, zero
    # modelled latency and no jitter: whatever latency a hop shows is the machinery's.
    corners = [(0, 0), (100, 0), (100, 100), (0, 100), (50, -50), (150, 50), (50, 150), (-50, 50)]
    lines = [
        "version: 1", f"name: bench-latency-{n}", "seed: 5",
        f"clock: {{mode: {mode}, dt: {dt}, duration: {duration}, speed: 1.0}}",
        "world:", "  agents:",
    ]
    for i in range(n):
        x, y = corners[i % len(corners)]
        lines.append(f"    - {{id: {i + 1}, start: [{x + 200.0 * (i // len(corners))}, {y}.0], heading: {0.5 * i},"
                     f" motion: {{kind: circle, speed: 1.0, turn_rate: 0.015}}}}")
    lines.append("radio: {model: unit-disk, range_m: .inf, latency_s: 0.0, jitter_s: 0.0}")
    return "\n".join(lines) + "\n"


def hop_stats(metrics: dict) -> dict:
    st = [s for s in metrics.get("agent_stats", {}).values() if s.get("hop_us_median") is not None]
    if not st:
        raise RuntimeError("no agent reported hop latencies (agent_stats empty)")
    return {"median_us": statistics.median(s["hop_us_median"] for s in st),
            "p99_us": max(s["hop_us_p99"] for s in st), "hops": sum(s["hops"] for s in st),
            "frames": metrics["radio"]["delivered"], "ticks_per_s": metrics.get("ticks_per_s"),
            # netsim's own share: its Zenoh callback receiving the frame -> its put to the receivers
            # (recorded only where routing happens on arrival, i.e. lockstep without rounds).
            "netsim_median_us": metrics["radio"].get("netsim_hop_us_median"),
            "netsim_p99_us": metrics["radio"].get("netsim_hop_us_p99")}


def frame_sizes(run_dir: Path) -> list[int]:
    import numpy as np

    with np.load(run_dir / "radio.npz") as d:
        return [int(v) for v in d["size"][d["delivered"]]]


def run_agents_run(procs: Procs, scenario: Path, out: Path, swarm: str, budget: float) -> dict:
    """`python -m agents run` as a user would; SIGINT (its clean stop) if it overruns."""
    cmd = [PY, "-m", "agents", "run", str(scenario), "--port", "0", "--no-plots", "--out", str(out), "--swarm", swarm]
    p = procs.start(cmd, out.parent / f"{out.name}.cli.log")
    rc = procs.wait(p, budget)
    if rc is None:
        procs.stop(p, first=signal.SIGINT, grace=10.0)
        raise RuntimeError(f"`agents run` overran {budget:.0f} s (log {out.parent / (out.name + '.cli.log')})")
    if rc != 0:
        raise RuntimeError(f"`agents run` exited {rc}: {(out.parent / (out.name + '.cli.log')).read_text()[-2000:]}")
    return json.loads((out / "metrics.json").read_text())


def run_direct(procs: Procs, kind: str, tmp: Path, tag: str, count: int, size: int, interval: float) -> dict:
    port = free_port()
    endpoint = f"tcp/{HOST}:{port}"
    res = tmp / f"{tag}.json"
    started: list[subprocess.Popen] = []
    timeout = count * interval + 30.0
    sub_role, pub_role = "_sub", "_pub"
    try:
        if kind == "peer":
            sub_args = ["--mode", "peer", "--listen", endpoint]
            pub_args = ["--mode", "peer", "--connect", endpoint]
        elif kind == "relay":
            relay = procs.start([PY, str(HERE), "_relay", "--listen", endpoint, "--timeout", str(timeout + 30)],
                                tmp / f"{tag}.relay.log")
            started.append(relay)
            if not wait_listening(port, relay):
                raise RuntimeError(f"relay did not start: {(tmp / f'{tag}.relay.log').read_text()[-2000:]}")
            sub_args = ["--mode", "client", "--connect", endpoint, "--key", f"{KEY}/out"]
            pub_args = ["--mode", "client", "--connect", endpoint, "--key", f"{KEY}/in"]
        elif kind == "netsim":
            # netsim routing between two processes that are an agent's radio and nothing else:
            # the same pub/sub pacing as the other direct paths, netsim's relay in the middle.
            scen = tmp / f"{tag}.yaml"
            scen.write_text(scenario_yaml(2, "realtime", 0.1, count * interval + 15.0))
            swarm = f"{tag}x"
            net = procs.start([PY, "-m", "netsim", str(scen), "--swarm", swarm, "--listen", endpoint],
                              tmp / f"{tag}.netsim.log", cwd=HERE.parent.parent)
            started.append(net)
            if not wait_listening(port, net):
                raise RuntimeError(f"netsim did not start: {(tmp / f'{tag}.netsim.log').read_text()[-2000:]}")
            sub_role, pub_role = "_asub", "_apub"
            sub_args = pub_args = ["--connect", endpoint, "--swarm", swarm]
        else:
            router = procs.start([PY, str(HERE), "_router", "--listen", endpoint, "--timeout", str(timeout + 30)],
                                 tmp / f"{tag}.router.log")
            started.append(router)
            if not wait_listening(port, router):
                raise RuntimeError(f"router did not start: {(tmp / f'{tag}.router.log').read_text()[-2000:]}")
            sub_args = pub_args = ["--mode", "client", "--connect", endpoint]
        sub_log = tmp / f"{tag}.sub.log"
        sub = procs.start([PY, str(HERE), sub_role, *sub_args, "--count", str(count), "--timeout", str(timeout),
                           "--out", str(res)], sub_log)
        started.append(sub)
        if not wait_line(sub_log, "ready", sub):
            raise RuntimeError(f"subscriber did not start: {sub_log.read_text()[-2000:]}")
        if kind == "peer" and not wait_listening(port, sub):
            raise RuntimeError("subscriber is not listening")
        pub = procs.start([PY, str(HERE), pub_role, *pub_args, "--count", str(count), "--size", str(size),
                           "--interval", str(interval), "--timeout", str(timeout)], tmp / f"{tag}.pub.log")
        started.append(pub)
        if procs.wait(sub, timeout + 10) is None:
            raise RuntimeError(f"{kind}: subscriber did not finish")
        procs.wait(pub, 10)
    finally:
        for p in reversed(started):
            procs.stop(p)
    lat = sorted(json.loads(res.read_text())["lat_s"])
    if len(lat) < count // 2:
        raise RuntimeError(f"{kind}: only {len(lat)} of {count} frames arrived")
    return {"median_us": pct(lat, 0.5) * 1e6, "p99_us": pct(lat, 0.99) * 1e6, "hops": len(lat)}


# --------------------------------------------------------------------------- report


PATHS = [
    ("realtime", "netsim, real time"),
    ("lockstep", "netsim, lockstep (unit disk: routed on arrival)"),
    ("peer-fast", "Zenoh peer to peer, a frame every {fast} ms"),
    ("router-fast", "Zenoh client -> router -> client, a frame every {fast} ms"),
    ("peer-tick", "Zenoh peer to peer, a frame every dt = {tick} ms"),
    ("router-tick", "Zenoh client -> router -> client, a frame every dt = {tick} ms"),
    ("relay-fast", "bare Python relay (router session; subscribe, put), a frame every {fast} ms"),
    ("netsim-fast", "netsim's relay alone (real time; two radio-only agents), a frame every {fast} ms"),
    ("relay-tick", "bare Python relay (router session; subscribe, put), a frame every dt = {tick} ms"),
    ("netsim-tick", "netsim's relay alone (real time; two radio-only agents), a frame every dt = {tick} ms"),
]
# Issue 16's hop target: netsim's added latency against a bare relay's, same pacing, same run.
RELAY_TARGET = [("netsim-fast", "relay-fast", "router-fast"), ("netsim-tick", "relay-tick", "router-tick")]
# (netsim path, direct path it is compared with): same pacing regime (hot back-to-back vs once a tick).
DIFFS = [("realtime", "router-tick"), ("realtime", "peer-tick"), ("lockstep", "router-fast"), ("lockstep", "peer-fast")]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--agents", type=int, default=2)
    p.add_argument("--dt", type=float, default=0.1, help="tick of the netsim scenario (s)")
    p.add_argument("--duration", type=float, default=30.0, help="simulated = wall seconds of each real-time run")
    p.add_argument("--count", type=int, default=1000, help="frames per direct-path run")
    p.add_argument("--interval", type=float, default=0.002, help="s between frames on the direct paths")
    p.add_argument("--paths", default=",".join(k for k, _ in PATHS), help="comma-separated subset of: "
                   + ", ".join(k for k, _ in PATHS))
    a = p.parse_args()
    chosen = [(k, label) for k, label in PATHS if k in a.paths.split(",")]
    load_start = os.getloadavg()[0]
    code_start = code_version()
    procs = Procs()

    def on_term(*_):
        raise SystemExit(143)

    signal.signal(signal.SIGTERM, on_term)
    rows: dict[str, list[dict]] = {k: [] for k, _ in PATHS}
    size = None
    sizes: list[int] = []
    tag = f"bl{os.getpid()}"
    with tempfile.TemporaryDirectory(prefix="bench_latency_") as tmp_s:
        tmp = Path(tmp_s)
        scen = {}
        for mode in ("realtime", "lockstep"):
            scen[mode] = tmp / f"{mode}.yaml"
            scen[mode].write_text(scenario_yaml(a.agents, mode, a.dt, a.duration))
        budget = a.duration + 90.0
        try:
            for rep in range(a.repeat):
                for key, _ in chosen:
                    name = f"r{rep}-{key}"
                    t0 = time.monotonic()
                    if key in ("realtime", "lockstep"):
                        r = hop_stats(run_agents_run(procs, scen[key], tmp / name, f"{tag}{rep}{key[0]}", budget))
                        if size is None:  # the direct paths send frames of the agents' median size
                            sizes = frame_sizes(tmp / name)
                            size = int(statistics.median(sizes))
                    else:
                        kind, pace = key.split("-")
                        count, interval = (a.count, a.interval) if pace == "fast" else (int(round(a.duration / a.dt)), a.dt)
                        r = run_direct(procs, kind, tmp, name, count, size or 91, interval)
                    rows[key].append(r)
                    print(f"rep {rep + 1} {key:10s} median {r['median_us']:10.1f} us  p99 {r['p99_us']:10.1f} us  "
                          f"hops {r['hops']}  ({time.monotonic() - t0:.1f} s)", file=sys.stderr, flush=True)
        finally:
            procs.stop_all()
            left = procs.leftovers()
            if left:
                print(f"WARNING: processes still alive after cleanup: {left}", file=sys.stderr)

    med = {k: {f: statistics.median(r[f] for r in rs) for f in ("median_us", "p99_us")} for k, rs in rows.items() if rs}
    internal = {k: [(r["netsim_median_us"], r["netsim_p99_us"]) for r in rs if r.get("netsim_median_us") is not None]
                for k, rs in rows.items()}
    load_end = os.getloadavg()[0]
    argv = " ".join(sys.argv[1:])
    print(f"## Latency netsim adds to a radio hop ({date.today()})\n")
    print(f"Machine: {os.cpu_count()} vCPU ({cpu_model()}), Python {platform.python_version()}, Linux {platform.release()}. "
          f"Code (last commit to netsim/, swarmloc/, agents/): {code_start if code_start == code_version() else code_start + ' at start, ' + code_version() + ' at end'}. Command: `.venv/bin/python benchmarks/bench_latency.py{(' ' + argv) if argv else ''}`. "
          f"1-min load average {load_start:.1f} at start, {load_end:.1f} at end (other work shares the machine).\n")
    print(f"netsim runs: {a.agents} agents (UKF-DCL), unit disk with latency_s 0, dt {a.dt} s, {a.duration:g} s per real-time "
          f"run at speed 1; hop = median of the agents' medians, p99 = largest agent p99. Direct paths: frames of "
          f"{size or 91} B ({f'median size of the frames the agents sent, which range {min(sizes)}-{max(sizes)} B' if sizes else 'a typical beacon'}), either {a.count} "
          f"every {a.interval * 1e3:g} ms (processes kept hot, like lockstep) or {int(round(a.duration / a.dt))} every dt "
          f"(processes idle between frames, like real time). "
          f"{a.repeat} repetitions, each running every path in turn.\n")
    print("| path | " + " | ".join(f"rep {i + 1} median / p99 (us)" for i in range(a.repeat)) + " | **median** (us) | **p99** (us) |")
    print("|---|" + "---|" * a.repeat + "---|---|")
    for key, label in chosen:
        label = label.format(fast=f"{a.interval * 1e3:g}", tick=f"{a.dt * 1e3:g}")
        cells = [f"{r['median_us']:,.0f} / {r['p99_us']:,.0f}" for r in rows[key]]
        print(f"| {label} | " + " | ".join(cells) + f" | **{med[key]['median_us']:,.0f}** | **{med[key]['p99_us']:,.0f}** |")
    print()
    for key, base in DIFFS:
        if key not in med or base not in med:
            continue
        d_med = med[key]["median_us"] - med[base]["median_us"]
        d_p99 = med[key]["p99_us"] - med[base]["p99_us"]
        print(f"- added by netsim ({key} minus {base}): median {d_med:+,.0f} us, p99 {d_p99:+,.0f} us")
    for key, relay, base in RELAY_TARGET:
        if all(k in med for k in (key, relay, base)):
            added = {f: med[key][f] - med[base][f] for f in ("median_us", "p99_us")}
            bare = {f: med[relay][f] - med[base][f] for f in ("median_us", "p99_us")}
            print(f"- netsim against a bare relay ({key} vs {relay}, each minus {base}): added median {added['median_us']:+,.0f} "
                  f"us vs {bare['median_us']:+,.0f} us (ratio {added['median_us'] / bare['median_us']:.2f}; target <= 1.5), "
                  f"p99 {added['p99_us']:+,.0f} vs {bare['p99_us']:+,.0f} us")
    for key, vals in internal.items():
        if vals:
            print(f"- netsim internal ({key}; its callback -> its put, per repetition median / p99): "
                  + ", ".join(f"{m:,.0f} / {q:,.0f} us" for m, q in vals))


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1].startswith("_"):
        role = sys.argv[1]
        cp = argparse.ArgumentParser(prog=f"bench_latency.py {role}")
        cp.add_argument("--mode", default="peer")
        cp.add_argument("--listen", default="")
        cp.add_argument("--connect", default="")
        cp.add_argument("--count", type=int, default=1000)
        cp.add_argument("--size", type=int, default=91)
        cp.add_argument("--interval", type=float, default=0.002)
        cp.add_argument("--timeout", type=float, default=60.0)
        cp.add_argument("--out", default="")
        cp.add_argument("--key", default=KEY)
        cp.add_argument("--swarm", default="bench")
        ca = cp.parse_args(sys.argv[2:])
        if role in ("_router", "_relay"):
            signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
        {"_router": role_router, "_relay": role_relay, "_sub": role_sub, "_pub": role_pub,
         "_apub": role_agent_pub, "_asub": role_agent_sub}[role](ca)
    else:
        main()
