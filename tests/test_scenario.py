"""Scenario files: built-ins load, and every mistake names its field."""

import numpy as np
import pytest
import yaml

from swarmloc.experiment import scenario as S


def test_builtins_load():
    names = S.builtin_names()
    assert {"wang2019", "random7"} <= set(names)
    sc = S.load("wang2019")
    assert sc.clock.steps == 800 and len(sc.world.agents) == 4
    turns = [a.motion.turn_rate for a in sc.world.agents]
    assert sum(t < 0 for t in turns) == 1 and sum(t > 0 for t in turns) == 3  # A2 clockwise


def base():
    return yaml.safe_load(S.load("wang2019").to_yaml())


@pytest.mark.parametrize(
    "edit, field",
    [
        (lambda d: d["sensors"]["range"].update(probability=1.5), "sensors.range.probability"),
        (lambda d: d["clock"].update(dt=-1), "clock.dt"),
        (lambda d: d["world"]["agents"][2].update(start=[1.0]), "world.agents.2"),
        (lambda d: d["world"]["agents"][0].update(model="hovercraft"), "world.agents.0.model"),
        (lambda d: d["radio"].update(model="carrier-pigeon"), "radio.model"),
        (lambda d: d.update(version=9), "version"),
        (lambda d: d.update(faults=[{"at": 1, "action": "cut", "link": [1, 99]}]), "unknown agents"),
        (lambda d: d["world"]["agents"][1].update(id=1), "unique"),
        (lambda d: d.update(faults=[{"at": 1, "action": "cut", "link": [1, 1]}]), "two different agents"),
    ],
)
def test_errors_name_the_field(edit, field):
    d = base()
    edit(d)
    with pytest.raises(S.ScenarioError) as exc:
        S.parse(d, "test.yaml")
    assert field in str(exc.value)
    assert "test.yaml" in str(exc.value)


def test_file_errors(tmp_path):
    with pytest.raises(S.ScenarioError, match="neither a scenario file nor a built-in"):
        S.load("no-such-scenario")
    bad = tmp_path / "bad.yaml"
    bad.write_text("version: 1\nname: [unclosed\n")
    with pytest.raises(S.ScenarioError, match="not valid YAML"):
        S.load(bad)


def test_overrides_are_validated():
    sc = S.load("wang2019").with_overrides(**{"sensors.range.probability": 0.05, "seed": 3})
    assert sc.sensors.range.probability == 0.05 and sc.seed == 3
    with pytest.raises(S.ScenarioError, match="probability"):
        S.load("wang2019").with_overrides(**{"sensors.range.probability": -1})


def test_yaml_round_trip(tmp_path):
    sc = S.load("random7")
    p = tmp_path / "r.yaml"
    p.write_text(sc.to_yaml())
    assert S.load(p) == sc


def test_radio_parameters_are_validated_by_netsim():
    from netsim.sim import Simulation

    sc = S.load("wang2019").with_overrides(radio={"model": "log-distance", "path_loss_exponent": -1, "rnage": 3})
    with pytest.raises(S.ScenarioError) as exc:
        Simulation(sc)
    assert "radio.path_loss_exponent" in str(exc.value) and "radio.rnage" in str(exc.value)


def _uas(n=2, **extra):
    return {"version": 1, "name": "u", "clock": {"dt": 0.1, "duration": 2},
            "world": {"agents": [{"id": i + 1, "model": "uas-ins", "start": [10.0 * i, 0, 50]} for i in range(n)]}, **extra}


def test_without_an_estimator_the_swarm_gets_one_that_fits_its_models():
    assert S.parse(_uas()).estimator.name == "ekf"
    assert S.load("wang2019").with_overrides(estimator={"name": "il", "params": {}}).reference_names == ["ukf-ccl"]


@pytest.mark.parametrize("extra, named", [
    ({"sensors": {"imu": {"rate_hz": 50000}}}, "4096 IMU samples"),
    ({"sensors": {"imu": {"rate_hz": 15}}}, "clock.dt * sensors.imu.rate_hz"),
    ({"estimator": {"name": "ekf-centre"}}, "needs a ground-station agent"),
    ({"estimator": {"name": "ekf-ci", "params": {"criterion": "max"}}}, "criterion"),
    ({"estimators": "il"}, "must be a list"),
])
def test_uas_scenario_errors_name_the_problem(extra, named):
    with pytest.raises(S.ScenarioError, match=named.replace("*", r"\*")):
        S.parse(_uas(**extra))


def test_too_many_uas_for_one_frame_of_relative_measurements():
    with pytest.raises(S.ScenarioError, match="at most 64 relative"):
        S.parse(_uas(66, sensors={"relpos": {"enabled": True}}))


def test_a_planar_swarm_without_an_estimator_runs_ukf_dcl():
    data = S.load("wang2019").model_dump()
    del data["estimator"]
    assert S.parse(data).estimator.name == "ukf-dcl"


def test_a_formation_generates_agents_on_its_arc_driving_at_its_centre():
    d = base()
    d["world"].pop("agents")
    d["world"]["formation"] = {"count": 4, "center": [500.0, 0.0], "radius": 400.0, "spread_deg": 40.0}
    sc = S.parse(d)
    at = np.array([a.start for a in sc.world.agents])
    assert [a.id for a in sc.world.agents] == [1, 2, 3, 4]
    assert np.allclose(np.linalg.norm(at - [500.0, 0.0], axis=1), 400.0)
    bearings = np.degrees(np.arctan2(at[:, 1], at[:, 0] - 500.0)) % 360
    assert np.allclose(bearings, [160.0, 160 + 40 / 3, 200 - 40 / 3, 200.0])
    for a, p in zip(sc.world.agents, at):  # each heads at the centre, straight
        ahead = p + 400.0 * np.array([np.cos(a.heading), np.sin(a.heading)])
        assert np.allclose(ahead, [500.0, 0.0], atol=1e-9) and a.motion.turn_rate == 0.0
    # an override of the formation regenerates the agents; a dump holds the formation alone
    closer = sc.with_overrides(**{"world.formation.radius": 300.0})
    assert np.allclose(np.linalg.norm(np.array([a.start for a in closer.world.agents]) - [500.0, 0.0], axis=1), 300.0)
    assert "agents" not in yaml.safe_load(closer.to_yaml())["world"]
    assert S.parse(yaml.safe_load(closer.to_yaml())).world.agents == closer.world.agents


def test_a_formation_and_agents_together_are_an_error():
    d = base()
    d["world"]["formation"] = {"count": 2, "center": [0.0, 0.0], "radius": 10.0}
    with pytest.raises(S.ScenarioError, match="not both"):
        S.parse(d)
    d["world"].pop("agents")
    d["world"]["formation"]["center"] = [0.0]
    with pytest.raises(S.ScenarioError, match="world.formation.center"):
        S.parse(d)


def test_errors_are_in_the_schemas_words_not_pydantics():
    bad = {"version": 1, "name": "x", "clock": 5, "seed": 1.5,
           "world": {"agents": [{"id": 1, "start": [0, 0], "motion": {"kind": "zigzag"}},
                                {"id": 2, "start": [0, 0], "motion": {"kind": "circle", "speed": -1}}], "landmark": []},
           "sensors": {"range": {"probability": 2}}, "faults": [{"action": "explode", "at": 3}]}
    with pytest.raises(S.ScenarioError) as info:
        S.parse(bad)
    text = str(info.value)
    for internal in ("Input should", "Value error", "Extra inputs", "instance of", "NoneType", "(top level)"):
        assert internal not in text, text
    problems = dict(info.value.problems)
    assert problems["clock"] == "must be a mapping of fields, got 5"
    assert problems["seed"] == "must be a whole number, got 1.5"
    assert problems["world.landmark"] == "unknown field"
    assert problems["world.agents.0.motion"].startswith("unknown kind 'zigzag'; one of: circle, random")
    assert problems["world.agents.1.motion.speed"] == "must be >= 0.0, got -1"
    assert problems["faults.0"].startswith("unknown action 'explode'")
    with pytest.raises(S.ScenarioError, match="got an empty file"):
        S.parse(None)


@pytest.mark.parametrize("name", ["csl-ctl", "il-ctl"])
def test_an_estimator_of_targets_needs_targets(name):
    with pytest.raises(S.ScenarioError) as info:
        S.load("wang2019").with_overrides(estimator={"name": name, "params": {}})
    assert dict(info.value.problems)["estimator"].startswith(f"{name} needs targets")
    renamed = str(info.value.renamed("wang2019", {"estimator": "--estimator"}))
    assert renamed.startswith(f"wang2019: --estimator: {name} needs targets")
