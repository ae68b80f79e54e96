"""netsim: the emulated environment (world truth, sensors, radio channel, faults, clock)."""

import gc


def tune_gc() -> None:
    """Garbage collection for the netsim process, called once its imports are done.

    Routing allocates a short-lived object per delivery (the RadioRx the server puts), none of
    them in a reference cycle, and Python's cyclic collector, run every 700 allocations by
    default, rescanned everything alive each time: a fifth of a 32-agent round. Freezing what
    the imports created and collecting every 50,000 allocations keeps cycles collected while
    routing stops paying for them (docs/benchmarks.md, target 3)."""
    gc.freeze()
    gc.set_threshold(50_000, 20, 100)
