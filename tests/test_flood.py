"""A flood on one agent of a running swarm (docs/security.md#limits): 10,000 frames a second for
10 s on agent 2's radio key, from a process without the run's key. Real processes, real Zenoh
sessions on 127.0.0.1."""

import threading
import time

import pytest
import zenoh
from conftest import NetsimClient, agent_pid
from test_hostile import rss_mb

from swarmloc import wire
from swarmloc.experiment import scenario as S

pytestmark = pytest.mark.slow

RATE, SECONDS = 10_000, 10.0
SPEED = 20.0  # realtime at 20x: 40 ticks of 0.5 s a wall second


def flood(endpoint: str, key: str, frame: bytes, attachment: bytes) -> int:
    """RATE frames a second on `key` for SECONDS; how many were published."""
    session = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("client", connect=[endpoint])))
    pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP)
    sent, start = 0, time.monotonic()
    try:
        while (now := time.monotonic()) < start + SECONDS:
            due = int((now - start) * RATE)
            while sent < due:
                pub.put(frame, attachment=attachment)
                sent += 1
            time.sleep(0.001)
    finally:
        session.close()
    return sent


def test_a_flooded_agent_keeps_estimating_in_bounded_memory(cli, tmp_path):
    """Agent 2 is flooded with forged radio frames (a real frame's bytes, unsealed, under the
    next delivery number): its memory grows by less than 40 MB (its inbox holds at most 32 MB),
    it keeps estimating, the swarm keeps its real-time tick rate within 20 %, and the flood is
    in its counters."""
    sc = S.load("wang2019").with_overrides(**{"clock.duration": 1200.0, "clock.mode": "realtime",
                                              "clock.speed": SPEED})
    path = tmp_path / "flood.yaml"
    path.write_text(sc.to_yaml())
    run = cli.start_run(str(path), tmp_path / "run")
    cli.wait_tick(40, run)
    pid = agent_pid(cli.swarm, 2)
    ns = NetsimClient(cli.endpoint, cli.swarm)
    keys = wire.Keys(cli.swarm)
    import numpy as np

    from swarmloc.wire.messages import Beacon

    forged = wire.encode(Beacon(0, np.zeros(2), np.eye(2), {}), 1, 1, None)
    try:
        def rate(seconds: float) -> float:
            k0, t0 = ns.request("status")["k"], time.monotonic()
            time.sleep(seconds)
            return (ns.request("status")["k"] - k0) / (time.monotonic() - t0)

        before_rate = rate(3.0)
        before_mb = rss_mb(pid)
        result = {}
        flooder = threading.Thread(target=lambda: result.update(
            sent=flood(cli.endpoint, keys.radio_rx(2), forged, wire.encode_delivery(10**6))))
        flooder.start()
        time.sleep(1.0)
        during_rate = rate(SECONDS - 2.0)
        flooder.join()
        peak_mb = rss_mb(pid)
        status = ns.request("status")
        stats = None
        for r in ns.session.get(keys.stats(2), timeout=3.0):
            if r.ok is not None:
                stats = wire.decode(r.ok.payload.to_bytes()).body.data
    finally:
        ns.close()
        run.terminate()
        run.communicate(timeout=30)
    sent = result["sent"]
    print(f"\nsent {sent} frames in {SECONDS:g} s; agent 2 RSS {before_mb:.1f} -> {peak_mb:.1f} MB; ticks/s "
          f"{before_rate:.1f} before, {during_rate:.1f} during; rejected {stats['rejected']}, inbox {stats['inbox']}")
    assert sent >= 0.9 * RATE * SECONDS, sent
    assert peak_mb - before_mb < 40, (before_mb, peak_mb)
    expected = 2 * SPEED  # ticks a second
    assert abs(before_rate - expected) < 0.2 * expected and abs(during_rate - expected) < 0.2 * expected, \
        (before_rate, during_rate)
    assert status["agents"]["2"]["responsive"], status["agents"]["2"]
    refused = stats["rejected"].get("auth-unauthenticated", 0) + stats["inbox"]["dropped"]
    assert refused >= 0.9 * sent, (refused, sent, stats["rejected"], stats["inbox"])
    assert stats["k"] >= status["k"] - 2  # still estimating, tick by tick
