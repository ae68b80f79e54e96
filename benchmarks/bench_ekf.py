"""Benchmark: the EKF family (issue 9): per-node filter cost, the centralized EKF, radio bytes.

Three parts, measured in one run on the same machine, the estimators alternating within each
repetition:

1. Per-node cost (goel10 and goel-dist, in-process lockstep runs, GNSS on every UAS): every
   call of a node's step and receive is timed where the runner makes it, so the filters run on
   real frames and real neighbour beacons decoded from the wire. Step on an IMU-only frame, on
   an epoch frame (IMU + GNSS fix + relative positions), receive of a neighbour's beacon that
   is fused (and the CI / naive fuse() inside it) for ekf-ci (trace, det), ekf-naive, plus
   EkfNode (ekf) and the fusion centre's client (ekf-centre) for reference.
2. Centralized EKF (CentralizedEkf.step, the offline ekf-ccl) at 10 and 20 UAS, GNSS on all and
   on half: frames recorded from netsim's Simulation, replayed into a fresh filter, each tick
   timed (normal ticks, epoch ticks; predict and update separately). The fusion centre's own
   tick (FusionCentre._run) and its per-datum checks are timed inside the ekf-centre runs.
3. Radio bytes (goel10 and goel20, in process, the real wire codec): every frame a node hands
   to the radio, counted at the sender (a broadcast counts once).

Usage: python benchmarks/bench_ekf.py [--quick] [--repeat 3] [--duration 20] [--json FILE]
Timing only; nothing here is a pass/fail test.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from collections import defaultdict
from datetime import date

from machine import code_version, cpu_model  # benchmarks/machine.py

from swarmloc.process import pin_blas

pin_blas()  # before numpy loads

import numpy as np  # noqa: E402

from netsim.sim import Simulation  # noqa: E402
from swarmloc.estimators import make_nodes  # noqa: E402
from swarmloc.estimators.ekf.ccl import CentralizedEkf  # noqa: E402
from swarmloc.experiment import scenario as S  # noqa: E402
from swarmloc.experiment.runner import InProcessRunner  # noqa: E402
from swarmloc.wire.messages import CentreData  # noqa: E402

clock = time.perf_counter
GNSS_HALF = {"goel10": [3, 5, 6, 7, 8], "goel20": [2, 4, 6, 8, 10, 12, 14, 16, 18, 20]}  # the scenarios' comments
# (label, registry name, params)
PER_NODE = [("ekf", "ekf", None), ("ekf-ci trace", "ekf-ci", {"criterion": "trace"}),
            ("ekf-ci det", "ekf-ci", {"criterion": "det"}), ("ekf-naive", "ekf-naive", {"criterion": "trace"}),
            ("ekf-centre", "ekf-centre", None)]


def stats(xs: list[float]) -> dict:
    """Median and p90 in microseconds, and the sample count."""
    if not xs:
        return {"n": 0, "median_us": None, "p90_us": None}
    a = np.asarray(xs) * 1e6
    return {"n": len(xs), "median_us": float(np.median(a)), "p90_us": float(np.percentile(a, 90))}


def frame_kind(s) -> str:
    if s.align is not None:
        return "align"
    if s.relpos or s.ranges or s.gnss is not None or s.pseudoranges is not None:
        return "epoch"
    return "imu"


def scenario(name: str, duration: float, gnss_half: bool = False):
    o = {"clock.duration": float(duration)}
    if gnss_half:
        o["sensors.gnss.agents"] = GNSS_HALF[name]
    return S.load(name).with_overrides(**o)


# ---------------------------------------------------------------------- instrumented runs


class Probe:
    """Times node calls and counts the frames every node hands to the radio."""

    def __init__(self):
        self.t: dict[str, list[float]] = defaultdict(list)
        self.frames: list[tuple[int, int | None, str, int | None]] = []  # (src, dst, kind, bytes | None = too big)
        self._nested = 0.0

    def wrap_outbox(self, runner: InProcessRunner) -> None:
        for a, ob in runner.outbox.items():
            def encode(send, _enc=ob.encode, _a=a):
                tx = _enc(send)
                kind = type(send.msg).__name__
                if isinstance(send.msg, CentreData) and send.msg.x is not None:
                    kind += "+x,P"
                self.frames.append((_a, send.dst, kind, None if tx is None else len(tx.data)))
                return tx
            ob.encode = encode

    def wrap_uas(self, node) -> None:
        step, receive, fuse = node.step, node.receive, getattr(node, "fuse", None)

        def timed_step(sensors):
            t0 = clock()
            out = step(sensors)
            self.t[f"step {frame_kind(sensors)}"].append(clock() - t0)
            return out

        def timed_receive(src, msg):
            fused = node.stats.get("fused", 0)
            adopted = node.stats.get("centre_ticks", 0)
            t0 = clock()
            out = receive(src, msg)
            dt = clock() - t0
            if node.stats.get("fused", 0) > fused:
                self.t["receive beacon, fused"].append(dt)
            elif node.stats.get("centre_ticks", 0) > adopted:
                self.t["receive centre estimate, adopted"].append(dt)
            else:
                self.t[f"receive {type(msg).__name__}, not used"].append(dt)
            return out

        def timed_fuse(dz, Pz):
            t0 = clock()
            out = fuse(dz, Pz)
            self.t["fuse"].append(clock() - t0)
            return out

        node.step, node.receive = timed_step, timed_receive
        if fuse is not None:
            node.fuse = timed_fuse

    def wrap_centre(self, node) -> None:
        run, receive = node._run, node.receive

        def timed_run():
            epoch = any(frame_kind(d.sensors) == "epoch" for d in node.data.values())
            joined = node.stats["joined"]
            t0 = clock()
            out = run()
            dt = clock() - t0
            self._nested += dt
            kind = "join" if node.stats["joined"] > joined else ("epoch" if epoch else "normal")
            self.t[f"centre tick {kind}"].append(dt)
            return out

        def timed_receive(src, msg):
            self._nested = 0.0
            t0 = clock()
            out = receive(src, msg)
            self.t["centre receive datum (excl. tick)"].append(clock() - t0 - self._nested)
            return out

        node._run, node.receive = timed_run, timed_receive


def instrumented_run(sc, algorithm: str, params: dict | None) -> tuple[Probe, float, int]:
    """One in-process lockstep run with every node instrumented: (probe, wall s, ticks)."""
    from swarmloc.estimators.ekf.centre import FusionCentre

    ids = sc.agent_ids if algorithm == "ekf-centre" else sc.localized_ids
    nodes = make_nodes(algorithm, sc, ids, params)
    runner = InProcessRunner(Simulation(sc), nodes)
    probe = Probe()
    probe.wrap_outbox(runner)
    for node in nodes.values():
        if isinstance(node, FusionCentre):
            probe.wrap_centre(node)
        elif node.model.state_dim > 0:
            probe.wrap_uas(node)
    t0 = clock()
    runner.run()
    return probe, clock() - t0, runner.env.steps + 1


def traffic(probe: Probe, sc, ticks: int) -> dict:
    """Bytes and frames per second of flight (ticks x dt), by direction."""
    T = ticks * sc.clock.dt
    uas = set(sc.localized_ids)
    n = len(uas)
    groups = {"UAS -> all": lambda s, d: s in uas and d is None, "UAS -> centre": lambda s, d: s in uas and d is not None,
              "centre -> UAS": lambda s, d: s not in uas}
    out = {"seconds": T, "uas": n, "directions": {}, "kinds": {}}
    for name, pick in groups.items():
        sizes = [b for s, d, _, b in probe.frames if pick(s, d) and b is not None]
        if not sizes:
            continue
        out["directions"][name] = {"frames": len(sizes), "frames_per_s": len(sizes) / T, "mean_bytes": float(np.mean(sizes)),
                                   "bytes_per_s": sum(sizes) / T, "bytes_per_s_per_uas": sum(sizes) / T / n}
    sizes_all = [b for *_, b in probe.frames if b is not None]
    out["total"] = {"frames": len(sizes_all), "frames_per_s": len(sizes_all) / T,
                    "mean_bytes": float(np.mean(sizes_all)) if sizes_all else 0.0,
                    "bytes_per_s": sum(sizes_all) / T, "bytes_per_s_per_uas": sum(sizes_all) / T / n,
                    "too_big": sum(1 for *_, b in probe.frames if b is None)}
    by_kind = defaultdict(list)
    for _, _, kind, b in probe.frames:
        if b is not None:
            by_kind[kind].append(b)
    out["kinds"] = {k: {"frames": len(v), "mean_bytes": float(np.mean(v)), "min_bytes": min(v), "max_bytes": max(v)}
                    for k, v in sorted(by_kind.items())}
    return out


# ---------------------------------------------------------------------- centralized EKF


def record_frames(sc) -> list[dict]:
    sim = Simulation(sc)
    return [sim.tick()[2] for _ in range(sim.steps + 1)]


def replay_centralized(sc, frames: list[dict], times: dict[str, list[float]]) -> None:
    ids = sc.localized_ids
    ekf = CentralizedEkf.from_scenario(sc, ids)
    predict, update = ekf.joint.predict, ekf.joint.update
    last = {}

    def timed_predict(imus):
        t0 = clock()
        predict(imus)
        last["predict"] = clock() - t0

    def timed_update(fr):
        t0 = clock()
        out = update(fr)
        last["update"] = clock() - t0
        return out

    ekf.joint.predict, ekf.joint.update = timed_predict, timed_update
    for fr in frames:
        mine = {a: fr[a] for a in ids}
        kinds = {frame_kind(f) for f in mine.values()}
        kind = "join" if "align" in kinds else ("epoch" if "epoch" in kinds else "normal")
        t0 = clock()
        ekf.step(mine)
        dt = clock() - t0
        times[f"step {kind}"].append(dt)
        times[f"predict {kind}"].append(last["predict"])
        times[f"update {kind}"].append(last["update"])


def update_side_by_side(duration: float, repeat: int) -> None:
    """The centralized EKF's relative-position update, information form (JointEkf.linear_relpos,
    the default) against 8N-row batches, alternating on the same recorded frames."""
    from swarmloc.estimators.ekf.ccl import JointEkf

    print("| swarm | relative positions | epoch tick: median (p90) ms | update at epoch: median ms | normal tick: median ms |")
    print("|---|---|---|---|---|")
    for name in ("goel10", "goel20"):
        sc = scenario(name, duration)
        frames = record_frames(sc)
        times = {True: defaultdict(list), False: defaultdict(list)}
        for _ in range(repeat):
            for linear in (False, True):
                JointEkf.linear_relpos = linear
                replay_centralized(sc, frames, times[linear])
        JointEkf.linear_relpos = True
        for linear in (False, True):
            t = times[linear]
            ep, up, nm = stats(t["step epoch"]), stats(t["update epoch"]), stats(t["step normal"])
            print(f"| {name} | {'one information-form update' if linear else '8N-row batches'} | "
                  f"{ep['median_us'] / 1e3:.1f} ({ep['p90_us'] / 1e3:.1f}) | {up['median_us'] / 1e3:.1f} | "
                  f"{nm['median_us'] / 1e3:.1f} |")


# ---------------------------------------------------------------------- main


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="one repetition, 10 s of flight (under 2 minutes)")
    p.add_argument("--repeat", type=int, default=None, help="repetitions of the timed runs (default 3, quick 1)")
    p.add_argument("--duration", type=float, default=None, help="seconds of flight per run (default 20, quick 10)")
    p.add_argument("--dist-duration", type=float, default=None, help="goel-dist flight (default 60, quick 20)")
    p.add_argument("--no-goel20", action="store_true", help="skip the 20-UAS runs")
    p.add_argument("--json", metavar="FILE", help="also write every figure as JSON")
    p.add_argument("--update-only", action="store_true",
                   help="only the centralized EKF's relative-position update, both ways side by side")
    a = p.parse_args()
    if a.update_only:
        return update_side_by_side(a.duration or 20.0, a.repeat or 3)
    repeat = a.repeat or (1 if a.quick else 3)
    duration = a.duration or (10.0 if a.quick else 20.0)
    dist_duration = a.dist_duration or (20.0 if a.quick else 60.0)
    big = [] if a.no_goel20 else ["goel20"]
    started = clock()
    load0 = os.getloadavg()[0]
    log = lambda msg: print(f"[{clock() - started:6.1f} s] {msg}", file=sys.stderr, flush=True)

    # Warm-up: imports, caches and scipy's first calls; nothing recorded.
    for label, alg, params in PER_NODE:
        if alg != "ekf-centre":
            instrumented_run(scenario("goel-dist", 3.0), alg, params)
    instrumented_run(scenario("goel10", 2.0), "ekf-centre", None)
    w = scenario("goel10", 2.0)
    replay_centralized(w, record_frames(w), defaultdict(list))
    log("warm-up done")

    # 1 + 3. Per-node timings and bytes: estimators alternate within each repetition.
    node_t = {sc: {lab: defaultdict(list) for lab, *_ in PER_NODE} for sc in ("goel10", "goel-dist")}
    centre_t = {sc: defaultdict(list) for sc in ["goel10"] + big}
    bytes_ = {sc: {} for sc in ["goel10"] + big}
    walls = defaultdict(list)
    for r in range(repeat):
        for label, alg, params in PER_NODE:
            sc = scenario("goel10", duration)
            probe, wall, ticks = instrumented_run(sc, alg, params)
            walls[f"goel10 {label}"].append(wall)
            for k, v in probe.t.items():
                (centre_t["goel10"] if k.startswith("centre") else node_t["goel10"][label])[k] += v
            if r == 0:
                bytes_["goel10"][label] = traffic(probe, sc, ticks)
            log(f"goel10 {label} rep {r + 1}: {wall:.1f} s")
            if alg != "ekf-centre":
                probe, wall, _ = instrumented_run(scenario("goel-dist", dist_duration), alg, params)
                walls[f"goel-dist {label}"].append(wall)
                for k, v in probe.t.items():
                    node_t["goel-dist"][label][k] += v
    for name in big:  # once: bytes are deterministic, the centre's tick is timed per tick
        for label, alg, params in PER_NODE:
            if label == "ekf-ci det":
                continue  # the same beacons as trace, byte for byte in size
            sc = scenario(name, duration)
            probe, wall, ticks = instrumented_run(sc, alg, params)
            walls[f"{name} {label}"].append(wall)
            bytes_[name][label] = traffic(probe, sc, ticks)
            for k, v in probe.t.items():
                if k.startswith("centre"):
                    centre_t[name][k] += v
            log(f"{name} {label}: {wall:.1f} s")

    # 2. Centralized EKF on recorded frames.
    configs = [(n, half) for n in ["goel10"] + big for half in (False, True)]
    recorded = {}
    for n, half in configs:
        sc = scenario(n, duration, half)
        recorded[(n, half)] = (sc, record_frames(sc))
    ccl_t = {c: defaultdict(list) for c in configs}
    for r in range(repeat):
        for c in configs:
            sc, frames = recorded[c]
            replay_centralized(sc, frames, ccl_t[c])
            log(f"ekf-ccl {c[0]} gnss {'half' if c[1] else 'all'} rep {r + 1}")

    total = clock() - started
    result = {
        "date": str(date.today()),
        "machine": {"vcpu": os.cpu_count(), "cpu": cpu_model(), "python": platform.python_version(),
                    "numpy": np.__version__, "linux": platform.release(), "code": code_version(),
                    "load_start": load0, "load_end": os.getloadavg()[0]},
        "command": "python benchmarks/bench_ekf.py " + " ".join(sys.argv[1:]),
        "repeat": repeat, "duration_s": duration, "dist_duration_s": dist_duration, "wall_s": total,
        "per_node": {sc: {lab: {k: stats(v) for k, v in d.items()} for lab, d in t.items()} for sc, t in node_t.items()},
        "centre": {sc: {k: stats(v) for k, v in d.items()} for sc, d in centre_t.items()},
        "centralized": {f"{n} gnss {'half' if h else 'all'}": {k: stats(v) for k, v in d.items()}
                        for (n, h), d in ccl_t.items()},
        "bytes": bytes_,
        "run_wall_s": {k: float(np.median(v)) for k, v in walls.items()},
    }
    print_tables(result)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(result, f, indent=1)


def cell(s: dict | None) -> str:
    if not s or not s["n"]:
        return "-"
    return f"{s['median_us']:,.0f} / {s['p90_us']:,.0f} ({s['n']})"


def print_tables(r: dict) -> None:
    m = r["machine"]
    print(f"### EKF family ({r['date']})\n")
    print(f"Machine: {m['vcpu']} vCPU ({m['cpu']}), Python {m['python']}, numpy {m['numpy']}, Linux {m['linux']}. "
          f"Code (last commit to netsim/, swarmloc/, agents/): {m['code']}. Command: `{r['command'].strip()}` "
          f"({r['repeat']} repetition{'s' if r['repeat'] > 1 else ''}, {r['duration_s']:g} s of flight per run, goel-dist {r['dist_duration_s']:g} s; "
          f"whole run {r['wall_s']:.0f} s). 1-min load average {m['load_start']:.1f} at start, {m['load_end']:.1f} at end.\n")

    labels = [lab for lab, *_ in PER_NODE]
    rows = ["step imu", "step epoch", "receive beacon, fused", "fuse", "receive centre estimate, adopted"]
    names = {"step imu": "step, IMU-only frame", "step epoch": "step, epoch frame (IMU + GNSS fix + relpos)",
             "receive beacon, fused": "receive a neighbour's beacon (fused)", "fuse": "of which fuse()",
             "receive centre estimate, adopted": "receive the centre's estimate (adopted)"}
    for sc, per in r["per_node"].items():
        nb = {"goel10": 9, "goel-dist": 1}[sc]
        print(f"Per node, {sc} ({nb} neighbour{'s' if nb > 1 else ''} measured per epoch), median / p90 us (samples):\n")
        cols = [lab for lab in labels if per[lab]]
        print("| call | " + " | ".join(cols) + " |")
        print("|---" * (len(cols) + 1) + "|")
        for row in rows:
            if any(per[lab].get(row, {}).get("n") for lab in cols):
                print(f"| {names[row]} | " + " | ".join(cell(per[lab].get(row)) for lab in cols) + " |")
        print()

    print("Centralized EKF (CentralizedEkf.step, the offline ekf-ccl) on recorded frames, median / p90 us (ticks):\n")
    print("| swarm | GNSS | normal tick | epoch tick | epoch: predict | epoch: update | epoch / normal |")
    print("|---|---|---|---|---|---|---|")
    for key, d in r["centralized"].items():
        n, _, which = key.split()
        ratio = d["step epoch"]["median_us"] / d["step normal"]["median_us"]
        print(f"| {n} | {which} | {cell(d['step normal'])} | {cell(d['step epoch'])} | {cell(d['predict epoch'])} | "
              f"{cell(d['update epoch'])} | {ratio:.1f}x |")
    print()
    print("Fusion centre (FusionCentre, inside the ekf-centre runs, GNSS on all), median / p90 us (samples):\n")
    print("| swarm | tick, normal | tick, epoch | tick, UAS joining | receive one datum (checks, excl. the tick) |")
    print("|---|---|---|---|---|")
    for sc, d in r["centre"].items():
        print(f"| {sc} | {cell(d.get('centre tick normal'))} | {cell(d.get('centre tick epoch'))} | "
              f"{cell(d.get('centre tick join'))} | {cell(d.get('centre receive datum (excl. tick)'))} |")
    print()

    print("Radio traffic per second of flight (frames counted at the sender, a broadcast once):\n")
    print("| swarm | estimator | direction | frames/s | mean frame (B) | bytes/s per UAS | bytes/s, swarm |")
    print("|---|---|---|---|---|---|---|")
    for sc, per in r["bytes"].items():
        for lab, t in per.items():
            if not t["directions"]:
                print(f"| {sc} | {lab} | (nothing sent) | 0 | - | 0 | 0 |")
                continue
            for d, v in t["directions"].items():
                print(f"| {sc} | {lab} | {d} | {v['frames_per_s']:,.1f} | {v['mean_bytes']:,.0f} | "
                      f"{v['bytes_per_s_per_uas']:,.0f} | {v['bytes_per_s']:,.0f} |")
            if len(t["directions"]) > 1:
                v = t["total"]
                print(f"| {sc} | {lab} | **total** | {v['frames_per_s']:,.1f} | {v['mean_bytes']:,.0f} | "
                      f"**{v['bytes_per_s_per_uas']:,.0f}** | **{v['bytes_per_s']:,.0f}** |")
    print()
    print("Frame sizes by message (bytes on the wire, envelope included):\n")
    print("| swarm | estimator | message | frames | mean | min | max |")
    print("|---|---|---|---|---|---|---|")
    for sc, per in r["bytes"].items():
        for lab, t in per.items():
            for kind, v in t["kinds"].items():
                print(f"| {sc} | {lab} | {kind} | {v['frames']} | {v['mean_bytes']:,.0f} | {v['min_bytes']} | {v['max_bytes']} |")
    too_big = {f"{sc} {lab}": t["total"]["too_big"] for sc, per in r["bytes"].items() for lab, t in per.items()
               if t["total"]["too_big"]}
    if too_big:
        print(f"\nFrames not sent, over the {64 * 1024} B frame limit: {too_big}")
    print("\nWall time of one in-process run (median): " +
          ", ".join(f"{k} {v:.1f} s" for k, v in r["run_wall_s"].items()))


if __name__ == "__main__":
    main()
