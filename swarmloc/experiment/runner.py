"""In-process deterministic runner: the same node objects, an event queue instead of Zenoh.

The environment (world truth, sensors, radio) is passed in; netsim.sim.Simulation is the one
swarmloc ships. Frames go through the real wire codec, so what a node receives here is
bit-for-bit what it would receive from the agent daemon.
"""

from __future__ import annotations

import logging
from typing import Callable, Iterable, Protocol

import numpy as np

from swarmloc import wire
from swarmloc.experiment.results import RunRecord
from swarmloc.models.motion import platform_model
from swarmloc.node import Node, Outbox, RadioRx, RadioTx, Timers, estimate_of
from swarmloc.wire.messages import Sensors

log = logging.getLogger(__name__)


class Environment(Protocol):
    """What the runner needs from a world (netsim.sim.Simulation is the one swarmloc ships)."""

    ids: list[int]
    steps: int

    def tick(self) -> tuple[int, float, dict[int, Sensors]]:
        """Advance one tick; every agent's sensor frame."""

    def truth(self) -> dict[int, np.ndarray]:
        """True states now."""

    def targets(self) -> dict[int, np.ndarray]:
        """True target positions now ({} without targets)."""

    def exchange(self, frames: list) -> list:
        """One lockstep round: frames (src, dst, seq, data) in, deliveries (receiver, t, data | nack) out."""

    def command(self, aid: int, u) -> str | None:
        """A vehicle's actuator command, in force from the next tick (closed loop)."""


class InProcessRunner:
    """Lockstep in rounds, exactly as the netsim process runs it: every frame the nodes send in
    reaction to one round of deliveries forms the next round."""

    def __init__(self, env: Environment, nodes: dict[int, Node], max_rounds_per_tick: int = 10_000):
        self.env, self.nodes = env, nodes
        self.max_rounds = max_rounds_per_tick
        self.outbox = {a: Outbox(a) for a in nodes}
        self.timers = {a: Timers() for a in nodes}
        self.frames = 0
        self.t = 0.0

    def run(self, record: RunRecord | None = None,
            on_tick: Callable[[int, dict[int, Sensors]], None] | None = None) -> RunRecord:
        record = record or RunRecord([a for a, n in self.nodes.items() if n.model.state_dim > 0],
                                     {a: platform_model(n.model) for a, n in self.nodes.items() if n.model.state_dim > 0})
        for _ in range(self.env.steps + 1):
            k, t, frames = self.env.tick()
            self.t = t
            sent = []
            for a in sorted(self.nodes):
                node, tags = self.nodes[a], self.timers[a].pop_due(t)
                actions = [x for tag in tags for x in node.on_timer(tag, t)]  # Timer: lockstep semantics
                if tags:
                    # A timer may have finished the last tick's estimate: the agent daemon
                    # publishes it before it steps, and netsim records it for that tick.
                    record.add_estimate(node.algorithm, a, estimate_of(node))
                # A recorded world may have no frame for an agent in a tick: it steps on nothing.
                sent += self._encode(a, actions + (node.step(frames[a]) if frames[a] is not None else []))
            rounds = 0
            while sent:
                rounds += 1
                if rounds > self.max_rounds:
                    raise RuntimeError(f"tick {k}: more than {self.max_rounds} radio rounds (livelock?)")
                sent = [tx for rx in self.env.exchange(sent) if rx.receiver in self.nodes
                        for tx in self._encode(rx.receiver, self._deliver(rx))]
            record.add_tick(k, t, {a: f if f is not None else Sensors(k, t, None, []) for a, f in frames.items()},
                            self.env.truth(), self.env.targets())
            for a, node in self.nodes.items():
                record.add_estimate(node.algorithm, a, estimate_of(node))
            self._command()
            if on_tick:
                on_tick(k, frames)
        return record



    def _command(self) -> None:
        """Each closed-loop node's command from its final estimate of the tick, through the wire
        codec, to the world: netsim applies the last command an agent published before its
        final `done` of the tick, which is this one."""
        for a in sorted(self.nodes):
            ask = getattr(self.nodes[a], "command", None)  # a stand-in (a dead agent) is no Node
            cmd = ask() if ask is not None else None
            if cmd is not None:
                self.env.command(a, wire.decode(wire.encode(cmd, a, 1)).body.u)

    def _deliver(self, rx: RadioRx) -> list:
        node = self.nodes[rx.receiver]
        if rx.nack is not None:
            failed = self.outbox[rx.receiver].failed(rx.nack)
            return node.link_failed(failed.dst, failed.msg) if failed else []
        env = wire.decode(rx.data)
        return [] if env.src == rx.receiver else node.receive(env.src, env.body)

    def _encode(self, src: int, actions) -> list[RadioTx]:
        sends = self.timers[src].split(actions, self.t)
        txs = [tx for s in sends if (tx := self.outbox[src].encode(s)) is not None]
        self.frames += len(txs)
        return txs


def make_nodes(algorithm: str, scenario, ids: Iterable[int] | None = None) -> dict[int, Node]:
    """One node per agent with the scenario's prior (Scenario.prior)."""
    from swarmloc.estimators import make_nodes as make

    return make(algorithm, scenario, ids)
