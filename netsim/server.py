"""The netsim process: owns the clock, the world and the radio; routes every frame.

Lockstep: publish tick k and every agent's sensor frame, then route radio frames until the
swarm is quiet, i.e. for every live agent its last `done` says it handled tick k, consumed
every frame netsim delivered to it and sent nothing netsim has not yet received. Nothing
else is trusted about ordering across keys.

As in the agent daemon, Zenoh callbacks only enqueue; one loop does the work.
"""

from __future__ import annotations

import logging
import queue
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import zenoh

from netsim.sim import Simulation
from swarmloc import wire
from swarmloc.messages import Clock, Control, Done, EstimateMsg, LinkMsg, LinkNack, Links, Reply, Truth
from swarmloc.node import Estimate
from swarmloc.results import RunRecord, compute_references, write_run
from swarmloc.scenario import Scenario

log = logging.getLogger("swarmloc.netsim")
NETSIM_ID = 0  # sender id netsim uses on the wire (agent ids are the scenario's)


class SetupError(RuntimeError):
    pass


@dataclass
class ServerConfig:
    swarm: str = "default"
    listen: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    out: Path | None = None
    seed: int | None = None
    join_timeout: float = 30.0  # s to wait for every agent to come alive
    tick_timeout: float = 10.0  # s of silence before a lagging agent is declared unresponsive
    plots: bool = True
    on_tick: Callable[[int, int], None] | None = field(default=None, repr=False)


class NetsimServer:
    def __init__(self, scenario: Scenario, cfg: ServerConfig):
        self.sc, self.cfg = scenario, cfg
        self.sim = Simulation(scenario, cfg.seed)
        self.ids = self.sim.ids
        self.keys = wire.Keys(cfg.swarm)
        self.q: queue.SimpleQueue = queue.SimpleQueue()
        self.alive: set[int] = set()
        self.unresponsive: set[int] = set()
        self.done: dict[int, Done] = {}
        self.delivered = {a: 0 for a in self.ids}  # frames put on radio/rx/<a>
        self.received = {a: 0 for a in self.ids}  # frames taken from radio/tx/<a>
        self.invalid_tx = 0
        self.pending_faults: list[tuple[str, list[int]]] = []
        self.record = RunRecord(self.ids, len(scenario.agent(self.ids[0]).start))
        self.seq = 0
        self.hop_latency: list[float] = []  # wall seconds from tx arrival to rx publish

    # ---------------------------------------------------------------- zenoh plumbing

    def open(self) -> None:
        conf = zenoh.Config.from_json5(wire.zenoh_config("router", self.cfg.listen))
        try:
            self.session = zenoh.open(conf)
        except zenoh.ZError as exc:
            raise SetupError(f"cannot open Zenoh router on {', '.join(self.cfg.listen)}: {exc}") from None
        put, k = self.q.put, self.keys
        block = dict(congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE)
        self._subs = [
            self.session.declare_subscriber(f"{k.prefix}/radio/tx/*", lambda s: put(("tx", str(s.key_expr), s.payload.to_bytes(), (time.perf_counter(), s.attachment)))),
            self.session.declare_subscriber(f"{k.prefix}/agent/*/done", lambda s: put(("done", str(s.key_expr), s.payload.to_bytes(), None))),
            self.session.declare_subscriber(f"{k.prefix}/agent/*/estimate", lambda s: put(("est", str(s.key_expr), s.payload.to_bytes(), None))),
            self.session.liveliness().declare_subscriber(f"{k.prefix}/agent/*/alive", lambda s: put(("alive", str(s.key_expr), s.kind, None)), history=True),
        ]
        self._ctl = self.session.declare_queryable(k.control, lambda q: put(("ctl", "", q, None)))
        self.pub_clock = self.session.declare_publisher(k.clock, **block)
        self.pub_links = self.session.declare_publisher(k.links, **block)
        self.pub_sensors = {a: self.session.declare_publisher(k.sensors(a), **block) for a in self.ids}
        self.pub_truth = {a: self.session.declare_publisher(k.truth(a), **block) for a in self.ids}
        self.pub_rx = {a: self.session.declare_publisher(k.radio_rx(a), **block) for a in self.ids}

    def close(self) -> None:
        self.session.close()

    def _put(self, pub, msg) -> None:
        self.seq += 1
        pub.put(wire.encode(msg, NETSIM_ID, self.seq))

    # ---------------------------------------------------------------- inputs

    def _handle(self, item) -> None:
        kind, key, payload, stamp = item
        if kind == "tx":
            self._route(key, payload, stamp)
        elif kind == "done":
            try:
                env = wire.decode(payload, expect=(Done,))
                aid = wire.Keys.agent_of(key)
            except (wire.WireError, ValueError) as exc:
                log.warning("bad done on %s: %s", key, exc)
                return
            if aid in self.delivered:
                self.done[aid] = env.body
                self.unresponsive.discard(aid)
        elif kind == "est":
            try:
                env = wire.decode(payload, expect=(EstimateMsg,))
                aid = wire.Keys.agent_of(key)
            except (wire.WireError, ValueError) as exc:
                log.warning("bad estimate on %s: %s", key, exc)
                return
            e = env.body
            if aid in self.delivered:
                self.record.add_estimate(e.algorithm, aid, Estimate(e.k, e.mean, e.cov))
        elif kind == "alive":
            aid = wire.Keys.agent_of(key)
            if payload == zenoh.SampleKind.PUT:
                self.alive.add(aid)
            else:
                self.alive.discard(aid)
                log.warning("agent %s left the swarm", aid)
        elif kind == "ctl":
            self._control(payload)

    def _route(self, key: str, payload: bytes, stamp) -> None:
        arrived, attachment = stamp
        sent = wire.decode_send_time(attachment.to_bytes() if attachment is not None else None)
        try:
            src = wire.Keys.agent_of(key)
        except ValueError:
            return
        if src not in self.received:
            return
        self.received[src] += 1
        try:
            env = wire.decode(payload)
        except wire.WireError as exc:
            self.invalid_tx += 1
            log.warning("agent %s sent an invalid frame: %s", src, exc)
            return
        receivers = self.sim.route(src, env.dst, len(payload), self.sim.t)
        for r, _t in receivers:
            self._deliver(r, payload, sent)
        if env.dst is not None and not receivers:
            self.seq += 1
            self._deliver(src, wire.encode(LinkNack(env.seq, env.dst, "unreachable"), NETSIM_ID, self.seq))
        self.hop_latency.append(time.perf_counter() - arrived)

    def _deliver(self, r: int, payload: bytes, sent: float | None = None) -> None:
        self.delivered[r] += 1
        self.pub_rx[r].put(payload, attachment=wire.encode_delivery(self.delivered[r], sent))

    def _control(self, query) -> None:
        def reply(ok: bool, error: str = "", data: dict | None = None):
            query.reply(query.key_expr, wire.encode(Reply(ok, error[:500], data or {}), NETSIM_ID, 0))

        try:
            req = wire.decode(query.payload.to_bytes() if query.payload is not None else b"", expect=(Control,)).body
        except wire.WireError as exc:
            return reply(False, f"bad request: {exc}")
        if not isinstance(req.args, dict):
            return reply(False, "args must be a map")
        try:
            self._control_op(req, reply)
        except Exception as exc:  # a bad request must never take netsim down
            log.exception("control %s failed", req.op)
            reply(False, f"{req.op} failed: {exc}")

    def _control_op(self, req, reply) -> None:
        if req.op in ("cut", "restore"):
            link = req.args.get("link")
            if not (isinstance(link, list) and len(link) == 2 and all(isinstance(x, int) for x in link)):
                return reply(False, "args.link must be two agent ids")
            a, b = link
            if a not in self.ids or b not in self.ids or a == b:
                return reply(False, f"no link {a}-{b}: agents are {self.ids}")
            self.pending_faults.append((req.op, link))
            return reply(True, "", {"applies_at_tick": self.sim.k + 1})
        if req.op == "status":
            return reply(True, "", self.status())
        return reply(False, f"unknown op {req.op!r} (cut, restore, status)")

    def status(self) -> dict:
        return {
            "scenario": self.sc.name, "mode": self.sc.clock.mode, "k": self.sim.k, "t": self.sim.t,
            "steps": self.sim.steps, "agents": {str(a): {"alive": a in self.alive, "responsive": a not in self.unresponsive,
                                                         "done_k": self.done[a].k if a in self.done else -1} for a in self.ids},
            "links": self.sim.link_table(), "cut": sorted(sorted(p) for p in self.sim.cut),
        }

    # ---------------------------------------------------------------- lockstep

    def _pump(self, until: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not until():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            try:
                item = self.q.get(timeout=remaining)
            except queue.Empty:
                return until()
            self._handle(item)
            # Drain whatever else is already queued before testing the condition again.
            while True:
                try:
                    self._handle(self.q.get_nowait())
                except queue.Empty:
                    break
        return True

    def _quiet(self, k: int) -> bool:
        for a in self.ids:
            if a in self.unresponsive:
                continue
            d = self.done.get(a)
            if d is None or d.k < k or d.consumed != self.delivered[a] or d.sent != self.received[a]:
                return False
        return True

    def wait_for_agents(self) -> None:
        if not self._pump(lambda: self.alive >= set(self.ids), self.cfg.join_timeout):
            missing = sorted(set(self.ids) - self.alive)
            raise SetupError(f"agents {missing} did not come alive within {self.cfg.join_timeout:.0f} s")

    def run(self) -> dict:
        self.open()
        try:
            self.wait_for_agents()
            t0 = time.perf_counter()
            for _ in range(self.sim.steps + 1):
                self._tick()
            wall = time.perf_counter() - t0
            agent_stats = self.agent_stats()
            self._put(self.pub_clock, Clock(self.sim.k, self.sim.t, "stop", self.sc.clock.dt))
            return self._finish(wall, agent_stats)
        finally:
            self.close()

    def _tick(self) -> None:
        k, t, frames = self.sim.tick(self.pending_faults)
        self.pending_faults = []
        self._put(self.pub_clock, Clock(k, t, "lockstep", self.sc.clock.dt))
        truth = self.sim.truth()
        for a in self.ids:
            self._put(self.pub_truth[a], Truth(k, t, truth[a]))
            self._put(self.pub_sensors[a], frames[a])
        while not self._pump(lambda: self._quiet(k), self.cfg.tick_timeout):
            lagging = [a for a in self.ids if a not in self.unresponsive and not self._quiet_agent(a, k)]
            log.error("tick %d: agents %s silent for %.0f s; going on without them", k, lagging, self.cfg.tick_timeout)
            self.unresponsive.update(lagging)
        self.record.add_tick(k, t, frames, truth)
        if k % max(1, int(round(1.0 / self.sc.clock.dt))) == 0 or self.pending_faults:
            self._put(self.pub_links, Links(k, [LinkMsg(**row) for row in self.sim.link_table()]))
        if self.cfg.on_tick:
            self.cfg.on_tick(k, self.sim.steps)

    def _quiet_agent(self, a: int, k: int) -> bool:
        d = self.done.get(a)
        return d is not None and d.k >= k and d.consumed == self.delivered[a] and d.sent == self.received[a]

    def agent_stats(self, timeout: float = 2.0) -> dict:
        """Each live agent's own counters (drops by reason, hop latency), via its stats queryable."""
        out = {}
        for r in self.session.get(self.keys.stats("*"), timeout=timeout):
            if r.ok is None:
                continue
            try:
                out[str(wire.Keys.agent_of(str(r.ok.key_expr)))] = wire.decode(r.ok.payload.to_bytes(), expect=(Reply,)).body.data
            except (wire.WireError, ValueError) as exc:
                log.warning("bad stats reply: %s", exc)
        return out

    def _finish(self, wall: float, agent_stats: dict) -> dict:
        # Estimates are published before each `done`, so at quiet they have all arrived.
        self._pump(lambda: False, 0.05)
        compute_references(self.sc, self.record, [a for a in ("il", "ukf-ccl") if a in self.sc.estimators])
        lat = np.array(self.hop_latency) * 1e6
        extra = {
            "transport": "zenoh-lockstep",
            "wall_time_s": wall,
            "ticks_per_s": (self.sim.steps + 1) / wall if wall > 0 else None,
            "radio": {**self.sim.radio_summary(), "invalid_tx": self.invalid_tx,
                      "netsim_hop_us_median": float(np.median(lat)) if lat.size else None,
                      "netsim_hop_us_p99": float(np.percentile(lat, 99)) if lat.size else None},
            "faults": self.sim.fault_log,
            "agent_stats": agent_stats,
            "unresponsive_agents": sorted(self.unresponsive),
        }
        algorithms = [a for a in ("il", "ukf-dcl", "ukf-ccl") if a in self.sc.estimators or a in self.record.est]
        if self.cfg.out is None:
            from swarmloc.results import metrics

            return {**metrics(self.record, algorithms), **extra}
        m = write_run(self.cfg.out, self.sc, self.record, algorithms, extra, plots=self.cfg.plots)
        np.savez(Path(self.cfg.out) / "radio.npz", **self.sim.radio_arrays())
        return m
