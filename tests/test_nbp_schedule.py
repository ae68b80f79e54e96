"""The dNBP message schedule (swarmloc.estimators.nbp.schedule): node rule and reference rounds."""

import random

import pytest

from swarmloc.estimators.nbp.schedule import Schedule, simulate

# Fig. 3-4 of Wan et al. 2014: UAV1-3 normal, UAV4-6 fault. Edges inferred from the text of
# section 4.1 (the figure itself is not in the extracted text):
#   iter 0: "UAV4 receives messages from UAV1, UAV2, and UAV3"   -> 1-4, 2-4, 3-4
#           "UAV5 receives messages from UAV 1 and UAV 2"         -> 1-5, 2-5 (not 3-5)
#           "UAV 6 just receives message from UAV 3"              -> 3-6 (not 1-6, 2-6)
#   iter 1: "UAV4 will transmit outgoing messages to UAV5 and UAV6" -> 4-5, 4-6
#   iter 2: UAV6 combines "messages from UAV3, UAV4, and UAV5"     -> 5-6
# Edges among UAV1-3 are not stated; they do not matter to the schedule (checked below).
FIG34 = {1: {4, 5}, 2: {4, 5}, 3: {4, 6}, 4: {5, 6}, 5: {6}}
FIG34_NORMAL = {1, 2, 3}


def nodes_of(graph, normal):
    adj = {}
    for a, nbrs in graph.items():
        for b in nbrs:
            adj.setdefault(a, set()).add(b)
            adj.setdefault(b, set()).add(a)
    for n in normal:
        adj.setdefault(n, set())
    return {n: Schedule(n in normal, adj[n]) for n in adj}


def lockstep(graph, normal):
    """Schedules driven in rounds, told to relax when no waiting fault node is ready (global)."""
    nodes = nodes_of(graph, normal)
    sent, rounds = set(), []
    while True:
        waiting = [n for n in sorted(nodes) if n not in sent]
        while waiting and not any(nodes[n].ready() for n in waiting):
            if not any([nodes[n].relax() for n in waiting]):
                break
        starters = [n for n in waiting if nodes[n].ready()]
        if not starters:
            return rounds
        rounds.append(starters)
        sent.update(starters)
        for s in sent:  # a node that has sent keeps sending
            for n in nodes[s].neighbours:
                nodes[n].hear(s, s in normal)


def lockstep_timers(graph, normal, quiet):
    """Schedules with the timer rule: relax after `quiet` rounds without a new message."""
    nodes = nodes_of(graph, normal)
    since = {n: 0 for n in nodes}  # timer armed when the iteration begins
    sent, rounds = set(), []
    for _ in range(10 * len(nodes) + 10):
        waiting = [n for n in sorted(nodes) if n not in sent]
        for n in waiting:
            if since[n] >= quiet and not nodes[n].ready() and nodes[n].relax():
                since[n] = 0
        starters = [n for n in waiting if nodes[n].ready()]
        rounds.append(starters)
        sent.update(starters)
        new = {n: False for n in nodes}
        for s in sent:
            for n in nodes[s].neighbours:
                new[n] |= nodes[n].hear(s, s in normal)
        for n in nodes:
            since[n] = 0 if new[n] else since[n] + 1
    while rounds and not rounds[-1]:
        rounds.pop()
    return rounds


def random_graph(rng, n):
    graph = {i: set() for i in range(n)}
    for a in range(n):
        for b in range(a + 1, n):
            if rng.random() < 0.3:
                graph[a].add(b)
    normal = {i for i in range(n) if rng.random() < 0.35}
    return graph, normal


def test_fig34_uav4_then_uav5_then_uav6():
    assert simulate(FIG34, FIG34_NORMAL) == [[1, 2, 3], [4], [5], [6]]
    assert simulate(FIG34, FIG34_NORMAL, relax="local") == [[1, 2, 3], [4], [5], [6]]
    assert lockstep(FIG34, FIG34_NORMAL) == [[1, 2, 3], [4], [5], [6]]


def test_fig34_unstated_normal_edges_do_not_matter():
    g = {k: set(v) for k, v in FIG34.items()}
    g[1] |= {2, 3}
    g[2] |= {3}
    assert simulate(g, FIG34_NORMAL) == [[1, 2, 3], [4], [5], [6]]


def test_fig34_held_messages_follow_the_walkthrough():
    nodes = nodes_of(FIG34, FIG34_NORMAL)
    u4, u5, u6 = nodes[4], nodes[5], nodes[6]
    for s in (1, 2, 3):  # iter 0: the normal nodes send
        for n in nodes[s].neighbours:
            nodes[n].hear(s, True)
    assert (u4.held, u5.held, u6.held) == ({1, 2, 3}, {1, 2}, {3})
    assert u4.ready() and not u5.ready() and not u6.ready()
    for n in u4.neighbours:  # iter 1: UAV4 sends to UAV5 and UAV6 (and UAV1-3, who ignore it)
        nodes[n].hear(4, False)
    assert u5.held == {1, 2, 4} and u5.ready()
    assert u6.held == {3, 4} and not u6.ready()
    assert all(nodes[k].held == set() for k in (1, 2, 3))
    u6.hear(5, False)  # iter 2: UAV5 sends
    assert u6.held == {3, 4, 5} and u6.ready()


def test_normal_node_ignores_fault_messages():
    s = Schedule(True, {2, 3, 4})
    assert s.ready()
    assert not s.hear(4, src_is_normal=False)
    assert s.hear(2, src_is_normal=True)
    assert s.held == {2}
    assert not s.relax() and s.threshold == 3


def test_fault_node_counts_each_neighbour_once_and_only_neighbours():
    s = Schedule(False, {1, 2, 3})
    assert s.hear(1, True) and not s.hear(1, True)
    assert not s.hear(9, True)
    assert s.hear(2, False)
    assert s.held == {1, 2} and not s.ready()


def test_fault_node_with_two_normal_neighbours_waits_for_relaxation():
    s = Schedule(False, {1, 2})
    s.hear(1, True)
    s.hear(2, True)
    assert s.threshold == 3 and not s.ready()
    assert s.relax() and s.threshold == 2 and s.ready()
    assert simulate({1: {7}, 2: {7}}, {1, 2}) == [[1, 2], [7]]
    assert simulate({1: {7}, 2: {7}}, {1, 2}, relax="local") == [[1, 2], [], [7]]
    assert simulate({1: {7}, 2: {7}}, {1, 2}, relax="local", quiet=2) == [[1, 2], [], [], [7]]


def test_global_relaxation_waits_while_another_fault_node_progresses():
    # 7 has 2 normal neighbours; 8 has 3 and sends first; 7 then holds 3 (1, 2, 8): no relaxation.
    g = {1: {7, 8}, 2: {7, 8}, 3: {8}, 7: {8}}
    assert simulate(g, {1, 2, 3}) == [[1, 2, 3], [8], [7]]


def test_isolated_fault_node_never_sends():
    s = Schedule(False, set())
    for _ in range(5):
        s.relax()
    assert not s.ready()
    g = {1: {2}, 2: set(), 9: set()}
    assert simulate(g, {1}) == [[1], [2]]
    assert simulate(g, {1}, relax="local") == [[1], [], [], [2]]  # two quiet rounds: 3 -> 2 -> 1
    assert simulate({9: set()}, set()) == []
    assert simulate({}, {1}) == [[1]]


def test_threshold_never_below_one():
    s = Schedule(False, {1})
    assert [s.relax() for _ in range(5)] == [True, True, False, False, False]
    assert s.threshold == 1
    for bad in [(3, 2, 0), (), (2, 2, 1), (1, 2), (3, -1)]:
        with pytest.raises(ValueError):
            Schedule(False, {1}, bad)
        with pytest.raises(ValueError):
            simulate({1: {2}}, {1}, bad)
    assert Schedule(False, {1}, (4, 1)).thresholds == (4, 1)


def test_begin_starts_a_new_iteration():
    s = Schedule(False, {1, 2})
    s.hear(1, True)
    s.relax()
    s.relax()
    assert s.ready()
    s.begin()
    assert s.held == set() and s.threshold == 3 and not s.ready()


def test_chain_of_fault_nodes_relaxes_to_one():
    g = {1: {2, 3}, 2: {3}, 3: {4}, 4: {5}}
    assert simulate(g, {1, 2}) == [[1, 2], [3], [4], [5]]


def test_deterministic_and_independent_of_input_order():
    rng = random.Random(7)
    for _ in range(50):
        graph, normal = random_graph(rng, rng.randint(1, 12))
        ref = simulate(graph, normal)
        shuffled = list(graph.items())
        rng.shuffle(shuffled)
        assert simulate(dict(shuffled), set(normal)) == ref
        assert simulate(graph, normal) == ref
        assert all(r == sorted(r) for r in ref)


def test_node_schedules_in_lockstep_match_references():
    rng = random.Random(11)
    for _ in range(100):
        graph, normal = random_graph(rng, rng.randint(1, 12))
        assert lockstep(graph, normal) == simulate(graph, normal)
        for q in (1, 2):
            local = simulate(graph, normal, relax="local", quiet=q)
            assert lockstep_timers(graph, normal, q) == local
        senders = [n for r in simulate(graph, normal) for n in r]
        assert len(senders) == len(set(senders))
