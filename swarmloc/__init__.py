"""swarmloc: the estimation core (pure numpy/scipy; no Zenoh, sockets or threads).

Rooms (docs/design.md has the map and the import rules):
  node.py       the sans-I/O node protocol every estimator implements
  filters/      the one Kalman core, EKF update and covariance intersection
  models/       motion and measurement models, the strapdown INS, vehicle dynamics and controllers
  estimators/   the registry, and one package per family (ukf, ekf, vehicles, nbp, ctl) plus IL
  wire/         every wire type, the codec, frame authentication and input limits
  experiment/   scenario schema and built-in scenarios, faults, the in-process runner, results, plots
  datasets/     loaders of recorded data (MR.CLAM)
  process.py    entry-point plumbing for processes (not imported by the core)
"""

import importlib

__version__ = "0.1.0"


def resolve(path: str):
    """The object a "module:attribute.path" string names (registry factories, node specs)."""
    module, _, attr = path.partition(":")
    obj = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj
