"""What a killed agent's UKF-DCL estimate does once it is back: `inject kill 3 --for 20` on
wang2019 (as a timeline fault at t = 100 s, so every run kills at the same tick), over agent
processes with `swarmloc run`, in lockstep and in real time.

Per run: the error of agent 3 when it is back (about the distance it moved while down: it
resumes from its checkpoint and missed the odometry), how long it stays above 15 m and above
5 m, and the dead-reckoning error (il) meanwhile. The restarted agent is *lost* (its position
std is above estimation.rejoin_std) and fuses no range until a window of its own ranges pins its
position by multilateration; in wang2019 the swarm takes one range per step with probability
0.5, so agent 3 measures about one range every 4 s and needs several of them.

    .venv/bin/python benchmarks/kill_recovery.py [--seeds 7,8,9] [--realtime-seeds 7] [--speed 1]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parent.parent
KILL_AT, DOWN_FOR, AGENT = 100.0, 20.0, 3


def scenario(directory: Path) -> Path:
    out = subprocess.run([sys.executable, "-m", "agents", "scenarios", "wang2019"], capture_output=True, text=True,
                         check=True, cwd=ROOT).stdout
    data = yaml.safe_load(out)
    data["name"] = "wang2019-kill"
    data["faults"] = [{"at": KILL_AT, "action": "kill", "node": AGENT, "duration": DOWN_FOR}]
    path = directory / "wang2019-kill.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def recovery(run: Path) -> dict:
    truth = np.load(run / "truth.npz")
    t, ci = truth["t"], list(truth["ids"]).index(AGENT)

    def error(alg):
        mean = np.load(run / "estimates" / f"{alg}.npz")["mean"]
        return np.linalg.norm(mean[:, ci, :2] - truth["state"][:, ci, :2], axis=1)

    ukf, il = error("ukf-dcl"), error("il")
    back = t >= KILL_AT + DOWN_FOR
    first = int(np.flatnonzero(back & ~np.isnan(ukf))[0])

    def above(limit):
        over = np.flatnonzero(back & (ukf > limit))
        return float(t[over[-1]] - t[first]) if over.size else 0.0

    m = json.loads((run / "metrics.json").read_text())
    stats = m["agent_stats"].get(str(AGENT), {})
    return {"back_at_s": float(t[first]), "error_back_m": float(ukf[first]), "max_after_m": float(np.nanmax(ukf[back])),
            "above_15m_s": above(15.0), "above_5m_s": above(5.0), "il_mean_after_m": float(np.nanmean(il[back])),
            "ukf_mean_after_m": float(np.nanmean(ukf[back])), "lost": stats.get("lost"), "refound": stats.get("refound"),
            "dropped": stats.get("measurements_dropped"), "used": stats.get("measurements_used")}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", default="7,8,9,10,11", help="lockstep runs")
    p.add_argument("--realtime-seeds", default="7", help="real-time runs ('' for none)")
    p.add_argument("--speed", type=float, default=1.0, help="real time: simulated seconds per wall second")
    p.add_argument("--duration", type=float, default=250.0, help="simulated seconds per run")
    a = p.parse_args()
    runs = [("lockstep", int(s)) for s in a.seeds.split(",") if s] + \
        [("realtime", int(s)) for s in a.realtime_seeds.split(",") if s]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        spec = scenario(Path(tmp))
        for mode, seed in runs:
            out = Path(tmp) / f"{mode}-{seed}"
            args = [sys.executable, "-m", "agents", "run", str(spec), "--seed", str(seed), "--duration", str(a.duration),
                    "--out", str(out), "--no-plots", "--port", "0", "--swarm", f"kill-{mode}-{seed}"]
            if mode == "realtime":
                args += ["--realtime", "--speed", str(a.speed)]
            subprocess.run(args, check=True, capture_output=True, cwd=ROOT)
            rows.append({"mode": mode + (f" x{a.speed:g}" if mode == "realtime" else ""), "seed": seed,
                         **recovery(out)})
            print(json.dumps(rows[-1]), flush=True)
    cols = ["mode", "seed", "error_back_m", "max_after_m", "above_15m_s", "above_5m_s", "ukf_mean_after_m",
            "il_mean_after_m", "dropped", "used"]
    print("\n| " + " | ".join(cols) + " |\n|" + "---|" * len(cols))
    for r in rows:
        print("| " + " | ".join(f"{r[c]:.1f}" if isinstance(r[c], float) else str(r[c]) for c in cols) + " |")


if __name__ == "__main__":
    main()
