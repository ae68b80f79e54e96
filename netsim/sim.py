"""The environment as pure code: world, radio and faults, with no transport.

The netsim process wraps this in Zenoh; the in-process runner (swarmloc.runner) drives it
directly. Both therefore see the same trajectories, sensor noise and link decisions.
"""

from __future__ import annotations

import logging
from collections import Counter

import numpy as np

from netsim.world import World
from swarmloc.scenario import Scenario

log = logging.getLogger(__name__)


class Simulation:
    def __init__(self, scenario: Scenario, seed: int | None = None):
        self.sc = scenario
        self.world = World(scenario, seed)
        self.ids = scenario.agent_ids
        self.steps = self.world.steps
        self.cut: set[frozenset[int]] = set()
        self.timeline = sorted(scenario.faults, key=lambda f: f.at)
        self.fault_log: list[dict] = []  # every fault applied, for the run directory
        self.delivered: Counter[tuple[int, int]] = Counter()
        self.dropped: Counter[tuple[int, int, str]] = Counter()
        self.radio_log: list[tuple[int, int, int, int, str]] = []  # (k, src, receiver, size, drop reason or "")
        self.k, self.t = -1, 0.0

    # ---------------------------------------------------------------- clock

    def tick(self, live_faults=()):
        """Advance one tick; scenario and live faults take effect for this tick's frames."""
        frames = self.world.step()
        self.k, self.t = self.world.k, self.world.t
        while self.timeline and self.timeline[0].at <= self.t:
            f = self.timeline.pop(0)
            self.apply(f.action, f.link, source="scenario")
        for action, link in live_faults:
            self.apply(action, link, source="live")
        return self.k, self.t, frames

    def truth(self) -> dict[int, np.ndarray]:
        return self.world.positions()

    # ---------------------------------------------------------------- faults

    def apply(self, action: str, link, source: str = "live") -> None:
        a, b = (int(x) for x in link)
        if a not in self.ids or b not in self.ids or a == b:
            raise ValueError(f"no link {a}-{b} in this swarm (agents {self.ids})")
        pair = frozenset((a, b))
        if action == "cut":
            self.cut.add(pair)
        elif action == "restore":
            self.cut.discard(pair)
        else:
            raise ValueError(f"unknown fault action {action!r}")
        self.fault_log.append({"k": self.k, "t": self.t, "action": action, "link": [a, b], "source": source})
        log.info("fault %s %s-%s at t=%.1f (%s)", action, a, b, self.t, source)

    # ---------------------------------------------------------------- radio

    def link_state(self, a: int, b: int) -> tuple[bool, float, str]:
        """(up, distance, reason if down) for the unit-disk radio and the active faults."""
        pos = self.world.pos
        dist = float(np.linalg.norm(pos[a] - pos[b]))
        if frozenset((a, b)) in self.cut:
            return False, dist, "fault"
        if dist > self.sc.radio.range:
            return False, dist, "distance"
        return True, dist, ""

    def route(self, src: int, dst: int | None, size: int, t: float) -> list[tuple[int, float]]:
        targets = [dst] if dst is not None else [a for a in self.ids if a != src]
        out = []
        for r in targets:
            if r not in self.world.pos:
                self.dropped[(src, r, "unknown")] += 1
                continue
            up, _, reason = self.link_state(src, r)
            self.radio_log.append((self.k, src, r, size, reason))
            if up:
                self.delivered[(src, r)] += 1
                out.append((r, t + self.sc.radio.latency))
            else:
                self.dropped[(src, r, reason)] += 1
        return out

    def link_table(self) -> list[dict]:
        rows = []
        for i, a in enumerate(self.ids):
            for b in self.ids[i + 1:]:
                up, dist, reason = self.link_state(a, b)
                dropped = sum(n for (s, r, _), n in self.dropped.items() if {s, r} == {a, b})
                delivered = self.delivered[(a, b)] + self.delivered[(b, a)]
                rows.append({"a": a, "b": b, "up": up, "distance": dist, "reason": reason,
                             "delivered": delivered, "dropped": dropped})
        return rows

    def radio_arrays(self) -> dict[str, np.ndarray]:
        """Every frame reception attempt, for radio.npz (docs/run-format.md)."""
        rows = self.radio_log
        return {
            "k": np.array([r[0] for r in rows], np.int64), "src": np.array([r[1] for r in rows], np.int64),
            "receiver": np.array([r[2] for r in rows], np.int64), "size": np.array([r[3] for r in rows], np.int64),
            "delivered": np.array([r[4] == "" for r in rows], bool), "reason": np.array([r[4] for r in rows], dtype="U16"),
            "fault_t": np.array([f["t"] for f in self.fault_log], float),
            "fault_action": np.array([f["action"] for f in self.fault_log], dtype="U16"),
            "fault_link": np.array([f["link"] for f in self.fault_log], np.int64).reshape(-1, 2),
        }

    def radio_summary(self) -> dict:
        reasons: Counter[str] = Counter()
        for (_, _, why), n in self.dropped.items():
            reasons[why] += n
        return {"delivered": sum(self.delivered.values()), "dropped": dict(reasons)}
