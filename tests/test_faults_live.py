"""Every fault kind injected live through the CLI into a running swarm of agent processes:
it shows in the link table (or the sensors), in the recorded drops, and clears on restore or
after --for. The run uses the real-time clock so a fault window lasts long enough to watch."""

import json

import numpy as np
import pytest
from conftest import NetsimClient

from swarmloc.experiment import scenario as S

pytestmark = pytest.mark.slow


def link(s, a, b):
    return next(l for l in s["links"] if {l["a"], l["b"]} == {a, b})


def scenario_file(tmp_path, duration=160.0, speed=4.0):
    sc = S.load("wang2019").with_overrides(**{"clock.duration": duration, "clock.mode": "realtime", "clock.speed": speed,
                                              "sensors.gnss.enabled": True})
    path = tmp_path / "live.yaml"
    path.write_text(sc.to_yaml())
    return path


def agent_position(ns: NetsimClient, aid: int) -> np.ndarray:
    """Agent aid's true position now, from netsim's truth key."""
    import queue

    from swarmloc.wire.messages import Truth

    got: queue.SimpleQueue = queue.SimpleQueue()
    sub = ns.session.declare_subscriber(ns.keys.truth(aid), lambda s: got.put(s.payload.to_bytes()))
    try:
        return ns.wire.decode(got.get(timeout=10), expect=(Truth,)).body.state[:2]
    finally:
        sub.undeclare()


def test_every_fault_kind_live(cli, tmp_path):
    out = tmp_path / "run"
    run = cli.start_run(str(scenario_file(tmp_path)), out)
    cli.wait_tick(4, run)
    ns = NetsimClient(cli.endpoint, cli.swarm)

    def inject(*args):
        p = cli.control("inject", *args)
        assert p.returncode == 0, p.stderr
        return p

    def faults():
        p = cli.control("faults", "--json")
        assert p.returncode == 0, p.stderr
        return json.loads(p.stdout)["active"]

    try:
        # radio off, cleared by --for
        inject("radio-off", "2", "--for", "6")
        s = ns.wait(lambda s: not link(s, 1, 2)["up"], what="radio-off")
        assert link(s, 2, 3)["reason"] == "radio-off" and link(s, 1, 3)["up"]
        assert [f["action"] for f in s["faults"]] == ["radio-off"]
        ns.wait(lambda s: link(s, 1, 2)["up"] and not s["faults"], what="radio-on after --for")

        # partition and heal; `swarmloc faults` lists it while it is in force (it has no --for,
        # so however long the command takes to start, it is still there)
        inject("partition", "1,2", "3,4")
        s = ns.wait(lambda s: not link(s, 1, 3)["up"], what="partition")
        assert link(s, 2, 4)["reason"] == "partition" and link(s, 1, 2)["up"] and link(s, 3, 4)["up"]
        assert [f["action"] for f in faults()] == ["partition"]
        inject("heal")
        ns.wait(lambda s: link(s, 1, 3)["up"], what="heal")

        # extra loss on one link, cleared by id
        inject("loss", "0.6", "--link", "1,3")
        (f,) = ns.wait(lambda s: s["faults"], what="loss")["faults"]
        assert f["action"] == "loss" and f["args"]["link"] == [1, 3]
        p = cli.control("clear", str(f["id"]))
        assert p.returncode == 0, p.stderr
        ns.wait(lambda s: not s["faults"], what="loss cleared")

        # a jammer on top of agent 4, wherever it is now (unit disk: silences receivers within
        # 20 m; the others never come within 45 m of it), long enough to be seen however slowly
        # the machine polls
        x, y = agent_position(ns, 4)
        inject("jammer", f"{x:.1f}", f"{y:.1f}", "--radius", "20", "--for", "20")
        s = ns.wait(lambda s: not link(s, 1, 4)["up"], what="jammer")
        assert link(s, 1, 4)["reason"] == "jammed" and link(s, 1, 2)["up"] and link(s, 2, 3)["up"]
        ns.wait(lambda s: link(s, 1, 4)["up"], what="jammer off after --for")

        # one-way cut
        inject("cut", "3", "4", "--forward", "--for", "4")
        s = ns.wait(lambda s: not link(s, 3, 4)["up"], what="cut")
        assert link(s, 3, 4)["reason"] == "fault"
        ns.wait(lambda s: link(s, 3, 4)["up"], what="cut cleared")

        # GNSS outage
        inject("gnss-off", "4", "--for", "4")
        ns.wait(lambda s: any(f["action"] == "gnss-off" for f in s["faults"]), what="gnss-off")
        ns.wait(lambda s: not s["faults"], what="gnss back")

        # bad injections get clear errors, not a dead netsim
        p = cli.control("inject", "radio-off", "99")
        assert p.returncode != 0 and "unknown agents" in p.stderr
        p = cli.control("inject", "loss", "1.5")
        assert p.returncode != 0 and "probability" in p.stderr

        # Everything is checked: end the run now rather than at its 160 s.
        p = cli.control("stop")
        assert p.returncode == 0 and "stopping after tick" in p.stdout, p.stderr
    finally:
        ns.close()
    stdout, stderr = run.communicate(timeout=300)
    assert run.returncode == 0, stderr

    m = json.loads((out / "metrics.json").read_text())
    assert 0 < m["stopped_at_tick"] < 320 and m["ticks"] == m["stopped_at_tick"] + 1
    applied = [(f["action"], f["source"]) for f in m["faults"]]
    for action in ("radio-off", "partition", "heal", "loss", "clear-loss", "jammer", "cut", "gnss-off"):
        assert (action, "live") in applied, applied
    for action in ("radio-on", "jammer-off", "restore", "gnss-on"):
        assert (action, "duration") in applied, applied
    with np.load(out / "radio.npz") as r:
        reasons = set(r["reason"].tolist())
        assert {"radio-off", "partition", "loss", "jammed", "fault"} <= reasons, reasons
        lossy = r["reason"] == "loss"
        assert set(zip(r["src"][lossy].tolist(), r["receiver"][lossy].tolist())) <= {(1, 3), (3, 1)}
        cut = r["reason"] == "fault"
        assert set(zip(r["src"][cut].tolist(), r["receiver"][cut].tolist())) == {(3, 4)}  # one way only
        assert r["link_k"].size and r["fault_action"].size == len(m["faults"])
    with np.load(out / "sensors.npz") as sens:
        gnss = sens["gnss"][:, 3, 0]  # agent 4
        outage = [f for f in m["faults"] if f["action"] == "gnss-off"][0]
        k0 = outage["k"]
        assert np.isnan(gnss[k0:k0 + 8]).all() and not np.isnan(gnss[k0 - 2]) and not np.isnan(gnss[-1])


def test_kill_and_restart_agent(cli, tmp_path):
    """Killing an agent mid-run: the others keep estimating, the restarted agent rejoins from
    its checkpoint, nothing hangs."""
    out = tmp_path / "run"
    run = cli.start_run(str(scenario_file(tmp_path, duration=50.0, speed=4.0)), out)
    cli.wait_tick(20, run)
    ns = NetsimClient(cli.endpoint, cli.swarm)
    try:
        p = cli.control("inject", "kill", "3", "--for", "10")
        assert p.returncode == 0, p.stderr
        s = ns.wait(lambda s: not s["agents"]["3"]["alive"], what="agent 3 dead")
        k_dead = s["k"]
        s = ns.wait(lambda s: s["k"] >= k_dead + 8, what="ticks go on without agent 3")
        assert all(s["agents"][a]["alive"] for a in ("1", "2", "4"))
        ns.wait(lambda s: s["agents"]["3"]["alive"] and s["agents"]["3"]["done_k"] > k_dead + 10, timeout=60,
                what="agent 3 back and acknowledging ticks")
    finally:
        ns.close()
    stdout, stderr = run.communicate(timeout=300)
    assert run.returncode == 0, stderr
    assert "killed agent-3" in stdout and "restarted agent-3" in stdout
    with np.load(out / "estimates" / "ukf-dcl.npz") as e:
        mean = e["mean"]
    gap = np.isnan(mean[:, 2, 0])
    assert gap.any() and not gap[-20:].any()  # a hole while dead, estimates again after
    assert not np.isnan(mean[:, [0, 1, 3], 0]).any()  # the others never stopped
    log = (out / "logs" / "agent-3.log").read_text()
    assert "resumed from its checkpoint" in log


def test_lockstep_waits_for_a_restarting_agent(cli, tmp_path):
    """In lockstep netsim does not run on while a restarted agent's process starts: the agent
    takes the frame of the very tick it was restarted at, so its hole is the kill window."""
    sc = S.load("wang2019").with_overrides(**{"clock.duration": 30.0},
                                           faults=[{"at": 10.0, "action": "kill", "node": 3, "duration": 5.0}])
    path = tmp_path / "kill.yaml"
    path.write_text(sc.to_yaml())
    out = tmp_path / "run"
    cli.run("run", str(path), "--out", str(out), "--port", str(cli.port), "--swarm", cli.swarm, "--no-plots",
            check=True, timeout=200)
    with np.load(out / "estimates" / "ukf-dcl.npz") as e:
        hole = np.flatnonzero(np.isnan(e["mean"][:, 2, 0]))
    assert hole.tolist() == list(range(20, 30))  # killed at tick 20, back at tick 30
    m = json.loads((out / "metrics.json").read_text())
    assert {"k": 30, "agent": 3, "event": "joined"}.items() <= next(
        e for e in m["agent_events"] if e["event"] == "joined").items()
