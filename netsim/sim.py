"""The environment as pure code: world, radio and faults, with no transport.

The netsim process wraps this in Zenoh; the in-process runner (swarmloc.runner) drives it
directly. Both therefore see the same trajectories, sensor noise and link decisions.

Two ways to move frames, one per clock mode:
- exchange(round): lockstep. Every frame the swarm sent since the last round is offered at
  the same modelled instant, in (sender, seq) order, and resolved to the end. The content of
  a round depends only on what the agents computed, never on wall-clock arrival order, so a
  lockstep run is deterministic for a seed, whatever the radio model.
- offer(frame, t) / advance(t): real time. Frames enter the medium when they arrive and
  come out after their modelled airtime, queueing and latency.
"""

from __future__ import annotations

import logging
from collections import Counter
import numpy as np
from pydantic import TypeAdapter, ValidationError

from netsim.channel import ChannelConfig, Jammer, RadioMedium, TxFrame, UnitDisk
from netsim.faults import FaultState
from netsim.world import World, streams
from swarmloc.faults import FaultError, _Fault
from swarmloc.messages import LinkNack
from swarmloc.node import RadioRx as Rx
from swarmloc.node import RadioTx as Tx
from swarmloc.scenario import Scenario, ScenarioError

log = logging.getLogger(__name__)


def _pos3(p) -> np.ndarray:
    """A 2D (planar) or 3D position as 3D: planar robots and jammers sit at height 0."""
    p = np.asarray(p, float)
    return np.pad(p, (0, 3 - p.size))
CHANNEL = TypeAdapter(ChannelConfig)


def channel_of(scenario: Scenario):
    try:
        return CHANNEL.validate_python(scenario.radio)
    except ValidationError as exc:
        lines = [f"  radio.{'.'.join(str(p) for p in e['loc'][1:])}: {e['msg']}" for e in exc.errors()]
        raise ScenarioError(f"{scenario.name}: invalid radio\n" + "\n".join(lines)) from None


class Simulation:
    def __init__(self, scenario: Scenario, seed: int | None = None):
        self.sc = scenario
        self.world = World(scenario, seed)
        rng = streams(scenario.seed if seed is None else seed)
        self.ids = scenario.agent_ids
        self.steps = self.world.steps
        self.channel = channel_of(scenario)
        self.medium = RadioMedium(self.channel, rng["radio"])
        self.loss_seed = int(rng["loss"].integers(2**62))
        self.faults = FaultState(self.ids)
        self.down: set[int] = set()  # agents whose process is not running (netsim's view)
        self.medium.set_positions(self.world.pos)  # a link table is available before tick 0
        self.timeline = sorted(scenario.faults, key=lambda f: f.at)
        self.k, self.t = -1, 0.0
        self.vt = 0.0  # modelled time of the next lockstep round
        self._uid = 0
        self._inflight: dict[int, list] = {}  # uid -> [frame, outcomes still to come]
        self.delivered: Counter[tuple[int, int]] = Counter()
        self.attempts: Counter[tuple[int, int]] = Counter()  # frames src -> receiver, whatever their fate
        self.dropped: Counter[tuple[int, int, str]] = Counter()
        self.last_heard: dict[tuple[int, int], float] = {}
        self.last_sinr: dict[tuple[int, int], float] = {}  # SINR of the last frame src -> receiver
        self.radio_log: list[tuple[int, int, int, int, str]] = []  # (k, src, receiver, size, drop reason or "")
        self.link_log: list[tuple] = []  # per tick and pair: (k, a, b, snr_db, up, delivered, dropped)

    @property
    def fault_log(self) -> list[dict]:
        return self.faults.log

    # ---------------------------------------------------------------- clock

    def tick(self, live_faults: list[_Fault] = ()):
        """Advance one tick; faults due by now (timeline, expiring --for, live) apply to its frames."""
        # Faults first, so a GNSS outage or a kill due at t already shapes tick t's frames.
        self.k, self.t = self.world.k + 1, (self.world.k + 1) * self.world.dt
        while self.timeline and self.timeline[0].at <= self.t + 1e-9:
            self.apply(self.timeline.pop(0), "scenario")
        for f in self.faults.due(self.t):
            self.apply(f, "duration")
        for f in live_faults:
            self.apply(f, "live")
        frames = self.world.step(self.faults.gnss_ok)
        self.medium.set_positions(self.world.pos)
        self.medium.set_jammers([Jammer(tuple(pos), f.power_dbm, self.t, float("inf"), f.band_hz)
                                 for f, pos in self.faults.jammers(self.t)])
        self.vt = max(self.t, self.medium.now)
        self._record_links()
        return self.k, self.t, frames

    def truth(self) -> dict[int, np.ndarray]:
        """Every agent's true state in its model's layout (docs/run-format.md)."""
        return self.world.states()

    def apply(self, f: _Fault, source: str) -> None:
        try:
            self.faults.apply(f, self.t, self.k, source)
        except FaultError as exc:
            log.error("fault not applied: %s", exc)
            raise
        log.info("t=%.1f %s fault: %s", self.t, source, f.model_dump(exclude_none=True))

    # ---------------------------------------------------------------- radio

    def exchange(self, frames: list[Tx]) -> list[Rx]:
        """Lockstep: one round of frames, offered together, resolved completely."""
        out: list[Rx] = []
        for tx in sorted(frames, key=lambda f: (f.src, f.seq)):
            out += self.offer(tx, self.vt)
        # Resolve event by event (advancing to infinity would leave the medium's clock there).
        while (t := self.medium.next_event_time()) is not None:
            out += self.advance(t)
        if out:
            self.vt = max(self.vt, max(r.t for r in out))
        return sorted(out, key=lambda r: (r.t, r.receiver, r.nack is not None))

    def offer(self, tx: Tx, t: float) -> list[Rx]:
        if tx.src not in self.world.pos or (tx.dst is not None and (tx.dst not in self.world.pos or tx.dst == tx.src)):
            self.dropped[(tx.src, tx.dst if tx.dst is not None else -1, "unknown")] += 1
            return self._nack(tx, t, "unknown") if tx.dst is not None else []
        receivers = [tx.dst] if tx.dst is not None else [a for a in self.ids if a != tx.src]
        if self.faults.blocked(tx.src, tx.src) == "radio-off":
            # A radio that is off does not even transmit (and so interferes with nobody).
            for r in receivers:
                self._drop(tx, r, "radio-off")
            return self._nack(tx, t, "radio-off") if tx.dst is not None else []
        self._uid += 1
        self._inflight[self._uid] = [tx, len(receivers)]
        outcomes = self.medium.offer(TxFrame(self._uid, tx.src, tx.dst, len(tx.data)), t)
        return self._resolve(outcomes)

    def advance(self, t: float) -> list[Rx]:
        return self._resolve(self.medium.advance(t))

    def next_event_time(self) -> float | None:
        return self.medium.next_event_time()

    def _resolve(self, outcomes) -> list[Rx]:
        out: list[Rx] = []
        for o in outcomes:
            entry = self._inflight[o.uid]
            tx = entry[0]
            entry[1] -= 1
            if entry[1] == 0:
                del self._inflight[o.uid]
            reason = o.reason
            if np.isfinite(o.sinr_db):
                self.last_sinr[(tx.src, o.receiver)] = float(o.sinr_db)
            if o.delivered:
                reason = ("down" if o.receiver in self.down else None) or self.faults.blocked(tx.src, o.receiver) \
                    or self._jammed(o.receiver)
                if reason is None:
                    p = self.faults.extra_loss(tx.src, o.receiver)
                    if p > 0 and self._uniform(tx, o.receiver) < p:
                        reason = "loss"
            if reason is None:
                self.attempts[(tx.src, o.receiver)] += 1
                self.delivered[(tx.src, o.receiver)] += 1
                self.last_heard[(tx.src, o.receiver)] = o.t
                self.radio_log.append((self.k, tx.src, o.receiver, len(tx.data), ""))
                out.append(Rx(o.receiver, o.t, data=tx.data, src=tx.src, seq=tx.seq, unicast=tx.dst is not None))
            else:
                self._drop(tx, o.receiver, reason)
                if tx.dst is not None:
                    out += self._nack(tx, o.t, reason)
        return out

    def _uniform(self, tx: Tx, receiver: int) -> float:
        # Keyed by the frame, not drawn in arrival order: the same frame meets the same fate
        # whichever order frames reach netsim, so lockstep stays deterministic without rounds.
        return float(np.random.default_rng([self.loss_seed, self.k, tx.src, tx.seq, receiver]).random())

    def _jammed(self, receiver: int) -> str | None:
        # Unit disk has no notion of power: a jammer there silences receivers within its radius.
        if not isinstance(self.channel, UnitDisk):
            return None
        for f, pos in self.faults.jammers(self.t):
            if np.linalg.norm(_pos3(self.world.pos[receiver]) - _pos3(pos)) <= f.radius_m:
                return "jammed"
        return None

    def _drop(self, tx: Tx, receiver: int, reason: str) -> None:
        self.attempts[(tx.src, receiver)] += 1
        self.dropped[(tx.src, receiver, reason)] += 1
        self.radio_log.append((self.k, tx.src, receiver, len(tx.data), reason))

    @staticmethod
    def _nack(tx: Tx, t: float, reason: str) -> list[Rx]:
        return [Rx(tx.src, t, nack=LinkNack(tx.seq, tx.dst, reason[:32]))]

    # ---------------------------------------------------------------- link table

    def link_state(self, a: int, b: int) -> tuple[bool, float, str]:
        """(up, distance, reason if down) for a -> b: physics and faults, no random draw."""
        info = self.medium.link(a, b)
        blocked = ("down" if self.down & {a, b} else None) or self.faults.blocked(a, b) or self._jammed(b)
        if blocked:
            return False, info.distance_m, blocked
        return info.up, info.distance_m, "" if info.up else "distance"

    def link_table(self) -> list[dict]:
        rows = []
        for i, a in enumerate(self.ids):
            for b in self.ids[i + 1:]:
                info = self.medium.link(a, b)
                up_ab, dist, reason_ab = self.link_state(a, b)
                up_ba, _, reason_ba = self.link_state(b, a)
                dlv = self.delivered[(a, b)] + self.delivered[(b, a)]
                total = self.attempts[(a, b)] + self.attempts[(b, a)]
                heard = [self.last_heard[d] for d in ((a, b), (b, a)) if d in self.last_heard]
                sinr = [self.last_sinr[d] for d in ((a, b), (b, a)) if d in self.last_sinr]
                rows.append({"a": a, "b": b, "up": up_ab and up_ba, "distance": dist,
                             "reason": reason_ab or reason_ba, "snr_db": float(info.snr_db),
                             "sinr_db": min(sinr) if sinr else None,
                             "pdr_model": float(info.pdr), "delivered": dlv, "dropped": total - dlv,
                             "delivery_ratio": dlv / total if total else None,
                             "last_heard": max(heard) if heard else None})
        return rows

    def _record_links(self) -> None:
        for row in self.link_table():
            self.link_log.append((self.k, self.t, row["a"], row["b"], row["snr_db"], row["up"], row["delivered"],
                                  row["dropped"]))

    def radio_arrays(self) -> dict[str, np.ndarray]:
        """Every reception attempt, the link table per tick and every fault (radio.npz)."""
        rows, links = self.radio_log, self.link_log
        faults = self.faults.log
        return {
            "k": np.array([r[0] for r in rows], np.int64), "src": np.array([r[1] for r in rows], np.int64),
            "receiver": np.array([r[2] for r in rows], np.int64), "size": np.array([r[3] for r in rows], np.int64),
            "delivered": np.array([r[4] == "" for r in rows], bool), "reason": np.array([r[4] for r in rows], dtype="U16"),
            "link_k": np.array([r[0] for r in links], np.int64), "link_t": np.array([r[1] for r in links], float),
            "link_a": np.array([r[2] for r in links], np.int64), "link_b": np.array([r[3] for r in links], np.int64),
            "link_snr_db": np.array([r[4] for r in links], float), "link_up": np.array([r[5] for r in links], bool),
            "link_delivered": np.array([r[6] for r in links], np.int64),
            "link_dropped": np.array([r[7] for r in links], np.int64),
            "fault_t": np.array([f["t"] for f in faults], float),
            "fault_k": np.array([f["k"] for f in faults], np.int64),
            "fault_action": np.array([f["action"] for f in faults], dtype="U16"),
            "fault_source": np.array([f["source"] for f in faults], dtype="U16"),
        }

    def radio_summary(self) -> dict:
        reasons: Counter[str] = Counter()
        for (_, _, why), n in self.dropped.items():
            reasons[why] += n
        return {"delivered": sum(self.delivered.values()), "dropped": dict(reasons)}
