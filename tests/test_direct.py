"""Direct mode (no netsim, so no NACKs): UKF-DCL's timeouts and Zenoh liveliness membership.

The first tests drive UkfDclNode objects sans I/O with a radio that delivers at once and
silently loses what is sent to a dead agent; the last runs `swarmloc agent` processes on
loopback and kills one."""

import os
import queue
import signal
import subprocess
import sys
import time
from collections import deque

import numpy as np
import pytest
import zenoh
from conftest import free_port

from netsim.sim import Simulation
from swarmloc import wire
from swarmloc.experiment import scenario as S
from swarmloc.experiment.runner import make_nodes
from swarmloc.node import Timers
from swarmloc.wire.messages import Reply

KILLED, AT = 4, 6  # agent 4 dies at the start of tick 6; the others list it for three more ticks


class Direct:
    """Real time with no latency: every frame arrives at once, in order, except to a dead agent,
    where it is lost without a word (or, with `nack`, NACKed as netsim would). Between ticks the
    clock moves to each due timer (modelled seconds, speed 1) and fires it."""

    def __init__(self, nodes, nack=False, fire=True):
        self.nodes, self.nack, self.fire = nodes, nack, fire
        self.dead: set[int] = set()
        self.timers = {a: Timers() for a in nodes}
        self.lost = 0  # frames sent to a dead agent

    def live(self):
        return [a for a in sorted(self.nodes) if a not in self.dead]

    def tick(self, t, dt, frames):
        q = deque()
        for a in self.live():
            self._queue(q, a, self.nodes[a].step(frames[a]), t)
        self._drain(q, t)
        while self.fire:
            due = min((d for a in self.live() if (d := self.timers[a].next_due()) is not None), default=None)
            if due is None or due >= t + dt:
                break
            for a in self.live():
                for tag in self.timers[a].pop_due(due):
                    self._queue(q, a, self.nodes[a].on_timer(tag, due), due)
            self._drain(q, due)

    def tell(self, actions_of, t):
        """Hand every live node an event (e.g. peer_left) and deliver what follows."""
        q = deque()
        for a in self.live():
            self._queue(q, a, actions_of(self.nodes[a]), t)
        self._drain(q, t)

    def _queue(self, q, a, actions, now):
        q.extend((a, s) for s in self.timers[a].split(actions, now))

    def _drain(self, q, now):
        while q:
            a, s = q.popleft()
            msg = wire.decode(wire.encode(s.msg, a, 1, s.dst)).body  # each receiver its own copy
            if s.dst is None:
                for b in self.live():
                    if b != a:
                        self._queue(q, b, self.nodes[b].receive(a, msg), now)
            elif s.dst in self.dead:
                self.lost += 1
                if self.nack:
                    self._queue(q, a, self.nodes[a].link_failed(s.dst, s.msg), now)
            else:
                self._queue(q, s.dst, self.nodes[s.dst].receive(a, msg), now)


def run(ticks, left=False, **kw):
    """wang2019 (every range measured), agent 4 killed at tick AT; per tick the chains each
    survivor committed. `left`: the survivors are told at once (liveliness)."""
    sc = S.load("wang2019").with_overrides(**{"clock.duration": ticks * 0.5, "sensors.range.probability": 1.0})
    nodes = make_nodes("ukf-dcl", sc)
    for n in nodes.values():
        n.synchronous = False  # real time: nobody ends a tick for the swarm
    sim, radio = Simulation(sc), Direct(nodes, **kw)
    committed = []
    for _ in range(sc.clock.steps + 1):
        k, t, frames = sim.tick()
        if k == AT:
            radio.dead.add(KILLED)
            if left:
                radio.tell(lambda n: n.peer_left(KILLED), t)
        before = {a: nodes[a].stats["chains_committed"] for a in radio.live()}
        radio.tick(t, sc.clock.dt, frames)
        committed.append({a: nodes[a].stats["chains_committed"] - before[a] for a in radio.live()})
    return nodes, radio, committed


def survivors(nodes):
    return {a: n for a, n in nodes.items() if a != KILLED}


def test_unanswered_token_times_out_as_if_nacked():
    """Without NACKs, a token sent to the dead agent stalls its chain for the tick: what the
    survivors measure while they still list it is never committed. With the timers fired, each
    such hop is given up as netsim's NACK would have it (after the resends), and the survivors
    end in exactly the state the NACKing radio leaves them in."""
    stalled, _, stalled_commits = run(14, fire=False)
    timed, radio, timed_commits = run(14)
    nacked, _, _ = run(14, nack=True)
    assert radio.lost > 0
    assert sum(n.drops["timed-out"] for n in survivors(timed).values()) > 0
    assert sum(n.drops["timed-out"] for n in survivors(nacked).values()) == 0  # the NACK settled each wait
    after = lambda commits: sum(sum(c.values()) for c in commits[AT:])
    assert after(timed_commits) > after(stalled_commits)
    for a, n in survivors(timed).items():
        assert n.version == nacked[a].version and n.stats == nacked[a].stats
        np.testing.assert_array_equal(n.x, nacked[a].x)
        assert set(n.row) == set(nacked[a].row)
        for j in n.row:
            np.testing.assert_array_equal(n.row[j], nacked[a].row[j])
        assert n.stats["orphaned"] == 0 and not n.busy


def test_a_peer_that_left_is_unreachable_at_once():
    """Told by the membership that 4 left, the survivors send it nothing more and wait on
    nothing: no frame lost, no timeout, and the chains of the NACKing radio."""
    nodes, radio, commits = run(14, left=True)
    nacked, _, nacked_commits = run(14, nack=True)
    assert radio.lost == 0 and commits == nacked_commits
    for a, n in survivors(nodes).items():
        assert n.drops["timed-out"] == 0 and n.stats == nacked[a].stats
        np.testing.assert_array_equal(n.x, nacked[a].x)
    node = nodes[1]
    node.peer_joined(KILLED)
    assert KILLED not in node.gone


# ---------------------------------------------------------------------------- processes


def stats_of(session, keys, aid):
    (r,) = [r for r in session.get(keys.stats(aid), timeout=5.0) if r.ok is not None]
    return wire.decode(r.ok.payload.to_bytes(), expect=(Reply,)).body.data


@pytest.mark.slow
def test_killed_agent_is_routed_around_in_direct_mode(tmp_path):
    """Four `swarmloc agent --direct` processes, Zenoh peers on loopback, the test playing the
    sensor driver in real time. Agent 4 is SIGKILLed: the others hear its liveliness token go,
    keep an estimate every tick and keep committing chains among themselves."""
    sc = S.load("wang2019").with_overrides(**{"clock.duration": 9.0, "sensors.range.probability": 1.0})
    dt, kill_at = sc.clock.dt, 6
    swarm = f"direct{os.getpid()}"
    keys = wire.Keys(swarm)
    hub = f"tcp/127.0.0.1:{free_port()}"
    session = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("peer", listen=[hub])))
    estimates = queue.SimpleQueue()
    sub = session.declare_subscriber(keys.prefix + "/agent/*/estimate",
                                     lambda s: estimates.put((time.monotonic(), s.payload.to_bytes())))
    alive = queue.SimpleQueue()
    live_sub = session.liveliness().declare_subscriber(keys.alive("*"), lambda s: alive.put(str(s.key_expr)),
                                                       history=True)
    scenario_file = tmp_path / "s.yaml"
    scenario_file.write_text(sc.to_yaml())
    procs = {a: subprocess.Popen([sys.executable, "-m", "agents", "agent", "--id", str(a), "--scenario",
                                  str(scenario_file), "--swarm", swarm, "--mode", "peer", "--listen",
                                  f"tcp/127.0.0.1:{free_port()}", "--connect", hub, "--direct"],
                                 stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for a in sc.agent_ids}
    try:
        for _ in sc.agent_ids:
            alive.get(timeout=30)
        time.sleep(1.0)  # the agents find each other (gossip) and each other's tokens
        pubs = {a: session.declare_publisher(keys.sensors(a), congestion_control=zenoh.CongestionControl.BLOCK)
                for a in sc.agent_ids}
        sim = Simulation(sc)
        start = time.monotonic()
        before = None
        for i in range(sc.clock.steps + 1):
            k, t, frames = sim.tick()
            if k == kill_at:
                before = {a: stats_of(session, keys, a)["chains_committed"] for a in sc.agent_ids if a != KILLED}
                procs[KILLED].send_signal(signal.SIGKILL)
            for a in sc.agent_ids:
                if a != KILLED or k < kill_at:
                    pubs[a].put(wire.encode(frames[a], 0, k + 1))
            time.sleep(max(0.0, start + (i + 1) * dt - time.monotonic()))
        time.sleep(0.5)
        after = {a: stats_of(session, keys, a) for a in before}
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.terminate()
        logs = {a: p.communicate(timeout=10)[0] for a, p in procs.items()}
        session.close()
    got: dict[int, dict[int, float]] = {a: {} for a in before}
    while not estimates.empty():
        at, data = estimates.get()
        env = wire.decode(data)
        if env.src in got:
            got[env.src].setdefault(env.body.k, at)
    for a in before:
        assert f"peer {KILLED} left" in logs[a], logs[a][-2000:]
        assert set(got[a]) >= set(range(kill_at, sc.clock.steps + 1)), (a, sorted(got[a]))  # no tick skipped
        gaps = np.diff([got[a][k] for k in range(kill_at, sc.clock.steps + 1)])
        assert gaps.max() < 2 * dt, (a, gaps)
        s = after[a]
        assert s["ticks_skipped"] == 0 and s["orphaned"] == 0, s
        assert s["chains_committed"] > before[a], (a, before[a], s["chains_committed"])
        # Senders stamp their UNIX time: on one machine the apparent delay is the hop alone.
        delays = s["peer_delay_ms"]
        assert delays and all(0 <= d["min"] <= d["median"] < 100 for d in delays.values()), delays
