"""The sans-I/O node protocol every estimator implements.

A node is a state machine: it is handed a tick (the agent's sensor frame) or a radio message,
and returns the radio messages it wants sent. It never opens a socket, starts a thread or
reads a clock, so the same object runs in the in-process runner and in the agent daemon.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections import Counter, OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np

from swarmloc import resolve, wire
from swarmloc.models.motion import MOTION_MODELS, MotionModel, Odometry
from swarmloc.wire.messages import LinkNack, Sensors

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class NodeSpec:
    """One agent's node as plain values: "module:Class" and its constructor's keyword arguments.

    The launcher, which has the scenario, writes it (`REGISTRY[name].node_spec`); the agent
    process builds its node from it (`swarmloc agent --spec FILE`) without parsing a scenario.
    JSON, with numpy arrays as {"array": nested lists} and frozen dataclasses as
    {"dataclass": "module:Class", "fields": {...}}; floats round-trip exactly (repr)."""

    factory: str
    kwargs: dict

    @classmethod
    def of(cls, node_cls: type, **kwargs) -> "NodeSpec":
        return cls(f"{node_cls.__module__}:{node_cls.__qualname__}", kwargs)

    def with_(self, **kwargs) -> "NodeSpec":
        """The same node with some constructor arguments added or replaced (a subclass's own)."""
        return NodeSpec(self.factory, {**self.kwargs, **kwargs})

    def build(self) -> "Node":
        return resolve(self.factory)(**{k: _decode(v) for k, v in self.kwargs.items()})

    def dumps(self) -> str:
        return json.dumps({"factory": self.factory, "kwargs": {k: _encode(v) for k, v in self.kwargs.items()}})

    @classmethod
    def loads(cls, text: str) -> "NodeSpec":
        d = json.loads(text)
        if not isinstance(d, dict) or not isinstance(d.get("factory"), str) or not isinstance(d.get("kwargs"), dict):
            raise ValueError("a node spec is {\"factory\": \"module:Class\", \"kwargs\": {...}}")
        if not d["factory"].startswith("swarmloc."):
            raise ValueError(f"node spec factory {d['factory']!r} is not a swarmloc class")
        return cls(d["factory"], d["kwargs"])


def _encode(v):
    if isinstance(v, np.ndarray):
        return {"array": v.tolist()}
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return {"dataclass": f"{type(v).__module__}:{type(v).__qualname__}",
                "fields": {f.name: _encode(getattr(v, f.name)) for f in dataclasses.fields(v)}}
    if isinstance(v, (list, tuple)):
        return [_encode(x) for x in v]
    if isinstance(v, dict):
        raise TypeError("node spec values are numbers, strings, lists, arrays or dataclasses, not maps")
    return v


def _decode(v):
    if isinstance(v, dict):
        if "array" in v:
            return np.array(v["array"], dtype=float)
        if not str(v.get("dataclass", "")).startswith("swarmloc."):
            raise ValueError(f"node spec: unknown value {v!r}")
        return resolve(v["dataclass"])(**{k: _decode(x) for k, x in v["fields"].items()})
    if isinstance(v, list):
        return [_decode(x) for x in v]
    return v


@dataclass(frozen=True)
class Send:
    """A radio message to `dst`, or to every neighbour in range when dst is None."""

    msg: Any
    dst: int | None = None


@dataclass(frozen=True)
class Timer:
    """Returned among a node's sends: call `on_timer(tag, t)` once `delay` seconds have passed.

    Lockstep: modelled time, deterministic. The timer fires at the start of the first tick whose
    time t is at least (time of the tick it was set in) + delay, before that tick's sensor frame.
    Real time: wall time, the clock's speed applied. Setting a tag again replaces its timer."""

    delay: float
    tag: str


@dataclass(frozen=True)
class Estimate:
    k: int
    mean: np.ndarray
    cov: np.ndarray
    nis: tuple = ()  # (NIS, dof) of each innovation the estimator formed in tick k
    targets: tuple = ()  # (target id, mean, cov) of each target the estimator localizes


def estimate_of(node) -> Estimate:
    """A node's estimate with the NIS values of its current tick (`node.nis`, where it has them)."""
    e = node.estimate()
    nis = tuple(getattr(node, "nis", ()) or ())
    return dataclasses.replace(e, nis=nis) if nis else e


# Kinds of relative measurement, in the order a measurer's measurements of one tick apply.
RANGE, RANGE_BEARING, LANDMARK = 0, 1, 2


def keyed_measurements(measurer: int, sensors: Sensors):
    """(key, message) for each relative measurement of a sensor frame, key = (measurer, kind,
    target, q): kind RANGE (sensors.ranges), RANGE_BEARING (sensors.rb, target an agent) or
    LANDMARK (sensors.landmarks, target a landmark id), q counting earlier measurements of the
    frame of the same kind and target. A tick's measurements apply in key order, in a
    distributed chain and in the centralized reference alike: updates do not commute. Among
    ranges this is the (measurer, measured, q) order of a swarm that only ranges."""
    for kind, items in ((RANGE, sensors.ranges), (RANGE_BEARING, sensors.rb), (LANDMARK, sensors.landmarks)):
        counts: dict[int, int] = {}
        for r in items:
            q = counts.get(r.target, 0)
            counts[r.target] = q + 1
            yield (measurer, kind, r.target, q), r


def odometry_of(s: Sensors) -> Odometry:
    o = s.odometry
    return Odometry(o.dt, o.speed, o.heading, o.speed_std, o.heading_std, o.turn_rate, o.turn_rate_std)


class Node:
    """Base class: identity, model, estimate and the drop counter shared by every algorithm."""

    algorithm: str = ""
    # Whether a tick is over for everyone when the next one starts (lockstep: the emulator
    # waits until the swarm is quiet). The driver says so; with a real-time or physical clock a
    # frame of the last tick may still be on its way.
    synchronous: bool = True

    def __init__(self, aid: int, x0, P0, model: MotionModel | str = "planar-speed-heading"):
        self.id = int(aid)
        self.model = MOTION_MODELS[model] if isinstance(model, str) else model
        self.k = -1
        self.x = np.array(x0, dtype=float)
        self.P = np.array(P0, dtype=float)
        if self.x.shape != (self.model.state_dim,) or self.P.shape != (self.model.state_dim,) * 2:
            raise ValueError(f"x0/P0 do not match {self.model.name} (state_dim {self.model.state_dim})")
        self.drops: Counter[str] = Counter()

    @classmethod
    def spec(cls, scenario, aid: int, settings=None) -> NodeSpec:
        """The node of agent `aid` as the scenario configures it (the estimator registry's factory)."""
        x0, P0 = scenario.prior(aid)
        return NodeSpec.of(cls, aid=aid, x0=x0, P0=P0, model=scenario.agent(aid).model)

    def on_timer(self, tag: str, t: float) -> list:
        """A Timer this node set has expired; t is the current time (modelled or wall, s)."""
        return []

    def step(self, sensors: Sensors) -> list[Send]:
        """Handle the sensor frame of tick sensors.k (time update first, then measurements)."""
        raise NotImplementedError

    def receive(self, src: int, msg: Any) -> list[Send]:
        """Handle a radio message from `src`. Never raises on bad content: it counts a drop."""
        return []

    def resume(self, k: int, x, P) -> None:
        """Continue from a checkpoint (an agent restarted after a crash or a kill)."""
        self.k, self.x, self.P = int(k), np.array(x, float), np.array(P, float)

    def missed_motion(self, sensors: Sensors) -> np.ndarray | None:
        """Covariance to add for ticks this node never saw (it was dead, or started late from
        its prior of tick -1): how far it could have gone, from the speed it reports now plus
        three standard deviations, in every direction."""
        gap = sensors.k - self.k - 1
        if gap <= 0:
            return None
        o = sensors.odometry
        reach = gap * o.dt * (abs(o.speed) + 3.0 * o.speed_std)
        cov = np.zeros((self.model.state_dim,) * 2)
        p = self.model.position_dim
        cov[:p, :p] = np.eye(p) * reach**2
        return cov

    def link_failed(self, dst: int, msg: Any) -> list[Send]:
        """The radio reports that unicast `msg` never reached `dst`."""
        return []

    def peer_joined(self, aid: int) -> list[Send]:
        """The driver's membership (direct mode: Zenoh liveliness) says agent `aid` is up."""
        return []

    def peer_left(self, aid: int) -> list[Send]:
        """The driver's membership says agent `aid` is gone (crashed, stopped, out of reach):
        nothing sent to it arrives until `peer_joined`, and no radio will say so."""
        return []

    def command(self):
        """Closed loop: the actuator command (swarmloc.wire.messages.Command) for the vehicle, computed
        from the current estimate, or None for a node that commands nothing. The driver publishes
        it after each estimate; it must depend only on the node's state, so asking twice within
        a tick gives the same command."""
        return None

    def estimate(self) -> Estimate:
        return Estimate(self.k, self.x.copy(), self.P.copy())

    def drop(self, reason: str, detail: str = "") -> list[Send]:
        self.drops[reason] += 1
        log.debug("node %s drops frame: %s %s", self.id, reason, detail)
        return []


class Timers:
    """A driver's record of one node's timers (Timer): tag -> due time, in the driver's clock."""

    def __init__(self):
        self.due: dict[str, float] = {}

    def split(self, actions, now: float) -> list[Send]:
        """Take the Timers out of a node's returned actions (arming them at `now`); the sends remain."""
        sends = []
        for a in actions:
            if isinstance(a, Timer):
                self.due[a.tag] = now + a.delay
            else:
                sends.append(a)
        return sends

    def pop_due(self, now: float) -> list[str]:
        """Tags due by `now`, earliest first (ties by tag), disarmed."""
        tags = sorted((d, tag) for tag, d in self.due.items() if d <= now + 1e-9)
        for _, tag in tags:
            del self.due[tag]
        return [tag for _, tag in tags]

    def next_due(self) -> float | None:
        return min(self.due.values(), default=None)


class Idle(Node):
    """A ground station under an estimator that has no role for one: on the radio (its frames
    would be relayed like anyone's), in nobody's estimate, doing nothing."""

    def __init__(self, aid: int, algorithm: str):
        super().__init__(aid, np.zeros(0), np.zeros((0, 0)), "ground-station")
        self.algorithm = algorithm

    def step(self, sensors: Sensors) -> list:
        self.k = sensors.k
        return []

    def receive(self, src: int, msg: Any) -> list:
        return self.drop("unexpected", type(msg).__name__)


@dataclass(frozen=True)
class RadioTx:
    """A frame as sent on the radio: sender, destination (None = broadcast), envelope seq, bytes."""

    src: int
    dst: int | None
    seq: int
    data: bytes


@dataclass(frozen=True)
class RadioRx:
    """What the radio hands `receiver` at modelled time t: a frame's bytes, or a NACK for its sender."""

    receiver: int
    t: float
    data: bytes | None = None
    nack: LinkNack | None = None
    src: int = -1  # the frame's sender (for a NACK: the radio)
    seq: int = -1  # the frame's envelope seq
    unicast: bool = False  # addressed to receiver alone (a broadcast copy otherwise)


class Outbox:
    """Numbers a node's frames and remembers recent unicasts, so a driver can hand a radio
    NACK back to the node as the message it refers to. Shared by every driver."""

    def __init__(self, node_id: int, keep: int = 1024):
        self.node_id, self.keep = node_id, keep
        self.seq = 0
        self.unicast: OrderedDict[int, Send] = OrderedDict()

    def encode(self, send: Send) -> RadioTx | None:
        """The frame, or None if it would exceed the frame limit: it is not sent and takes no
        seq, so a receiver still sees this node's frames numbered without gaps."""
        data = wire.encode(send.msg, self.node_id, self.seq + 1, send.dst)
        if len(data) > wire.max_bytes(send.msg):
            return None
        self.seq += 1
        if send.dst is not None:
            self.unicast[self.seq] = send
            if len(self.unicast) > self.keep:
                self.unicast.popitem(last=False)
        return RadioTx(self.node_id, send.dst, self.seq, data)

    def failed(self, nack: LinkNack) -> Send | None:
        send = self.unicast.pop(nack.seq, None)
        return send if send is not None and send.dst == nack.dst else None
