"""The netsim process: owns the clock, the world and the radio; routes every frame.

Lockstep (default): publish tick k and every agent's sensor frame, then run radio rounds.
A round ends when the swarm is quiet: for every live agent its last `done` says it handled
tick k, consumed every frame netsim delivered to it and sent nothing netsim has not yet
received. Then the frames collected in the round go through the radio together
(Simulation.exchange_batch) and are delivered; the tick ends when a round sends nothing. Nothing
else is trusted about ordering across keys, so the run is deterministic for a seed.

Real time: the clock runs at wall speed times `clock.speed`; frames enter the radio when
they arrive and are delivered when their modelled time comes; nobody waits for anybody.

As in the agent daemon, Zenoh callbacks only enqueue; one loop does the work.
"""

from __future__ import annotations

import json
import logging
import queue
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import msgspec
import numpy as np
import zenoh

from netsim.sim import Deliveries, Simulation
from swarmloc import wire
from swarmloc.estimators import REGISTRY
from swarmloc.experiment.faults import FaultError, inverse_of, nodes_named, parse_fault
from swarmloc.experiment.recording import withheld_key
from swarmloc.experiment.results import RunRecord, compute_references, metrics
from swarmloc.experiment.rundir import write_run
from swarmloc.experiment.scenario import Scenario
from swarmloc.node import Estimate, RadioRx, RadioTx
from swarmloc.wire import auth, limits
from swarmloc.wire.messages import (
    Clock,
    Command,
    Control,
    Done,
    EstimateMsg,
    Event,
    LinkMsg,
    LinkNack,
    Links,
    Reply,
    Sensors,
    Truth,
)

log = logging.getLogger("swarmloc.netsim")
NETSIM_ID = 0  # sender id netsim uses on the wire (agent ids are the scenario's)
STATS_REASONS = ("unknown-agent", "malformed", "src-mismatch", "stale-nonce")  # not the seal's: no auth- prefix
KEY_TYPES = {"done": Done, "estimate": EstimateMsg, "command": Command}  # what an agent's own keys carry


class SetupError(RuntimeError):
    pass


MAX_LINK_ROWS = next(f.type.max_length for f in msgspec.inspect.type_info(Links).fields if f.name == "links")
"""The rows a Links frame may carry (its decoder refuses more)."""
LAST_TICK_GRACE = 2.0  # s a real-time run waits, after its last tick, for the agents to finish it
RECORD_SLICE = 2e-4  # s of the recording's held work done at a time while the loop is idle
RECORD_POLL = 2e-5  # s the loop blocks between two slices: long enough to let a callback in


@dataclass
class ServerConfig:
    swarm: str = "default"
    listen: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    out: Path | None = None
    seed: int | None = None
    join_timeout: float = 30.0  # s to wait for every agent to come alive
    tick_timeout: float = 10.0  # s of silence before a lagging agent is declared unresponsive
    plots: bool = True
    await_rejoin: bool = False  # lockstep: an agent that went away (a crash) is restarted by the launcher
    keyring: object | None = None  # swarmloc.wire.auth.Keyring: every frame sealed and opened with it (docs/security.md)
    keys_path: Path | None = None  # where the keyring came from: revocations made while the run goes are read there
    record: Path | None = None  # run.mcap: every frame and the Foxglove view, written as the run goes
    view_port: int | None = None  # the live view: a Foxglove WebSocket server on 127.0.0.1 (0: any free port)
    ros2: object | None = None  # swarmloc.wire.ros2.Topics: every estimate also on ROS 2 topics (docs/ros2.md)
    on_tick: Callable[[int, int], None] | None = field(default=None, repr=False)


class NetsimServer:
    def __init__(self, scenario: Scenario, cfg: ServerConfig):
        self.sc, self.cfg = scenario, cfg
        self.sim = Simulation(scenario, cfg.seed)
        self.ids = self.sim.ids
        self.mode = scenario.clock.mode
        self.keys = wire.Keys(cfg.swarm)
        # Bounded: a flood is dropped and counted at the door, never buffered (docs/security.md#limits).
        self.q = limits.Inbox()
        self.rate = limits.RateLimit()
        self.alive: set[int] = set()
        self.unresponsive: set[int] = set()
        self.joined_at = {a: 0 for a in self.ids}  # first tick an agent must acknowledge
        self.done: dict[int, Done] = {}
        self.delivered = {a: 0 for a in self.ids}  # frames put on radio/rx/<a> since it (re)joined
        # Frames accepted from radio/tx/<a> since it (re)joined. An agent numbers its frames
        # 1, 2, 3... and one Zenoh publisher delivers them in order, so this is also the last
        # accepted seq: anything else on that key (a repeat, a replay, a stranger) is refused.
        self.received = {a: 0 for a in self.ids}
        # Envelope seq of the last accepted `done` and `estimate` per agent: each increases.
        self.last_seq = {kind: {a: -1 for a in self.ids} for kind in ("done", "estimate")}
        # Commands an agent published since it (re)joined, numbered 1, 2, 3... (envelope seq):
        # lockstep waits until it has the number its last `done` states.
        self.commands = {a: 0 for a in self.ids}
        self.tick_timeouts = 0  # times a lockstep tick waited out tick_timeout
        self.rejected: dict[str, Counter[str]] = {k: Counter() for k in ("tx", "done", "estimate", "command", "alive",
                                                                        "control", "stats")}
        self.agent_events: list[dict] = []  # agents leaving (crash, kill) or joining after tick 0
        # Lockstep always resolves frames in rounds, in (sender, seq) order, never on arrival:
        # with arrival order a node could meet a token and a log replay in either order.
        self.round: list[RadioTx] = []
        self._new_event = False
        self.pending_faults: list = []
        self.record = RunRecord.for_scenario(scenario)
        self.sim.down.update(self.ids)  # nobody is up until their liveliness token appears
        self.seq = 0
        self.sent_at: dict[tuple[int, int], float] = {}  # (src, seq) -> sender's send time
        self.hop_latency: list[float] = []  # wall s from tx arrival at netsim to rx publish
        self.t0 = 0.0
        self.finished = False  # the last tick is over: agents leaving now are not events
        self.stop_requested: int | None = None  # `swarmloc stop`: the tick at which it was asked
        self.awaited: set[int] = set()  # agents lockstep waits for before its next tick
        ring = cfg.keyring
        self.sealer = auth.Sealer(ring, NETSIM_ID) if ring is not None else None
        # The hub's ring: every member's MAC key derives from it (netsim opens each agent's frames
        # with that agent's key and seals what it sends one agent with that agent's key); its
        # broadcasts (clock, events, links) carry its signature.
        self.opener = auth.Opener(ring, NETSIM_ID) if ring is not None else None
        # Refused in Zenoh's callbacks, before the queue: oversize, no seal or a wrong one.
        self.door = limits.Door(self.q, self.opener)
        self.revocations = auth.Revocations(ring, cfg.keys_path) if ring is not None and cfg.keys_path else None
        self.revoked: set[int] = set()  # agents of the run revoked while it went: gone for good
        self.recorder = None  # swarmloc.experiment.recording.Recorder, made by open()
        self.view = None  # the live view's foxglove WebSocketServer
        self.ros2 = None  # swarmloc.wire.ros2.Ros2Publisher
        self._pub_keys: dict[int, str] = {}
        self._faults_seen = 0  # entries of the fault log already recorded

    # ---------------------------------------------------------------- zenoh plumbing

    def open(self) -> None:
        conf = zenoh.Config.from_json5(wire.zenoh_config("router", self.cfg.listen))
        try:
            self.session = zenoh.open(conf)
        except zenoh.ZError as exc:
            raise SetupError(f"cannot open Zenoh router on {', '.join(self.cfg.listen)}: {exc}") from None
        k = self.keys

        door = self.door

        def put(item):
            self.q.put(item)

        def frame(kind, stamp=None):
            # What the key carries at most (the radio: every type; the others: one), refused by
            # its length before it costs a MAC.
            limit = wire.key_limit(KEY_TYPES[kind]) if kind in KEY_TYPES else wire.MAX_WIRE_BYTES

            def arrived(s):
                key = str(s.key_expr)

                def known():  # a key naming no agent of the run costs no MAC
                    try:
                        return None if wire.Keys.agent_of(key) in self.delivered else "unknown-agent"
                    except ValueError:
                        return "unknown-agent"

                door.admit(kind, s.payload, lambda d: (kind, key, d, stamp and (time.perf_counter(), s.attachment)), known,
                           limit, key=key)
            return arrived

        block = wire.publisher_options(zenoh)
        self._subs = [
            self.session.declare_subscriber(f"{k.prefix}/radio/tx/*", frame("tx", True)),
            self.session.declare_subscriber(f"{k.prefix}/agent/*/done", frame("done")),
            self.session.declare_subscriber(f"{k.prefix}/agent/*/estimate", frame("estimate")),
            self.session.declare_subscriber(f"{k.prefix}/agent/*/command", frame("command")),
            self.session.liveliness().declare_subscriber(f"{k.prefix}/agent/*/alive", lambda s: put(("alive", str(s.key_expr), s.kind, None)), history=True),
        ]
        self._ctl = self.session.declare_queryable(k.control, lambda q: put(("ctl", "", q, None)))
        self.pub_clock = self.session.declare_publisher(k.clock, **block)
        self.pub_links = self.session.declare_publisher(k.links, **block)
        self.pub_events = self.session.declare_publisher(k.events, **block)
        self.pub_sensors = {a: self.session.declare_publisher(k.sensors(a), **block) for a in self.ids}
        self.pub_truth = {a: self.session.declare_publisher(k.truth(a), **block) for a in self.ids}
        self.pub_rx = {a: self.session.declare_publisher(k.radio_rx(a), **block) for a in self.ids}
        self._pub_keys = {id(p): str(p.key_expr) for p in (self.pub_clock, self.pub_links, self.pub_events,
                                                           *self.pub_sensors.values(), *self.pub_truth.values())}
        self._open_view()
        if self.cfg.ros2 is not None:
            from swarmloc.wire.ros2 import Ros2Publisher

            self.ros2 = Ros2Publisher(self.session, self.cfg.ros2, "swarmloc_netsim", self.sc.localized_ids, block)

    def _open_view(self) -> None:
        """run.mcap and the live view: one recorder, its channels going to the file and, with
        view_port, to a Foxglove WebSocket server on 127.0.0.1."""
        if self.cfg.record is None and self.cfg.view_port is None:
            return
        from swarmloc.experiment.recording import Recorder

        meta = {"writer": "netsim", "swarm": self.cfg.swarm, "scenario": self.sc.to_yaml(), "seed": self.sc.seed if self.cfg.seed is None else self.cfg.seed,
                "mode": self.mode, "dt": self.sc.clock.dt, "agents": self.ids}
        # Deferred: its work is done while the loop waits (`_pump`), off lockstep's critical path.
        self.recorder = Recorder(self.cfg.record, meta, self.sc, deferred=True)
        if self.cfg.record is not None:
            self._write_layout()  # for a live viewer, on the start; the run's end frames the whole run
        if self.cfg.view_port is not None:
            import foxglove

            self.view = foxglove.start_server(name=f"swarmloc {self.cfg.swarm}", host="127.0.0.1",
                                              port=self.cfg.view_port, context=self.recorder.context)
            log.warning("live view: Foxglove WebSocket ws://127.0.0.1:%d", self.view.port)

    def _rec_t(self) -> float:
        """Modelled time to stamp a recorded frame with: the tick's (lockstep), now (real time)."""
        return self.sim.t if self.mode == "lockstep" or not self.t0 else max(self.sim.t, self._now())

    def close(self) -> None:
        if self.recorder is not None:
            self.recorder.close()
        if self.view is not None:
            self.view.stop()
        if self.ros2 is not None:
            self.ros2.close()
        self.session.close()

    def _seal(self, data: bytes, key: str, to: int = auth.BROADCAST) -> bytes:
        return data if self.sealer is None else self.sealer.seal(data, key, to)

    def _open(self, kind: str, key: str, payload: bytes, sender: int | None = None) -> tuple[bytes, int | None] | None:
        """(frame, sealer) of an authentic payload (sealed by `sender` if given), or (payload,
        None) without a keyring; None if it is not authentic, refused and counted as
        `auth-<reason>`."""
        if self.opener is None:
            return payload, None
        try:  # the door verified the tag: what is left is the sealer and its counter window
            return self.opener.admit(payload, sender)
        except auth.AuthError as exc:
            return self._refuse(kind, key, f"auth-{exc.reason}", str(exc))

    def _put(self, pub, msg, dst: int | None = None, to: int | None = None) -> None:
        """`msg` on `pub`, sealed for `to` (default: `dst`, the envelope's receiver; without
        either, for everyone: signed)."""
        self.seq += 1
        to = dst if to is None else to
        data = self._seal(wire.encode(msg, NETSIM_ID, self.seq, dst), self._pub_keys[id(pub)],
                          auth.BROADCAST if to is None else to)
        pub.put(data)
        if self.recorder is not None:
            self.recorder.frame(self._pub_keys[id(pub)], data, self._rec_t())

    # ---------------------------------------------------------------- inputs

    def _rejected(self) -> dict[str, dict[str, int]]:
        """Refusals by kind and reason: the loop's and the door's."""
        out = {kind: Counter(c) for kind, c in self.rejected.items()}
        for (kind, reason), n in self.door.snapshot().items():
            out.setdefault(kind, Counter())[reason] += n
        return {kind: dict(c) for kind, c in out.items()}

    def _refuse(self, kind: str, key: str, reason: str, detail: str = "") -> None:
        counter = self.rejected[kind]
        counter[reason] += 1
        if counter[reason] <= 10 or counter[reason] % 1000 == 0:
            log.warning("refused %s on %s (%s, %d so far) %s", kind, key, reason, counter[reason], detail)

    def _from_agent(self, kind: str, key: str, payload: bytes | None, cls=None) -> tuple[int, wire.Envelope] | None:
        """(agent id, envelope) of a frame an agent sent on its own key, or None, refused and
        counted (docs/wire.md, "Receiver rules"). cls=None leaves the body undecoded."""
        try:
            aid = wire.Keys.agent_of(key)
        except ValueError:
            aid = None
        if aid not in self.delivered:
            return self._refuse(kind, key, "unknown-agent")
        opened = self._open(kind, key, payload, aid)
        if opened is None:
            return None
        if not self.rate.allow(aid, time.monotonic()):  # an agent flooding its own keys
            return self._refuse(kind, key, "rate-limited")
        frame, sealer = opened
        try:
            env = wire.decode(frame, expect=None if cls is None else (cls,), body=cls is not None)
        except wire.WireError as exc:
            return self._refuse(kind, key, "malformed", str(exc))
        if env.src != aid or (sealer is not None and sealer != aid):
            return self._refuse(kind, key, "src-mismatch", f"src {env.src}, sealed by {sealer}")
        return aid, env

    def _newer(self, kind: str, key: str, payload: bytes | None):
        """(agent id, body) of a `done` or `estimate` newer than the last accepted from that
        agent, or None, refused and counted. An agent publishes several estimates of one tick as
        its chains commit: an older one arriving again must not replace the newest."""
        got = self._from_agent(kind, key, payload, Done if kind == "done" else EstimateMsg)
        if got is None:
            return None
        aid, env = got
        if env.seq <= self.last_seq[kind][aid]:
            return self._refuse(kind, key, "stale", f"seq {env.seq}")
        self.last_seq[kind][aid] = env.seq
        return aid, env.body

    def _handle(self, item) -> None:
        kind, key, payload, stamp = item
        if self.recorder is not None and kind in ("tx", "done", "estimate", "command") and payload is not None:
            self.recorder.frame(key, payload, self._rec_t())
        if kind == "tx":
            self._on_tx(key, payload, stamp)
        elif kind in ("done", "estimate") and (got := self._newer(kind, key, payload)):
            aid, body = got
            if kind == "done":
                self.done[aid] = body
                self.unresponsive.discard(aid)
            else:
                nis = () if body.nis is None else tuple((float(v), int(d)) for v, d in body.nis)
                targets = tuple((t.target, t.mean, t.cov) for t in body.targets)
                self.record.add_estimate(body.algorithm, aid, Estimate(body.k, body.mean, body.cov, nis, targets))
                t = body.k * self.sc.clock.dt
                if self.recorder is not None:
                    self.recorder.estimate(body.algorithm, aid, body.k, t, body.mean, body.cov, targets)
                if self.ros2 is not None and aid in self.record.col:
                    self.ros2.publish(aid, self.sc.agent(aid).model, t, body.mean, body.cov, time.time_ns())
        elif kind == "command":
            self._on_command(key, payload)
        elif kind == "alive":
            try:
                aid = wire.Keys.agent_of(key)
            except ValueError:
                return self._refuse("alive", key, "unknown-agent")
            self._on_alive(aid, payload == zenoh.SampleKind.PUT)
        elif kind == "ctl":
            self._control(payload)

    def _on_alive(self, aid: int, up: bool, event: bool = True) -> None:
        if aid not in self.delivered:
            return self._refuse("alive", self.keys.alive(aid), "unknown-agent")
        if aid in self.revoked:  # left already; a token it declares again is not a return
            return self._refuse("alive", self.keys.alive(aid), "revoked") if up else None
        # Zenoh reports a key's first token and its last one going: a second token on an
        # agent's key (a stranger's) makes no event at all.
        if up:
            # A (re)joining agent starts counting from zero and is waited for from the next tick.
            self.alive.add(aid)
            self.sim.down.discard(aid)
            self.delivered[aid] = self.received[aid] = self.commands[aid] = 0
            for seqs in self.last_seq.values():
                seqs[aid] = -1
            self.done.pop(aid, None)
            self.joined_at[aid] = self.sim.k + 1
            if self.sim.k >= 0:
                log.warning("agent %s joined at tick %d", aid, self.sim.k)
                self.agent_events.append({"k": self.sim.k, "t": self.sim.t, "agent": aid, "event": "joined"})
                if self.recorder is not None:
                    self.recorder.event(self.sim.t, f"agent {aid} joined at tick {self.sim.k}")
        else:
            self.alive.discard(aid)
            self.sim.down.add(aid)  # the radio now drops (and NACKs) frames to it as "down"
            log.warning("agent %s left the swarm at tick %d", aid, self.sim.k)
            if not self.finished and event:
                self.agent_events.append({"k": self.sim.k, "t": self.sim.t, "agent": aid, "event": "left"})
                if self.recorder is not None:
                    self.recorder.event(self.sim.t, f"agent {aid} left the swarm at tick {self.sim.k}", "warning")
                if self.cfg.await_rejoin and aid not in self.sim.faults.killed():
                    self.awaited.add(aid)

    def _on_tx(self, key: str, payload: bytes | None, stamp) -> None:
        arrived, attachment = stamp
        got = self._from_agent("tx", key, payload)
        if got is None:
            return
        src, env = got
        if src not in self.alive:
            return self._refuse("tx", key, "not-joined")
        if env.seq != self.received[src] + 1:
            return self._refuse("tx", key, "out-of-sequence", f"seq {env.seq} after {self.received[src]}")
        self.received[src] = env.seq
        sent = wire.decode_send_time(attachment.to_bytes() if attachment is not None else None)
        self.sent_at[(src, env.seq)] = sent if sent is not None else float("nan")
        if len(self.sent_at) > 100_000:  # only recent frames are still in flight
            for old in list(self.sent_at)[:50_000]:
                del self.sent_at[old]
        tx = RadioTx(src, env.dst, env.seq, payload)
        if self.mode == "realtime":
            self._deliver_all(self.sim.offer(tx, self._now()), arrived)
            self._new_event = True
        else:
            self.round.append(tx)

    def _on_command(self, key: str, payload: bytes | None) -> None:
        """An agent's actuator command: in force from the next tick (netsim.sim.Simulation.command).
        A malformed body still counts as the command its number says, so lockstep does not wait
        for it; the vehicle keeps its last command."""
        got = self._from_agent("command", key, payload)
        if got is None:
            return
        aid, env = got
        if aid not in self.alive:
            return self._refuse("command", key, "not-joined")
        if env.seq <= self.commands[aid]:
            return self._refuse("command", key, "stale", f"seq {env.seq}")
        self.commands[aid] = env.seq
        try:
            u = wire.decode_body(Command, env.body).u
        except wire.WireError as exc:
            log.warning("agent %s: malformed command dropped: %s", aid, exc)
            u = None
        self.sim.command(aid, u)

    def _deliver_all(self, rxs: list[RadioRx] | Deliveries, arrived: float | None = None) -> None:
        if isinstance(rxs, Deliveries):
            for r, t, data, src, seq, unicast in rxs.raw():
                self._deliver_frame(r, t, data, None, src, seq, unicast)
        else:
            for rx in rxs:
                self._deliver(rx)
        if arrived is not None and rxs:
            self.hop_latency.append(time.perf_counter() - arrived)

    def _deliver(self, rx: RadioRx) -> None:
        self._deliver_frame(rx.receiver, rx.t, rx.data, rx.nack, rx.src, rx.seq, rx.unicast)

    def _deliver_frame(self, r: int, t: float, data: bytes | None, nack: LinkNack | None, src: int, seq: int,
                       unicast: bool) -> None:
        if r not in self.alive:
            # A dead agent hears nothing and is not counted; like a missing MAC ACK, its sender
            # learns that a unicast did not get through.
            if unicast and src in self.alive:
                self._deliver(RadioRx(src, t, nack=LinkNack(seq, r, "down")))
            return
        if nack is not None:
            self.seq += 1
            data, sent = self._seal(wire.encode(nack, NETSIM_ID, self.seq), self.keys.radio_rx(r), r), None
        else:  # the sender's frame as it sealed it
            sent = self.sent_at.get((src, seq))
        self.delivered[r] += 1
        attachment = wire.encode_delivery(self.delivered[r], sent if sent == sent else None)
        if self.sealer is not None:
            attachment += auth.delivery_tag(self.cfg.keyring, r, attachment, data)
        self.pub_rx[r].put(data, attachment=attachment)
        if self.recorder is not None:
            self.recorder.frame(self.keys.radio_rx(r), data, self._rec_t())

    # ---------------------------------------------------------------- control

    def _control(self, query) -> None:
        key = str(query.key_expr)
        asker, nonce = auth.BROADCAST, None  # until the request is open: a refusal is signed, for anyone

        def reply(ok: bool, error: str = "", data: dict | None = None):
            # Sealed for the operator who asked (its MAC key), holding its request's nonce: a
            # captured answer answers no other request (issue 26).
            data = {**(data or {}), **({"nonce": nonce} if nonce else {})}
            query.reply(key, self._seal(wire.encode(Reply(ok, error[:500], data), NETSIM_ID, 0), key, asker))

        payload = query.payload.to_bytes() if query.payload is not None else b""
        if self.opener is not None:
            try:
                payload, asker = self.opener.open(payload, key)
            except auth.AuthError as exc:
                self._refuse("control", self.keys.control, f"auth-{exc.reason}", str(exc))
                return reply(False, f"not authenticated ({exc.reason}): control requests need the swarm's key")
        try:
            req = wire.decode(payload, expect=(Control,)).body
        except wire.WireError as exc:
            return reply(False, f"bad request: {exc}")
        if not isinstance(req.args, dict):
            return reply(False, "args must be a map")
        nonce = req.args.get("nonce") if isinstance(req.args.get("nonce"), str) else None
        try:
            self._control_op(req, reply)
        except Exception as exc:  # a bad request must never take netsim down
            log.exception("control %s failed", req.op)
            reply(False, f"{req.op} failed: {exc}")

    def _control_op(self, req, reply) -> None:
        if req.op == "inject":
            try:
                f = parse_fault(req.args.get("fault"))
            except FaultError as exc:
                return reply(False, f"bad fault: {exc}")
            unknown = [a for a in nodes_named(f) if a not in self.ids]
            if unknown:
                return reply(False, f"{f.action}: unknown agents {unknown}; agents are {self.ids}")
            self.pending_faults.append(f)
            return reply(True, "", {"applies_at_tick": self.sim.k + 1, "fault": f.model_dump(mode="json", exclude_none=True)})
        if req.op == "clear":
            fid = req.args.get("id")
            match = [a for a in self.sim.faults.active if a.id == fid]
            if not match:
                return reply(False, f"no active fault {fid!r}; active: {[a.id for a in self.sim.faults.active]}")
            self.pending_faults.append(inverse_of(match[0].fault))
            return reply(True, "", {"applies_at_tick": self.sim.k + 1})
        if req.op == "faults":
            return reply(True, "", {"k": self.sim.k, "t": self.sim.t, "active": self.sim.faults.describe()})
        if req.op == "status":
            return reply(True, "", self.status())
        if req.op == "stop":
            # The run ends after the tick in progress, as it would at its last tick.
            self.stop_requested = self.sim.k
            return reply(True, "", {"k": self.sim.k, "t": self.sim.t, "steps": self.sim.steps})
        return reply(False, f"unknown op {req.op!r} (inject, clear, faults, status, stop)")

    def status(self) -> dict:
        return {
            "scenario": self.sc.name, "mode": self.mode, "k": self.sim.k, "t": self.sim.t,
            "steps": self.sim.steps, "radio": self.sc.radio["model"],
            "agents": {str(a): {"alive": a in self.alive, "responsive": a not in self.unresponsive,
                                "done_k": self.done[a].k if a in self.done else -1} for a in self.ids},
            "links": self.sim.link_table(), "faults": self.sim.faults.describe(),
        }

    # ---------------------------------------------------------------- the loop

    def _pump(self, until: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not until():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            wait = remaining
            rec = self.recorder
            if rec is not None and rec.pending:
                # The recording's work in time the loop would spend waiting anyway: in slices,
                # since foxglove-sdk logs holding the GIL and a Zenoh callback handing over the
                # frame we wait for gets it only when this thread blocks.
                rec.drain(time.perf_counter() + RECORD_SLICE)
                if rec.pending:
                    wait = min(remaining, RECORD_POLL)
            try:
                item = self.q.get(timeout=wait)
            except queue.Empty:
                if wait < remaining:
                    continue
                return until()
            self._handle(item)
            item = None  # a held Zenoh query is only answered (final) once released
            while True:  # drain what is already queued before testing the condition again
                try:
                    self._handle(self.q.get(0))
                except queue.Empty:
                    break
        return True

    def _waited_for(self) -> list[int]:
        killed = self.sim.faults.killed()
        return [a for a in self.ids if a in self.alive and a not in self.unresponsive and a not in killed
                and self.joined_at[a] <= self.sim.k]

    def _quiet_agent(self, a: int, k: int) -> bool:
        d = self.done.get(a)
        return (d is not None and d.k >= k and d.consumed == self.delivered[a] and d.sent == self.received[a]
                and d.commands <= self.commands[a])

    def _quiet(self, k: int) -> bool:
        return all(self._quiet_agent(a, k) for a in self._waited_for())

    def wait_for_agents(self) -> None:
        if not self._pump(lambda: self.alive >= set(self.ids), self.cfg.join_timeout):
            missing = sorted(set(self.ids) - self.alive)
            raise SetupError(f"agents {missing} did not come alive within {self.cfg.join_timeout:.0f} s")

    def run(self) -> dict:
        self.open()
        try:
            self.wait_for_agents()
            self.t0 = time.perf_counter()
            for _ in range(self.sim.steps + 1):
                if self.stop_requested is not None:
                    log.warning("stopped on request after tick %d of %d", self.sim.k, self.sim.steps)
                    break
                if self.mode == "lockstep":
                    self._lockstep_tick()
                else:
                    self._realtime_tick()
            wall = time.perf_counter() - self.t0
            self.finished = True
            if self.mode == "realtime":
                # Real time waited for nobody: give the live agents a moment to finish the last
                # tick (its estimate comes before its `done`), or an agent a little behind
                # would end the run without one.
                last = self.sim.k
                killed = self.sim.faults.killed()
                live = [a for a in self.alive if a not in self.unresponsive and a not in killed]
                self._pump(lambda: all(a in self.done and self.done[a].k >= last for a in live), LAST_TICK_GRACE)
            agent_stats = self.agent_stats()
            self._put(self.pub_clock, Clock(self.sim.k, self.sim.t, "stop", self.sc.clock.dt))
            return self._finish(wall, agent_stats)
        finally:
            self.close()

    def _revoke(self) -> None:
        """An agent revoked while the run goes (`swarmloc keys revoke`) leaves it for good: its
        frames are refused from now on (`auth-revoked`), nothing is delivered to it and lockstep
        stops waiting for it."""
        for name in self.revocations.poll(time.monotonic()):
            if not name.startswith("agent-") or int(name[6:]) not in self.delivered:
                continue
            aid = int(name[6:])
            log.warning("agent %s revoked at tick %d: its frames are refused from now on", aid, self.sim.k)
            self.agent_events.append({"k": self.sim.k, "t": self.sim.t, "agent": aid, "event": "revoked"})
            if self.recorder is not None:
                self.recorder.event(self.sim.t, f"agent {aid} revoked at tick {self.sim.k}", "warning")
            if aid in self.alive:
                self._on_alive(aid, False, event=False)
            self.revoked.add(aid)
            self.awaited.discard(aid)

    def _start_tick(self) -> int:
        if self.revocations is not None:
            self._revoke()
        before = self.sim.faults.killed()
        k, t, frames = self.sim.tick(self.pending_faults)
        self.pending_faults = []
        after = self.sim.faults.killed()
        killed, restarted = sorted(after - before), sorted(before - after)
        for a in killed:
            self._put(self.pub_events, Event("kill", a, t))
        for a in restarted:
            self._put(self.pub_events, Event("restart", a, t))
        if self.mode == "lockstep" and killed:
            # The launcher kills the process on this event; until it is gone it could still
            # take frames, and a quick restart would find it alive.
            if not self._pump(lambda: not any(a in self.alive for a in killed), self.cfg.join_timeout):
                log.error("tick %d: killed agents %s are still alive after %.0f s", k,
                          [a for a in killed if a in self.alive], self.cfg.join_timeout)
        if self.mode == "lockstep" and (restarted or self.awaited):
            # Lockstep does not run on without a restarting agent (a kill fault's restart, or
            # a crash its launcher restarts): it takes this tick's frame when it is up.
            back = sorted(set(restarted) | self.awaited)
            self.awaited.clear()
            if not self._pump(lambda: all(a in self.alive for a in back), self.cfg.join_timeout):
                log.error("tick %d: restarted agents %s did not come back within %.0f s", k,
                          [a for a in back if a not in self.alive], self.cfg.join_timeout)
            for a in back:
                self.joined_at[a] = min(self.joined_at[a], k)
        self._put(self.pub_clock, Clock(k, t, self.mode, self.sc.clock.dt, self.sc.clock.speed))
        truth = self.sim.truth()
        targets = self.sim.targets()
        rec = self.recorder
        if rec is not None:
            self._record_faults()
            rec.truth(k, t, truth, targets)
            for a in killed:
                rec.event(t, f"kill agent {a}", "warning")
            for a in restarted:
                rec.event(t, f"restart agent {a}")
        for a in self.ids:
            self._put(self.pub_truth[a], Truth(k, t, truth[a]), to=a)  # a MAC, not a signature per agent a tick
            if frames[a] is None:  # a recorded world without a frame for it this tick
                frames[a] = Sensors(k, t, None, [])
            elif a in self.alive and a not in after:
                # Addressed under the seal: a copy replayed to another agent is misaddressed there
                # (issue 26, finding 2: agent 1's frames, replayed to agent 4, were taken).
                self._put(self.pub_sensors[a], frames[a], dst=a)
            elif rec is not None:
                rec.frame(withheld_key(self.keys, a), wire.encode(frames[a], NETSIM_ID, 0), t)
        self.record.add_tick(k, t, frames, truth, targets)
        return k

    def _write_layout(self) -> str:
        """The Foxglove layout beside run.mcap, framed on every position the run's platforms,
        landmarks and targets took; before tick 0 (for a live viewer, replaced when the run
        ends), on where they start."""
        from swarmloc.experiment.recording import LAYOUT, layout

        world = self.sc.world
        pts = [np.asarray(m.position, float)[:2].reshape(1, 2) for m in world.landmarks]
        if self.record.truth:
            pts += [self.record.truth_array()[:, :, :2].reshape(-1, 2)]
            pts += [np.asarray(x, float)[:, :2].reshape(-1, 2) for x in self.record.target_truth]
        else:
            pts += [np.asarray(a.start, float)[:2].reshape(1, 2) for a in world.agents]
            pts += [np.asarray(o.position, float)[:2].reshape(1, 2) for o in world.targets]
        path = self.cfg.record.with_name(LAYOUT)
        path.write_text(json.dumps(layout(np.concatenate(pts), self.sc.estimator.name, self.sc.localized_ids),
                                   indent=2) + "\n")
        return path.name

    def _record_faults(self) -> None:
        log_ = self.sim.fault_log
        if len(log_) > self._faults_seen:
            active = self.sim.faults.describe()
            for entry in log_[self._faults_seen:]:
                self.recorder.fault(entry, active)
            self._faults_seen = len(log_)

    def _end_tick(self, k: int) -> None:
        if k % max(1, int(round(1.0 / self.sc.clock.dt))) == 0:
            # Pairs out of radio range are not links: left out (at 256 agents they are 9 pairs
            # in 10, and building, sealing, recording and drawing them was most of a tick).
            rows = self.sim.link_table(in_reach=True)[:MAX_LINK_ROWS]
            self._put(self.pub_links, Links(k, [LinkMsg(**row) for row in rows]))
            if self.recorder is not None:
                self.recorder.links(rows)
        if self.recorder is not None:
            self.recorder.end_tick(k, self.sim.t)
        if self.cfg.on_tick:
            self.cfg.on_tick(k, self.sim.steps)

    def _lockstep_tick(self) -> None:
        k = self._start_tick()
        while True:
            while not self._pump(lambda: self._quiet(k), self.cfg.tick_timeout):
                lagging = [a for a in self._waited_for() if not self._quiet_agent(a, k)]
                log.error("tick %d: agents %s silent for %.0f s; going on without them", k, lagging, self.cfg.tick_timeout)
                self.tick_timeouts += 1
                self.unresponsive.update(lagging)
            if not self.round:
                break
            batch, self.round = self.round, []
            started = time.perf_counter()
            self._deliver_all(self.sim.exchange_batch(batch), started)
        self._end_tick(k)

    def _now(self) -> float:
        """Simulated time now (real-time mode)."""
        return (time.perf_counter() - self.t0) * self.sc.clock.speed

    def _realtime_tick(self) -> None:
        k = self._start_tick()
        self._check_lag(k)
        t_next = (k + 1) * self.sc.clock.dt  # the last tick lasts dt too, so its frames land
        while True:
            now = self._now()
            self._deliver_all(self.sim.advance(now))
            if now >= t_next:
                break
            event = self.sim.next_event_time()
            wake = min(t_next, event if event is not None else t_next)
            # Wake early when a new frame enters the radio: its delivery may come before `wake`.
            self._new_event = False
            self._pump(lambda: self._new_event, max(0.0, (wake - now) / self.sc.clock.speed))
        self._end_tick(k)

    def _check_lag(self, k: int) -> None:
        """Real time waits for nobody, but an agent whose last `done` is more than tick_timeout
        of modelled ticks behind is not keeping up: marked unresponsive until it catches up."""
        behind = max(1, int(round(self.cfg.tick_timeout * self.sc.clock.speed / self.sc.clock.dt)))
        killed = self.sim.faults.killed()
        for a in self.alive:
            d = self.done.get(a)
            last = d.k if d is not None else self.joined_at[a] - 1
            if a not in self.unresponsive and a not in killed and k - last > behind:
                log.error("tick %d: agent %s has handled nothing since tick %d: marked unresponsive", k, a, last)
                self.unresponsive.add(a)

    # ---------------------------------------------------------------- the end

    def agent_stats(self, timeout: float = 2.0) -> dict:
        """Each live agent's own counters (drops by reason, hop latency), via its stats queryable."""
        out = {}
        expected = len(self.alive)
        nonce = auth.query_nonce()
        # No consolidation: Zenoh would keep one answer per key, a stranger's as readily as the agent's.
        for r in self.session.get(self.keys.stats("*"), payload=nonce.encode(), timeout=timeout,
                                  consolidation=zenoh.ConsolidationMode.NONE):
            if r.ok is None:
                continue
            try:  # the first answer is not the answer: only the agent's own, to this query (finding 3)
                aid, data = auth.open_stats_reply(self.opener, str(r.ok.key_expr), r.ok.payload.to_bytes(), nonce)
            except auth.AuthError as exc:
                self._refuse("stats", str(r.ok.key_expr), exc.reason if exc.reason in STATS_REASONS
                             else f"auth-{exc.reason}", str(exc))
                continue
            out.setdefault(str(aid), data)
            if len(out) >= expected:
                break  # do not sit out the timeout once everyone has answered
        return out

    def _finish(self, wall: float, agent_stats: dict) -> dict:
        # Estimates are published before each `done`, so at quiet they have all arrived.
        self._pump(lambda: False, 0.05)
        compute_references(self.sc, self.record)
        lat = np.array(self.hop_latency) * 1e6
        extra = {
            "transport": f"zenoh-{self.mode}",
            "wall_time_s": wall,
            "ticks_per_s": (self.sim.k + 1) / wall if wall > 0 else None,
            **({"stopped_at_tick": self.sim.k} if self.stop_requested is not None else {}),
            "radio": {"model": self.sc.radio["model"], **self.sim.radio_summary(),
                      "netsim_hop_us_median": float(np.median(lat)) if lat.size else None,
                      "netsim_hop_us_p99": float(np.percentile(lat, 99)) if lat.size else None},
            "faults": self.sim.fault_log,
            "agent_stats": agent_stats,
            "unresponsive_agents": sorted(self.unresponsive),
            "tick_timeouts": self.tick_timeouts,
            "agent_events": self.agent_events,
            "rejected": self._rejected(),
            "inbox": self.q.stats(),
            **({"commands": self.sim.commands} if self.sim.commands else {}),
        }
        if self.recorder is not None:
            extra["recording"] = {"frames": self.recorder.frames, **({"file": self.cfg.record.name}
                                                                     if self.cfg.record is not None else {})}
            self.recorder.close()  # everything on disk before the slower run directory
            if self.cfg.record is not None:
                extra["recording"]["layout"] = self._write_layout()
        if self.ros2 is not None:
            extra["ros2"] = {"published": self.ros2.published, "skipped": self.ros2.skipped}
        algorithms = REGISTRY.order({self.sc.estimator.name, *self.sc.reference_names, *self.record.est})
        if self.cfg.out is None:
            return {**metrics(self.record, algorithms), **extra}
        # The run directory states the radio with every default filled in.
        used = self.sc.with_overrides(radio=self.sim.channel.model_dump())
        m = write_run(self.cfg.out, used, self.record, algorithms, extra, plots=self.cfg.plots,
                      radio=self.sim.radio_arrays())
        return m

