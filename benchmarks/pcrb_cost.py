"""What the posterior Cramér-Rao bound adds to a run (docs/benchmarks.md, "The PCRB: what it adds to a run").

Usage: python benchmarks/pcrb_cost.py [SCENARIO ...] [--repeats N (2)] [--duration S] [--out FILE]

Two measurements per scenario (default: wang2019 and swarm32, 32 agents):

- `swarmloc run SCENARIO` end to end (processes, Zenoh, plots, as a user runs it), N times with
  the bound and N times with the scenario's `bound: false`, alternated so that a change in the
  machine's load falls on both; the median wall time of each, and the bound's own wall and CPU
  seconds as the runs' metrics.json report them (`pcrb.wall_s`, `pcrb.cpu_s`). The bound is
  computed once, after the last tick, so it adds its own time and nothing else.
- In-process (the lockstep run's computation, no processes): the CPU seconds of the simulation
  with every agent's estimator and the references, and of the bound, which does not depend on
  other work on the machine the way wall time does.

--duration overrides clock.duration (default: the scenario's own). A `swarmloc run` that does
not start (on a machine so loaded that netsim's router is not up in time) is tried 3 times, then
left out of its median; the table says how many runs each median has.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from swarmloc.process import pin_blas  # noqa: E402

pin_blas()  # before numpy loads

from netsim.sim import Simulation  # noqa: E402
from swarmloc.experiment import scenario as S  # noqa: E402
from swarmloc.experiment.bounds import pcrb  # noqa: E402
from swarmloc.experiment.results import compute_references  # noqa: E402
from swarmloc.experiment.runner import InProcessRunner, make_nodes  # noqa: E402


def end_to_end(path: Path, out: Path, swarm: str, tries: int = 3) -> tuple[float | None, dict | None]:
    for attempt in range(1, tries + 1):
        if out.exists():
            shutil.rmtree(out)
        t = time.perf_counter()
        p = subprocess.run([sys.executable, "-m", "agents", "run", str(path), "--out", str(out), "--port", "0",
                            "--swarm", f"{swarm}-{attempt}"], capture_output=True, text=True, cwd=ROOT)
        wall = time.perf_counter() - t
        if p.returncode == 0:
            return wall, json.loads((out / "metrics.json").read_text())
        # On a machine so loaded that netsim's router is not up in time, the run does not start;
        # that says nothing about the bound: try again, and say so.
        print(f"  {path.name}: exit {p.returncode} after {wall:.0f} s (try {attempt} of {tries}): "
              f"{p.stderr.strip().splitlines()[-1] if p.stderr.strip() else ''}", flush=True)
    return None, None


def in_process(sc) -> tuple[float, float, int]:
    cpu = time.process_time()
    record = InProcessRunner(Simulation(sc), make_nodes(sc.estimator.name, sc)).run()
    compute_references(sc.with_overrides(bound=False), record, sc.reference_names)
    run_cpu = time.process_time() - cpu
    cpu = time.process_time()
    pcrb(sc, record)
    return run_cpu, time.process_time() - cpu, len(record.k)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenarios", nargs="*", default=["wang2019", "swarm32"])
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--duration", type=float)
    p.add_argument("--out", type=Path)
    a = p.parse_args(argv)
    lines = ["| scenario | agents | ticks | `swarmloc run`, bound on (s, runs) | bound off (s, runs) | difference (s) | "
             "bound in metrics.json, wall / CPU (s) | in-process run CPU (s) | bound CPU (s) | bound / run CPU |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for name in a.scenarios:
            sc = S.load(name)
            if a.duration:
                sc = sc.with_overrides(**{"clock.duration": a.duration})
            files = {}
            for on in (True, False):
                files[on] = tmp / f"{name}-{'on' if on else 'off'}.yaml"
                files[on].write_text(sc.with_overrides(bound=on).to_yaml())
            run_cpu, bound_cpu, ticks = in_process(sc)
            print(f"{name} in-process: run {run_cpu:.2f} s CPU, bound {bound_cpu:.2f} s CPU", flush=True)
            walls: dict[bool, list[float]] = {True: [], False: []}
            own = []
            for i in range(a.repeats):
                for on in ((True, False) if i % 2 == 0 else (False, True)):
                    wall, m = end_to_end(files[on], tmp / f"run-{name}-{on}-{i}", f"pcrbcost{i}{int(on)}")
                    if wall is None:
                        print(f"{name} run {i + 1} bound {'on' if on else 'off'}: did not start", flush=True)
                        continue
                    walls[on].append(wall)
                    if on:
                        own.append((m["pcrb"]["wall_s"], m["pcrb"]["cpu_s"]))
                    else:
                        assert "pcrb" not in m
                    print(f"{name} run {i + 1} bound {'on' if on else 'off'}: {wall:.1f} s"
                          + (f" (bound {own[-1][0]:.2f} s wall, {own[-1][1]:.2f} s CPU)" if on else ""), flush=True)

            def med(x, fmt="{:.1f}"):
                return fmt.format(statistics.median(x)) if x else "-"
            diff = (f"{statistics.median(walls[True]) - statistics.median(walls[False]):+.1f}"
                    if walls[True] and walls[False] else "-")
            lines.append(f"| {name} | {len(sc.world.agents)} | {ticks} | {med(walls[True])} ({len(walls[True])}) | "
                         f"{med(walls[False])} ({len(walls[False])}) | {diff} | "
                         f"{med([w for w, _ in own], '{:.2f}')} / {med([c for _, c in own], '{:.2f}')} | "
                         f"{run_cpu:.2f} | {bound_cpu:.2f} | {bound_cpu / run_cpu:.1%} |")
            print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    if a.out:
        a.out.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
