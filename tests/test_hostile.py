"""A hostile publisher outside the swarm, during a lockstep run over real Zenoh: every bad
frame is counted where it lands, nothing raises, no tick waits out its timeout, and the
estimates are bit for bit those of the same run in process."""

import json
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from helpers import in_process

from swarmloc.experiment import scenario as S

pytestmark = pytest.mark.slow
HOSTILE = Path(__file__).with_name("hostile.py")


def test_hostile_frames_on_every_key_are_counted_and_change_nothing(cli, tmp_path):
    out = tmp_path / "run"
    sc = S.load("wang2019")
    run = cli.start_run("wang2019", out)
    hostile = subprocess.run([sys.executable, str(HOSTILE), cli.endpoint, cli.swarm,
                              ",".join(map(str, sc.agent_ids)), "50", "500"],
                             capture_output=True, text=True, timeout=200)
    assert hostile.returncode == 0, hostile.stderr
    stdout, stderr = run.communicate(timeout=300)
    assert run.returncode == 0, stderr
    report = json.loads(hostile.stdout)
    sent = Counter(report["sent"])
    assert report["rounds"] >= 20  # the attack overlapped the run for long enough to matter

    m = json.loads((out / "metrics.json").read_text())
    assert m["tick_timeouts"] == 0 and m["unresponsive_agents"] == []
    # netsim: every frame on its keys refused with the reason the attacker meant.
    for kind in ("tx", "done", "estimate", "alive"):
        expected = {r.split("/")[1]: n for r, n in sent.items() if r.startswith(kind + "/")}
        assert m["rejected"][kind] == expected, kind
    # Each agent: what landed on its radio and sensor keys and the clock.
    for aid in sc.agent_ids:
        st = m["agent_stats"][str(aid)]
        mine = {r.split("/")[1]: n for r, n in sent.items() if r.startswith(f"{aid}/")}
        clock = {r.split("/")[1]: n for r, n in sent.items() if r.startswith("clock/")}
        expected = Counter(mine) + Counter(clock)
        stale = expected.pop("stale-tick", 0)
        assert st["rejected"] == dict(expected), aid
        assert st["node_drops"].get("stale-tick", 0) == stale, aid
    zen = np.load(out / "estimates" / "ukf-dcl.npz")
    record, _, _ = in_process(sc)
    assert np.array_equal(zen["mean"], record.trace("ukf-dcl").mean)
    assert np.array_equal(zen["cov"], record.trace("ukf-dcl").cov)


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError(f"no VmRSS for {pid}")


def test_large_frames_are_dropped_before_they_are_buffered(cli, tmp_path):
    """1 MB and 8 MB payloads on an agent's radio key and on netsim's: dropped (by Zenoh's
    message limit for the agent, uncopied and counted by netsim), and neither process keeps
    the memory (before the fix: agent 88 -> 160 MB, netsim 67 -> 280 MB)."""
    import zenoh
    from conftest import agent_pid, netsim_pid
    from test_processes import long_scenario

    from swarmloc import wire

    _, path = long_scenario(tmp_path)
    run = cli.start_run(str(path), tmp_path / "run")
    cli.wait_tick(20, run)
    agent = agent_pid(cli.swarm, 2)
    netsim = netsim_pid(cli.swarm)
    keys = wire.Keys(cli.swarm)
    session = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("client", connect=[cli.endpoint])))
    pubs = [session.declare_publisher(k, **wire.publisher_options(zenoh)) for k in (keys.radio_rx(2), keys.radio_tx(2))]

    def flood(rounds):
        for size, count in ((1 << 20, 20 * rounds), (8 << 20, 4 * rounds)):
            blob = bytes(size)
            for _ in range(count):
                for pub in pubs:
                    pub.put(blob)

    try:
        start = {p: rss_mb(p) for p in (agent, netsim)}
        flood(1)
        warm = {p: rss_mb(p) for p in (agent, netsim)}
        flood(3)  # three times as much again: memory must not follow
        s = cli.wait_tick(cli.wait_tick(0, run)["k"] + 20, run)  # the swarm still ticks
    finally:
        session.close()
    end = {p: rss_mb(p) for p in (agent, netsim)}
    assert end[agent] - start[agent] < 30 and end[netsim] - start[netsim] < 40, (start, warm, end)
    assert all(end[p] - warm[p] < 8 for p in end), (start, warm, end)
    assert all(a["responsive"] for a in s["agents"].values())
    run.terminate()


@pytest.mark.parametrize("receiver", ["client", "router"])
def test_no_session_takes_a_message_above_zenohs_limit(receiver):
    """Issue 26, finding 6: with max_message_size alone, Zenoh 1.10 handed 0.3-8 MB messages to
    every subscriber. wire.zenoh_config's ingress filter stops them at the session they enter:
    a client's subscriber (an agent) and a router's own (netsim) see none of them, and a frame
    under the limit still arrives (to be counted oversize by the door)."""
    import threading
    import time

    import zenoh
    from conftest import free_port

    from swarmloc import wire

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("router", [endpoint])))
    sessions = [router]
    try:
        if receiver == "client":
            sub_session = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("client", connect=[endpoint])))
            sessions.append(sub_session)
        else:
            sub_session = router
        got, lock = [], threading.Lock()

        def heard(s):
            with lock:
                got.append(len(s.payload))

        sub = sub_session.declare_subscriber("hostile/big", heard)
        # The publisher is the attacker's: its own session, no filter of ours.
        attacker = zenoh.open(zenoh.Config.from_json5(json.dumps({
            "mode": "client", "connect": {"endpoints": [endpoint]}, "scouting": {"multicast": {"enabled": False}}})))
        sessions.append(attacker)
        pub = attacker.declare_publisher("hostile/big", **wire.publisher_options(zenoh))
        under = wire.ZENOH_MAX_MESSAGE_BYTES - 1024
        deadline = time.monotonic() + 20
        while not got and time.monotonic() < deadline:  # the subscription has reached the router
            pub.put(bytes(16))
            time.sleep(0.1)
        for size in (300_000, 1 << 20, 8 << 20, under):
            pub.put(bytes(size))
        while under not in got and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)
        with lock:
            big = [n for n in got if n > 16]
        assert big == [under], big
        sub.undeclare()
    finally:
        for s in reversed(sessions):
            s.close()
