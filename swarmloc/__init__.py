"""swarmloc: the estimation core (pure numpy/scipy; no Zenoh, sockets or threads; the two
process helpers below are for entry points only).

Layout: models (motion and measurement), kalman (the one Kalman core), estimators/ (IL,
UKF-CCL, UKF-DCL), node (the sans-I/O node protocol), messages + wire (every wire type and
the codec), scenario (YAML schema), runner (in-process deterministic runner), results and
plots (the run directory).
"""

import _thread
import importlib
import os
import signal
import sys
import threading

__version__ = "0.1.0"


def resolve(path: str):
    """The object a "module:attribute.path" string names (registry factories, node specs)."""
    module, _, attr = path.partition(":")
    obj = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


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
