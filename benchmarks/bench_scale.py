"""Scale of the estimators themselves (issue 16, target 4; issue 29, items 4-5): cost per tick
of the decentralized estimators against swarm size, in lockstep, with their accuracy, NEES and
ranges used next to dead reckoning (il) and the centralized filter (ukf-ccl) from the same run.

Usage: python benchmarks/bench_scale.py [--sizes 4 8 16 32 64] [--estimators ukf-dcl:3 ukf-dcl:6 ukf-dcl rdl]
       [--in-process-from N] [--seed 1] [--timeout 600] [--budget 2000] [--plot docs/img/ukf_dcl_scale.png] [--json PATH]
       python benchmarks/bench_scale.py --report PATH.json   (report and plot again from a saved run)

`--estimators`: `ukf-dcl:B` is UKF-DCL with `max_chain: B`, plain `ukf-dcl` is unbounded, any
other name is that estimator with its default settings (e.g. `rdl`); `ekf-ci` runs on the
scenario's pose twin (`pose_twin`: range and bearing instead of ranges), with its own IL and
UKF-CCL.
`--in-process-from N`: swarms of N platforms and more run the same scenario, nodes, radio model
and wire codec by swarmloc.experiment.runner.InProcessRunner in this process instead of one
process per platform over Zenoh (the sizes whose processes would not fit in memory).

Each configuration is one real multi-process run (`python -m agents run SCENARIO --out DIR
--port P --no-plots --swarm UNIQUE`, from this checkout) of a random scenario: N planar platforms
uniform in a square of side 40*sqrt(N) m (constant density), random walks at 1 m/s, ranges within
80 m with probability 0.5 per platform and step (about 0.5 ranges per platform per tick, whatever
N), a 120 m unit-disk radio, and the estimator (for UKF-DCL `params: {max_chain: B}`). Bound
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


def parse_config(s: str) -> tuple[str, int | None]:
    """`ukf-dcl:3` -> ("ukf-dcl", 3); `ukf-dcl` -> ("ukf-dcl", None) (unbounded); `rdl` -> ("rdl", None)."""
    name, _, bound = s.partition(":")
    return name, (None if bound.lower() in ("", "none", "null", "unbounded") else int(bound))


def config_label(name: str, bound: int | None) -> str:
    if name in POSE_TWIN:
        return f"{name} (pose twin)"
    if name != "ukf-dcl":
        return name
    return "ukf-dcl unbounded" if bound is None else f"ukf-dcl max_chain {bound}"


def config_tag(name: str, bound: int | None) -> str:
    if name != "ukf-dcl":
        return name
    return "unbounded" if bound is None else f"b{bound}"


def scenario(n: int, name: str, bound: int | None, duration: float, seed: int = SEED) -> dict:
    """The shape of tests/test_ukf_dcl_bounded.py and swarmloc/experiment/scenarios/swarm32.yaml.

    EKF-CI runs on its pose twin (`pose_twin`): it fuses relative measurements that give a
    neighbour's position (Goel et al. 2016, section 4), which a range alone does not."""
    rng = np.random.default_rng(seed)
    side = 40.0 * math.sqrt(n)
    pts, heads = rng.uniform(0, side, (n, 2)), rng.uniform(0, 2 * np.pi, n)
    agents = [{"id": i + 1, "start": [round(float(x), 2), round(float(y), 2)], "heading": round(float(h), 3),
               "motion": {"kind": "random", "speed": 1.0, "turn_rate_std": 0.08}}
              for i, ((x, y), h) in enumerate(zip(pts, heads))]
    estimator = {"name": "ukf-dcl", "params": {"max_chain": bound}} if name == "ukf-dcl" else {"name": name}
    sc = {"version": 1, "name": f"scale{n}-{config_tag(name, bound)}", "seed": seed,
          "clock": {"mode": "lockstep", "dt": DT, "duration": duration}, "world": {"agents": agents},
          "sensors": {"odometry": {"turn_rate_noise": 0.0},
                      "range": {"noise": 1.0, "probability": 0.5, "max_per_step": n, "max_range": 80.0}},
          "radio": {"model": "unit-disk", "range_m": 120.0},
          "estimator": estimator, "references": ["il", "ukf-ccl"]}
    return pose_twin(sc) if name in POSE_TWIN else sc


# Estimators that run on the pose twin of the scenario, not on the scenario itself.
POSE_TWIN = ("ekf-ci",)
# The twin's sensing reach: a platform sees about as many others per tick as it takes ranges in
# the scenario (0.5: pi r^2 / 1600 m^2, the density), each pair from both ends.
TWIN_REACH_M = 16.0


def pose_twin(sc: dict) -> dict:
    """The same platforms, starts, walks, odometry and radio as planar-pose robots that measure
    range and body-frame bearing (1 m, 0.05 rad) to every other within TWIN_REACH_M, every tick,
    instead of random ranges; no landmarks. IL and UKF-CCL (joint pose UKF) are computed on it."""
    agents = [{**a, "model": "planar-pose"} for a in sc["world"]["agents"]]
    sensors = {"odometry": sc["sensors"]["odometry"],
               "range_bearing": {"enabled": True, "max_range": TWIN_REACH_M, "landmarks": False,
                                 "range_noise": sc["sensors"]["range"]["noise"], "bearing_noise": 0.05}}
    return {**sc, "world": {**sc["world"], "agents": agents}, "sensors": sensors}


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


def summarize(metrics: dict, name: str) -> dict:
    est = metrics["estimators"]
    used = sum(s.get("measurements_used", 0) for s in metrics.get("agent_stats", {}).values())
    dropped = sum(s.get("measurements_dropped", 0) for s in metrics.get("agent_stats", {}).values())
    out = {"ticks": metrics["ticks"], "wall_s": metrics["wall_time_s"], "ticks_per_s": metrics["ticks_per_s"],
           "measurements_used": used, "measurements_dropped": dropped,
           "fraction_used": used / (used + dropped) if used + dropped else None,
           "unresponsive_agents": metrics.get("unresponsive_agents"), "tick_timeouts": metrics.get("tick_timeouts"),
           "crashes": metrics.get("crashes"), "radio": {k: metrics["radio"].get(k) for k in ("delivered", "dropped")}}
    for alg in (name, "il", "ukf-ccl"):
        e = est.get(alg)
        if e is None:
            continue
        out["est" if alg == name else alg] = {"mean_error_m": e["mean_error_m"],
                    "nees": {k: e["nees"][k] for k in ("mean", "bounds", "inside", "n")} if e.get("nees") else None,
                    "ticks_missing": sum(a.get("ticks_missing", 0) for a in e.get("agents", {}).values())}
    return out


class OutOfTime(Exception):
    pass


def measure_in_process(n: int, name: str, bound: int | None, duration: float, timeout: float) -> dict:
    """One run by the in-process runner: the same nodes, radio model and wire codec, no Zenoh.
    A run that reaches its wall-clock limit stops at the end of a tick, reported as not finished."""
    from netsim.sim import Simulation
    from swarmloc.estimators import make_nodes
    from swarmloc.experiment.results import compute_bound, compute_references, metrics
    from swarmloc.experiment.runner import InProcessRunner
    from swarmloc.experiment.scenario import parse

    sc = parse(scenario(n, name, bound, duration, SEED), source="bench_scale")
    sim = Simulation(sc)
    nodes = make_nodes(name, sc)
    started = time.perf_counter()
    seen = []

    def on_tick(k, frames):
        seen.append(time.perf_counter())
        if seen[-1] - started > timeout:
            raise OutOfTime

    planned = int(round(duration / DT)) + 1
    try:
        record = InProcessRunner(sim, nodes).run(on_tick=on_tick)
    except OutOfTime:
        rate = (len(seen) - 1) / (seen[-1] - seen[0]) if len(seen) > 1 else None
        return {"n": n, "estimator": name, "bound": bound, "duration_s": duration, "in_process": True,
                "ticks_planned": planned, "finished": False, "timeout_s": timeout, "ticks_seen": len(seen),
                "ticks_per_s_seen": rate, "error": f"did not finish in {timeout:.0f} s"}
    wall = time.perf_counter() - started
    reference_s = {}  # each offline reference's own time, the whole swarm in this process
    for ref in sc.reference_names:
        t0 = time.perf_counter()
        compute_references(sc, record, [ref], bound=False)
        reference_s[ref] = time.perf_counter() - t0
    compute_bound(sc, record)
    m = metrics(record, [name, "il", "ukf-ccl"])
    m.update({"wall_time_s": wall, "ticks_per_s": m["ticks"] / wall, "radio": sim.radio_summary(),
              "agent_stats": {str(a): node.stats for a, node in nodes.items()}})
    return {"n": n, "estimator": name, "bound": bound, "duration_s": duration, "in_process": True,
            "ticks_planned": planned, "finished": True, "total_s": wall, "reference_s": reference_s,
            **summarize(m, name)}


def measure(n: int, name: str, bound: int | None, duration: float, timeout: float, tmp: Path, per_process: int = 1) -> dict:
    tag = config_tag(name, bound)
    swarm, port = f"scale{os.getpid()}n{n}{tag.replace('-', '')}", free_port()
    tmp.mkdir(parents=True, exist_ok=True)
    run_dir = tmp / f"n{n}-{tag}"
    path = tmp / f"n{n}-{tag}.yaml"
    path.write_text(yaml.safe_dump(scenario(n, name, bound, duration, SEED), sort_keys=False))
    result = {"n": n, "estimator": name, "bound": bound, "duration_s": duration, "agents_per_process": per_process,
              "ticks_planned": int(round(duration / DT)) + 1, "timeout_s": timeout, "finished": False}
    watch = ClockWatch(port, swarm)
    launcher_log = (tmp / f"n{n}-{tag}.launcher.log").open("w")
    started = time.perf_counter()
    launcher = subprocess.Popen([sys.executable, "-m", "agents", "run", str(path), "--out", str(run_dir), "--port", str(port),
                                 "--no-plots", "--swarm", swarm, "--agents-per-process", str(per_process)], cwd=ROOT, stdout=launcher_log, stderr=subprocess.STDOUT,
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
            result.update(summarize(json.loads((run_dir / "metrics.json").read_text()), name))
            result["finished"] = True
    if leftovers(swarm):
        stop(launcher, swarm)
    return result


# ------------------------------------------------------------------------------------ report


def fmt(x, spec=".2f", none="-"):
    return none if x is None else format(x, spec)


def label_of(r: dict) -> str:
    return config_label(r.get("estimator", "ukf-dcl"), r["bound"])


def est_of(r: dict) -> dict:
    """The run's own estimator's summary (saved runs of before issue 29 keyed it "ukf-dcl")."""
    return r.get("est") or r.get("ukf-dcl") or {}


def frames_per_agent_tick(r: dict) -> float | None:
    delivered = (r.get("radio") or {}).get("delivered")
    return delivered / (r["n"] * r["ticks"]) if delivered is not None and r.get("ticks") else None


def markdown(results: list[dict], command: str, load0, load1, started: str, total_s: float, code: str) -> str:
    transports = {"in process" if r.get("in_process") else "over Zenoh" for r in results if r["finished"]}
    lines = ["## Decentralized estimators: cost per tick, accuracy, NEES and ranges used against swarm size", "",
             f"Machine: {cpu_model()}, {os.cpu_count()} CPUs, Python {sys.version.split()[0]}; code {code}; "
             f"{started}.  ",
             f"Command: `{command}`  ",
             f"Load average (1/5/15 min) at start {load0[0]:.2f}/{load0[1]:.2f}/{load0[2]:.2f}, at end "
             f"{load1[0]:.2f}/{load1[1]:.2f}/{load1[2]:.2f} (shared machine); whole benchmark {total_s / 60:.1f} min.", "",
             f"Lockstep, {' and '.join(sorted(transports)) or '-'} (over Zenoh: one process per platform plus netsim; "
             "in process: the same nodes, radio model and wire codec in one process). Scenario: N planar platforms "
             "uniform in a square of side 40*sqrt(N) m, random walks at 1 m/s, perfect gyro, ranges (1 m noise) "
             f"within 80 m with probability 0.5 per platform and step, 120 m unit-disk radio, dt {DT} s, seed {SEED}. "
             "`ukf-dcl max_chain B` is UKF-DCL with `estimator.params.max_chain: B`; unbounded is exact (equals "
             "UKF-CCL). IL and UKF-CCL are the references computed from the same run's sensor data. Wall s is the "
             "tick loop (netsim's `wall_time_s` over Zenoh), s/tick = wall s / ticks. NEES is the average over "
             "platforms and ticks (2 dof) with its 95% bounds. Ranges used = sum of measurements_used / (used + "
             "dropped) over agents. Frames = radio deliveries per platform per tick. Larger swarms run fewer ticks, "
             "so errors compare across estimators at one N, not across N.", "",
             *([f"`(pose twin)`: the estimator runs on the scenario's pose twin, which it needs (EKF-CI fuses "
                "relative measurements that give a neighbour's position; a range does not): the same platforms, "
                "starts, walks, odometry and radio as planar-pose robots, each measuring range (1 m) and bearing "
                f"(0.05 rad) to every other within {TWIN_REACH_M:g} m every tick (about as many measurements per "
                "platform and tick as the ranges above) instead of the ranges. Its IL and UKF-CCL columns are "
                "computed on the twin, its NEES is of the pose (3 dof) and its ranges used are not counted.", ""]
               if any(map(twin, results)) else []),
             "| N | estimator | ticks | wall s | s/tick | error m | IL error m | UKF-CCL error m | error / UKF-CCL "
             "| NEES mean [95% bounds] | ranges used | frames |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    notes = []
    for r in results:
        b = label_of(r) + (" (in process)" if r.get("in_process") else
                           f" ({r['agents_per_process']} agents a process)" if r.get("agents_per_process", 1) > 1 else "")
        if not r["finished"]:
            rate = r.get("ticks_per_s_seen")
            lines.append(f"| {r['n']} | {b} | stopped in tick {max(r.get('ticks_seen', 0) - 1, 0)} of "
                         f"0..{r['ticks_planned'] - 1} | > {r.get('timeout_s', 0):.0f} | "
                         f"{'~' + fmt(1 / rate, '.3g') if rate else '-'} | - | - | - | - | - | - | - |")
            notes.append(f"N={r['n']}, {b}: {r.get('error')}"
                         + (f" (it had reached tick {r['ticks_seen'] - 1} of 0..{r['ticks_planned'] - 1}; ~{rate:.3g} "
                            f"ticks/s over the ticks it ran; no metrics, so no accuracy or NEES)"
                            if rate else f" (clock frames seen: {r.get('ticks_seen', 0)})"))
            continue
        d = est_of(r)
        ccl = r.get("ukf-ccl", {}).get("mean_error_m")
        nees = d.get("nees") or {}
        nees_s = (f"{nees['mean']:.2f} [{nees['bounds'][0]:.2f}, {nees['bounds'][1]:.2f}]"
                  + ("" if nees.get("inside") else " outside") if nees else "-")
        ratio = d.get("mean_error_m") / ccl if ccl and d.get("mean_error_m") is not None else None
        lines.append(f"| {r['n']} | {b} | {r['ticks']} | {r['wall_s']:.1f} | {fmt(r['wall_s'] / r['ticks'], '.3g')} | "
                     f"{fmt(d.get('mean_error_m'), '.3f')} | {fmt(r.get('il', {}).get('mean_error_m'), '.3f')} | "
                     f"{fmt(ccl, '.3f')} | {fmt(ratio, '.3f')} | {nees_s} | "
                     f"{'-' if r['fraction_used'] is None else format(100 * r['fraction_used'], '.1f') + '%'} | "
                     f"{fmt(frames_per_agent_tick(r), '.1f')} |")
        issues = []
        if r.get("unresponsive_agents"):
            issues.append(f"unresponsive agents {r['unresponsive_agents']}")
        if r.get("tick_timeouts"):
            issues.append(f"tick timeouts {r['tick_timeouts']}")
        if r.get("crashes"):
            issues.append(f"crashes {r['crashes']}")
        if r.get("attempts") or r.get("first_attempt"):
            issues.append(f"attempt {r.get('attempts', 2)}: the earlier ones did not start (netsim did not listen within the "
                          "launcher's 20 s under load)")
        if d.get("ticks_missing"):
            issues.append(f"{d['ticks_missing']} agent-ticks missing from the estimates")
        if issues:
            notes.append(f"N={r['n']}, {b}: " + "; ".join(str(i) for i in issues))
    seen, ccl = set(), []
    for r in results:
        ne = r.get("ukf-ccl", {}).get("nees") if r["finished"] and not twin(r) else None
        if ne and r["n"] not in seen:
            seen.add(r["n"])
            ccl.append(f"N={r['n']}: {ne['mean']:.2f}{'' if ne['inside'] else ' (outside)'}")
    if ccl:
        lines += ["", "UKF-CCL NEES mean, same runs: " + ", ".join(ccl) + "."]
    costs = {}
    for r in results:
        for alg, s in ((r.get("reference_s") or {}).items() if r["finished"] else ()):
            costs.setdefault(alg.upper() + (" (pose twin)" if twin(r) else ""), {}).setdefault(r["n"], s / r["ticks"])
    if costs:
        lines += ["", "The offline references' cost, s per tick for the whole swarm in this process: "
                  + "; ".join(f"{alg} " + ", ".join(f"N={n}: {fmt(x, '.3g')}" for n, x in sorted(by_n.items()))
                              for alg, by_n in costs.items()) + "."]
    if notes:
        lines += ["", "Notes:", *[f"- {x}" for x in notes]]
    return "\n".join(lines) + "\n"


def twin(r: dict) -> bool:
    """Whether the run was of the scenario's pose twin."""
    return r.get("estimator") in POSE_TWIN


def reference_lines(ax, results: list[dict], value, names: dict) -> None:
    """One line per reference (IL dashed, UKF-CCL dotted) and scenario (the twin's grey: its
    references are its own, other sensors and another joint state): `value(r, alg)` of the first
    finished run of each N, where it is not None."""
    for is_twin, grey in ((False, "k"), (True, "0.55")):
        for alg, style in (("il", "--"), ("ukf-ccl", ":")):
            by_n = {}
            for r in results:
                if r["finished"] and twin(r) == is_twin and (v := value(r, alg)) is not None:
                    by_n.setdefault(r["n"], v)
            ns = sorted(by_n)
            if ns:
                ax.plot(ns, [by_n[n] for n in ns], style, color=grey, marker="s", ms=4,
                        label=names[alg] + (", pose twin" if is_twin else ""))


def plot(results: list[dict], path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2, ax3) = plt.subplots(1, 3, figsize=(15, 4.5))
    configs = list(dict.fromkeys(label_of(r) for r in results))
    colors = dict(zip(configs, ["C3", "C0", "C2", "C4", "C6", "C5", "C8"]))
    for c in configs:
        rs = [r for r in results if label_of(r) == c]
        ok = sorted((r for r in rs if r["finished"]), key=lambda r: r["n"])
        ax1.plot([r["n"] for r in ok], [r["wall_s"] / r["ticks"] for r in ok], "o-", color=colors[c], label=c)
        dnf = [r for r in rs if not r["finished"] and r.get("ticks_per_s_seen")]
        if dnf:
            ax1.plot([r["n"] for r in dnf], [1 / r["ticks_per_s_seen"] for r in dnf], "^", color=colors[c], mfc="none",
                     ms=9, label=f"{c}: did not finish (rate of ticks reached)")
        ax2.plot([r["n"] for r in ok], [est_of(r)["mean_error_m"] for r in ok], "o-", color=colors[c], label=c)
        ratio = [(r["n"], est_of(r)["mean_error_m"] / r["ukf-ccl"]["mean_error_m"]) for r in ok if r.get("ukf-ccl")]
        ax3.plot([n for n, _ in ratio], [x for _, x in ratio], "o-", color=colors[c], label=c)
    reference_lines(ax2, results, lambda r, alg: (r.get(alg) or {}).get("mean_error_m"),
                    {"il": "IL (dead reckoning)", "ukf-ccl": "UKF-CCL (centralized)"})
    ax3.axhline(1.0, color="k", ls=":", lw=1, label="UKF-CCL of the same run")
    ax3.axhline(1.15, color="k", ls="--", lw=0.8, alpha=0.5, label="1.15 (issue 29's bar)")
    inproc = sorted({r["n"] for r in results if r.get("in_process")})
    sizes = sorted({r["n"] for r in results})
    for ax in (ax1, ax2, ax3):
        ax.set_xscale("log", base=2)
        ax.set_xticks(sizes, [str(n) + ("*" if n in inproc else "") for n in sizes])
        ax.set_xlabel("platforms N" + (" (* in process, else over Zenoh)" if inproc else ""))
        ax.grid(True, which="both", alpha=0.3)
    # The offline references' cost (in process only: a Zenoh run computes them in netsim).
    reference_lines(ax1, results, lambda r, alg: (r.get("reference_s") or {}).get(alg, 0) / r["ticks"] or None,
                    {"il": "IL (offline, one process)", "ukf-ccl": "UKF-CCL (offline, one process)"})
    ax1.set_yscale("log")
    ax1.set_ylabel("wall s per tick, whole swarm (lockstep)")
    ax1.set_title("Cost per tick")
    ax2.set_ylabel("mean position error (m)")
    ax2.set_title("Accuracy")
    ax3.set_ylabel("mean error / UKF-CCL's on the same run")
    ax3.set_title("Against the centralized filter")
    for ax in (ax1, ax2, ax3):
        ax.legend(fontsize=7)
    fig.suptitle("Decentralized estimators against swarm size", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    global SEED
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[4, 8, 16, 32, 64])
    p.add_argument("--estimators", type=parse_config, nargs="+",
                   default=[("ukf-dcl", 3), ("ukf-dcl", 6), ("ukf-dcl", None)],
                   help="ukf-dcl:B (max_chain B), ukf-dcl (unbounded), or another estimator's name "
                        "(default: ukf-dcl:3 ukf-dcl:6 ukf-dcl)")
    p.add_argument("--in-process-from", type=int, metavar="N",
                   help="swarms of N platforms and more run in this process (InProcessRunner) instead of over Zenoh "
                        "(0: every size)")
    p.add_argument("--duration", type=float, help="simulated seconds for every size (default: 40 s for N <= 8, "
                                                  "30 s for 16, 20 s for 32, 12 s for 64)")
    p.add_argument("--agents-per-process", type=int, default=1, metavar="K",
                   help="over Zenoh: K agents to a process (swarmloc run --agents-per-process)")
    p.add_argument("--timeout", type=float, default=600.0, help="wall-clock limit of one run, s")
    p.add_argument("--budget", type=float, default=2000.0,
                   help="wall-clock budget of the whole benchmark, s: a run's limit is cut to what is left")
    p.add_argument("--plot", type=Path, default=ROOT / "docs" / "img" / "ukf_dcl_scale.png")
    p.add_argument("--json", type=Path)
    p.add_argument("--report", type=Path, metavar="JSON",
                   help="run nothing: print the report and draw the plot from a --json file of an earlier run")
    p.add_argument("--code", help="what code is measured, when this checkout has no git metadata (e.g. a git archive)")
    p.add_argument("--seed", type=int, default=SEED, help="the scenarios' seed (default %(default)s)")
    a = p.parse_args()
    SEED = a.seed
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
            for name, b in a.estimators:  # the unbounded run last: it is the one that may hit its limit
                left = a.budget - (time.perf_counter() - t0)
                duration = a.duration or duration_for(n)
                if left < 30:
                    results.append({"n": n, "estimator": name, "bound": b, "duration_s": duration, "finished": False,
                                    "ticks_seen": 0,
                                    "ticks_planned": int(round(duration / DT)) + 1, "error": "skipped: benchmark budget spent"})
                    log(f"N={n} {config_label(name, b)}: skipped, budget spent")
                    continue
                timeout = min(a.timeout, left)
                log(f"N={n} {config_label(name, b)}: {int(round(duration / DT)) + 1} ticks, limit {timeout:.0f} s, "
                    f"load {os.getloadavg()[0]:.1f}")
                if a.in_process_from is not None and n >= a.in_process_from:
                    r = measure_in_process(n, name, b, duration, timeout)
                else:
                    r = measure(n, name, b, duration, timeout, Path(tmp), a.agents_per_process)
                    for attempt in (2, 3):
                        if r["finished"] or r.get("ticks_seen") or "launcher exit code" not in r.get("error", ""):
                            break
                        # Under load netsim may take longer to listen than the launcher waits (20 s),
                        # and the launcher's own session then fails: the swarm never started, so
                        # running it again measures the same thing.
                        log(f"  did not start ({r['error'][:80]}...), attempt {attempt}")
                        r = measure(n, name, b, duration, max(30.0, min(a.timeout, a.budget - (time.perf_counter() - t0))),
                                    Path(tmp) / f"attempt{attempt}", a.agents_per_process)
                        r["attempts"] = attempt
                results.append(r)
                if r["finished"]:
                    log(f"  {r['ticks']} ticks in {r['wall_s']:.1f} s ({r['ticks_per_s']:.3g} ticks/s; whole run "
                        f"{r['total_s']:.0f} s); error {name} {r['est']['mean_error_m']:.3f} m, "
                        f"il {r['il']['mean_error_m']:.3f}, ukf-ccl {r['ukf-ccl']['mean_error_m']:.3f}; "
                        f"NEES {r['est']['nees']['mean']:.2f}, ranges used {fmt(r['fraction_used'])}")
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
