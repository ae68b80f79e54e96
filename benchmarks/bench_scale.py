"""Scale of the estimator itself (issue 16, target 4): ticks/s of UKF-DCL against swarm size, in
lockstep over Zenoh, for several chain bounds, with its accuracy and consistency next to dead
reckoning (il) and the centralized filter (ukf-ccl) from the same run.

Usage: python benchmarks/bench_scale.py [--sizes 4 8 16 32 64] [--bounds none 3 6]
       [--timeout 600] [--budget 2000] [--plot docs/img/ukf_dcl_scale.png] [--json PATH]
       python benchmarks/bench_scale.py --report PATH.json   (report and plot again from a saved run)

Each configuration is one real multi-process run (`python -m agents run SCENARIO --out DIR
--port P --no-plots --swarm UNIQUE`, from this checkout) of a random scenario: N planar platforms
uniform in a square of side 40*sqrt(N) m (constant density), random walks at 1 m/s, ranges within
80 m with probability 0.5 per platform and step (about 0.5 ranges per platform per tick, whatever
N), a 120 m unit-disk radio, and `estimator: {name: ukf-dcl, params: {max_chain: B}}`. Bound
`none` is unbounded: every chain visits the whole connected swarm, one chain at a time (exact,
equal to UKF-CCL). Large swarms run fewer ticks, and every run has a wall-clock limit: a run that
hits it is stopped (SIGTERM to the launcher, which stops its swarm) and reported as not finished,
with the ticks it reached. Progress goes to stderr, the markdown report to stdout. Not a test.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import yaml

from machine import code_version, cpu_model  # benchmarks/machine.py

ROOT = Path(__file__).resolve().parent.parent
SEED = 1
# Ticks run (duration / dt) per swarm size: fewer for large swarms, never under 20.
DURATION_S = {4: 40.0, 8: 40.0, 16: 30.0, 32: 20.0, 64: 12.0}
DT = 0.5


def duration_for(n: int) -> float:
    if n in DURATION_S:
        return DURATION_S[n]
    return 40.0 if n <= 8 else 30.0 if n <= 16 else 20.0 if n <= 32 else 12.0


def scenario(n: int, bound: int | None, duration: float, seed: int = SEED) -> dict:
    """The shape of tests/test_ukf_dcl_bounded.py and swarmloc/scenarios/swarm32.yaml."""
    rng = np.random.default_rng(seed)
    side = 40.0 * math.sqrt(n)
    pts, heads = rng.uniform(0, side, (n, 2)), rng.uniform(0, 2 * np.pi, n)
    agents = [{"id": i + 1, "start": [round(float(x), 2), round(float(y), 2)], "heading": round(float(h), 3),
               "motion": {"kind": "random", "speed": 1.0, "turn_rate_std": 0.08}}
              for i, ((x, y), h) in enumerate(zip(pts, heads))]
    return {"version": 1, "name": f"scale{n}-{'unbounded' if bound is None else f'b{bound}'}", "seed": seed,
            "clock": {"mode": "lockstep", "dt": DT, "duration": duration}, "world": {"agents": agents},
            "sensors": {"odometry": {"turn_rate_noise": 0.0},
                        "range": {"noise": 1.0, "probability": 0.5, "max_per_step": n, "max_range": 80.0}},
            "radio": {"model": "unit-disk", "range_m": 120.0},
            "estimator": {"name": "ukf-dcl", "params": {"max_chain": bound}}, "references": ["il", "ukf-ccl"]}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def log(msg: str) -> None:
    print(f"[{datetime.now():%H:%M:%S}] {msg}", file=sys.stderr, flush=True)


class ClockWatch:
    """Counts netsim's clock frames (one per tick) over Zenoh, so a run stopped at its limit
    still says how far it got."""

    def __init__(self, port: int, swarm: str):
        self.port, self.swarm = port, swarm
        self.ticks, self.first, self.last = 0, None, None
        self.session = self.sub = None
        self._lock = threading.Lock()

    def _on(self, sample) -> None:
        now = time.perf_counter()
        with self._lock:
            self.ticks += 1
            self.first = self.first if self.first is not None else now
            self.last = now

    def try_connect(self) -> bool:
        if self.session is not None:
            return True
        try:
            import zenoh
            conf = zenoh.Config()
            conf.insert_json5("mode", '"client"')
            conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{self.port}"]')
            self.session = zenoh.open(conf)
            self.sub = self.session.declare_subscriber(f"swarmloc/{self.swarm}/clock", self._on)
            return True
        except Exception:  # the router is not up yet (zenoh.ZError), or zenoh is missing
            self.session = None
            return False

    def close(self) -> None:
        try:
            if self.sub is not None:
                self.sub.undeclare()
            if self.session is not None:
                self.session.close()
        except Exception:
            pass


def leftovers(swarm: str) -> list[int]:
    """Pids of processes of this run's swarm still alive (their command line names it)."""
    pids = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            args = (d / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"--swarm" in args and swarm.encode() in args:
            pids.append(int(d.name))
    return pids


def stop(launcher: subprocess.Popen, swarm: str) -> None:
    """SIGTERM the launcher (it stops netsim and every agent), then make sure nothing is left."""
    if launcher.poll() is None:
        launcher.send_signal(signal.SIGTERM)
        try:
            launcher.wait(30)
        except subprocess.TimeoutExpired:
            launcher.kill()  # its children get SIGTERM from their parent-death signal
            launcher.wait()
    deadline = time.monotonic() + 10
    while leftovers(swarm) and time.monotonic() < deadline:
        time.sleep(0.5)
    for pid in leftovers(swarm):
        log(f"  killing leftover process {pid} of swarm {swarm}")
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def summarize(metrics: dict) -> dict:
    est = metrics["estimators"]
    used = sum(s.get("measurements_used", 0) for s in metrics.get("agent_stats", {}).values())
    dropped = sum(s.get("measurements_dropped", 0) for s in metrics.get("agent_stats", {}).values())
    out = {"ticks": metrics["ticks"], "wall_s": metrics["wall_time_s"], "ticks_per_s": metrics["ticks_per_s"],
           "measurements_used": used, "measurements_dropped": dropped,
           "fraction_used": used / (used + dropped) if used + dropped else None,
           "unresponsive_agents": metrics.get("unresponsive_agents"), "tick_timeouts": metrics.get("tick_timeouts"),
           "crashes": metrics.get("crashes"), "radio": {k: metrics["radio"].get(k) for k in ("delivered", "dropped")}}
    for alg in ("ukf-dcl", "il", "ukf-ccl"):
        e = est.get(alg)
        if e is None:
            continue
        out[alg] = {"mean_error_m": e["mean_error_m"],
                    "nees": {k: e["nees"][k] for k in ("mean", "bounds", "inside", "n")} if e.get("nees") else None,
                    "ticks_missing": sum(a.get("ticks_missing", 0) for a in e.get("agents", {}).values())}
    return out


def measure(n: int, bound: int | None, duration: float, timeout: float, tmp: Path) -> dict:
    tag = "unbounded" if bound is None else f"b{bound}"
    swarm, port = f"scale{os.getpid()}n{n}{tag}", free_port()
    run_dir = tmp / f"n{n}-{tag}"
    path = tmp / f"n{n}-{tag}.yaml"
    path.write_text(yaml.safe_dump(scenario(n, bound, duration), sort_keys=False))
    result = {"n": n, "bound": bound, "duration_s": duration, "ticks_planned": int(round(duration / DT)) + 1,
              "timeout_s": timeout, "finished": False}
    watch = ClockWatch(port, swarm)
    launcher_log = (tmp / f"n{n}-{tag}.launcher.log").open("w")
    started = time.perf_counter()
    launcher = subprocess.Popen([sys.executable, "-m", "agents", "run", str(path), "--out", str(run_dir), "--port", str(port),
                                 "--no-plots", "--swarm", swarm], cwd=ROOT, stdout=launcher_log, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL)
    try:
        deadline = started + timeout
        next_report = started + 60
        while launcher.poll() is None and time.perf_counter() < deadline:
            watch.try_connect()
            time.sleep(0.2)
            if time.perf_counter() > next_report:
                log(f"  ... {time.perf_counter() - started:.0f} s, {watch.ticks}/{result['ticks_planned']} ticks")
                next_report += 60
        if launcher.poll() is None:
            result["error"] = f"did not finish in {timeout:.0f} s"
            stop(launcher, swarm)
    except BaseException:
        stop(launcher, swarm)
        raise
    finally:
        launcher_log.close()
        watch.close()
    result["total_s"] = time.perf_counter() - started
    result["ticks_seen"] = watch.ticks
    if watch.ticks >= 2:  # frames 1..k after the first: a rate over the ticks it did run
        result["ticks_per_s_seen"] = (watch.ticks - 1) / (watch.last - watch.first) if watch.last > watch.first else None
    if "error" not in result:
        if launcher.returncode != 0 or not (run_dir / "metrics.json").is_file():
            tail = (tmp / f"n{n}-{tag}.launcher.log").read_text(errors="replace").splitlines()[-8:]
            result["error"] = f"launcher exit code {launcher.returncode}: " + " / ".join(line.strip() for line in tail)
        else:
            result.update(summarize(json.loads((run_dir / "metrics.json").read_text())))
            result["finished"] = True
    if leftovers(swarm):
        stop(launcher, swarm)
    return result


# ------------------------------------------------------------------------------------ report


def fmt(x, spec=".2f", none="-"):
    return none if x is None else format(x, spec)


def bound_label(b) -> str:
    return "none (unbounded)" if b is None else str(b)


def markdown(results: list[dict], command: str, load0, load1, started: str, total_s: float, code: str) -> str:
    lines = ["## UKF-DCL: ticks/s, accuracy and NEES against swarm size, per chain bound", "",
             f"Machine: {cpu_model()}, {os.cpu_count()} CPUs, Python {sys.version.split()[0]}; code {code}; "
             f"{started}.  ",
             f"Command: `{command}`  ",
             f"Load average (1/5/15 min) at start {load0[0]:.2f}/{load0[1]:.2f}/{load0[2]:.2f}, at end "
             f"{load1[0]:.2f}/{load1[1]:.2f}/{load1[2]:.2f} (shared machine); whole benchmark {total_s / 60:.1f} min.", "",
             "Lockstep over Zenoh, one process per platform plus netsim. Scenario: N planar platforms uniform in a "
             "square of side 40*sqrt(N) m, random walks at 1 m/s, perfect gyro, ranges (1 m noise) within 80 m with "
             f"probability 0.5 per platform and step, 120 m unit-disk radio, dt {DT} s, seed {SEED}. `bound` is "
             "`estimator.params.max_chain`; none is unbounded (exact, equals UKF-CCL). IL and UKF-CCL are the "
             "references computed by netsim from the same run's sensor data. Wall s is netsim's tick loop "
             "(`wall_time_s`), ticks/s = ticks / wall s. NEES is the average over platforms and ticks "
             "(2 dof) with its 95% bounds. Ranges used = sum of measurements_used / (used + dropped) over agents. "
             "Larger swarms run fewer ticks, so errors compare across bounds at one N, not across N (dead "
             "reckoning drifts with time: IL's error falls with N only because the runs get shorter).", "",
             "| N | bound | ticks | wall s | ticks/s | UKF-DCL error m | IL error m | UKF-CCL error m | UKF-DCL NEES mean [95% bounds] | ranges used |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    notes = []
    for r in results:
        b = bound_label(r["bound"])
        if not r["finished"]:
            rate = r.get("ticks_per_s_seen")
            lines.append(f"| {r['n']} | {b} | stopped in tick {max(r.get('ticks_seen', 0) - 1, 0)} of 0..{r['ticks_planned'] - 1} | "
                         f"> {r.get('timeout_s', 0):.0f} | "
                         f"{'~' + fmt(rate, '.3g') if rate else '-'} | - | - | - | - | - |")
            notes.append(f"N={r['n']}, bound {b}: {r.get('error')}"
                         + (f" (netsim had started tick {r['ticks_seen'] - 1} of 0..{r['ticks_planned'] - 1}; ~{rate:.3g} "
                            f"ticks/s from the clock frames of the ticks it ran; no metrics, so no accuracy or NEES)"
                            if rate else f" (clock frames seen: {r.get('ticks_seen', 0)})"))
            continue
        d = r.get("ukf-dcl", {})
        nees = d.get("nees") or {}
        nees_s = (f"{nees['mean']:.2f} [{nees['bounds'][0]:.2f}, {nees['bounds'][1]:.2f}]"
                  + ("" if nees.get("inside") else " outside") if nees else "-")
        lines.append(f"| {r['n']} | {b} | {r['ticks']} | {r['wall_s']:.1f} | {fmt(r['ticks_per_s'], '.3g')} | "
                     f"{fmt(d.get('mean_error_m'), '.3f')} | {fmt(r.get('il', {}).get('mean_error_m'), '.3f')} | "
                     f"{fmt(r.get('ukf-ccl', {}).get('mean_error_m'), '.3f')} | {nees_s} | "
                     f"{fmt(None if r['fraction_used'] is None else 100 * r['fraction_used'], '.1f')}% |")
        issues = []
        if r.get("unresponsive_agents"):
            issues.append(f"unresponsive agents {r['unresponsive_agents']}")
        if r.get("tick_timeouts"):
            issues.append(f"tick timeouts {r['tick_timeouts']}")
        if r.get("crashes"):
            issues.append(f"crashes {r['crashes']}")
        if d.get("ticks_missing"):
            issues.append(f"{d['ticks_missing']} agent-ticks missing from UKF-DCL's estimates")
        if issues:
            notes.append(f"N={r['n']}, bound {b}: " + "; ".join(str(i) for i in issues))
    ref_nees = [(r["n"], alg, r[alg]["nees"]) for r in results if r["finished"] for alg in ("ukf-ccl",)
                if r.get(alg, {}).get("nees")]
    seen = set()
    ccl = []
    for n, alg, ne in ref_nees:
        if n not in seen:
            seen.add(n)
            ccl.append(f"N={n}: {ne['mean']:.2f}{'' if ne['inside'] else ' (outside)'}")
    if ccl:
        lines += ["", "UKF-CCL NEES mean, same runs: " + ", ".join(ccl) + "."]
    if notes:
        lines += ["", "Notes:", *[f"- {x}" for x in notes]]
    return "\n".join(lines) + "\n"


def plot(results: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.3))
    bounds = list(dict.fromkeys(r["bound"] for r in results))
    colors = dict(zip(bounds, ["C3", "C0", "C2", "C4", "C5", "C6"]))
    for b in bounds:
        rs = [r for r in results if r["bound"] == b]
        ok = [r for r in rs if r["finished"]]
        label = f"max_chain {bound_label(b)}"
        ax1.plot([r["n"] for r in ok], [r["ticks_per_s"] for r in ok], "o-", color=colors[b], label=label)
        dnf = [r for r in rs if not r["finished"] and r.get("ticks_per_s_seen")]
        if dnf:
            ax1.plot([r["n"] for r in dnf], [r["ticks_per_s_seen"] for r in dnf], "v", color=colors[b], mfc="none",
                     ms=9, label=f"{label}: did not finish (rate of ticks reached)")
        ax2.plot([r["n"] for r in ok], [r["ukf-dcl"]["mean_error_m"] for r in ok], "o-", color=colors[b],
                 label=f"UKF-DCL, {label}")
    for alg, style in (("il", "k--"), ("ukf-ccl", "k:")):
        by_n = {}
        for r in results:
            if r["finished"] and r.get(alg):
                by_n.setdefault(r["n"], r[alg]["mean_error_m"])
        ns = sorted(by_n)
        ax2.plot(ns, [by_n[n] for n in ns], style, marker="s", ms=4, label={"il": "IL (dead reckoning)",
                                                                            "ukf-ccl": "UKF-CCL (centralized)"}[alg])
    sizes = sorted({r["n"] for r in results})
    for ax in (ax1, ax2):
        ax.set_xscale("log", base=2)
        ax.set_xticks(sizes, [str(n) for n in sizes])
        ax.set_xlabel("platforms N")
        ax.grid(True, which="both", alpha=0.3)
    ax1.set_yscale("log")
    ax1.set_ylabel("ticks/s (lockstep over Zenoh)")
    ax1.set_title("Throughput")
    ax2.set_ylabel("mean position error (m)")
    ax2.set_title("Accuracy")
    ax1.legend(fontsize=7)
    ax2.legend(fontsize=7)
    fig.suptitle("UKF-DCL scale, per chain bound (max_chain)", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def parse_bound(s: str) -> int | None:
    return None if s.lower() in ("none", "null", "unbounded") else int(s)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[4, 8, 16, 32, 64])
    p.add_argument("--bounds", type=parse_bound, nargs="+", default=[3, 6, None],
                   help="max_chain values; none = unbounded (default: 3 6 none)")
    p.add_argument("--duration", type=float, help="simulated seconds for every size (default: 40 s for N <= 8, "
                                                  "30 s for 16, 20 s for 32, 12 s for 64)")
    p.add_argument("--timeout", type=float, default=600.0, help="wall-clock limit of one run, s")
    p.add_argument("--budget", type=float, default=2000.0,
                   help="wall-clock budget of the whole benchmark, s: a run's limit is cut to what is left")
    p.add_argument("--plot", type=Path, default=ROOT / "docs" / "img" / "ukf_dcl_scale.png")
    p.add_argument("--json", type=Path)
    p.add_argument("--report", type=Path, metavar="JSON",
                   help="run nothing: print the report and draw the plot from a --json file of an earlier run")
    p.add_argument("--code", help="what code is measured, when this checkout has no git metadata (e.g. a git archive)")
    a = p.parse_args()
    if a.report:
        saved = json.loads(a.report.read_text())
        print(markdown(saved["results"], saved["command"], saved["load_start"], saved["load_end"], saved["date"],
                       saved["total_s"], saved["code"]), flush=True)
        if a.plot:
            plot(saved["results"], a.plot)
        return
    command = "python " + " ".join(shlex.quote(x) for x in sys.argv)
    load0, t0 = os.getloadavg(), time.perf_counter()
    started = f"{datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC"
    results = []
    with tempfile.TemporaryDirectory(prefix="bench_scale") as tmp:
        for n in a.sizes:
            for b in a.bounds:  # bounded first: the unbounded run is the one that may hit its limit
                left = a.budget - (time.perf_counter() - t0)
                duration = a.duration or duration_for(n)
                if left < 30:
                    results.append({"n": n, "bound": b, "duration_s": duration, "finished": False, "ticks_seen": 0,
                                    "ticks_planned": int(round(duration / DT)) + 1, "error": "skipped: benchmark budget spent"})
                    log(f"N={n} bound={bound_label(b)}: skipped, budget spent")
                    continue
                timeout = min(a.timeout, left)
                log(f"N={n} bound={bound_label(b)}: {int(round(duration / DT)) + 1} ticks, limit {timeout:.0f} s, "
                    f"load {os.getloadavg()[0]:.1f}")
                r = measure(n, b, duration, timeout, Path(tmp))
                results.append(r)
                if r["finished"]:
                    log(f"  {r['ticks']} ticks in {r['wall_s']:.1f} s ({r['ticks_per_s']:.3g} ticks/s; whole run "
                        f"{r['total_s']:.0f} s); error ukf-dcl {r['ukf-dcl']['mean_error_m']:.3f} m, "
                        f"il {r['il']['mean_error_m']:.3f}, ukf-ccl {r['ukf-ccl']['mean_error_m']:.3f}; "
                        f"NEES {r['ukf-dcl']['nees']['mean']:.2f}")
                else:
                    log(f"  {r.get('error')} (ticks seen {r.get('ticks_seen')})")
    load1, total = os.getloadavg(), time.perf_counter() - t0
    code = code_version() if code_version() != "unknown" or not a.code else a.code
    print(markdown(results, command, load0, load1, started, total, code), flush=True)
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps({"machine": cpu_model(), "cpus": os.cpu_count(), "code": code,
                                      "date": started, "command": command, "load_start": load0, "load_end": load1,
                                      "total_s": total, "results": results}, indent=1))
    if a.plot:
        plot(results, a.plot)
        log(f"plot: {a.plot}")


if __name__ == "__main__":
    main()
