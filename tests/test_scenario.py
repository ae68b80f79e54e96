"""Scenario files: built-ins load, and every mistake names its field."""

import pytest
import yaml

from swarmloc import scenario as S


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
