"""What the EKF family's estimators share: how a filter refuses an input, the plausibility bounds
of anything a peer or a sensor hands it, the tick rule of CI beacons, and the fusion-centre role
(ekf-centre on UAS, ekf-cl on vehicles)."""

from __future__ import annotations

import math

import numpy as np


class RejectedInput(ValueError):
    """An input the filter refuses, leaving its estimate as it was: `reason` is the drop counter
    the node bumps ("malformed" or "non-finite")."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason, self.detail = reason, detail


def guarded(node, what: str, action, *args):
    """action(*args), one filter input of `node`: its result, or None if it was refused or
    failed numerically, which the node counts as a drop and which changes nothing."""
    try:
        return action(*args)
    except RejectedInput as exc:
        node.drop(exc.reason, f"{what}: {exc.detail}")
    except np.linalg.LinAlgError as exc:
        node.drop("numerical", f"{what}: {exc}")
    return None


def checked(a, shape: tuple, what: str) -> np.ndarray:
    """a as a float array of this shape (None: any length on that axis), all finite."""
    try:
        arr = np.asarray(a, dtype=float)
    except (TypeError, ValueError):
        raise RejectedInput("malformed", f"{what}: not numeric") from None
    if arr.ndim != len(shape) or any(s is not None and n != s for n, s in zip(arr.shape, shape)):
        raise RejectedInput("malformed", f"{what}: shape {arr.shape}, want {shape}")
    if not np.all(np.isfinite(arr)):
        raise RejectedInput("non-finite", what)
    return arr


def checked_std(s, what: str, optional: bool = False) -> float | None:
    if s is None and optional:
        return None
    try:
        s = float(s)
    except (TypeError, ValueError):
        raise RejectedInput("malformed", f"{what}: not a number") from None
    if not math.isfinite(s):
        raise RejectedInput("non-finite", what)
    if s <= 0.0:
        raise RejectedInput("malformed", f"{what} = {s}: a std must be positive")
    return s


def checked_covariance(P, n: int, what: str) -> np.ndarray:
    """P as a symmetric positive semi-definite n x n matrix (rounding asymmetry removed)."""
    P = checked(P, (n, n), what)
    if not np.allclose(P, P.T, rtol=1e-9, atol=1e-12):
        raise RejectedInput("malformed", f"{what}: not symmetric")
    P = 0.5 * (P + P.T)
    # Semi-definite is allowed (a perfectly known bias); a clearly negative direction is not.
    if np.linalg.eigvalsh(P)[0] < -1e-9 * max(1.0, float(np.abs(P).max())):
        raise RejectedInput("malformed", f"{what}: not positive semi-definite")
    return P


MAX_HELD = 256  # early beacons kept; a neighbour far ahead cannot fill our memory


def beacon_timing(node, src: int, msg) -> list | None:
    """The tick rule of a CI node's beacons (node: k, held, stats, drop): None for a beacon of
    the node's current tick, to be fused now; otherwise what the node answers (a drop: its own,
    malformed or stale; [] for an early one, held until the node steps to its tick)."""
    if src == node.id:
        return node.drop("malformed", "own beacon")
    try:
        k = int(msg.k)
    except (TypeError, ValueError):
        return node.drop("malformed", f"beacon tick {msg.k!r}")
    if k < node.k:
        return node.drop("stale", f"beacon of tick {k} from {src} at tick {node.k}")
    if k > node.k:
        if len(node.held) >= MAX_HELD:
            return node.drop("held-overflow", f"beacon of tick {k} from {src}")
        node.held.append((src, msg))
        node.stats["held"] += 1
        return []
    return None


def release_held(node) -> list:
    """Handle the beacons held for the tick the node has just stepped to."""
    out, (held, node.held) = [], (node.held, [])
    for src, beacon in held:
        out += node.receive(src, beacon)
    return out


MAX_ABS = 1e9
"""Largest magnitude accepted in any number of a datum or an estimate (m, m/s, rad, m^2...):
far beyond any real value (GNSS satellites are 2.7e7 m away), near enough that the joint
arithmetic cannot overflow."""


MIN_STD = 1e-6
"""Smallest measurement std accepted (m): a thousandth of the best relative sensor's, large
enough that no innovation covariance of the joint update can be singular."""


GROUND_STATION = "ground-station"
RUN = "run"
"""The centre's timer tag: run the pending tick."""


def centre_id(scenario, settings) -> int:
    """The fusion centre's agent: settings.centre, or the scenario's only ground station."""
    stations = [a.id for a in scenario.world.agents if a.model == GROUND_STATION]
    if settings.centre is not None:
        if settings.centre not in stations:
            raise ValueError(f"ekf-centre: centre {settings.centre} is not a {GROUND_STATION} agent "
                             f"(ground stations: {stations})")
        return settings.centre
    if len(stations) != 1:
        raise ValueError(f"ekf-centre needs one {GROUND_STATION} agent to run the fusion centre, the scenario has "
                         f"{len(stations)}{' ' + str(stations) if stations else ''}; name one with params.centre")
    return stations[0]


def bounded(a: np.ndarray, what: str) -> np.ndarray:
    if a.size and float(np.abs(a).max()) > MAX_ABS:
        raise RejectedInput("implausible", f"{what}: magnitude beyond {MAX_ABS:g}")
    return a


def plausible_std(v, what: str, optional: bool = False) -> None:
    v = checked_std(v, what, optional)
    if v is not None and not MIN_STD <= v <= MAX_ABS:
        raise RejectedInput("implausible", f"{what} = {v:g} outside [{MIN_STD:g}, {MAX_ABS:g}]")
