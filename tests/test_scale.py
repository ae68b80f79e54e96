"""Swarms in real time: 32 agents (the built-in `swarm32`: UKF-DCL with chains bounded to 3
platforms, dt = 0.5 s; its first 15 s of 30) and 256 (`swarm256`: RDL, 32 agents to a process,
its whole 60 s): every agent handles every tick's sensor frame in time and none is marked
unresponsive."""

import json
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import require_spare_cores

from swarmloc.experiment import scenario as S
from swarmloc.process import process_tree

pytestmark = pytest.mark.slow


def test_32_agents_keep_up_in_real_time_with_bounded_chains(cli, tmp_path):
    # Keeping up is a claim about this machine's spare CPU, not about the protocol (which
    # test_realtime.py's starved agent covers): measured first, skipped with the reason if absent.
    require_spare_cores(1.6, "32 real-time agents at dt 0.5 s keep up only on a machine with its cores free")
    sc = S.load("swarm32").with_overrides(**{"clock.duration": 15.0})
    assert sc.clock.mode == "realtime" and len(sc.agent_ids) == 32 and sc.estimator.params["max_chain"] == 3
    path = tmp_path / "swarm32.yaml"
    path.write_text(sc.to_yaml())
    out = tmp_path / "run"
    p = cli.run("run", str(path), "--out", str(out), "--port", str(cli.port), "--swarm", cli.swarm, "--no-plots",
                timeout=240)
    assert p.returncode == 0, p.stderr
    m = json.loads((out / "metrics.json").read_text())
    if m["unresponsive_agents"] or m["agent_events"]:
        pytest.fail(f"unresponsive {m['unresponsive_agents']}, events {m['agent_events']}")
    ticks = sc.clock.steps + 1
    stats = m["agent_stats"]
    assert sorted(map(int, stats)) == sc.agent_ids
    for a, s in stats.items():
        assert s["ticks"] == ticks and s["ticks_skipped"] == 0 and s["k"] == sc.clock.steps, (a, s)
        # An overrun is a sensor frame still waiting in the agent's queue when the next tick comes.
        assert s["sensor_lag_ms_max"] < 1e3 * sc.clock.dt, (a, s["sensor_lag_ms_max"])
    assert sum(s["measurements_used"] for s in stats.values()) > 0
    with np.load(out / "estimates" / "ukf-dcl.npz") as d:
        assert not np.isnan(d["mean"]).any(), "an agent missed a tick's estimate"


def _rss_mb(pids: list[int]) -> float:
    kb = 0
    for p in pids:
        try:
            kb += next(int(line.split()[1]) for line in Path(f"/proc/{p}/status").read_text().splitlines()
                       if line.startswith("VmRSS:"))
        except (OSError, StopIteration, ValueError):
            pass
    return kb / 1024


# At the edge on two free cores since RDL beacons every 3 ticks (docs/benchmarks.md, "A beacon
# every 3 ticks": passed in 2 of 5 runs on a quiet machine, the others about one agent short),
# behind on two shared ones (196-220 of 256). Expected to fail on its keep-up assertions only until it holds on a
# shared machine too: a crash, a hang or a run that does not end is still a failure; a pass is
# reported (XPASS).
@pytest.mark.xfail(raises=AssertionError, strict=False, reason="issue 29: swarm256 keeps up in real time on 2 free "
                   "cores only at times, not on 2 shared ones")
def test_256_agents_keep_up_in_real_time(cli, tmp_path):
    """Issue 29's `swarm256`: 256 planar agents running RDL, 32 to a process, in real time at dt
    0.5 s for its full 60 s: every agent handles every tick, none is marked unresponsive, no
    sensor frame waits a tick, the whole process tree stays within 6 GB and tick 0 comes within
    20 s of the command. Measured on this machine it needs about 1.7 of its 2 cores
    (docs/benchmarks.md, "swarm256"): checked first, skipped with the reason when they are not
    free. The offline UKF-CCL reference is left out (the keep-up property is the test's, and a
    dense 512-state filter over 121 ticks would take minutes after the run)."""
    require_spare_cores(1.8, "256 real-time agents at dt 0.5 s need about 1.7 cores of a 2-core machine")
    sc = S.load("swarm256").with_overrides(references=["il"])
    assert sc.clock.mode == "realtime" and sc.clock.dt == 0.5 and sc.clock.duration == 60 and len(sc.agent_ids) == 256
    assert sc.estimator.name == "rdl"
    path = tmp_path / "swarm256.yaml"
    path.write_text(sc.to_yaml())
    out = tmp_path / "run"
    import zenoh

    from swarmloc import wire

    started = time.monotonic()
    p = cli.start_run(str(path), out, "--agents-per-process", "32")
    first: list[float] = []
    session = sub = None
    peak_mb = 0.0
    deadline = started + 300
    while p.poll() is None and time.monotonic() < deadline:
        if session is None:
            try:  # netsim's router: up once it listens
                session = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("client", connect=[cli.endpoint])))
                sub = session.declare_subscriber(wire.Keys(cli.swarm).clock,
                                                 lambda s: first or first.append(time.monotonic()))
            except zenoh.ZError:
                session = None
        peak_mb = max(peak_mb, _rss_mb(process_tree(p.pid)))
        time.sleep(0.25)
    if sub is not None:
        sub.undeclare()
        session.close()
    # What was met (docs/benchmarks.md) fails hard (pytest.fail, not an AssertionError the xfail
    # expects): the run ends, on time, within its memory, nobody unresponsive.
    if p.poll() is None:
        pytest.fail("swarm256 did not finish within 300 s")
    stdout, stderr = p.communicate()
    if p.returncode != 0:
        pytest.fail(stderr[-3000:])
    if not (first and first[0] - started < 20.0):
        pytest.fail(f"tick 0 {first[0] - started if first else None} s after the command")
    if peak_mb > 6 * 1024:
        pytest.fail(f"{peak_mb:.0f} MB")
    m = json.loads((out / "metrics.json").read_text())
    if m["unresponsive_agents"] or m["agent_events"]:
        pytest.fail(f"unresponsive {m['unresponsive_agents']}, events {m['agent_events']}")
    stats = m["agent_stats"]
    assert sorted(map(int, stats)) == sc.agent_ids
    late = {a: s for a, s in stats.items() if not (s["ticks"] == sc.clock.steps + 1 and s["ticks_skipped"] == 0
                                                   and s["k"] == sc.clock.steps)}
    assert not late, f"{len(late)} agents missed ticks, e.g. {next(iter(late.items()))}"
    lag = {a: s["sensor_lag_ms_max"] for a, s in stats.items() if s["sensor_lag_ms_max"] >= 1e3 * sc.clock.dt}
    assert not lag, f"{len(lag)} agents' sensor lag reached dt: max {max(lag.values()):.0f} ms"
    assert sum(s["measurements_used"] for s in stats.values()) > 0
    with np.load(out / "estimates" / "rdl.npz") as d:
        assert not np.isnan(d["mean"]).any(), "an agent missed a tick's estimate"
