"""`swarm256` in real time (issue 29, item 2): does a swarm of 256 agents keep up on this machine?

Usage: python benchmarks/bench_swarm256.py [--per-process 32 ...] [--repeat 1] [--duration 60]
       [--scenario swarm256] [--references il] [--json PATH]

Each run is `python -m agents run SCENARIO --out DIR --port P --no-plots --swarm UNIQUE
--agents-per-process K` from this checkout (the runs alternate over the K given), measured from
outside:
- start to tick 0: wall time from starting the command to netsim's first clock frame (a Zenoh
  subscriber of this script counts every clock frame and stamps its arrival);
- tick lateness: each clock frame's arrival against tick 0's + k dt (netsim keeping its own pace);
- memory: the whole process tree's resident memory (launcher, netsim, every agent process),
  summed over the processes alive at each sample (every 0.25 s), its peak;
- CPU: user + system seconds of the whole tree (this process's reaped children);
and from the run's metrics.json: per agent, ticks handled, ticks skipped, last tick, sensor lag
(median and max: ms from a sensor frame's arrival in the agent's Zenoh callback to its node
stepping on it), agents marked unresponsive, tick timeouts, agent events; the estimator's error
and the references'. The keep-up properties are issue 29's: every agent handles every tick,
none unresponsive, sensor lag under dt, at most 6 GB, tick 0 within 20 s.
Progress to stderr, the markdown report to stdout. Not a test (tests/test_scale.py is).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from bench_memory import cmdline, rss_kb  # benchmarks/bench_memory.py
from bench_scale import ClockWatch, free_port, leftovers, log, stop  # benchmarks/bench_scale.py
from machine import code_version, cpu_model  # benchmarks/machine.py

from swarmloc.experiment import scenario as S
from swarmloc.process import process_tree

ROOT = Path(__file__).resolve().parent.parent
MEMORY_MB, START_S = 6 * 1024, 20.0  # issue 29's limits


class Clock(ClockWatch):
    """bench_scale's watch of netsim's clock frames, keeping every arrival time (tick 0, 1, ...,
    and the final stop frame): how late each tick came."""

    def __init__(self, port: int, swarm: str):
        super().__init__(port, swarm)
        self.arrivals: list[float] = []

    def _on(self, sample) -> None:
        super()._on(sample)
        self.arrivals.append(time.perf_counter())


def cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of a live process."""
    try:
        f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def role(pid: int, launcher: int) -> str | None:
    """What a process of the run is; None while it cannot tell yet (a child between its fork and
    its exec still shows the launcher's command line: once counted as the launcher, a host's
    whole CPU went to the launcher's column)."""
    if pid == launcher:
        return "launcher"
    cmd = cmdline(pid)
    return "netsim" if " -m netsim " in cmd else "agents" if (" -m agents.host " in cmd or " -m agents.daemon " in cmd) \
        else None if " -m agents run " in cmd else "other"


def pct(xs, q):
    return float(np.percentile(np.asarray(xs, dtype=float), q)) if len(xs) else None


def measure(scenario: Path, steps: int, dt: float, k: int, tmp: Path, timeout: float) -> dict:
    swarm, port = f"s256p{os.getpid()}k{k}t{int(time.time()) % 100000}", free_port()
    run_dir = tmp / f"{swarm}"
    logf = (tmp / f"{swarm}.launcher.log").open("w")
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    clock = Clock(port, swarm)
    started = time.perf_counter()
    launcher = subprocess.Popen([sys.executable, "-m", "agents", "run", str(scenario), "--out", str(run_dir),
                                 "--port", str(port), "--no-plots", "--swarm", swarm, "--agents-per-process", str(k)],
                                cwd=ROOT, stdout=logf, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    peak_mb, peak_procs, samples = 0.0, 0, []
    cpu: dict[int, tuple[str, float]] = {}  # pid -> (role, CPU s at its last sample)
    out = {"agents_per_process": k, "swarm": swarm}
    try:
        while launcher.poll() is None and time.perf_counter() - started < timeout:
            clock.try_connect()
            pids = process_tree(launcher.pid)
            mb = sum(rss_kb(p) or 0 for p in pids) / 1024
            samples.append(mb)
            for p_ in pids:
                c = cpu_s(p_)
                if c is not None:
                    cpu[p_] = (cpu[p_][0] if p_ in cpu and cpu[p_][0] is not None else role(p_, launcher.pid), c)
            if mb > peak_mb:
                peak_mb, peak_procs = mb, len(pids)
            time.sleep(0.25)
        if launcher.poll() is None:
            out["error"] = f"did not finish in {timeout:.0f} s"
            stop(launcher, swarm)
    except BaseException:
        stop(launcher, swarm)
        raise
    finally:
        logf.close()
        clock.close()
    ended = time.perf_counter()
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    arr = clock.arrivals
    out.update({"total_s": ended - started, "cpu_s": (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime),
                "peak_rss_mb": peak_mb, "processes": peak_procs, "clock_frames": len(arr),
                "cpu_s_by_role": {r_ or "unknown": round(sum(c for rr, c in cpu.values() if rr == r_), 1)
                                  for r_ in sorted({rr for rr, _ in cpu.values()}, key=str)}})
    if arr:
        out["start_to_tick0_s"] = arr[0] - started
        ticks = np.array(arr[:steps + 1])
        late = (ticks - ticks[0] - dt * np.arange(len(ticks))) * 1e3
        out["tick_late_ms"] = {"median": pct(late, 50), "p99": pct(late, 99), "max": float(late.max())}
        out["tick0_to_end_s"] = ended - arr[0]
    if "error" in out:
        return out
    if launcher.returncode != 0 or not (run_dir / "metrics.json").is_file():
        tail = (tmp / f"{swarm}.launcher.log").read_text(errors="replace").splitlines()[-8:]
        out["error"] = f"launcher exit code {launcher.returncode}: " + " / ".join(s.strip() for s in tail)
        return out
    m = json.loads((run_dir / "metrics.json").read_text())
    stats = m["agent_stats"]
    med = [s["sensor_lag_ms_median"] for s in stats.values() if s["sensor_lag_ms_median"] is not None]
    mx = [s["sensor_lag_ms_max"] for s in stats.values() if s["sensor_lag_ms_max"] is not None]
    est = m["estimators"]
    out.update({
        "wall_time_s": m["wall_time_s"], "ticks": m["ticks"],
        "agents_reporting": len(stats),
        "agents_every_tick": sum(s["ticks"] == steps + 1 and s["ticks_skipped"] == 0 and s["k"] == steps
                                 for s in stats.values()),
        "ticks_handled_min": min((s["ticks"] for s in stats.values()), default=None),
        "ticks_skipped": sum(s["ticks_skipped"] for s in stats.values()),
        "unresponsive_agents": m["unresponsive_agents"], "tick_timeouts": m.get("tick_timeouts"),
        "agent_events": len(m["agent_events"]),
        "sensor_lag_ms": {"median_of_medians": pct(med, 50), "max_p50": pct(mx, 50), "max_p90": pct(mx, 90),
                          "max_p99": pct(mx, 99), "max": max(mx) if mx else None,
                          "agents_over_dt": sum(x >= 1e3 * dt for x in mx)},
        "measurements_used": sum(s.get("measurements_used", 0) for s in stats.values()),
        "measurements_dropped": sum(s.get("measurements_dropped", 0) for s in stats.values()),
        "deliveries_lost": sum(s.get("deliveries_lost", 0) for s in stats.values()),
        "radio": {k_: m["radio"].get(k_) for k_ in ("delivered", "dropped")},
        "error_m": {a: e["mean_error_m"] for a, e in est.items()},
        "nees": {a: (e["nees"] or {}).get("mean") for a, e in est.items() if e.get("nees")},
    })
    if leftovers(swarm):
        stop(launcher, swarm)
    return out


def keeps_up(r: dict, n: int) -> bool:
    return ("error" not in r and r["agents_every_tick"] == n and not r["unresponsive_agents"]
            and r["sensor_lag_ms"]["agents_over_dt"] == 0 and r["peak_rss_mb"] <= MEMORY_MB
            and r["start_to_tick0_s"] < START_S)


def fmt(x, spec=".1f"):
    return "-" if x is None else format(x, spec)


def markdown(results: list[dict], n: int, steps: int, dt: float, command: str, load0, load1, when: str) -> str:
    lines = [f"# bench_swarm256 ({when}, {cpu_model()}, {os.cpu_count()} cores, Python {sys.version.split()[0]}, "
             f"code {code_version()})", "", f"Command: `{command}`", "",
             f"Load average (1, 5, 15 min) before: {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}; after: "
             f"{load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}", "",
             f"{n} agents, {steps + 1} ticks of {dt:g} s.", "",
             "| K | run | start to tick 0 s | agents every tick | unresponsive | sensor lag ms: median of medians / "
             "p50, p99, max of maxima | tick late ms median / max | peak RSS MB (processes) | CPU s (netsim / agents) | keeps up |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for i, r in enumerate(results):
        if "error" in r and "agents_every_tick" not in r:
            lines.append(f"| {r['agents_per_process']} | {i + 1} | {fmt(r.get('start_to_tick0_s'))} | - | - | - | - | "
                         f"{r['peak_rss_mb']:.0f} ({r['processes']}) | {r['cpu_s']:.0f} | no: {r['error']} |")
            continue
        lag, late, by = r["sensor_lag_ms"], r.get("tick_late_ms", {}), r.get("cpu_s_by_role", {})
        lines.append(f"| {r['agents_per_process']} | {i + 1} | {fmt(r.get('start_to_tick0_s'))} | "
                     f"{r['agents_every_tick']}/{n} | {len(r['unresponsive_agents'])} | "
                     f"{fmt(lag['median_of_medians'], '.2f')} / {fmt(lag['max_p50'])}, {fmt(lag['max_p99'])}, "
                     f"{fmt(lag['max'])} | {fmt(late.get('median'))} / {fmt(late.get('max'))} | "
                     f"{r['peak_rss_mb']:.0f} ({r['processes']}) | {r['cpu_s']:.0f} ({by.get('netsim', 0):.0f} / "
                     f"{by.get('agents', 0):.0f}) | {'yes' if keeps_up(r, n) else 'no'} |")
    lines.append("")
    for i, r in enumerate(results):
        if "error_m" in r:
            errs = ", ".join(f"{a} {e:.3f} m" for a, e in r["error_m"].items())
            nees = ", ".join(f"{a} {v:.2f}" for a, v in r["nees"].items())
            used = r["measurements_used"] / max(1, r["measurements_used"] + r["measurements_dropped"])
            lines.append(f"- run {i + 1} (K {r['agents_per_process']}): error {errs}; NEES {nees}; ranges used "
                         f"{100 * used:.1f} %; deliveries lost {r['deliveries_lost']}; radio {r['radio']}; "
                         f"wall {r['wall_time_s']:.1f} s for {r['ticks']} ticks; whole command {r['total_s']:.1f} s")
    return "\n".join(lines) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="swarm256")
    p.add_argument("--per-process", action="append", type=int, metavar="K", help="agents to a process (repeatable; "
                   "default 32)")
    p.add_argument("--repeat", type=int, default=1)
    p.add_argument("--duration", type=float, help="simulated seconds (default: the scenario's)")
    p.add_argument("--references", help="comma-separated references instead of the scenario's ('' for none)")
    p.add_argument("--lockstep", action="store_true", help="lockstep instead of real time: the CPU a tick costs "
                   "when nobody falls behind (what optimizations are compared on)")
    p.add_argument("--timeout", type=float, default=900.0)
    p.add_argument("--json", type=Path)
    a = p.parse_args()
    sc = S.load(a.scenario)
    over = {}
    if a.duration:
        over["clock.duration"] = a.duration
    if a.lockstep:
        over["clock.mode"] = "lockstep"
    if a.references is not None:
        over["references"] = [r for r in a.references.split(",") if r]
    sc = sc.with_overrides(**over) if over else sc
    ks = a.per_process or [32]
    command = "python benchmarks/bench_swarm256.py " + shlex.join(sys.argv[1:])
    load0, when = os.getloadavg(), datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    results = []
    with tempfile.TemporaryDirectory(prefix="swarm256-") as tmp:
        path = Path(tmp) / f"{sc.name}.yaml"
        path.write_text(sc.to_yaml())
        for rep in range(a.repeat):
            for k in ks:  # alternating: the values of K meet the same machine state
                log(f"{sc.name}, K {k}, run {rep + 1}/{a.repeat} (load {os.getloadavg()[0]:.2f})")
                r = measure(path, sc.clock.steps, sc.clock.dt, k, Path(tmp), a.timeout)
                r["load_before"] = os.getloadavg()
                results.append(r)
                log(f"  -> {json.dumps({x: r.get(x) for x in ('start_to_tick0_s', 'agents_every_tick', 'unresponsive_agents', 'sensor_lag_ms', 'peak_rss_mb', 'cpu_s', 'cpu_s_by_role', 'tick_late_ms', 'error')})}")
                if a.json:
                    a.json.write_text(json.dumps({"command": command, "when": when, "results": results}, indent=1))
    report = markdown(results, len(sc.agent_ids), sc.clock.steps, sc.clock.dt, command, load0, os.getloadavg(), when)
    if a.json:
        a.json.write_text(json.dumps({"command": command, "when": when, "load_before": load0,
                                      "load_after": os.getloadavg(), "results": results}, indent=1))
    print(report)


if __name__ == "__main__":
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    main()
