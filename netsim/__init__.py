"""netsim: the emulated environment (world truth, sensors, radio channel, faults, clock)."""
