"""Across processes: netsim and agent daemons over real Zenoh sessions on 127.0.0.1."""

import json
import os
import signal
import subprocess
import time

import numpy as np
import pytest
import zenoh
from conftest import swarm_pids
from helpers import ccl_without, centralized, in_process

from swarmloc import wire
from swarmloc.experiment import scenario as S
from swarmloc.wire.messages import Reply

pytestmark = pytest.mark.slow
TOL = 1e-9


def load_npz(path):
    with np.load(path, allow_pickle=False) as f:
        return {k: f[k] for k in f.files}


def test_lockstep_over_zenoh_equals_in_process(cli, tmp_path):
    out = tmp_path / "run"
    p = cli.run("run", "wang2019", "--out", str(out), "--port", str(cli.port), "--swarm", cli.swarm, "--no-plots",
                check=True, timeout=300)
    assert "ukf-dcl" in p.stdout and "A4" in p.stdout
    assert "801/801" in p.stdout  # progress reached the last tick
    zen = load_npz(out / "estimates" / "ukf-dcl.npz")
    record, _, _ = in_process(S.load("wang2019"))
    ref = record.trace("ukf-dcl")
    assert zen["mean"].shape == ref.mean.shape == (801, 4, 2)
    assert np.abs(zen["mean"] - ref.mean).max() < TOL
    assert np.abs(zen["cov"] - ref.cov).max() < TOL
    ccl = load_npz(out / "estimates" / "ukf-ccl.npz")
    assert np.abs(zen["mean"] - ccl["mean"]).max() < TOL
    m = json.loads((out / "metrics.json").read_text())
    assert m["radio"]["dropped"] == {} and m["unresponsive_agents"] == []


def long_scenario(tmp_path, duration=1000.0):
    sc = S.load("wang2019").with_overrides(**{"clock.duration": duration})
    path = tmp_path / "long.yaml"
    path.write_text(sc.to_yaml())
    return sc, path


def link(status, a, b):
    return next(l for l in status["links"] if {l["a"], l["b"]} == {a, b})


def test_inject_cut_and_restore_live(cli, tmp_path):
    sc, path = long_scenario(tmp_path)
    out = tmp_path / "run"
    run = cli.start_run(str(path), out)
    cli.wait_tick(100, run)
    # Malformed control requests get an error reply and never take netsim down.
    from conftest import NetsimClient

    from swarmloc.wire.messages import Control

    ns = NetsimClient(cli.endpoint, cli.swarm)  # its sealer: the run's key (docs/security.md)
    session = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("client", connect=[cli.endpoint])))
    try:
        for req in (Control("cut", [1, 2]), Control("cut", {"link": [1, 99]}), Control("explode", {}), b"\x00junk"):
            payload = ns.sealer.seal(req if isinstance(req, bytes) else wire.encode(req, 0, 1),
                                     wire.Keys(cli.swarm).control, 0)
            (r,) = [r for r in session.get(wire.Keys(cli.swarm).control, payload=payload, timeout=5.0) if r.ok is not None]
            body = wire.decode(r.ok.payload.to_bytes(), expect=(Reply,)).body
            assert body.ok is False and body.error and "authenticated" not in body.error, body.error
        # A request without the key is refused before it is read.
        (r,) = [r for r in session.get(wire.Keys(cli.swarm).control, payload=wire.encode(Control("faults", {}), 0, 1),
                                       timeout=5.0) if r.ok is not None]
        body = wire.decode(r.ok.payload.to_bytes(), expect=(Reply,)).body
        assert body.ok is False and body.error.startswith("not authenticated (unauthenticated)"), body.error
    finally:
        session.close()
        ns.close()
    p = cli.control("inject", "cut", "1", "2")
    assert p.returncode == 0, p.stderr
    s = cli.wait_tick(int(p.stdout.split("tick")[-1]) + 5, run)
    assert link(s, 1, 2)["up"] is False and link(s, 1, 2)["reason"] == "fault"
    assert link(s, 1, 3)["up"] is True
    p = cli.control("inject", "restore", "1", "2")
    assert p.returncode == 0, p.stderr
    s = cli.wait_tick(int(p.stdout.split("tick")[-1]) + 5, run)
    assert link(s, 1, 2)["up"] is True
    stdout, stderr = run.communicate(timeout=300)
    assert run.returncode == 0, stderr

    m = json.loads((out / "metrics.json").read_text())
    (cut,), (restore,) = ([f for f in m["faults"] if f["action"] == a] for a in ("cut", "restore"))
    kc, kr = cut["k"], restore["k"]
    radio = load_npz(out / "radio.npz")
    pair = ((radio["src"] == 1) & (radio["receiver"] == 2)) | ((radio["src"] == 2) & (radio["receiver"] == 1))
    window = (radio["k"] >= kc) & (radio["k"] < kr)
    assert not (pair & window & radio["delivered"]).any()
    assert (pair & window & (radio["reason"] == "fault")).any()
    assert (pair & (radio["k"] >= kr) & radio["delivered"]).any()
    # Chains routed around the cut: UKF-DCL equals UKF-CCL minus the ranges between 1 and 2.
    from swarmloc.experiment.results import frames_from_arrays

    sensors = frames_from_arrays(load_npz(out / "sensors.npz"))
    expected = ccl_without(sc, sensors, lambda k, a, b: {a, b} == {1, 2} and kc <= k <= kr)
    assert np.abs(load_npz(out / "estimates" / "ukf-dcl.npz")["mean"] - expected).max() < TOL


def wait_gone(swarm, timeout=15.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not swarm_pids(swarm):
            return
        time.sleep(0.1)
    raise AssertionError(f"processes left behind: {swarm_pids(swarm)}")


def test_ctrl_c_stops_every_process(cli, tmp_path):
    _, path = long_scenario(tmp_path)
    run = cli.start_run(str(path), tmp_path / "run")
    cli.wait_tick(30, run)
    assert len(swarm_pids(cli.swarm)) >= 5
    assert run.poll() is None
    run.send_signal(signal.SIGINT)
    stdout, stderr = run.communicate(timeout=60)
    assert run.returncode == 130, f"exit {run.returncode}\n{stdout[-2000:]}\n{stderr[-2000:]}"
    assert "interrupted" in stderr
    wait_gone(cli.swarm)


def test_direct_mode_without_netsim(tmp_path):
    """Deployment shape: agents publish radio frames straight to each other (no netsim); the
    test plays the sensor drivers and a plain Zenoh router. UKF-DCL still equals UKF-CCL."""
    import queue
    import sys

    from conftest import free_port

    from netsim.world import World

    sc = S.load("wang2019").with_overrides(**{"clock.duration": 15.0, "sensors.range.probability": 0.8})
    port, swarm = free_port(), "direct" + str(os.getpid())
    endpoint = f"tcp/127.0.0.1:{port}"
    router = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("router", listen=[endpoint])))
    keys = wire.Keys(swarm)
    inbox = queue.SimpleQueue()
    subs = [router.declare_subscriber(keys.prefix + "/agent/*/estimate", lambda s: inbox.put(s.payload.to_bytes())),
            router.declare_subscriber(keys.prefix + "/radio/rx/*", lambda s: inbox.put(None))]
    alive = queue.SimpleQueue()
    live_sub = router.liveliness().declare_subscriber(keys.prefix + "/agent/*/alive", lambda s: alive.put(str(s.key_expr)), history=True)
    scenario_file = tmp_path / "s.yaml"
    scenario_file.write_text(sc.to_yaml())
    procs = [subprocess.Popen([sys.executable, "-m", "agents", "agent", "--id", str(a), "--scenario", str(scenario_file),
                               "--swarm", swarm, "--connect", endpoint, "--direct"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
             for a in sc.agent_ids]
    try:
        for _ in sc.agent_ids:
            alive.get(timeout=30)
        pubs = {a: router.declare_publisher(keys.sensors(a), congestion_control=zenoh.CongestionControl.BLOCK) for a in sc.agent_ids}
        world = World(sc)
        ccl = centralized(sc)
        latest = {}
        for _ in range(sc.clock.steps + 1):
            frames = world.step()
            ccl.step(frames)
            for a in sc.agent_ids:
                pubs[a].put(wire.encode(frames[a], 0, world.k + 1))
            while True:  # the swarm is done with the tick when nothing moves for 0.2 s
                try:
                    item = inbox.get(timeout=0.2)
                except queue.Empty:
                    break
                if item is not None:
                    env = wire.decode(item)
                    latest[env.src] = env.body
            for a in sc.agent_ids:
                assert latest[a].k == world.k
                assert np.abs(latest[a].mean - ccl.x[ccl.block(a)]).max() < TOL
                assert np.abs(latest[a].cov - ccl.P[ccl.block(a), ccl.block(a)]).max() < TOL
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(10)
        router.close()
