"""Agent configuration files (`swarmloc agent --config FILE`): the documented example loads and
builds its node, every bad field is named, and the real command checks a file or starts from it."""

import copy
import os
import select
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import ROOT, free_port

from agents.config import ConfigError, daemon_config, load, node_spec, parse_config

EXAMPLE = ROOT / "docs" / "examples" / "agent.yaml"


def example() -> dict:
    return yaml.safe_load(EXAMPLE.read_text())


def changed(**changes) -> dict:
    """The example with top-level fields replaced (None: removed)."""
    data = copy.deepcopy(example())
    for k, v in changes.items():
        if v is None:
            data.pop(k, None)
        else:
            data[k] = v
    return data


def vehicle(**changes) -> dict:
    """A closed-loop ground robot on a flight controller, with one other vehicle."""
    fields = dict(model="ground-robot", estimator={"name": "ekf-ci"},
                  prior={"position": [3.0, 0.0, 0.0], "heading": 1.5708, "std": 0.05},
                  sensors=[{"kind": "mavlink", "url": "udpin:0.0.0.0:14540", "tick": 0.05}],
                  outputs={"mavlink": {}, "setpoints": {"enabled": True}},
                  vehicle={"reference": {"center": [0.0, 0.0, 0.0], "radius": 3.0, "period": 40.0},
                           "roster": [{"id": 4, "model": "quadrotor"}]})
    return changed(**{**fields, **changes})


def problems(data: dict, base: Path | None = None) -> list[str]:
    with pytest.raises(ConfigError) as info:
        parse_config(data, base)
    return info.value.lines


def swarmloc(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "agents", *args], capture_output=True, text=True, timeout=60, cwd=cwd)


def test_the_documented_example_loads():
    cfg = load(EXAMPLE)
    assert (cfg.id, cfg.swarm, cfg.estimator.name, cfg.model) == (3, "field", "ukf-dcl", "planar-speed-heading")
    assert [s.kind for s in cfg.sensors] == ["mavlink", "zenoh"]
    assert cfg.outputs.mavlink.rate_hz == 30 and cfg.outputs.mavlink.frame == "local_ned"
    d = daemon_config(cfg)
    assert (d.swarm, d.mode, d.direct, d.gossip) == ("field", "peer", True, False)
    assert d.sensor_keys == () and d.measurement_keys == ("drivers/uwb/3",) and d.epoch == 1796083200.0
    assert d.listen == ("tcp/0.0.0.0:7447",) and d.connect == ("tcp/192.168.10.1:7447", "tcp/192.168.10.2:7447")
    assert d.state_file == Path("/var/lib/swarmloc/agent-3.state.npy")


@pytest.mark.parametrize("estimator, changes, node_class", [
    ("ukf-dcl", {}, "UkfDclNode"),
    ("ekf-ci", {"estimator": {"name": "ekf-ci", "params": {"criterion": "det"}}, "model": "planar-pose",
                "prior": {"position": [1.0, 2.0], "heading": 0.5, "std": 0.2, "heading_std": 0.05},
                "landmarks": [{"id": 6, "position": [3.0, 4.0]}, {"id": 7, "position": [-1.0, 0.5]}]}, "PoseCiNode"),
    ("il", {"estimator": {"name": "il"}}, "IndependentNode"),
])
def test_a_config_builds_its_estimators_node(estimator, changes, node_class):
    cfg = parse_config(changed(**changes))
    node = node_spec(cfg).build()
    assert type(node).__name__ == node_class and node.id == 3 and node.algorithm == estimator
    p = cfg.prior
    want_mean = [*p.position, *([p.heading] if p.heading is not None else [])]
    want_var = [p.std**2] * len(p.position) + ([p.heading_std**2] if p.heading is not None else [])
    e = node.estimate()
    assert np.array_equal(e.mean, want_mean) and np.array_equal(e.cov, np.diag(want_var))  # no drawn error
    if estimator == "ukf-dcl":
        assert node.max_chain == 4 and node.gate.p == 0.999
    if estimator == "ekf-ci":
        assert node.criterion == "det"
        assert {k: list(v) for k, v in node.filter.landmarks.items()} == {6: [3.0, 4.0], 7: [-1.0, 0.5]}


@pytest.mark.parametrize("data, field", [
    (changed(colour="red"), "colour: unknown field"),
    (changed(prior={"position": [0, 0], "sdt": 1}), "prior.sdt: unknown field"),
    (changed(version=2), "version: unsupported version 2"),
    (changed(id=None), "id: required"),
    (changed(swarm="a/b"), "swarm: bad swarm name"),
    (changed(estimator={"name": "ukf-ccl"}), "estimator.name: unknown estimator 'ukf-ccl'"),
    (changed(estimator={"name": "csl-ctl"}), "estimator.name: csl-ctl needs every agent's prior"),
    (changed(estimator={"name": "ukf-dcl", "params": {"max_chain": 1}}), "estimator.params: max_chain:"),
    (changed(estimator={"name": "ekf-ci"}), "model: estimator ekf-ci runs on uas-ins, planar-pose, quadrotor, ground-robot, not "
                                            "planar-speed-heading"),
    (changed(model="hovercraft"), "model: unknown model 'hovercraft'"),
    (changed(prior={"position": [1, 2, 3]}), "prior.position: 3 numbers; model planar-speed-heading needs 2"),
    (changed(model="planar-pose"), "prior.heading: required for model planar-pose"),
    (changed(prior={"position": [0, 0], "heading": 1}), "prior.heading: only planar-pose"),
    (changed(prior={"position": [0, float("nan")]}), "prior.position.1: must be a finite number, got nan"),
    (changed(landmarks=[{"id": 1, "position": [0, 0]}, {"id": 1, "position": [1, 1]}]), "landmarks: landmark ids"),
    (changed(gate=1.5), "gate: must be < 1"),
    (changed(zenoh={"connect": ["localhost:7447"]}), "zenoh.connect.0: 'localhost:7447' is not a Zenoh endpoint"),
    (changed(zenoh={"mode": "router", "listen": ["tcp/0.0.0.0:7447"]}), "zenoh.mode: must be 'peer' or 'client', got the text 'router'"),
    (changed(zenoh={"mode": "client", "connect": []}), "zenoh.connect: a client needs an endpoint"),
    (changed(zenoh={"mode": "peer", "connect": []}), "zenoh.listen: a peer needs endpoints"),
    (changed(sensors=[{"kind": "lidar"}]), "sensors.0.kind: unknown kind 'lidar'; one of: zenoh, mavlink, file"),
    (changed(sensors=[{"kind": "zenoh"}, {"kind": "mavlink", "url": "udpin:0.0.0.0:14540", "baud": 57600}]),
     "sensors.1.baud: a baud rate is for a serial device"),
    (changed(sensors=[{"kind": "mavlink", "url": "serial0"}]), "sensors.0.url: 'serial0' is not"),
    (changed(sensors=[{"kind": "file", "path": "missing.npz"}]), "sensors.0.path: no such file"),
    (changed(sensors=[{"kind": "zenoh", "key": "a//b"}]), "sensors.0.key: 'a//b' is not a Zenoh key expression"),
    (changed(outputs={"mavlink": {"rate_hz": -5}}), "outputs.mavlink.rate_hz: must be > 0"),
    (changed(sensors=[{"kind": "zenoh"}]), "outputs.mavlink: needs a sensors entry of kind mavlink"),
    (changed(outputs={"mavlink": {"message": "vision_position_estimate", "frame": "local_frd"}}),
     "outputs.mavlink.frame: only ODOMETRY carries a frame"),
    (changed(sensors=[{"kind": "zenoh", "role": "measurements"}], outputs={}),
     "sensors.0.role: measurements join the frames of another source"),
    (changed(sensors=[{"kind": "zenoh", "role": "odometry"}]), "sensors.0.role: must be 'frames' or"),
    (changed(zenoh={"mode": "client", "connect": ["tcp/10.0.0.1:7447"], "gossip": True}),
     "zenoh.gossip: gossip is for peers"),
    (changed(clock={"epoch": float("inf")}), "clock.epoch: must be a finite number"),
    (changed(vehicle={"roster": []}), "vehicle: only for quadrotor and ground-robot, not planar-speed-heading"),
    (vehicle(vehicle={"roster": [{"id": 3, "model": "quadrotor"}]}), "vehicle.roster: ids must be unique and not this"),
    (vehicle(vehicle={"roster": [{"id": 4, "model": "blimp"}]}), "vehicle.roster.0.model: must be"),
    (vehicle(vehicle={"reference": {"center": [0, 0], "radius": 1}}), "vehicle.reference.center: must have at least 3 items"),
    (vehicle(vehicle={"reference": {"center": [0, 0, 0], "period": 0}}), "vehicle.reference.period: must not be 0"),
    (vehicle(vehicle={}), "outputs.setpoints: only a closed-loop vehicle has commands"),
    (vehicle(sensors=[{"kind": "zenoh"}], outputs={"setpoints": {"enabled": True}}),
     "outputs.setpoints: needs a sensors entry of kind mavlink"),
    (vehicle(outputs={"setpoints": {"enabled": True, "rate_hz": 2}}),
     "outputs.setpoints.rate_hz: must be > 2"),
    (vehicle(sensors=[{"kind": "mavlink", "url": "udpin:0.0.0.0:14540", "tick": 0.1}]),
     "sensors.0.tick: 0.1 s: a ground-robot's dynamics and controller need a tick of at most 0.05 s"),
    (changed(clock={"offset_bound_ms": 0}), "clock.offset_bound_ms: must be > 0"),
], ids=lambda v: v.split(":")[0] if isinstance(v, str) else None)
def test_a_bad_config_names_the_field(tmp_path, data, field):
    assert any(line.startswith(field) for line in problems(data, tmp_path)), problems(data, tmp_path)


def test_without_a_zenoh_block_the_documented_defaults_apply():
    # docs/deploy.md: mode peer, no listen, connect the rule of --connect (the local router)
    z = parse_config(changed(zenoh=None)).zenoh
    assert (z.mode, z.listen, z.connect, z.gossip) == ("peer", [], ["tcp/127.0.0.1:7447"], False)
    # a peer that listens is dialled, and dials nobody unless told; a client connects by default
    assert parse_config(changed(zenoh={"listen": ["tcp/0.0.0.0:7447"]})).zenoh.connect == []
    assert parse_config(changed(zenoh={"mode": "client"})).zenoh.connect == ["tcp/127.0.0.1:7447"]


@pytest.mark.parametrize("speed", [-2, 0, "fast", None, True])
def test_a_bad_file_speed_is_one_problem_in_the_schemas_words(tmp_path, speed):
    np.savez(tmp_path / "sensors.npz", ids=np.array([3]))
    lines = problems(changed(sensors=[{"kind": "file", "path": "sensors.npz", "speed": speed}], outputs={}), tmp_path)
    assert len(lines) == 1 and lines[0].startswith("sensors.0.speed: must be a number > 0"), lines
    assert "as_fast_as_possible" in lines[0]


def test_errors_carry_no_pydantic_internals(tmp_path):
    lines = problems(changed(id="three", prior=5, sensors=[{"kind": "file", "path": "x", "speed": -1}, {"kind": "x"}],
                             outputs={"mavlink": {"rate_hz": "often"}}, gate=[1]), tmp_path)
    text = "\n".join(lines)
    for internal in ("constrained-float", "literal[", "Input should", "instance of", "NoneType", "Value error",
                     "function-", "Extra inputs", "Field required"):
        assert internal not in text, text


def test_the_documented_vehicle_example_loads():
    cfg = load(ROOT / "docs" / "examples" / "vehicle.yaml")
    node = node_spec(cfg).build()
    assert type(node).__name__ == "CiVehicleNode" and node.reference.radius == 3.0 and node.dt == 0.05
    assert daemon_config(cfg).setpoints.enabled


def test_a_closed_loop_vehicle_on_a_flight_controller():
    """Its node tracks the configured circle at the FC source's tick, knows the other vehicle's
    model (a relative position names it), starts from the prior; setpoints reach the daemon
    only when enabled."""
    cfg = parse_config(vehicle())
    node = node_spec(cfg).build()
    assert type(node).__name__ == "CiVehicleNode" and node.dt == 0.05 and node.models[4].name == "quadrotor"
    ref = node.reference
    assert (list(ref.center), ref.radius, ref.period, ref.phase) == ([0.0, 0.0, 0.0], 3.0, 40.0, 0.0)
    e = node.estimate()
    np.testing.assert_allclose(e.mean[:4], [3.0, 0.0, 0.0, 1.5708])
    d = daemon_config(cfg)
    assert d.setpoints.enabled and d.setpoints.rate_hz == 20.0 and d.mavlink_output.reset_gate == 5.0
    assert d.clock_bound == pytest.approx(0.010)
    off = daemon_config(parse_config(vehicle(outputs={"mavlink": {}, "setpoints": {"enabled": False}})))
    assert off.setpoints is None
    alone = node_spec(parse_config(vehicle(vehicle=None, outputs={"mavlink": {}}))).build()
    assert alone.reference is None and alone.command() is None  # estimation only


def test_every_bad_field_is_listed():
    lines = problems(changed(id=-1, gate=2, zenoh={"connect": ["nowhere"]}, outputs={"mavlink": {"rate_hz": 0}}))
    assert [line.split(":")[0] for line in lines] == ["id", "gate", "zenoh.connect.0", "outputs.mavlink.rate_hz"]


def test_relative_paths_are_the_files_directory(tmp_path):
    (tmp_path / "run").mkdir()
    np.savez(tmp_path / "run" / "sensors.npz", ids=np.array([3]))
    path = tmp_path / "agent.yaml"
    path.write_text(yaml.safe_dump(changed(sensors=[{"kind": "file", "path": "run/sensors.npz", "speed": 2}],
                                           outputs={"swarm": True, "log": "est.jsonl"}, state_dir="state")))
    cfg = load(path)
    assert cfg.sensors[0].path == tmp_path / "run" / "sensors.npz"
    assert daemon_config(cfg).state_file == tmp_path / "state" / "agent-3.state.npy"
    assert daemon_config(cfg).estimate_log == tmp_path / "est.jsonl"


def test_check_config_prints_the_summary():
    p = swarmloc("agent", "--config", str(EXAMPLE), "--check-config")
    assert p.returncode == 0, p.stderr
    rows = dict(line.split(None, 1) for line in p.stdout.splitlines()[1:])
    assert rows["id"] == "3" and rows["swarm"] == "field" and rows["model"] == "planar-speed-heading"
    assert rows["estimator"] == "ukf-dcl (max_chain: 4)"
    assert rows["prior"] == "position [12.5, -4.0] +- 0.5 m"
    assert rows["zenoh"] == "peer; listen tcp/0.0.0.0:7447; connect tcp/192.168.10.1:7447, tcp/192.168.10.2:7447"
    assert rows["sensors"] == "mavlink /dev/ttyACM0 at 921600 baud; zenoh drivers/uwb/3 (measurements)"
    assert rows["outputs"] == ("swarm swarmloc/field/agent/3/estimate; mavlink odometry local_ned at 30 Hz; "
                               "log /var/lib/swarmloc/estimates-3.jsonl")
    assert rows["clock"] == (
        "swarm: tick 0 at UNIX 1796083200.000 (2026-12-01T00:00:00.000+00:00); peers' offsets logged beyond 10 ms")
    assert rows["node"] == "swarmloc.estimators.ukf.dcl:UkfDclNode"
    assert "not" not in rows  # every field is read


def test_check_config_on_a_bad_file_is_error_lines(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(changed(prior={"position": [1, 2, 3]}, sensors=[{"kind": "lidar"}])))
    p = swarmloc("agent", "--config", str(bad), "--check-config")
    assert p.returncode == 2 and p.stdout == ""
    assert p.stderr.splitlines() == [
        f"error: {bad}: prior.position: 3 numbers; model planar-speed-heading needs 2",
        f"error: {bad}: sensors.0.kind: unknown kind 'lidar'; one of: zenoh, mavlink, file, ros2"]


@pytest.mark.parametrize("text, says", [(None, "cannot read it"), ("id: [\n", "not valid YAML: line 2"),
                                        ("- 1\n", "a YAML mapping of fields, got a list"),
                                        ("", "a YAML mapping of fields, got an empty file (null)")])
def test_an_unreadable_file_is_one_line(tmp_path, text, says):
    path = tmp_path / "agent.yaml"
    if text is not None:
        path.write_text(text)
    p = swarmloc("agent", "--config", str(path), "--check-config")
    assert p.returncode == 2 and p.stderr.startswith(f"error: {path}: ") and says in p.stderr
    assert len(p.stderr.splitlines()) == 1 and "Traceback" not in p.stderr


@pytest.mark.parametrize("args, refused", [(["--scenario", "wang2019"], "--scenario"), (["--id", "3"], "--id"),
                                           (["--start", "0,0"], "--start"), (["--mode", "client"], "--mode")])
def test_config_is_the_whole_agent(args, refused):
    p = swarmloc("agent", "--config", str(EXAMPLE), *args)
    assert p.returncode == 2
    assert p.stderr.strip() == f"error: --config is the whole agent: give it without {refused}"


def test_check_config_needs_a_config():
    p = swarmloc("agent", "--id", "1", "--start", "0,0", "--check-config")
    assert p.returncode == 2 and p.stderr.strip() == "error: --check-config needs --config FILE"


def test_the_daemon_starts_from_a_config(tmp_path):
    listen = f"tcp/127.0.0.1:{free_port()}"
    path = tmp_path / "agent.yaml"
    path.write_text(yaml.safe_dump(changed(swarm=f"c{os.getpid()}", zenoh={"listen": [listen]}, state_dir="state",
                                           sensors=[{"kind": "zenoh"}], outputs={"swarm": True})))
    p = subprocess.Popen([sys.executable, "-m", "agents", "agent", "--config", str(path), "-v"],
                         stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    lines = []
    try:
        while not any("INFO" in line for line in lines) and select.select([p.stderr], [], [], 30)[0]:
            lines.append(p.stderr.readline())
    finally:
        p.terminate()
        p.wait(10)
    *before, line = lines
    assert not any("warning:" in w for w in before), before  # every field is read now
    assert "agent-3 INFO agent 3 up (peer mode" in line and listen in line and "direct radio" in line, line
    assert f"swarmloc/c{os.getpid()}/agent/3/sensors" in line
    assert (tmp_path / "state").is_dir()


def test_security_names_a_key_directory_of_this_swarm(tmp_path):
    from swarmloc.wire.auth import Keyring

    keys = tmp_path / "keys"
    keys.mkdir()
    Keyring.generate("field", [3]).save_directory(keys)  # agent 3 reads agent-3.secret and members.json
    base = dict(swarm="field", security={"keys": "keys"})
    cfg = parse_config(changed(**base), tmp_path)
    assert daemon_config(cfg).keyring.swarm == "field" and daemon_config(cfg).tls_dir is None
    assert any(line.startswith("security.keys: ") and "swarm 'field', not 'other'" in line
               for line in problems(changed(swarm="other", security={"keys": "keys"}), tmp_path))
    assert any(line.startswith("security.tls: ") and "agent-3.pem, agent-3.key" in line
               for line in problems(changed(**{**base, "security": {"keys": "keys", "tls": True}}), tmp_path))
    assert any(line.startswith("security.tls: needs keys")
               for line in problems(changed(security={"tls": True}), tmp_path))
    (keys / "agent-3.secret").chmod(0o640)  # the agent's own keys
    assert any(line.startswith("security.keys: ") and "chmod 600" in line for line in problems(changed(**base), tmp_path))
