"""Estimators: each is a sans-I/O Node (distributed) or a batch reference over a sensor stream."""

from swarmloc.estimators.il import IndependentNode
from swarmloc.estimators.ukf_ccl import CentralizedUKF
from swarmloc.estimators.ukf_dcl import UkfDclNode

NODE_TYPES = {IndependentNode.algorithm: IndependentNode, UkfDclNode.algorithm: UkfDclNode}

__all__ = ["IndependentNode", "UkfDclNode", "CentralizedUKF", "NODE_TYPES"]
