"""Entry-point plumbing for the processes swarmloc starts (agents, netsim, study workers, the CLI):
one BLAS thread, SIGTERM handling, the console a command prints on.

Not part of the estimation core: nothing under swarmloc/ imports this module (the import test
checks it). It lives here because agents/ and netsim/ both need it and may not import each other.
"""

import _thread
import ctypes
import functools
import os
import signal
import sys
import threading

PR_SET_PDEATHSIG = 1
# Resolved here, not in the forked child, where only the call itself should run.
_prctl = ctypes.CDLL(None, use_errno=True).prctl if sys.platform.startswith("linux") else None


def _die_with(parent: int) -> None:
    _prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM))
    if os.getppid() != parent:  # the parent died before prctl took effect
        os._exit(1)


def die_with_parent():
    """A preexec_fn for subprocess.Popen: the child gets SIGTERM when this process dies, however
    it dies (kill -9 included); None where there is no prctl (not Linux).

    The kernel sends it when the thread that forked the child exits, so spawn such children
    from the main thread only."""
    return functools.partial(_die_with, os.getpid()) if _prctl is not None else None


def pin_blas() -> None:
    """One BLAS thread per process, unless the environment says otherwise. Call it before
    numpy is imported (every entry point's first line): dozens of agent processes share two
    cores, and a BLAS thread pool per process only spins and steals them (measured: 7 ms per
    4x4 triangular solve with the default pool)."""
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def exit_on_sigterm(grace: float = 2.0) -> None:
    """Entry-point plumbing for the agent and netsim processes: SIGTERM (from a launcher, a
    parent-death signal or a service manager) exits with 143 through the normal clean-up, and
    if that hangs (closing a Zenoh session whose peer is going down too) the process ends anyway
    after `grace` seconds. Call it before any thread starts.

    A Python signal handler alone is not enough: the kernel hands a process-directed signal to
    any thread that does not block it, usually one of Zenoh's, and the main thread, asleep in an
    untimed wait, never runs the handler. So SIGTERM is blocked here (threads started later
    inherit the mask) and one thread takes it with sigwait, starts the watchdog first and then
    raises the exit in the main thread."""

    def handler(*_):
        sys.exit(143)

    def waiter():
        signal.sigwait({signal.SIGTERM})
        watchdog = threading.Timer(grace, os._exit, (143,))
        watchdog.daemon = True
        watchdog.start()
        _thread.interrupt_main(signal.SIGTERM)

    signal.signal(signal.SIGTERM, handler)
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    threading.Thread(target=waiter, name="sigterm", daemon=True).start()


# Wide enough for any table swarmloc prints: rich lays a table out at its natural width when
# it fits, so nothing is folded or cut with "…".
PIPE_WIDTH = 100_000


def console(stderr: bool = False):
    """The rich Console a command prints on. On a terminal, rich's own (the terminal's width,
    colours, live progress). To a pipe or a file, no width limit (soft_wrap: a line is never
    folded either), so what reaches a script or a log is complete: rich would otherwise lay
    everything out for 80 columns and cut table cells to fit."""
    from rich.console import Console

    c = Console(stderr=stderr)
    return c if c.is_terminal else Console(stderr=stderr, width=PIPE_WIDTH, soft_wrap=True)


def process_tree(pid: int) -> list[int]:
    """pid and all its descendants, from /proc (Linux): what a run started, for the benchmarks'
    and tests' memory and CPU figures of a whole swarm."""
    from pathlib import Path

    children: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):  # gone meanwhile, or not readable
                continue
            children.setdefault(ppid, []).append(int(d.name))
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo.extend(children.get(p, []))
    return out
