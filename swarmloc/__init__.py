"""swarmloc: the estimation core (pure numpy/scipy; no Zenoh, sockets or threads).

Layout: models (motion and measurement), kalman (the one Kalman core), estimators/ (IL,
UKF-CCL, UKF-DCL), node (the sans-I/O node protocol), messages + wire (every wire type and
the codec), scenario (YAML schema), runner (in-process deterministic runner), results and
plots (the run directory).
"""

__version__ = "0.1.0"
