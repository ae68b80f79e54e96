"""The NBP message schedule of Wan et al. 2014 (dNBP, section 3.4): who may send, and when.

Pure and sans-I/O: no clock, no socket, no NBP maths (that is swarmloc.estimators.nbp.mixtures). The rule: a normal
node (GNSS available) sends from the start and never takes messages from fault nodes (no GNSS);
a fault node sends (broadcasts its belief) once it holds at least 3 incoming messages, from
normal nodes or from fault nodes that have already sent; when no fault node can reach the
threshold it drops to 2, then to 1. Once a node may send it keeps sending (its belief refines).

Over real transport nobody knows that "no fault node reaches the threshold". Rule chosen here:
each fault node relaxes only its own threshold, after a quiet period without a new message.
The node arms a Timer (swarmloc.node.Timer, tag RELAX_TAG, delay = quiet period Q, e.g. one or
two NBP rounds) when its iteration begins and re-arms it on every message that `hear` counts as
new; when it fires and `ready()` is false it calls `relax()` and re-arms it. No extra messages,
no agreement protocol. Consequence: the node reads "quiet around me" as "the swarm is stuck". A
fault node far from the normal ones relaxes while the swarm elsewhere still makes progress, so
it can send earlier, and on fewer messages, than the global rule would let it (its first belief
is then more ambiguous, as in Fig. 4(c)); a relaxation also costs Q of waiting, where the global
rule relaxes at once. In lockstep (one NBP round per tick, Q a whole number of rounds) the
distributed run therefore equals `simulate(..., relax="local", quiet=Q)` tick for tick, and equals
the global oracle `simulate(...)` (rounds without a new sender dropped) whenever every local quiet
period coincides with a global stall, e.g. the Fig. 3-4 case, or any swarm where the oracle never
relaxes. Ties are broken in node-id order everywhere, so both references are deterministic.
"""

from __future__ import annotations

from collections.abc import Iterable

THRESHOLDS = (3, 2, 1)
RELAX_TAG = "nbp-relax"


def _check_thresholds(thresholds) -> tuple[int, ...]:
    t = tuple(int(x) for x in thresholds)
    if not t or any(x < 1 for x in t) or any(a <= b for a, b in zip(t, t[1:])):
        raise ValueError(f"thresholds must be strictly decreasing integers >= 1: {thresholds!r}")
    return t


class Schedule:
    """One node's view of the schedule.

    Iteration: one intraslice NBP update, i.e. all the message rounds of one time step t. It
    starts when the Schedule is built or `begin()` is called, at the start of step t before
    any message of step t is heard; it ends at the next `begin()` (step t+1), which drops the
    held messages (they belong to step t) and puts the threshold back to its first value.
    Within an iteration the held set only grows and the threshold only drops, so `ready()`,
    once true, stays true until the next `begin()`. Passing only messages of the current step
    is the caller's job.
    """

    def __init__(self, normal: bool, neighbours: Iterable[int], thresholds=THRESHOLDS):
        self.normal = bool(normal)
        self.neighbours = frozenset(neighbours)
        self.thresholds = _check_thresholds(thresholds)
        self.begin()

    def begin(self) -> None:
        """Start a new iteration: nothing held, threshold back to thresholds[0]."""
        self._held: set[int] = set()
        self._level = 0

    def hear(self, src: int, src_is_normal: bool) -> bool:
        """Record a message from `src`; True if it newly counts towards the threshold.

        Not counted: a message from a non-neighbour, a second message from a neighbour already
        held, and, at a normal node, any message from a fault node (a normal node never takes
        them; the caller must not fuse it either)."""
        if src not in self.neighbours or src in self._held:
            return False
        if self.normal and not src_is_normal:
            return False
        self._held.add(src)
        return True

    def ready(self) -> bool:
        """May this node send now? Always for a normal node; a fault node once it holds at
        least `threshold` messages."""
        return self.normal or len(self._held) >= self.threshold

    def relax(self) -> bool:
        """Lower the threshold one step (3 -> 2 -> 1); True if it changed. Never below the
        last threshold (>= 1); a normal node has nothing to relax."""
        if self.normal or self._level == len(self.thresholds) - 1:
            return False
        self._level += 1
        return True

    @property
    def threshold(self) -> int:
        return self.thresholds[self._level]

    @property
    def held(self) -> frozenset[int]:
        return frozenset(self._held)

    def __repr__(self) -> str:
        role = "normal" if self.normal else "fault"
        return f"Schedule({role}, held={sorted(self._held)}, threshold={self.threshold})"


def _undirected(graph: dict[int, set[int]]) -> dict[int, set[int]]:
    """Symmetric adjacency (ranging links are mutual), self-loops dropped, every node listed."""
    adj: dict[int, set[int]] = {}
    for a, nbrs in graph.items():
        adj.setdefault(a, set())
        for b in nbrs:
            if b != a:
                adj[a].add(b)
                adj.setdefault(b, set()).add(a)
    return adj


def simulate(graph: dict[int, set[int]], normal: set[int], thresholds=THRESHOLDS,
             relax: str = "global", quiet: int = 1) -> list[list[int]]:
    """Reference schedule: the nodes that start sending in round 1, 2, ... (ids ascending).

    The graph is made symmetric; a node of `normal` missing from it is isolated. Round 1: every
    normal node. A message sent in round r is held from round r+1 on; a node that has sent keeps
    sending, so a fault node holds one message from each neighbour that has sent before.

    relax="global" (the oracle, the paper's rule): before each round, if some fault node has not
    sent and none reaches the current threshold, the threshold drops at once (no round is spent),
    and again if needed; it never rises within the simulation. Stops when no node can start.

    relax="local" (the lockstep image of the timer rule of the module docstring): each fault node
    has its own threshold and lowers it one step before a round when it is not ready and has held
    no new message in the last `quiet` rounds since its last new message or relaxation. Rounds
    are ticks: a round where nobody starts is kept as [] (trailing ones dropped)."""
    thr = _check_thresholds(thresholds)
    if relax not in ("global", "local"):
        raise ValueError(f"relax must be 'global' or 'local', got {relax!r}")
    if quiet < 1:
        raise ValueError("quiet must be >= 1 round")
    adj = _undirected(graph)
    for n in normal:
        adj.setdefault(n, set())
    first = sorted(n for n in adj if n in normal)
    if not first:
        return []
    rounds = [first]
    sent = set(first)
    fault = sorted(n for n in adj if n not in normal)

    def held(f):
        return len(adj[f] & sent)

    if relax == "global":
        level = 0
        while True:
            waiting = [f for f in fault if f not in sent]
            starters = [f for f in waiting if held(f) >= thr[level]]
            while waiting and not starters and level < len(thr) - 1:
                level += 1
                starters = [f for f in waiting if held(f) >= thr[level]]
            if not starters:
                return rounds
            rounds.append(starters)
            sent.update(starters)

    levels = {f: 0 for f in fault}
    counts = {f: held(f) for f in fault}
    since = {f: 0 if counts[f] else 1 for f in fault}  # rounds since a new message or relaxation
    while True:
        waiting = [f for f in fault if f not in sent]
        for f in waiting:
            if since[f] >= quiet and counts[f] < thr[levels[f]] and levels[f] < len(thr) - 1:
                levels[f] += 1
                since[f] = 0
        starters = [f for f in waiting if counts[f] >= thr[levels[f]]]
        if not starters and all(levels[f] == len(thr) - 1 for f in waiting):
            while rounds and not rounds[-1]:
                rounds.pop()
            return rounds
        rounds.append(starters)
        sent.update(starters)
        for f in waiting:
            c = held(f)
            since[f] = 0 if c > counts[f] else since[f] + 1
            counts[f] = c
