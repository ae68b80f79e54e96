"""Benchmark: what a per-frame call costs beside busy threads, when it lets go of the GIL.

An agent host runs Zenoh's callback threads (one per subscription: about 130 for 32 agents)
beside its loop (when measured, a thread per agent); netsim a few.
A C call that releases the GIL (to hash, sign or write) has to get it back, and with many
threads wanting it that wait can be milliseconds, whatever the call itself costs. This script
times each call alone and beside N threads doing small Python work (a loop, then a 0.5 ms sleep,
like hostmates handling frames): CPU of the calling thread (`time.thread_time`) and wall time,
per call, medians of --repeat runs. The MAC twice: `hmac.digest` (releases the GIL on every call)
and `swarmloc.wire.auth.mac` (the same bytes, keeps it; docs/benchmarks.md, "The GIL and the MAC").

Usage: python benchmarks/bench_gil.py [--threads 0 8 64] [--calls 2000] [--repeat 3]
Timing only; nothing here is a pass/fail test (tests/test_auth.py checks the MAC's bytes).
"""

from __future__ import annotations

import argparse
import hmac
import os
import platform
import statistics
import tempfile
import threading
import time
from datetime import datetime, timezone

from machine import cpu_model  # benchmarks/machine.py

from swarmloc.process import pin_blas

pin_blas()  # before numpy loads

import numpy as np  # noqa: E402
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey  # noqa: E402

from swarmloc.wire import auth  # noqa: E402

FRAME_BYTES = 470  # the median radio frame of wang2019 (docs/benchmarks.md, the wire on msgspec)


def calls(tmp: str) -> dict:
    key, msg = os.urandom(32), os.urandom(FRAME_BYTES)
    assert auth.mac(key, msg) == hmac.digest(key, msg, "sha256")
    signer = Ed25519PrivateKey.generate()
    public, sig = signer.public_key(), signer.sign(msg)
    fd = os.open(os.path.join(tmp, "checkpoint"), os.O_WRONLY | os.O_CREAT)
    a = np.eye(4) * 2 + 0.1
    return {
        "hmac.digest (sha256)": lambda: hmac.digest(key, msg, "sha256"),
        "auth.mac": lambda: auth.mac(key, msg),
        "Ed25519 sign": lambda: signer.sign(msg),
        "Ed25519 verify": lambda: public.verify(sig, msg),
        "os.pwrite (a checkpoint)": lambda: os.pwrite(fd, msg, 0),
        "np.linalg.cholesky 4x4": lambda: np.linalg.cholesky(a),
    }


def busy(stop: threading.Event) -> None:
    while not stop.is_set():
        s = 0
        for i in range(1000):
            s += i
        time.sleep(0.0005)


def timed(fn, n: int) -> tuple[float, float]:
    c0, w0 = time.thread_time(), time.perf_counter()
    for _ in range(n):
        fn()
    return (time.thread_time() - c0) / n * 1e6, (time.perf_counter() - w0) / n * 1e6


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=int, nargs="+", default=[0, 8, 64])
    p.add_argument("--calls", type=int, default=2000)
    p.add_argument("--repeat", type=int, default=3)
    a = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        ops = calls(tmp)
        rows: dict[tuple[str, int], list[tuple[float, float]]] = {}
        for _ in range(a.repeat):
            for n in a.threads:
                stop = threading.Event()
                others = [threading.Thread(target=busy, args=(stop,), daemon=True) for _ in range(n)]
                for t in others:
                    t.start()
                for name, fn in ops.items():
                    # Fewer calls of what costs milliseconds beside busy threads: same medians.
                    rows.setdefault((name, n), []).append(timed(fn, a.calls if n == 0 else max(50, a.calls // 10)))
                stop.set()
                for t in others:
                    t.join()
    now = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    print(f"# bench_gil ({now}, {cpu_model()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
          f"load {os.getloadavg()[0]:.1f})\n")
    print(f"Command: `python benchmarks/bench_gil.py --threads {' '.join(map(str, a.threads))} --calls {a.calls} "
          f"--repeat {a.repeat}`; a {FRAME_BYTES}-byte message; per call, median of {a.repeat} runs.\n")
    head = " | ".join(f"{n} threads: CPU / wall (us)" for n in a.threads)
    print(f"| call | {head} |")
    print("|---|" + "---|" * len(a.threads))
    for name in ops:
        cells = []
        for n in a.threads:
            cpu = statistics.median(c for c, _ in rows[(name, n)])
            wall = statistics.median(w for _, w in rows[(name, n)])
            cells.append(f"{cpu:.1f} / {wall:,.1f}")
        print(f"| {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
