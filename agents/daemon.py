"""The agent daemon: one swarmloc node hosted over a Zenoh session.

Zenoh runs subscriber callbacks on its own threads, and a slow callback stalls delivery, so
callbacks only enqueue; the daemon's single loop decodes, drives the node and publishes. The
node never sees Zenoh, and the daemon never does estimation.

Two radio modes:
- netsim (simulation): frames go to radio/tx/<id>; netsim decides who hears them and
  delivers on radio/rx/<id>, stamped with a delivery number that lockstep counts.
- direct (deployment): frames go straight to radio/rx/<dst> (or radio/rx/all for broadcast)
  and the physical network decides. Nobody NACKs: the swarm's liveliness tokens tell the node
  who left or came back (peer_left, peer_joined), and its timers stand in for the NACKs.

Sensor frames come from Zenoh keys (netsim, or a driver) and from sources the loop polls (a
flight controller, a recording: agents/companion/sources.py); the estimate goes to the swarm's key and,
when configured, to the flight controller (docs/deploy.md#sensor-sources).
"""

from __future__ import annotations

import argparse
import io
import json
import logging
import math
import os
import queue
import re
import sys
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zenoh
from msgspec.structs import replace

from agents import timesync
from agents.companion import output as fc_output
from agents.companion import sources as sensor_sources
from swarmloc import wire
from swarmloc.node import Node, NodeSpec, Outbox, Send, Timers, estimate_of
from swarmloc.process import exit_on_sigterm
from swarmloc.wire import auth, limits
from swarmloc.wire.messages import Clock, Done, EstimateMsg, LinkNack, Reply, Sensors, TargetEstimateMsg, TimeSync

log = logging.getLogger("swarmloc.agent")

MAX_PENDING = 256
"""Measurement frames held for the next frame at most; more are dropped and counted (a driver
publishing while the frame source is silent must not grow the agent without bound)."""
MAX_MERGED = 64  # measurements of one kind in a frame: the wire's limit (swarmloc.wire.messages.Sensors)
MERGED_LISTS = ("ranges", "relpos", "targets", "rb", "landmarks")
MERGED_SINGLE = ("gnss", "pseudoranges")

BROADCAST = "all"
RECORDED = ("sensors", "measurements", "rx", "clock")  # inputs an agent's recording keeps (with what it sends)
NETSIM_ID = 0  # sender id of netsim's own frames (clock, sensors, NACKs)
MAX_DELIVERY_GAP = 4 * limits.INBOX_FRAMES
PAGE_BYTES = 4096  # a checkpoint at most this long is rewritten in place (AgentDaemon._checkpoint)
"""Deliveries an agent steps over at once: more than its inbox could have lost between two it
took. A number further ahead is refused (rx-too-far), so that a forged one cannot push every
genuine delivery below the count."""


@dataclass
class AgentConfig:
    swarm: str = "default"
    connect: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    listen: tuple[str, ...] = ()
    mode: str = "client"  # client of netsim's router in simulation; peer on a real swarm
    gossip: bool | None = None  # peers find each other through those they connect to (None: Zenoh's way, on)
    direct: bool = False
    exit_on_stop: bool = True
    state_file: Path | None = None  # checkpoint: written every tick, resumed from at start
    sensor_keys: tuple[str, ...] | None = None  # keys of ready sensor frames; None: the swarm's agent/<id>/sensors
    measurement_keys: tuple[str, ...] = ()  # keys of partial frames whose measurements join the next frame
    sources: tuple = ()  # polled sources: agents.config's MavlinkSource and FileSource entries
    publish_swarm: bool = True  # the estimate on the swarm's estimate key
    mavlink_output: object | None = None  # agents.config.MavlinkOutput: the estimate to the flight controller
    setpoints: object | None = None  # agents.config.SetpointOutput: a closed-loop vehicle's commands to it
    clock_bound: float = 0.010  # s: direct mode, a peer's clock offset beyond this is logged and counted
    estimate_log: Path | None = None  # every estimate appended as a JSON line (docs/deploy.md#the-estimate-log)
    epoch: float | None = None  # the swarm clock: UNIX time of tick 0, which polled sources number ticks from
    keyring: object | None = None  # swarmloc.wire.auth.Keyring: frames sealed and opened with it (docs/security.md)
    tls_dir: Path | None = None  # key directory: Zenoh over mutual TLS with its ca.pem and agent-<id>.pem/.key
    ros2: object | None = None  # swarmloc.wire.ros2.Topics: the ROS 2 domain of ros2 sources and outputs (docs/ros2.md)
    ros2_publish: bool = False  # the estimate also on ROS 2 topics
    record: Path | None = None  # an MCAP recording of every frame in and out (docs/run-format.md#runmcap)
    record_meta: dict | None = None  # what the recording says about the agent (its configuration)


class AgentDaemon:
    def __init__(self, node: Node, cfg: AgentConfig):
        self.node, self.cfg = node, cfg
        node.synchronous = False  # until netsim's clock says lockstep: direct mode never does
        self.keys = wire.Keys(cfg.swarm)
        # Bounded: a flood is dropped and counted at the door, never buffered (docs/security.md#limits).
        self.inbox = limits.Inbox()
        self.rate = limits.RateLimit()
        self.outbox = Outbox(node.id)
        self.sent = 0  # radio frames published
        self.commands = 0  # actuator commands published (closed loop)
        self._pub_cmd = None  # declared by open()
        self.consumed = 0  # netsim's delivery number of the last radio frame accepted
        self.clock_k = -1  # tick of the last clock frame
        self.rejected: Counter[str] = Counter()
        self.deliveries_lost = 0  # netsim's deliveries that never reached us (an inbox overflowed): stepped over
        self.hop_latency: list[float] = []  # s from the sender's publish to our loop picking the frame up
        self.handled = 0
        self.ticks = 0  # sensor frames handled
        self.ticks_skipped = 0  # ticks whose sensor frame never reached the node
        self.sensor_lag: list[float] = []  # real time: s from a sensor frame's arrival to the node stepping on it
        self._last_published = None
        self.sources: list = []  # polled (agents/companion/sources.py), built by open()
        self.fc = None  # the FlightControllerTicks among them that outputs.mavlink goes to
        self.fc_out: fc_output.FcOutputs | None = None  # what goes to that FC (agents/companion/output.py)
        # Direct mode: the peers' clock offsets, from echoed send stamps (agents/timesync.py).
        self.clocks = timesync.PeerClocks(node.id, cfg.clock_bound) if cfg.direct else None
        self.frame_source = None  # the source of the last sensor frame stepped on, and its time
        self.frame_t = 0.0
        self._last_checkpoint = -1e9
        self._checkpoint_fd: int | None = None  # the checkpoint file, open for writing in place
        self._checkpoint_size = 0
        self._done_k: int | None = None  # real time: the tick of the last `done` published
        # Real time: a sensor frame the node took but holds until something else is done (RDL
        # waiting for a pair's commit): (k, t, source, arrival, node's tick before it). Its tick
        # counts, and its lag is measured, when the node reaches it.
        self._held_tick: tuple | None = None
        self.resumed = False  # from a checkpoint
        self.peers: set[int] = set()  # direct mode: the agents whose liveliness tokens are there
        self.peer_delay: dict[int, deque] = {}  # direct mode: s from a peer's send (its clock) to ours, recent frames
        self.frame_wall: float | None = None  # monotonic time of the last sensor frame stepped on
        self.pending: list[Sensors] = []  # measurement frames waiting for the next frame
        self.merged: Counter[str] = Counter()  # measurements merged into frames, and dropped, by kind
        self._log = None  # the estimate log's file
        self._stop = threading.Event()
        # Node timers: lockstep arms and fires them in modelled time (the tick's t, before its
        # sensor frame), real time in wall seconds scaled to modelled ones by the clock's speed.
        self.timers = Timers()
        # Authentication at the I/O boundary: every frame out sealed, every frame in opened first.
        # Our own keys (per-member identity): to netsim under our MAC key, which only netsim also
        # holds; without netsim (direct) under our signature. We open what is sealed for us.
        self.sealer = auth.Sealer(cfg.keyring, node.id) if cfg.keyring is not None else None
        self.opener = auth.Opener(cfg.keyring, node.id) if cfg.keyring is not None else None
        self.hub = auth.BROADCAST if cfg.direct else NETSIM_ID  # whom our swarm frames are sealed for
        # Refused in Zenoh's callbacks, before the inbox: oversize, no seal or a wrong one.
        self.door = limits.Door(self.inbox, self.opener)
        self.model_t = 0.0  # modelled time of the last sensor frame
        self.speed, self.clock_t, self.clock_wall = 1.0, 0.0, time.monotonic()  # real time: the last clock frame
        self.ros2 = None  # swarmloc.wire.ros2.Ros2Publisher
        self.recorder = None  # swarmloc.experiment.recording.Recorder
        self._unacked = False  # inputs handled since our last `done`
        self.wake_at = 0.0  # monotonic time of the next turn due without an input (service())

    # ---------------------------------------------------------------- zenoh plumbing

    def open(self) -> None:
        conf = wire.zenoh_config(self.cfg.mode, self.cfg.listen, self.cfg.connect, self.cfg.gossip)
        if self.cfg.tls_dir is not None:
            from agents import tls

            conf = json.dumps(tls.zenoh_tls(conf, self.cfg.tls_dir, f"agent-{self.node.id}"))
        conf = zenoh.Config.from_json5(conf)
        self.session = zenoh.open(conf)
        aid = self.node.id
        block = wire.publisher_options(zenoh)
        # A physical radio loses frames, and a blocking put to a peer whose link is down would
        # stall the loop (Zenoh blocks up to seconds before it gives the link up): direct radio
        # frames are dropped on congestion instead, and UKF-DCL's timeouts cover the loss.
        radio = wire.publisher_options(zenoh, lossy=self.cfg.direct)
        door = self.door

        def frame(kind, limit=wire.MAX_WIRE_BYTES):
            return lambda s: door.admit(kind, s.payload, lambda d: (kind, d, s.attachment), limit=limit,
                                        key=str(s.key_expr))

        tagged = self.opener is not None
        ring = self.cfg.keyring

        def delivery(s):
            att = s.attachment.to_bytes() if s.attachment is not None else None

            def numbered():
                # A delivery number we consumed already is a copy (a replay at any rate, issue
                # 26 finding 4), dropped before it costs a MAC or a place in the inbox that a
                # genuine delivery needs. Only netsim's numbers ever raise `consumed`.
                if att is None:  # netsim numbers every delivery
                    return "rx-unnumbered"
                d = wire.decode_delivery(att[:-auth.TAG_BYTES] if tagged else att)
                return "rx-out-of-sequence" if d is not None and d[0] <= self.consumed else None

            def verify(data):
                # netsim checked the sender's seal (with the sender's key, which we do not hold)
                # and vouches for the frame under OUR key: its delivery tag.
                auth.check_delivery(ring, aid, att, data)
                return auth.unwrap(data)[1]

            door.admit("rx", s.payload, lambda data: ("rx", data, s.attachment), numbered,
                       verify=verify if tagged else None)

        sensor_keys = (self.keys.sensors(aid),) if self.cfg.sensor_keys is None else self.cfg.sensor_keys
        self._subs = [
            # Sensor frames carry no attachment: the slot holds their arrival, for the lag stats.
            *(self.session.declare_subscriber(
                key, lambda s: door.admit("sensors", s.payload, lambda d: ("sensors", d, time.monotonic()),
                                          key=str(s.key_expr)))
              for key in dict.fromkeys(sensor_keys)),
            *(self.session.declare_subscriber(key, frame("measurements")) for key in dict.fromkeys(self.cfg.measurement_keys)),
            self.session.declare_subscriber(self.keys.radio_rx(aid), frame("rx") if self.cfg.direct else delivery),
            self.session.declare_subscriber(self.keys.clock, frame("clock", wire.key_limit(Clock))),
        ]
        if self.cfg.direct:
            # Remote only: our own broadcasts would come back to us on this key.
            self._subs.append(self.session.declare_subscriber(self.keys.radio_rx(BROADCAST), frame("rx"),
                                                              allowed_origin=zenoh.Locality.REMOTE))
            # No netsim to NACK frames to an agent that is gone: the swarm's liveliness tokens
            # tell the node who is there (history: the agents up before us as well).
            self._subs.append(self.session.liveliness().declare_subscriber(
                self.keys.alive("*"), lambda s: self.inbox.put(("alive", str(s.key_expr), s.kind == zenoh.SampleKind.PUT)),
                history=True))
        self._pub_tx = {} if self.cfg.direct else self.session.declare_publisher(self.keys.radio_tx(aid), **block)
        self._pub_est = self.session.declare_publisher(self.keys.estimate(aid), **radio)
        self._pub_done = self.session.declare_publisher(self.keys.done(aid), **block)
        self._pub_cmd = self.session.declare_publisher(self.keys.command(aid), **block)
        self._radio_options = radio
        self._stats_key = self.keys.stats(aid)
        self._stats_q = self.session.declare_queryable(self._stats_key, lambda q: self.inbox.put(("stats", q, None)))
        self.sources = sensor_sources.build(self.node, self.cfg.sources, self.cfg.mavlink_output, self.cfg.epoch,
                                            self.session, self.cfg.ros2)
        if self.cfg.ros2 is not None and self.cfg.ros2_publish and self.node.model.state_dim:
            from swarmloc.wire.ros2 import Ros2Publisher

            self.ros2 = Ros2Publisher(self.session, self.cfg.ros2, f"swarmloc_agent_{aid}", [aid], radio)
        if self.cfg.record is not None:
            from swarmloc.experiment.recording import Recorder

            # Wall-clock log times (UNIX ns): an agent's recording has no modelled clock of its own.
            self.recorder = Recorder(self.cfg.record, {"writer": "agent", "id": aid, "swarm": self.cfg.swarm,
                                                       "model": self.node.model.name, "algorithm": self.node.algorithm,
                                                       **(self.cfg.record_meta or {})}, start_ns=0)
        if self.cfg.estimate_log is not None:
            self.cfg.estimate_log.parent.mkdir(parents=True, exist_ok=True)
            self._log = open(self.cfg.estimate_log, "a", buffering=1)  # a line at a time: a kill loses none
        if self.cfg.mavlink_output is not None or self.cfg.setpoints is not None:
            self.fc = next(s for s in self.sources if isinstance(s, sensor_sources.FlightControllerTicks))
            self.fc_out = fc_output.FcOutputs(self.node, self.fc, self.cfg.mavlink_output, self.cfg.setpoints)
        # Declared last: once netsim sees the token, every subscription above is in place.
        self._token = self.session.liveliness().declare_token(self.keys.alive(aid))

    def close(self) -> None:
        for source in self.sources:
            source.close()
        if self.ros2 is not None:
            self.ros2.close()
        if self.recorder is not None:
            self.recorder.close()
        if self._log is not None:
            self._log.close()
        if self._checkpoint_fd is not None:
            os.close(self._checkpoint_fd)
            self._checkpoint_fd = None
        try:
            self._token.undeclare()
        except Exception:
            pass
        self.session.close()

    def stop(self) -> None:
        self._stop.set()
        self.inbox.put(("stop", b"", None), force=True)

    def stats(self) -> dict:
        lat = sorted(self.hop_latency)
        pct = lambda q: lat[min(len(lat) - 1, int(q * len(lat)))] * 1e6 if lat else None
        lag = sorted(self.sensor_lag)
        return {"hop_us_median": pct(0.5), "hop_us_p99": pct(0.99), "hops": len(lat), "id": self.node.id,
                "algorithm": self.node.algorithm, "k": self.node.k, "handled": self.handled, "ticks": self.ticks,
                "ticks_skipped": self.ticks_skipped,
                "sensor_lag_ms_median": lag[len(lag) // 2] * 1e3 if lag else None,
                "sensor_lag_ms_max": lag[-1] * 1e3 if lag else None,
                "sent": self.sent, "commands": self.commands, "consumed": self.consumed, "rejected": dict(self.rejected + self.door.counts()),
                "deliveries_lost": self.deliveries_lost,
                **({"peers": sorted(self.peers), "peer_delay_ms": {
                    a: {"min": min(d) * 1e3, "median": float(np.median(d)) * 1e3}
                    for a, d in sorted(self.peer_delay.items()) if d}} if self.cfg.direct else {}),
                "since_frame_s": None if self.frame_wall is None else time.monotonic() - self.frame_wall,
                "node_drops": dict(self.node.drops), **getattr(self.node, "stats", {}),
                **({"sources": {s.name: s.stats() for s in self.sources}} if self.sources else {}),
                **({"outputs": self.fc_out.stats()} if self.fc_out is not None else {}),
                **(self.clocks.stats() if self.clocks is not None else {}),
                **({"merged": dict(self.merged)} if self.cfg.measurement_keys else {}),
                "inbox": self.inbox.stats()}

    def _reply_stats(self, query) -> None:
        # Reply on our own key, not the query's: a wildcard query must not consolidate agents away.
        # The query's nonce goes back under our seal: only this answer answers that query.
        nonce = auth.nonce_of(query.payload) if query.payload is not None else ""
        data = {**self.stats(), **({"nonce": nonce} if nonce else {})}
        # Signed, for whoever asked (netsim or an operator): our private key, nobody else's.
        query.reply(self._stats_key, self._seal(wire.encode(Reply(True, "", data), self.node.id, 0), self._stats_key,
                                                auth.BROADCAST))

    # ---------------------------------------------------------------- loop

    def run(self) -> None:
        """Handle inputs until stopped (signal, stop clock, or stop()): this agent's own loop,
        for a process of one agent (a host serves several from one loop: agents/host.py)."""
        item = None
        while self.service(item):
            try:  # timed, so a signal handler gets its turn in this thread
                item = self.inbox.get(timeout=max(0.0, self.wake_at - time.monotonic()))
            except queue.Empty:
                item = None

    def service(self, item=None) -> bool:
        """One turn of the agent: `item` (taken from the inbox by the driver) and everything
        queued behind it handled, due timers fired, the batch acknowledged; never blocks. Then
        `wake_at` says when the agent next needs a turn if nothing arrives (a timer, a polled
        source); the inbox's `wake` hook says when something does. False once stopped."""
        while True:
            if self._stop.is_set():
                return False
            # Polled sources first, every input: a busy inbox must not starve a flight controller.
            now = time.monotonic()
            for source in self.sources:
                for body in source.ready(now):
                    self._unacked |= self._input("frame", body, source)
            self._fc_poll(now)
            self._time_sync(now)
            if item is None:
                try:
                    item = self.inbox.get(0)
                except queue.Empty:
                    due = self.timers.next_due()
                    if self.node.synchronous or due is None or due > self._now():
                        break
                    item = ("timers", None, None)
            kind, data, attachment = item
            item = None
            if kind == "stop":
                return False
            if kind == "stats":
                self._reply_stats(data)
                data = None  # release the query: Zenoh sends the final reply when it is freed
                continue
            self._unacked |= self._input(kind, data, attachment)
        if self._unacked:
            # One estimate and one `done` for everything that was queued together: fewer
            # frames, and fewer wake-ups of netsim, which acts on the last `done` only.
            self._unacked = False
            self._publish_estimate()
            # Always acknowledge in lockstep (and before netsim's first clock says which mode
            # this is, and in direct mode), even a rejected input: lockstep must not wait on us
            # for nothing. Under a real-time clock netsim waits for nobody and reads only the
            # tick of a `done` (who keeps up): one a tick, not one per radio frame (at 256
            # agents 6,000 a tick, as many as the deliveries, each sealed and opened).
            if self.node.synchronous or self.clock_k < 0 or self.node.k != self._done_k:
                self._done_k = self.node.k
                done = self._seal(wire.encode(Done(self.node.k, self.consumed, self.sent, self.commands),
                                               self.node.id, self.handled), self.keys.done(self.node.id), self.hub)
                self._pub_done.put(done)
                if self.recorder is not None:
                    self._record(self.keys.done(self.node.id), done)
                    self.recorder.end_tick(self.node.k, 0.0)  # flushes when one is due
        now = time.monotonic()
        wait = min([0.5, *(s.wait(now) for s in self.sources), self._fc_wait(now)])
        if not self.node.synchronous and (due := self.timers.next_due()) is not None:
            wait = min(wait, max(0.0, due - self._now()))
        self.wake_at = now + wait
        return True

    def _input(self, kind: str, data, attachment) -> bool:
        """Hand one input to the node and send what it answers; True if it is to be acknowledged."""
        try:
            sends = self._handle(kind, data, attachment)
        except Exception:  # a bug in a node must not take the agent down mid-swarm
            self.rejected["node-error"] += 1
            log.exception("agent %s: error handling %s", self.node.id, kind)
            sends = []
        if sends is None:
            return False  # clock: nothing to acknowledge
        self.handled += 1
        if self._held_tick is not None and self.node.k >= self._held_tick[0]:
            self._tick_done(*self._held_tick)
        for s in self.timers.split(sends, self._now()):
            self._send(s)
        return True

    def _record(self, key: str, data: bytes) -> None:
        self.recorder.frame(key, data, time.time())

    def _reject(self, reason: str, why: str) -> None:
        self.rejected[reason] += 1
        n = self.rejected[reason]
        if n <= 10 or n % 1000 == 0:
            log.warning("agent %s drops a frame: %s (%d so far): %s", self.node.id, reason, n, why)

    def _seal(self, data: bytes, key: str, to: int) -> bytes:
        return data if self.sealer is None else self.sealer.seal(data, key, to)

    def _envelope(self, kind: str, data: bytes, expect=None, delivered: bool = False) -> wire.Envelope | None:
        """A decoded frame, or None, refused and counted (docs/wire.md, "Receiver rules";
        docs/security.md: with a keyring the frame is authenticated before it is decoded).
        `delivered`: a netsim delivery, whose tag vouched for the sender's seal already and
        whose number is its place in sequence (no counter window)."""
        sender = None
        if self.opener is not None:
            try:  # the door verified the tag: what is left is the sender's counter window
                if delivered:
                    data, sender = auth.unwrap(data)[:2]
                else:
                    data, sender = self.opener.admit(data)
            except auth.AuthError as exc:
                return self._reject(f"auth-{exc.reason}", f"{kind}: {exc}")
            if not self.rate.allow(sender, time.monotonic()):  # before the costly decode
                return self._reject("rate-limited", f"{kind} from {sender}")
        try:
            env = wire.decode(data, expect=expect)
        except wire.WireError as exc:
            return self._reject("malformed", f"{kind}: {exc}")
        if sender is None and not self.rate.allow(env.src, time.monotonic()):
            return self._reject("rate-limited", f"{kind} from {env.src}")
        if sender is not None and env.src != sender:
            return self._reject("auth-src-mismatch", f"{kind}: sealed by {sender}, says src {env.src}")
        if kind in ("sensors", "clock") and not self.cfg.direct and env.src != NETSIM_ID:
            return self._reject("src-mismatch", f"{kind} from {env.src}")
        if kind == "sensors" and env.dst is not None and env.dst != self.node.id:
            return self._reject("misaddressed", f"sensor frame for {env.dst}")
        return env

    def _now(self) -> float:
        """The node's clock for timers: modelled time in lockstep, scaled wall time otherwise."""
        if self.node.synchronous:
            return self.model_t
        return self.clock_t + (time.monotonic() - self.clock_wall) * self.speed

    def _fire_timers(self, now: float) -> list:
        return [x for tag in self.timers.pop_due(now) for x in self.node.on_timer(tag, now)]

    def _handle(self, kind: str, data: bytes | None, attachment) -> list | None:
        """Radio frames to send in response; None for inputs that need no acknowledgement."""
        if kind == "timers":
            return self._fire_timers(self._now())
        if kind == "alive":
            return self._membership(data, attachment)
        if kind == "frame":  # from a polled source: decoded already, arrived just now
            if self.recorder is not None:  # as it would cross Zenoh from a driver
                self._record(self.keys.sensors(self.node.id), wire.encode(data, self.node.id, self.ticks + 1))
            return self._step(data, attachment, None)
        if self.recorder is not None and kind in RECORDED:
            aid = self.node.id
            key = {"sensors": self.keys.sensors(aid), "rx": self.keys.radio_rx(aid), "clock": self.keys.clock,
                   "measurements": (self.cfg.measurement_keys or (self.keys.sensors(aid),))[0]}[kind]
            self._record(key, data)
        if kind == "clock":
            env = self._envelope(kind, data, (Clock,))
            if env is None:
                return None
            if env.body.mode == "stop":
                if self.cfg.exit_on_stop:
                    self._stop.set()
            elif env.body.k <= self.clock_k:
                self._reject("clock-replay", f"tick {env.body.k} after {self.clock_k}")
            else:
                self.clock_k = env.body.k
                self.node.synchronous = env.body.mode == "lockstep"
                self.speed, self.clock_t, self.clock_wall = env.body.speed, env.body.t, time.monotonic()
            return None
        if kind == "sensors":
            env = self._envelope(kind, data, (Sensors,))
            return [] if env is None else self._step(env.body, None, attachment)
        if kind == "measurements":
            env = self._envelope(kind, data, (Sensors,))
            if env is not None:
                if len(self.pending) >= MAX_PENDING:
                    self.merged["dropped-overflow"] += 1
                else:
                    self.pending.append(env.body)
            return None
        if not self.cfg.direct:
            # netsim numbers what it delivers to us 1, 2, 3... on one publisher: anything else on
            # our key is not a delivery (a copy, a replay, a stranger) and must not be counted
            # as consumed, or lockstep would wait for frames that never come.
            attached = attachment.to_bytes() if attachment is not None else None
            if self.opener is not None and attached is not None:
                try:  # netsim's tag on the delivery number: nobody else can hand us the next one
                    attached = auth.check_delivery(self.cfg.keyring, self.node.id, attached, data)
                except auth.AuthError as exc:
                    return self._reject(f"auth-{exc.reason}", "radio delivery") or []
            delivery = wire.decode_delivery(attached)
            if delivery is None:
                return self._reject("rx-unnumbered", "radio frame without a delivery number") or []
            n, sent = delivery
            if n <= self.consumed:
                return self._reject("rx-out-of-sequence", f"delivery {n} after {self.consumed}") or []
            if n - self.consumed > MAX_DELIVERY_GAP:
                return self._reject("rx-too-far", f"delivery {n} after {self.consumed}") or []
            if n > self.consumed + 1:
                # Deliveries in between were lost (our inbox overflowed): a gap to step over, not
                # a reason to refuse every later one (issue 26, finding 4).
                self.deliveries_lost += n - self.consumed - 1
                log.warning("agent %s: deliveries %d..%d lost", self.node.id, self.consumed + 1, n - 1)
            self.consumed = n
            if sent is not None and len(self.hop_latency) < 100_000:
                self.hop_latency.append(time.perf_counter() - sent)
        env = self._envelope("radio", data, delivered=not self.cfg.direct)
        if env is None:
            return []
        if self.cfg.direct:
            sent = wire.decode_send_time(attachment.to_bytes() if attachment is not None else None)
            arrival = time.time()
            if sent is not None and math.isfinite(sent) and env.src in self.peers:
                self.peer_delay.setdefault(env.src, deque(maxlen=256)).append(arrival - sent)
                self.clocks.heard(env.src, sent, arrival)
            if isinstance(env.body, TimeSync):  # the daemon's, not the node's
                if env.src != self.node.id:
                    self.clocks.synced(env.src, env.body, sent, arrival)
                return []
        return self._radio(env)

    def _membership(self, key: str, up: bool) -> list:
        """Direct mode: an agent's liveliness token appeared or went (Zenoh reports a key's
        first token and its last one going)."""
        try:
            aid = wire.Keys.agent_of(key)
        except ValueError:
            return self._reject("alive-unknown", key) or []
        if aid == self.node.id:
            return []
        (self.peers.add if up else self.peers.discard)(aid)
        if up:
            log.info("agent %s: peer %s joined (liveliness)", self.node.id, aid)
            return self.node.peer_joined(aid)
        log.warning("agent %s: peer %s left (liveliness token gone); routing around it", self.node.id, aid)
        return self.node.peer_left(aid)

    def _step(self, frame: Sensors, source, arrival: float | None) -> list:
        """The node's step on a sensor frame (from a key, or a polled `source`)."""
        fired = []
        entry = time.monotonic()
        if self.node.synchronous:
            self.model_t = frame.t
            fired = self._fire_timers(self.model_t)
            arrival = None  # no lag in lockstep
        if self.pending:
            frame = self._merge(frame)
        before = self.node.k
        # The last tick's final estimate goes out before the node moves on, even when inputs
        # kept the queue from emptying (estimates are otherwise published when it is empty).
        self._publish_estimate()
        if before < 0 and not self.resumed and frame.k > 0 and getattr(source, "start", None) == frame.k:
            # A fresh agent's first tick on the swarm clock is where its prior holds, not tick 0:
            # no ticks were missed before it.
            prior = self.node.estimate()
            self.node.resume(frame.k - 1, prior.mean, prior.cov)
        sends = fired + self.node.step(frame)
        if self.node.k == frame.k and frame.k > before:  # a stale frame (dropped by the node) is no tick
            self._held_tick = None  # (a frame held before this one was dropped: skipped, below)
            self._tick_done(frame.k, frame.t, source, arrival, before, entry)
        elif self.node.k < frame.k and frame.k > before and not self.node.synchronous:
            # Taken but held (RDL: a tick that comes while the node waits for a pair's commit
            # runs when the commit is in): counted, and its lag measured, when it runs. A later
            # frame held in its place means this one was dropped (the node says tick-skipped).
            self._held_tick = (frame.k, frame.t, source, arrival, before)
        elif arrival is not None and len(self.sensor_lag) < 100_000:
            self.sensor_lag.append(entry - arrival)
        self._checkpoint()
        return sends

    def _tick_done(self, k: int, t: float, source, arrival: float | None, before: int,
                   stepped: float | None = None) -> None:
        """The node has stepped onto tick k, whose sensor frame arrived at `arrival`: handed to
        it at `stepped` (a held frame: now, when the node reached its tick)."""
        self._held_tick = None
        self.ticks += 1
        if before >= 0:
            self.ticks_skipped += max(0, k - before - 1)
        self.frame_source, self.frame_t, self.frame_wall = source, t, time.monotonic()
        if arrival is not None and len(self.sensor_lag) < 100_000:
            self.sensor_lag.append((stepped if stepped is not None else self.frame_wall) - arrival)

    def _merge(self, frame: Sensors) -> Sensors:
        """The frame with the measurements that arrived since the last one (docs/deploy.md,
        "Measurements from another source"): lists joined up to the wire's 64 each, a fix or
        pseudoranges taken where the frame has none; the partial frames' tick, time and
        motion data are not used."""
        lists = {f: list(getattr(frame, f)) for f in MERGED_LISTS}
        single = {f: getattr(frame, f) for f in MERGED_SINGLE}
        seen = {r.target: r for r in frame.vehicle.seen} if frame.vehicle is not None else {}
        for part in self.pending:
            for f in MERGED_LISTS:
                for m in getattr(part, f):
                    if len(lists[f]) < MAX_MERGED:
                        lists[f].append(m)
                        self.merged[f] += 1
                    else:
                        self.merged[f"{f}-dropped-full"] += 1
            for f in MERGED_SINGLE:
                if getattr(part, f) is not None:
                    if single[f] is None:
                        single[f] = getattr(part, f)
                        self.merged[f] += 1
                    else:
                        self.merged[f"{f}-dropped-taken"] += 1
            for f in ("odometry", "imu", "align"):
                if getattr(part, f) is not None:
                    self.merged[f"{f}-ignored"] += 1
            if part.vehicle is not None:
                # A camera's relative positions to other vehicles: the only part of a vehicle
                # reading a driver has (its command, attitude and dt are the frame source's).
                # The latest sighting of each vehicle supersedes earlier ones: a tick fuses one
                # per target, and a backlog (frames were late) costs no backlog of fusions.
                if frame.vehicle is None:
                    self.merged["vehicle-ignored"] += 1
                else:
                    for r in part.vehicle.seen:
                        if r.target in seen:
                            self.merged["seen-superseded"] += 1
                        self.merged["seen"] += 1
                        seen[r.target] = r
        self.pending = []
        merged_seen = list(seen.values())
        # Changed or not by identity: == on messages compares their arrays, which have no one
        # truth value (a superseded sighting raised ValueError here; tests/test_fuzz.py).
        if frame.vehicle is not None and (len(merged_seen) != len(frame.vehicle.seen) or
                                          any(a is not b for a, b in zip(merged_seen, frame.vehicle.seen))):
            lists["vehicle"] = replace(frame.vehicle, seen=merged_seen[:MAX_MERGED])
        return replace(frame, **lists, **single)

    def _checkpoint(self) -> None:
        # A file write costs ~2 ms here, a fifth of a lockstep tick: at most every 0.2 s of wall
        # time. Resuming from an older checkpoint is still sound: the node inflates its
        # covariance for every tick between the checkpoint and now (Node.missed_motion).
        now = time.monotonic()
        if self.cfg.state_file is None or now - self._last_checkpoint < 0.2:
            return
        self._last_checkpoint = now
        e = self.node.estimate()
        # One flat float64 .npy: [k, mean..., cov...]. np.savez cost 320 us a tick; this ~40 us.
        buf = io.BytesIO()
        np.save(buf, np.concatenate([[e.k], e.mean, e.cov.ravel()]))
        data = buf.getvalue()
        if self._checkpoint_fd is not None and len(data) == self._checkpoint_size:
            # The same shape, so the same size: overwritten in place by one write of less than
            # a page, which a kill cannot cut in half (the kernel copies it in one piece). A
            # new file and a rename cost ~105 us of CPU each (ext4), this ~6 us: with 256
            # agents checkpointing every tick, a twentieth of a core.
            os.pwrite(self._checkpoint_fd, data, 0)
            return
        tmp = self.cfg.state_file.with_name(self.cfg.state_file.name + ".tmp")
        with open(tmp, "wb") as f:
            f.write(data)
        os.replace(tmp, self.cfg.state_file)  # atomic: a kill never leaves half a checkpoint
        if self._checkpoint_fd is not None:
            os.close(self._checkpoint_fd)
            self._checkpoint_fd = None
        if len(data) <= PAGE_BYTES:
            self._checkpoint_fd, self._checkpoint_size = os.open(self.cfg.state_file, os.O_WRONLY), len(data)

    def resume(self) -> bool:
        """Load the checkpoint if there is one; True if the node resumed from it."""
        path = self.cfg.state_file
        if path is None or not path.exists():
            return False
        d = self.node.model.state_dim
        try:
            flat = np.load(path, allow_pickle=False)
            if flat.shape != (1 + d + d * d,) or not np.isfinite(flat).all():
                raise ValueError(f"shape {flat.shape}, want {(1 + d + d * d,)}")
            k, mean, cov = int(flat[0]), flat[1:1 + d], flat[1 + d:].reshape(d, d)
            self.node.resume(k, mean, cov)
        except (OSError, ValueError) as exc:
            # A restart all the same: resume from the prior (tick -1), so the node inflates its
            # covariance for every tick it missed, and a UKF-DCL node knows the others still
            # hold cross-covariances with its lost state (it rejoins as an orphan).
            log.warning("agent %s: checkpoint %s unusable (%s); resuming from the prior", self.node.id, path, exc)
            prior = self.node.estimate()
            self.node.resume(-1, prior.mean, prior.cov)
            return False
        log.warning("agent %s resumed from its checkpoint of tick %d", self.node.id, k)
        self.resumed = True
        return True

    def _radio(self, env: wire.Envelope) -> list:
        if isinstance(env.body, LinkNack):
            failed = self.outbox.failed(env.body) if env.src == NETSIM_ID and not self.cfg.direct else None
            if failed is None:
                return self._reject("nack-unmatched", f"nack for seq {env.body.seq}") or []
            return self.node.link_failed(failed.dst, failed.msg)
        if env.dst is not None and env.dst != self.node.id:
            return self._reject("misaddressed", f"frame for {env.dst}") or []
        if env.src == self.node.id:
            return self._reject("own-src", "a frame of our own") or []
        return self.node.receive(env.src, env.body)

    def _send(self, send) -> None:
        tx = self.outbox.encode(send)
        if tx is None:
            return self._reject("oversize-out", f"{send.msg.TYPE} to {send.dst}")
        if self.cfg.direct:
            key = self.keys.radio_rx(BROADCAST if send.dst is None else send.dst)
            data = self._seal(tx.data, key, auth.BROADCAST if send.dst is None else send.dst)
            pub = self._pub_tx.get(key)
            if pub is None:
                pub = self._pub_tx[key] = self.session.declare_publisher(key, **self._radio_options)
            # The sender's UNIX time: the receiver's apparent delay bounds the clocks' offset.
            pub.put(data, attachment=wire.encode_send_time(time.time()))
        else:
            key = self.keys.radio_tx(self.node.id)
            data = self._seal(tx.data, key, NETSIM_ID)
            self._pub_tx.put(data, attachment=wire.encode_send_time(time.perf_counter()))
        if self.recorder is not None:
            self._record(key, data)
        self.sent += 1

    def _publish_command(self) -> None:
        """Closed loop: the node's command from the estimate just published, numbered 1, 2, 3...
        (the count goes into `done`, so lockstep waits for it)."""
        cmd = self.node.command() if self._pub_cmd is not None else None
        if cmd is None:
            return
        self.commands += 1
        self._pub_cmd.put(self._seal(wire.encode(cmd, self.node.id, self.commands), self.keys.command(self.node.id),
                                     self.hub))
        self._fc_command(cmd)

    # ---------------------------------------------------------------- the flight controller's outputs

    def _fc_estimate(self, e) -> None:
        """A new estimate for the FC's stream (agents/companion/output.py propagates and paces it)."""
        if self.fc_out is not None:
            self.fc_out.estimate(e.k, e.mean, e.cov, self.frame_source is self.fc)

    def _fc_command(self, cmd) -> None:
        """The command in force for the FC's frames, and its setpoints when they are enabled."""
        if self.fc_out is not None:
            self.fc_out.command(cmd.u, self.node.estimate().mean)

    def _fc_poll(self, now: float) -> None:
        if self.fc_out is not None:
            self.fc_out.poll(now)

    def _fc_wait(self, now: float) -> float:
        return self.fc_out.wait(now) if self.fc_out is not None else math.inf

    # ---------------------------------------------------------------- the peers' clocks

    def _time_sync(self, now: float) -> None:
        """Direct mode: every period, the peers' send stamps echoed (agents/timesync.py)."""
        if self.clocks is not None and self.peers and self.clocks.due(now):
            self._send(Send(self.clocks.sync_frame()))

    def _publish_estimate(self) -> None:
        if self.node.model.state_dim == 0:
            return  # a ground station localizes nothing
        e = estimate_of(self.node)
        sig = (e.k, e.mean.tobytes(), e.cov.tobytes(), tuple(m.tobytes() for _, m, _ in e.targets))
        if sig == self._last_published or e.k < 0:
            return
        self._last_published = sig
        self._publish_command()
        if self._log is not None:
            self._log.write(json.dumps({"k": e.k, "t": self.frame_t, "wall": time.time(), "mean": e.mean.tolist(),
                                        "cov": e.cov.tolist()}) + "\n")
        self._fc_estimate(e)
        if self.ros2 is not None:
            self.ros2.publish(self.node.id, self.node.model.name, self.frame_t, e.mean, e.cov, time.time_ns())
        if not self.cfg.publish_swarm and self.recorder is None:
            return
        nis = np.array(e.nis, float).reshape(-1, 2) if e.nis else None
        targets = [TargetEstimateMsg(o, m, P) for o, m, P in e.targets]
        data = self._seal(wire.encode(EstimateMsg(e.k, self.node.algorithm, e.mean, e.cov, nis, targets), self.node.id,
                                      self.handled), self.keys.estimate(self.node.id), self.hub)
        if self.recorder is not None:
            self._record(self.keys.estimate(self.node.id), data)
        if self.cfg.publish_swarm:
            self._pub_est.put(data)


# ---------------------------------------------------------------------------- entry points


class OpenError(RuntimeError):
    """The agent's Zenoh session or a sensor source could not be opened (the message says which)."""


def zenoh_message(exc: Exception) -> str:
    """A Zenoh error without the Rust source locations it carries."""
    return re.sub(r"\s+at \S+\.rs:\d+\.?", "", str(exc)).strip()


def serve(node: Node, cfg: AgentConfig) -> None:
    """An agent's whole life: checkpoint resumed, session opened, inputs handled until stopped.
    `swarmloc agent` and the launcher's `python -m agents.daemon` both end here (and, one
    thread per agent, agents.host)."""
    exit_on_sigterm()
    daemon = open_daemon(node, cfg)
    try:
        run_daemon(daemon)
    except KeyboardInterrupt:
        pass


def open_daemon(node: Node, cfg: AgentConfig) -> AgentDaemon:
    """The node's daemon, resumed from its checkpoint, its session and sources open (OpenError
    saying which could not be)."""
    daemon = AgentDaemon(node, cfg)
    daemon.resume()
    try:
        daemon.open()
    except zenoh.ZError as exc:
        raise OpenError(f"agent {node.id}: cannot open a Zenoh session ({cfg.mode}, connect {', '.join(cfg.connect)}): "
                        f"{zenoh_message(exc)}") from None
    return daemon


def run_daemon(daemon: AgentDaemon) -> None:
    """An opened daemon's loop, said in the log first, until stopped; the session closed after."""
    announce(daemon)
    try:
        daemon.run()
    finally:
        daemon.close()


def announce(daemon: AgentDaemon) -> None:
    """What an agent about to run listens to, in the log."""
    node, cfg, keys = daemon.node, daemon.cfg, daemon.keys
    radio = [keys.radio_rx(node.id), *([keys.radio_rx(BROADCAST)] if cfg.direct else [])]
    inputs = [*((keys.sensors(node.id),) if cfg.sensor_keys is None else cfg.sensor_keys), *(s.name for s in daemon.sources)]
    log.info("agent %s up (%s mode, connect %s, listen %s, %s radio); waiting for sensor frames on %s, radio frames "
             "on %s, clock on %s", node.id, cfg.mode, ", ".join(cfg.connect), ", ".join(cfg.listen) or "-",
             "direct" if cfg.direct else "netsim", ", ".join(inputs) or "-", ", ".join(radio), keys.clock)
    if cfg.measurement_keys:
        log.info("agent %s: measurements on %s join the next sensor frame", node.id, ", ".join(cfg.measurement_keys))
    if len(inputs) > 1:
        log.warning("agent %s: %d sensor sources (%s); frames are not merged: each must carry whole ticks, and the "
                    "node steps on whichever tick comes next (docs/deploy.md#sensor-sources)", node.id, len(inputs),
                    ", ".join(inputs))
    if cfg.direct and cfg.keyring is None:
        log.warning("agent %s: no key file: frames are neither authenticated nor checked; anyone on the network "
                    "can speak for this swarm (docs/security.md)", node.id)
    if not cfg.publish_swarm:
        log.info("agent %s: outputs.swarm is false: no estimate on %s", node.id, keys.estimate(node.id))


def main(argv: list[str] | None = None) -> int:
    """python -m agents.daemon: the agent process `swarmloc run` starts, its node given as a spec
    file. No scenario and no CLI framework are imported (typer brings pydantic): an agent
    process stays small. By hand, use `swarmloc agent` (docs/cli.md)."""
    p = argparse.ArgumentParser(prog="python -m agents.daemon", description=main.__doc__.splitlines()[0])
    p.add_argument("--id", type=int, required=True)
    p.add_argument("--spec", type=Path, required=True, help="node spec (JSON), as `swarmloc run` writes it")
    p.add_argument("--swarm", default="default")
    p.add_argument("--connect", action="append", required=True, help="Zenoh endpoint (repeatable)")
    p.add_argument("--state-file", type=Path)
    p.add_argument("--keys", type=Path, help="the swarm's key directory: frames sealed with this agent's own keys "
                   "(agent-<id>.secret) and opened with members.json")
    p.add_argument("-v", "--verbose", action="store_true")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO if a.verbose else logging.WARNING,
                        format=f"%(asctime)s agent-{a.id} %(levelname)s %(message)s")
    try:
        node = load_node(a.spec, a.id)
        keyring = None if a.keys is None else auth.Keyring.load(a.keys, auth.member_of(a.id))
        serve(node, AgentConfig(swarm=a.swarm, connect=tuple(a.connect), state_file=a.state_file, keyring=keyring))
    except (ValueError, OpenError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2 if isinstance(exc, ValueError) else 3
    return 0


def load_node(path: Path, aid: int) -> Node:
    """Agent aid's node from its spec file (ValueError saying what is wrong otherwise)."""
    try:
        node = NodeSpec.loads(path.read_text()).build()
    except (OSError, ValueError, TypeError, KeyError, AttributeError, ImportError) as exc:
        raise ValueError(f"--spec {path}: {exc}") from None
    if node.id != aid:
        raise ValueError(f"--spec {path} is agent {node.id}'s node, not agent {aid}'s")
    return node


if __name__ == "__main__":
    sys.exit(main())
