"""Benchmark: this checkout's wire codec against another checkout's, side by side in one run.

Takes every radio frame of an in-process wang2019 UKF-DCL run (the frames the agents send,
with their real sizes), loads the other checkout's codec (its swarmloc/wire, or in a checkout
from before the wire had its room its swarmloc/wire.py and swarmloc/messages.py, under another
name) beside this one in the same process, checks that each reads every frame and writes it
back to the same bytes (that both read the same values is tests/test_wire_corpus.py's), then
times both frame by frame, alternating (A, B, A, B ...: a busy machine slows both alike):
`wire.decode` of the frame; the decode and a read of every field of the message (what a
receiver pays when it uses them all, whether or not a codec makes its arrays at decode);
`wire.encode` of a decoded message whose fields were read (what a relay does);
the message built by its type's constructor from its fields and encoded (a sender's whole
cost); the envelope-only decode netsim routes with. Then, with --lockstep N, N alternating
whole lockstep runs of wang2019 over Zenoh per checkout (netsim + 4 agent processes, `python
-m agents run`; "after" is the checkout this script is in): ticks/s and netsim's added latency
per hop (a frame in to its deliveries out, median). Usage (the other checkout needs msgpack,
which `pip install -e '.[test]'` brings); 1cc5259 is this repository's last commit before the
codec moved to msgspec (its hand-written schema layer, swarmloc/wire.py):
    mkdir /tmp/before && git archive 1cc5259 | tar -x -C /tmp/before
    python benchmarks/bench_wire.py --before /tmp/before [--ticks 200] [--rounds 3] [--lockstep 5]
Timing only; nothing here is a pass/fail test.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

from machine import cpu_model  # benchmarks/machine.py

from swarmloc.process import pin_blas

pin_blas()  # before numpy loads

import msgpack  # noqa: E402
import msgspec  # noqa: E402
import numpy as np  # noqa: E402
from bench_auth import frames_of_a_run  # noqa: E402

from swarmloc import wire  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def load_codec(tree: Path, tmp: Path):
    """The other checkout's codec as the package `_before_wire` (it imports only itself, numpy
    and its MessagePack library), in either layout: the room swarmloc/wire/*.py (main since
    700aaee), or the single module swarmloc/wire.py with its types in swarmloc/messages.py
    (1cc5259, the hand-written schema layer before msgspec)."""
    pkg = tmp / "_before_wire"
    pkg.mkdir()
    room = tree / "swarmloc" / "wire"
    if room.is_dir():
        sources = {src.name: src for src in room.glob("*.py")}
    else:
        sources = {"__init__.py": tree / "swarmloc" / "wire.py", "messages.py": tree / "swarmloc" / "messages.py"}
    for name, src in sources.items():
        text = src.read_text().replace("from swarmloc import messages", "from _before_wire import messages")
        (pkg / name).write_text(text.replace("swarmloc.wire", "_before_wire"))
    sys.path.insert(0, str(tmp))
    return importlib.import_module("_before_wire")


def fields_of(msg) -> list:
    names = getattr(msg, "__struct_fields__", None) or tuple(msg.__dataclass_fields__)
    return [getattr(msg, f) for f in names]


def _arrays_of(v) -> list:
    """The numpy arrays in a decoded message, nested messages and maps included."""
    if isinstance(v, np.ndarray):
        return [v]
    if isinstance(v, dict):
        return [a for x in v.values() for a in _arrays_of(x)]
    if isinstance(v, list):
        return [a for x in v for a in _arrays_of(x)]
    if isinstance(v, msgspec.Struct):
        return [a for f in v.__struct_fields__ for a in _arrays_of(getattr(v, f))]
    return []


def side_by_side(codecs: dict, frames: list[bytes], reps: int, rounds: int) -> dict:
    """{task: {codec: median over frames of µs per call}}, each frame timed by each codec in
    turn, `reps` calls a timing, the best of `rounds` timings."""
    envs = {name: [c.decode(f) for f in frames] for name, c in codecs.items()}
    built = {name: [(type(e.body), fields_of(e.body)) for e in es] for name, es in envs.items()}
    # A codec may leave a decoded message's arrays to their first read (the lazy arrays measured
    # in docs/benchmarks.md): "encode" is of a message whose fields were read (`built`), and
    # "decode + read" is what a receiver pays when it reads every field.
    tasks = {
        "decode": lambda c, i: c.decode(frames[i]),
        "decode + read every field": lambda c, i: fields_of(c.decode(frames[i]).body),
        "encode (decoded message)": lambda c, i, n=None: c.encode(envs[n][i].body, 1, 1, None),
        "build + encode": lambda c, i, n=None: c.encode(built[n][i][0](*built[n][i][1]), 1, 1, None),
        "envelope only (netsim)": lambda c, i: c.decode(frames[i], body=False),
    }
    out = {}
    for task, fn in tasks.items():
        times = {name: [float("inf")] * len(frames) for name in codecs}
        for _ in range(rounds):
            for i in range(len(frames)):
                for name, c in codecs.items():
                    call = (lambda: fn(c, i, name)) if "encode" in task else (lambda: fn(c, i))
                    t0 = time.perf_counter()
                    for _ in range(reps):
                        call()
                    times[name][i] = min(times[name][i], (time.perf_counter() - t0) / reps * 1e6)
        out[task] = {name: statistics.median(ts) for name, ts in times.items()}
        if len(codecs) == 2:
            a, b = (times[n] for n in codecs)
            out[task]["ratio"] = statistics.median(y / x for x, y in zip(a, b))
    # For scale, this checkout's decode in parts: msgspec's own work (its one typed pass over the
    # frame, envelope and body, that wire.decode makes; arrays left as their wire structs), and
    # libraries' untyped parsers.
    # ... and the floor numpy sets: one array object per array of the frame (views of one
    # buffer, what the decoder hands out), built alone.
    views = []
    for e in envs["after"]:
        shapes = [getattr(a, "shape", ()) for a in _arrays_of(e.body)]
        views.append((bytearray(sum(8 * math.prod(s) for s in shapes)), shapes))
    f8 = np.dtype("<f8")

    def arrays_alone(i):
        ba, shapes = views[i]
        o = 0
        for s in shapes:
            np.ndarray(s, f8, ba, o)
            o += 8 * math.prod(s)

    scale = {
        "decode: msgspec's part alone (one typed pass: envelope + body, no numpy)":
            lambda i: wire._FRAMES.decode(frames[i]),
        "numpy: the frame's arrays as views of one buffer, alone": arrays_alone,
        "msgpack.unpackb, untyped": lambda i: msgpack.unpackb(frames[i], strict_map_key=False),
        "msgspec.msgpack.decode, untyped": lambda i: msgspec.msgpack.decode(frames[i]),
    }
    for task, fn in scale.items():
        ts = [float("inf")] * len(frames)
        for _ in range(rounds):
            for i in range(len(frames)):
                t0 = time.perf_counter()
                for _ in range(reps):
                    fn(i)
                ts[i] = min(ts[i], (time.perf_counter() - t0) / reps * 1e6)
        out[task] = {"after": statistics.median(ts)}
    return out


def zenoh_run(tree: Path, out: Path) -> dict:
    cmd = [sys.executable, "-m", "agents", "run", "wang2019", "--out", str(out), "--port", "0", "--no-plots",
           "--swarm", f"benchwire{os.getpid()}"]
    r = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(tree)}, cwd=tree)
    if r.returncode:
        tail = "\n".join((r.stdout + r.stderr).strip().splitlines()[-6:])
        raise SystemExit(f"lockstep run of {tree} failed ({r.returncode}):\n{tail}")
    m = json.loads((out / "metrics.json").read_text())
    return {"ticks/s": m["ticks_per_s"], "netsim hop (µs)": m["radio"]["netsim_hop_us_median"],
            "agent hop (µs)": statistics.median(s["hop_us_median"] for s in m["agent_stats"].values())}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--before", type=Path, help="a checkout of swarmloc to compare with")
    p.add_argument("--ticks", type=int, default=200)
    p.add_argument("--reps", type=int, default=10, help="calls in one timing of a frame")
    p.add_argument("--rounds", type=int, default=3, help="timings of each frame by each codec (the best counts)")
    p.add_argument("--lockstep", type=int, default=0, help="alternating Zenoh runs of each checkout (0: none)")
    a = p.parse_args()
    frames, _ = frames_of_a_run(a.ticks)
    sizes = sorted(map(len, frames))
    with tempfile.TemporaryDirectory() as tmp:
        codecs = {"before": load_codec(a.before.resolve(), Path(tmp))} if a.before else {}
        codecs["after"] = wire
        for name, c in codecs.items():  # the same bytes, the same values
            for f in frames:
                e = c.decode(f)
                assert c.encode(e.body, e.src, e.seq, e.dst) == f, name
        res = side_by_side(codecs, frames, a.reps, a.rounds)
        envs_after = [wire.decode(f) for f in frames]
        names = list(codecs)
        two = len(names) == 2
        # The frame-by-frame table first: the lockstep runs take minutes and may fail on a busy machine.
        print(f"# bench_wire ({date.today()}, Python {platform.python_version()}, {os.cpu_count()} vCPU "
              f"{cpu_model()}, load average {os.getloadavg()[0]:.1f} after the frame timings)\n")
        arrays = sorted(len(_arrays_of(e.body)) for e in envs_after)
        values = sorted(sum(x.size for x in _arrays_of(e.body)) for e in envs_after)
        print(f"wang2019 UKF-DCL, {a.ticks + 1} ticks: {len(frames)} radio frames, sizes median "
              f"{sizes[len(sizes) // 2]} B (min {sizes[0]}, max {sizes[-1]}), arrays a frame median "
              f"{arrays[len(arrays) // 2]} (max {arrays[-1]}) of {values[len(values) // 2]} values in all "
              f"(max {values[-1]}). Median over frames of µs per call "
              f"(best of {a.rounds} timings of {a.reps} calls, the codecs alternating frame by frame)"
              + ("; ratio: median over frames of after / before." if two else ".") + "\n")
        print("| per frame (µs) | " + " | ".join(names) + (" | after / before |" if two else " |"))
        print("|---|" + "---|" * (len(names) + two))
        for task, row in res.items():
            cells = [f"{row[n]:.2f}" if n in row else "" for n in names]
            print(f"| {task} | " + " | ".join(cells) + (f" | {row['ratio']:.3f} |" if "ratio" in row else
                                                       " |" if two else " |"))
        sys.stdout.flush()
        runs: dict[str, list[dict]] = {n: [] for n in codecs}
        trees = {"before": a.before, "after": ROOT}
        for r in range(a.lockstep):
            for name in codecs:
                runs[name].append(zenoh_run(trees[name].resolve(), Path(tmp) / f"{name}{r}"))
                print(f"lockstep {r + 1} {name}: {json.dumps(runs[name][-1])}", file=sys.stderr)
        shutil.rmtree(Path(tmp) / "_before_wire", ignore_errors=True)
    if a.lockstep:
        print(f"\nwang2019 over Zenoh, lockstep, 801 ticks: median (min-max) of {a.lockstep} runs, the checkouts "
              f"alternating (load average {os.getloadavg()[0]:.1f} at the end):\n")
        print("| whole run | " + " | ".join(names) + " |")
        print("|---|" + "---|" * len(names))
        for k in runs[names[0]][0]:
            cells = []
            for n in names:
                v = [r[k] for r in runs[n]]
                cells.append(f"{statistics.median(v):.0f} ({min(v):.0f}-{max(v):.0f})")
            print(f"| {k} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
