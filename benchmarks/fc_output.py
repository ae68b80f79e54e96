"""Benchmark: the estimate a flight controller gets, against the simulated PX4 of tests/fake_fc.py.

One `swarmloc agent --config` process (IL on planar-speed-heading, one tick every `--tick` s)
reads a simulated PX4 rover that its pilot drives round a circle (1 m/s, 0.1 rad/s, 50 Hz
ODOMETRY) and sends it ODOMETRY at `--rate` Hz (outputs.mavlink): the swarm's estimate
propagated between ticks with the FC's samples (agents/companion/output.py). The simulated FC
reports what PX4's EKF2 would do with each message (Ekf2ExternalVision) and when it arrived.

Reported, over the run after its first `--settle` s: messages a second and their intervals
(jitter: their std), the age of each estimate when it arrives (arrival - its FC-clock stamp),
EKF2's verdicts, and what the stream adds between ticks: each message's position against the
latest tick's estimate moved by the vehicle's true motion since that tick (the estimator's own
error is the same on both sides and cancels), beside what repeating that tick's estimate (a
zero-order hold, an output at the tick rate) would have added: the motion itself.
Usage: python benchmarks/fc_output.py [--duration 30] [--tick 0.1] [--rate 30 50]
Timing only; nothing here is a pass/fail test.
"""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))
from fake_fc import Ekf2ExternalVision, SimulatedAutopilot  # noqa: E402
from machine import cpu_model  # noqa: E402  (benchmarks/machine.py)


def free(kind=socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(tick: float, rate: float, duration: float, settle: float, out: Path) -> dict:
    port = free(socket.SOCK_DGRAM)
    log = out / f"est-{tick}-{rate}.jsonl"
    cfg = {"version": 1, "id": 1, "swarm": f"fcbench{port}", "estimator": {"name": "il"},
           "model": "planar-speed-heading", "prior": {"position": [0.0, 0.0], "std": 0.05},
           "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{free()}"]},
           "sensors": [{"kind": "mavlink", "url": f"udpin:127.0.0.1:{port}", "tick": tick}],
           "outputs": {"swarm": False, "mavlink": {"rate_hz": rate}, "log": str(log)}}
    path = out / f"agent-{tick}-{rate}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    agent_log = out / f"agent-{tick}-{rate}.log"
    agent = subprocess.Popen([sys.executable, "-m", "agents", "agent", "--config", str(path), "-v"],
                             stderr=open(agent_log, "w"), cwd=ROOT)
    end = time.monotonic() + 120
    while "INFO agent 1 up" not in agent_log.read_text():  # its imports and Zenoh session, however loaded the host
        if agent.poll() is not None or time.monotonic() > end:
            raise SystemExit(f"the agent did not start:\n{agent_log.read_text()}")
        time.sleep(0.1)
    sim = SimulatedAutopilot(port, "rover", (0.0, 0.0, 0.0, 0.0), gps=False, drive=(1.0, 0.1),
                             ev=Ekf2ExternalVision(ev_delay=0.02))
    with sim:
        time.sleep(duration)
    agent.terminate()
    agent.wait(10)
    report = sim.report(since=settle)["ev"]
    if not sim.ev.positions:
        raise SystemExit(f"the FC got no estimate; the agent said:\n{agent_log.read_text()}")
    truth = np.array(sim.truth_log, float)  # (FC time, east, north, up, yaw, offboard)
    at = lambda t: np.c_[np.interp(t, truth[:, 0], truth[:, 1]), np.interp(t, truth[:, 0], truth[:, 2])]
    est = [json.loads(line) for line in log.read_text().splitlines()]
    tk = np.array([e["t"] for e in est])  # a tick's time on the FC's clock, its last estimate kept
    mk = np.array([e["mean"][:2] for e in est])
    sent = [(t, z) for t, z in sim.ev.positions if t >= settle and t >= tk[0]]
    stamps = np.array([t for t, _ in sent])
    z = np.array([z[:2] for _, z in sent])
    # What the stream adds between ticks: against the latest tick's estimate moved by the
    # vehicle's true motion since that tick. A hold of the tick's estimate adds that motion.
    i = np.searchsorted(tk, stamps, side="right") - 1
    moved = at(stamps) - at(tk[i])
    err = np.linalg.norm(z - (mk[i] + moved), axis=1)
    hold = np.linalg.norm(moved, axis=1)
    return {"tick": tick, "rate": rate, **report, "err_cm_p50": float(np.median(err) * 100),
            "err_cm_p99": float(np.quantile(err, 0.99) * 100), "hold_cm_p50": float(np.median(hold) * 100),
            "hold_cm_p99": float(np.quantile(hold, 0.99) * 100), "ticks": len(set(int(e["k"]) for e in est))}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=30.0)
    p.add_argument("--settle", type=float, default=3.0, help="s of FC time left out at the start")
    p.add_argument("--tick", type=float, default=0.1)
    p.add_argument("--rate", type=float, nargs="+", default=[30.0])
    a = p.parse_args()
    with tempfile.TemporaryDirectory(prefix="fcbench") as d:
        rows = [run(a.tick, r, a.duration, a.settle, Path(d)) for r in a.rate]
    print(f"{date.today()}, {cpu_model()}, {a.duration:g} s per run, tick {a.tick:g} s\n")
    print("| rate_hz asked | messages/s | interval p50 / p99 / max (ms) | jitter (ms) | age p50 / p99 (ms) "
          "| EKF2 verdicts | added between ticks p50 / p99 (cm) | a tick hold would add p50 / p99 (cm) |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['rate']:g} | {r['rate_hz']:.1f} | {r['interval_ms_p50']:.1f} / {r['interval_ms_p99']:.1f} / "
              f"{r['interval_ms_max']:.1f} | {r['jitter_ms']:.1f} | {r['age_ms_p50']:.1f} / {r['age_ms_p99']:.1f} | "
              f"{json.dumps(r['counts'])} | {r['err_cm_p50']:.1f} / {r['err_cm_p99']:.1f} | "
              f"{r['hold_cm_p50']:.1f} / {r['hold_cm_p99']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
