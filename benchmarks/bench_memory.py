"""Resident memory of a swarm's processes: each agent's and netsim's peak RSS during a run.

Usage: python benchmarks/bench_memory.py [--scenario wang2019] [--tree PATH ...] [--per-process K ...]
Each --tree is a checkout of swarmloc (default: this one) run as `python -m agents run` from
that directory, so two versions can be measured side by side in one run; each --per-process K
runs the swarm with K agents to a process (`--agents-per-process K`), alternating too. Not a test.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def rss_kb(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def children(pid: int) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if int((d / "stat").read_text().rsplit(")", 1)[1].split()[1]) == pid:
                    out.append(int(d.name))
            except (OSError, ValueError, IndexError):
                pass
    return out


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def measure(tree: Path, scenario: str, per_process: int = 1, duration: float | None = None) -> dict:
    """Peak RSS (MB) of netsim and of each agent process (or host of agents) over one run started from `tree`."""
    with tempfile.TemporaryDirectory() as tmp:
        launcher = subprocess.Popen([sys.executable, "-m", "agents", "run", scenario, "--out", f"{tmp}/run", "--port", "0",
                                     "--no-plots", "--swarm", f"mem{os.getpid()}",
                                     *(["--agents-per-process", str(per_process)] if per_process > 1 else []),
                                     *(["--duration", str(duration)] if duration else [])], cwd=tree,
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        peak: dict[str, int] = {}
        while launcher.poll() is None:
            for pid in children(launcher.pid):
                cmd = cmdline(pid)
                name = "netsim" if " -m netsim " in cmd else (
                    f"agent {cmd.split('--id ')[1].split()[0]}" if "--id " in cmd else
                    f"agent host {cmd.split('--agent ')[1].split('=')[0]}" if " -m agents.host " in cmd else None)
                kb = rss_kb(pid)
                if name and kb:
                    peak[name] = max(peak.get(name, 0), kb)
            time.sleep(0.2)
    agents = [v / 1024 for k, v in peak.items() if k.startswith("agent")]
    return {"processes": len(agents), "agent_median_mb": statistics.median(agents) if agents else None,
            "agent_max_mb": max(agents) if agents else None, "netsim_mb": peak.get("netsim", 0) / 1024,
            "total_mb": sum(peak.values()) / 1024}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="wang2019")
    p.add_argument("--tree", action="append", type=Path, help="a swarmloc checkout (repeatable; default: this one)")
    p.add_argument("--per-process", action="append", type=int, metavar="K",
                   help="agents to a process (repeatable; default: 1)")
    p.add_argument("--duration", type=float, help="simulated seconds of each run (default: the scenario's)")
    p.add_argument("--repeat", type=int, default=2)
    a = p.parse_args()
    trees = a.tree or [Path(__file__).resolve().parent.parent]
    cases = [(t, k) for t in trees for k in (a.per_process or [1])]
    print("| tree | agents to a process | processes | process peak RSS, median (max) MB | netsim peak RSS MB | "
          "total MB |")
    print("|---|---|---|---|---|---|")
    results = {c: [] for c in cases}
    for _ in range(a.repeat):
        for c in cases:  # alternating: the cases meet the same machine state
            results[c].append(measure(c[0], a.scenario, c[1], a.duration))
    for (t, k), runs in results.items():
        med = lambda key: statistics.median(r[key] for r in runs)  # noqa: E731
        print(f"| {t} | {k} | {runs[0]['processes']} | {med('agent_median_mb'):.1f} ({med('agent_max_mb'):.1f}) | "
              f"{med('netsim_mb'):.1f} | {med('total_mb'):.1f} |")

if __name__ == "__main__":
    main()
