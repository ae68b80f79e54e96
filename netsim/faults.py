"""The faults in force during a run, and the questions the radio asks about them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from swarmloc.experiment.faults import (
    ClearLoss,
    CommandOff,
    CommandOn,
    Cut,
    FaultError,
    GnssOff,
    GnssOn,
    Heal,
    JammerOff,
    JammerOn,
    Kill,
    Loss,
    Partition,
    RadioOff,
    RadioOn,
    Restart,
    Restore,
    _Fault,
    inverse_of,
    nodes_named,
)


@dataclass
class Active:
    id: int
    fault: _Fault
    since: float
    until: float | None

    def describe(self) -> dict:
        args = self.fault.model_dump(mode="json", exclude={"action", "duration", "at"}, exclude_none=True)
        return {"id": self.id, "action": self.fault.action, "args": args, "since": self.since, "until": self.until}


BLOCK_REASONS: tuple[str | None, ...] = (None, "radio-off", "fault", "partition")
"""What the codes of FaultState.blocked_matrix stand for."""


class FaultState:
    """The faults in force and the questions the radio asks about them."""

    def __init__(self, ids: list[int]):
        self.ids = list(ids)
        self.active: list[Active] = []
        self.log: list[dict] = []  # every fault applied or cleared, for the run directory
        self._next = 1
        self.version = 0  # bumped by every change, so answers over all pairs are computed once per change
        self._matrices: tuple[int, NDArray[np.int8], NDArray[np.float64]] | None = None

    # ---------------------------------------------------------------- changes

    def apply(self, f: _Fault, t: float, k: int, source: str) -> None:
        unknown = [a for a in nodes_named(f) if a not in self.ids]
        if unknown:
            raise FaultError(f"{f.action}: unknown agents {unknown} (agents are {self.ids})")
        inv = inverse_of(f)
        if inv is None:  # a clearing action: drop what it clears
            self.active = [a for a in self.active if not _clears(f, a.fault)]
        else:
            if f.action in ("partition", "jammer"):  # one partition, one jammer per name
                self.active = [a for a in self.active if not _clears(inv, a.fault)]
            until = t + f.duration if f.duration else None
            self.active.append(Active(self._next, f, t, until))
            self._next += 1
        self.log.append({"k": k, "t": t, "source": source, **f.model_dump(mode="json", exclude_none=True, exclude={"at"})})
        self.version += 1

    def due(self, t: float) -> list[_Fault]:
        """Inverses of faults whose duration has run out by time t."""
        out = []
        for a in self.active:
            if a.until is not None and a.until <= t + 1e-9:
                out.append(inverse_of(a.fault))
        return out

    def clear(self, fault_id: int, t: float, k: int) -> _Fault:
        for a in self.active:
            if a.id == fault_id:
                inv = inverse_of(a.fault)
                self.apply(inv, t, k, "live")
                return inv
        raise FaultError(f"no active fault {fault_id}; active: {[a.id for a in self.active]}")

    def describe(self) -> list[dict]:
        return [a.describe() for a in self.active]

    def _of(self, cls):
        return [a.fault for a in self.active if isinstance(a.fault, cls)]

    # ---------------------------------------------------------------- questions

    def blocked(self, src: int, dst: int) -> str | None:
        """Why a frame from src cannot reach dst whatever the physics, or None."""
        off = {f.node for f in self._of(RadioOff)}
        if src in off or dst in off:
            return "radio-off"
        for f in self._of(Cut):
            a, b = f.link
            if (src, dst) == (a, b) or (f.direction == "both" and (src, dst) == (b, a)):
                return "fault"
        for f in self._of(Partition):
            if _side(f, src) != _side(f, dst):
                return "partition"
        return None

    def extra_loss(self, src: int, dst: int) -> float:
        keep = 1.0
        for f in self._of(Loss):
            if (f.node is None and f.link is None) or f.node in (src, dst) or (f.link and {src, dst} == set(f.link)):
                keep *= 1.0 - f.probability
        return 1.0 - keep

    def blocked_matrix(self) -> NDArray[np.int8]:
        """blocked(ids[i], ids[j]) for every pair, as codes into BLOCK_REASONS."""
        return self._pairs()[1]

    def loss_matrix(self) -> NDArray[np.float64]:
        """extra_loss(ids[i], ids[j]) for every pair."""
        return self._pairs()[2]

    def _pairs(self) -> tuple[int, NDArray[np.int8], NDArray[np.float64]]:
        if self._matrices is None or self._matrices[0] != self.version:
            self._matrices = (self.version, self._blocked_codes(), 1.0 - self._keep())
        return self._matrices

    def _blocked_codes(self) -> NDArray[np.int8]:
        # Written from the weakest reason to the strongest, so each pair ends with the one blocked() gives.
        index = {a: i for i, a in enumerate(self.ids)}
        n = len(self.ids)
        codes = np.zeros((n, n), np.int8)
        for f in self._of(Partition):
            side = np.array([_side(f, a) for a in self.ids])
            codes[side[:, None] != side[None, :]] = BLOCK_REASONS.index("partition")
        for f in self._of(Cut):
            a, b = (index[v] for v in f.link)
            codes[a, b] = BLOCK_REASONS.index("fault")
            if f.direction == "both":
                codes[b, a] = BLOCK_REASONS.index("fault")
        off = np.isin(self.ids, [f.node for f in self._of(RadioOff)])
        codes[off[:, None] | off[None, :]] = BLOCK_REASONS.index("radio-off")
        return codes

    def _keep(self) -> NDArray[np.float64]:
        index = {a: i for i, a in enumerate(self.ids)}
        n = len(self.ids)
        keep = np.ones((n, n))
        for f in self._of(Loss):
            hit = np.zeros((n, n), bool)
            if f.node is None and f.link is None:
                hit[:] = True
            if f.node is not None and f.node in index:
                hit[index[f.node], :] = hit[:, index[f.node]] = True
            if f.link and len(set(f.link)) == 2:
                a, b = (index[v] for v in f.link)
                hit[a, b] = hit[b, a] = True
            keep[hit] *= 1.0 - f.probability
        return keep

    def jammers(self, t: float) -> list[tuple[JammerOn, np.ndarray]]:
        """Active jammers with their position at time t (moving ones move from where they started)."""
        out = []
        for a in self.active:
            if isinstance(a.fault, JammerOn):
                f = a.fault
                out.append((f, np.array(f.position) + (t - a.since) * np.array(f.velocity)))
        return out

    def gnss_ok(self, node: int) -> bool:
        return node not in {f.node for f in self._of(GnssOff)}

    def command_ok(self, node: int) -> bool:
        return node not in {f.node for f in self._of(CommandOff)}

    def killed(self) -> set[int]:
        return {f.node for f in self._of(Kill)}


def _side(p: Partition, node: int) -> int:
    for i, g in enumerate(p.groups):
        if node in g:
            return i
    return -1


def _clears(clearing: _Fault, f: _Fault) -> bool:
    match clearing:
        case Restore():
            return isinstance(f, Cut) and set(f.link) == set(clearing.link)
        case RadioOn():
            return isinstance(f, RadioOff) and f.node == clearing.node
        case Heal():
            return isinstance(f, Partition)
        case ClearLoss():
            return isinstance(f, Loss) and f.node == clearing.node and (
                (f.link is None and clearing.link is None) or (f.link and clearing.link and set(f.link) == set(clearing.link)))
        case JammerOff():
            return isinstance(f, JammerOn) and f.name == clearing.name
        case GnssOn():
            return isinstance(f, GnssOff) and f.node == clearing.node
        case CommandOn():
            return isinstance(f, CommandOff) and f.node == clearing.node
        case Restart():
            return isinstance(f, Kill) and f.node == clearing.node
    return False
