"""Start-up of a swarm: wall time from `swarmloc run` to netsim's first clock frame (tick 0),
and every process's peak resident memory, for swarms of several sizes.

Usage: python benchmarks/bench_startup.py [--sizes 4 16 64] [--tree PATH ...]
Each --tree is a checkout run as `python -m agents run` from that directory (default: this
one), so versions are measured side by side in one run. The swarm is planar robots running IL
(no radio traffic) for 5 s of lockstep: what is measured is starting, not estimating. Not a test.
"""

from __future__ import annotations

import argparse
import math
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from bench_memory import children, cmdline, rss_kb  # benchmarks/bench_memory.py

from swarmloc.process import pin_blas

pin_blas()

import yaml  # noqa: E402
import zenoh  # noqa: E402


def scenario(n: int) -> dict:
    side = math.ceil(math.sqrt(n))
    agents = [{"id": i + 1, "start": [30.0 * (i % side), 30.0 * (i // side)]} for i in range(n)]
    return {"version": 1, "name": f"startup{n}", "seed": 1, "clock": {"mode": "lockstep", "dt": 0.5, "duration": 5.0},
            "world": {"agents": agents}, "sensors": {"range": {"probability": 0.0}},
            "radio": {"model": "unit-disk", "range_m": 100.0}, "estimator": {"name": "il"}, "references": []}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def measure(tree: Path, n: int) -> dict:
    port, swarm = free_port(), f"start{os.getpid()}x{n}"
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "s.yaml"
        path.write_text(yaml.safe_dump(scenario(n)))
        first = threading.Event()
        started = time.perf_counter()
        launcher = subprocess.Popen([sys.executable, "-m", "agents", "run", str(path), "--out", f"{tmp}/run", "--port",
                                     str(port), "--no-plots", "--swarm", swarm], cwd=tree,
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        session = None
        while session is None and launcher.poll() is None:  # netsim's router is not up at once
            try:
                conf = zenoh.Config()
                conf.insert_json5("mode", '"client"')
                conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
                session = zenoh.open(conf)
            except zenoh.ZError:
                time.sleep(0.05)
        tick0 = {}
        sub = session.declare_subscriber(f"swarmloc/{swarm}/clock",
                                         lambda s: (tick0.setdefault("t", time.perf_counter()), first.set()))
        peak: dict[int, int] = {}
        while launcher.poll() is None:
            for pid in children(launcher.pid):
                if (kb := rss_kb(pid)) and ("--id " in cmdline(pid) or " -m netsim " in cmdline(pid)):
                    peak[pid] = max(peak.get(pid, 0), kb)
            time.sleep(0.2)
        ended = time.perf_counter()
        sub.undeclare()
        session.close()
    return {"tick0_s": tick0["t"] - started if "t" in tick0 else None, "total_s": ended - started,
            "processes": len(peak), "total_rss_mb": sum(peak.values()) / 1024, "ok": launcher.returncode == 0}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[4, 16, 64])
    p.add_argument("--tree", action="append", type=Path)
    a = p.parse_args()
    trees = a.tree or [Path(__file__).resolve().parent.parent]
    print("| tree | agents | run -> tick 0 (s) | whole run (s) | processes | total peak RSS (MB) | exit 0 |")
    print("|---|---|---|---|---|---|---|")
    for n in a.sizes:
        for t in trees:  # alternating at each size
            r = measure(t, n)
            tick0 = f"{r['tick0_s']:.1f}" if r["tick0_s"] is not None else "-"
            print(f"| {t} | {n} | {tick0} | {r['total_s']:.1f} | {r['processes']} | {r['total_rss_mb']:.0f} | "
                  f"{'yes' if r['ok'] else 'NO'} |", flush=True)


if __name__ == "__main__":
    main()
