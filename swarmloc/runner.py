"""In-process deterministic runner: the same node objects, an event queue instead of Zenoh.

The environment (world truth, sensors, radio) is passed in; netsim.sim.Simulation is the one
swarmloc ships. Frames go through the real wire codec, so what a node receives here is
bit-for-bit what it would receive from the agent daemon.
"""

from __future__ import annotations

import heapq
import logging
from typing import Callable, Iterable, Protocol

import numpy as np

from swarmloc import wire
from swarmloc.messages import LinkNack, Sensors
from swarmloc.node import Node, Outbox
from swarmloc.results import RunRecord

log = logging.getLogger(__name__)


class Environment(Protocol):
    ids: list[int]
    steps: int

    def tick(self) -> tuple[int, float, dict[int, Sensors]]:
        """Advance one tick; every agent's sensor frame."""

    def truth(self) -> dict[int, np.ndarray]:
        """True states now."""

    def route(self, src: int, dst: int | None, size: int, t: float) -> list[tuple[int, float]]:
        """Receivers of a frame sent at time t, each with its arrival time; lost frames are absent."""


class InProcessRunner:
    def __init__(self, env: Environment, nodes: dict[int, Node], max_events_per_tick: int = 200_000):
        self.env, self.nodes = env, nodes
        self.max_events = max_events_per_tick
        self.outbox = {a: Outbox(a) for a in nodes}
        self.frames = 0

    def run(self, record: RunRecord | None = None, on_tick: Callable[[int, dict[int, Sensors]], None] | None = None) -> RunRecord:
        record = record or RunRecord(sorted(self.nodes), next(iter(self.nodes.values())).model.state_dim)
        for _ in range(self.env.steps + 1):
            k, t, frames = self.env.tick()
            queue: list = []
            order = 0
            for a in sorted(self.nodes):
                for send in self.nodes[a].step(frames[a]):
                    order = self._transmit(queue, a, send, t, order)
            events = 0
            while queue:
                t_arr, _, dst, data = heapq.heappop(queue)
                env = wire.decode(data)
                if isinstance(env.body, LinkNack):
                    failed = self.outbox[dst].failed(env.body)
                    sends = self.nodes[dst].link_failed(failed.dst, failed.msg) if failed else []
                else:
                    sends = self.nodes[dst].receive(env.src, env.body)
                for send in sends:
                    order = self._transmit(queue, dst, send, t_arr, order)
                events += 1
                if events > self.max_events:
                    raise RuntimeError(f"tick {k}: more than {self.max_events} radio events (livelock?)")
            record.add_tick(k, t, frames, self.env.truth())
            for a, node in self.nodes.items():
                record.add_estimate(node.algorithm, a, node.estimate())
            if on_tick:
                on_tick(k, frames)
        return record

    def _transmit(self, queue, src, send, t, order) -> int:
        outbox = self.outbox[src]
        data = outbox.encode(send)
        self.frames += 1
        receivers = self.env.route(src, send.dst, len(data), t)
        for receiver, t_arr in receivers:
            if receiver in self.nodes:
                heapq.heappush(queue, (t_arr, order, receiver, data))
                order += 1
        if send.dst is not None and not receivers:
            nack = wire.encode(LinkNack(outbox.seq, send.dst, "unreachable"), 0, outbox.seq)
            heapq.heappush(queue, (t, order, src, nack))
            order += 1
        return order


def make_nodes(algorithm: str, scenario, ids: Iterable[int] | None = None) -> dict[int, Node]:
    """One node per agent with the scenario's known start and initial uncertainty."""
    from swarmloc.estimators import NODE_TYPES

    cls = NODE_TYPES[algorithm]
    est = scenario.estimation
    nodes = {}
    for a in ids or scenario.agent_ids:
        spec = scenario.agent(a)
        d = len(spec.start)
        P0 = np.eye(d) * est.initial_std**2
        kwargs = {"spread": est.spread} if algorithm == "ukf-dcl" else {}
        nodes[a] = cls(a, np.array(spec.start, float), P0, spec.model, **kwargs)
    return nodes
