"""The vehicle estimators as radio roles (swarmloc/estimators/vehicle_cl.py), in process.

EKF-CL over the radio, step by step side by side with the centralized joint EKF run offline on
the same frames (the shape of FilterPy's UKF tests); the centre out of reach; the controller's
command idempotent within a tick; EKF without CL fusing against the poses of the tick."""

import copy

import numpy as np
import pytest

from helpers import in_process
from swarmloc import scenario as S
from swarmloc.estimators.vehicle_ekf import JointVehicleEkf, VehicleEkf
from swarmloc.estimators.vehicle_cl import LocalNode
from swarmloc.results import position_errors
from swarmloc.vehicles import MODELS


def short(name, seconds, **over):
    return S.load(name).with_overrides(**{"clock.duration": seconds, **over})


def offline_joint(sc, record):
    """The paper's centralized EKF on the recorded frames: every vehicle joins at tick 0 from its
    prior after its own tick-0 sensors, then predict, own sensors, relative positions."""
    cfg = sc.sensors.vehicle
    ids = record.ids
    joint = JointVehicleEkf()
    means = []
    for frames in record.sensors:
        k = frames[ids[0]].k
        if k == 0:
            for a in ids:
                x0, P0 = sc.prior(a)
                m = MODELS[sc.agent(a).model]
                noise = np.r_[cfg.force_noise, np.full(m.input_dim - 1, cfg.moment_noise)]
                own = VehicleEkf(m, x0, P0, noise)
                v = frames[a].vehicle
                own.update_attitude(v.attitude, v.attitude_std)
                if frames[a].gnss is not None:
                    own.update_gps(frames[a].gnss.position, frames[a].gnss.std)
                joint.add(a, m, own.x, own.P, noise)
        else:
            joint.predict({a: (frames[a].vehicle.u, frames[a].vehicle.dt) for a in ids})
            for a in ids:
                v = frames[a].vehicle
                joint.update_attitude(a, v.attitude, v.attitude_std)
                if frames[a].gnss is not None:
                    joint.update_gps(a, frames[a].gnss.position, frames[a].gnss.std)
        for b in ids:
            for r in frames[b].vehicle.seen:
                joint.update_relpos(b, r.target, r.z, r.std)
        means.append({a: joint.marginal(a) for a in ids})
    return means


@pytest.mark.parametrize("control", ["netsim", "agents"])
def test_ekf_cl_over_the_radio_equals_the_offline_joint_ekf_every_tick(control):
    sc = short("oliveros3", 4.0, **{"world.control": control})
    record, nodes, _ = in_process(sc, "ekf-cl")
    tr = record.trace("ekf-cl")
    ref = offline_joint(sc, record)
    assert len(ref) == len(record.k) == 201
    worst = 0.0
    for ti, joint in enumerate(ref):
        for ci, a in enumerate(record.ids):
            x, P = joint[a]
            n = x.size
            worst = max(worst, float(np.abs(tr.mean[ti, ci, :n] - x).max()), float(np.abs(tr.cov[ti, ci, :n, :n] - P).max()))
    assert worst < 1e-12, worst
    assert all(nodes[a].stats["centre_ticks"] == 201 for a in record.ids)
    assert nodes[10].stats["relpos_updates"] > 0 and nodes[10].stats["numerical"] == 0


def test_without_the_centre_vehicles_go_on_alone_and_are_taken_back():
    sc = short("oliveros3", 4.0, faults=[{"at": 1.0, "action": "radio-off", "node": 10, "duration": 1.0}])
    record, nodes, _ = in_process(sc, "ekf-cl")
    for a in record.ids:
        s = nodes[a].stats
        assert 45 <= s["own_ticks"] <= 60 and s["centre_ticks"] >= 140, s
        assert s["centre_unreachable"] >= 45
    centre = nodes[10].stats
    assert centre["left"] == 3 and centre["joined"] == 6, centre
    err = position_errors(record, record.trace("ekf-cl"))
    assert np.isfinite(err).all() and err[-1].max() < 0.5


def test_a_command_asked_twice_in_a_tick_is_the_same_and_the_controller_moves_on_once_a_tick():
    sc = short("oliveros3", 1.0, **{"world.control": "agents"})
    record, nodes, _ = in_process(sc, "ekf-cl")
    node = nodes[1]
    first = node.command()
    again = node.command()
    assert np.array_equal(first.u, again.u) and first.k == node.k
    # The same node stepping on the same input from a copy: identical commands tick after tick.
    twin = copy.deepcopy(node)
    for _ in range(3):
        node.command()
    assert np.array_equal(node.command().u, twin.command().u)


def test_ekf_local_fuses_against_the_tick_poses_and_counts_what_never_came():
    sc = short("oliveros-caravan-2", 2.0, **{"estimator": {"name": "ekf-local", "params": {}}})
    record, nodes, _ = in_process(sc, "ekf-local")
    assert all(isinstance(nodes[a], LocalNode) for a in record.ids)
    # Chain 1->2->3->4 and 5->6->7->8, 1->5: one relative position per base and tick each.
    assert nodes[1].stats["relpos_updates"] == 2 * 101 and nodes[3].stats["relpos_updates"] == 101
    assert nodes[4].stats["relpos_updates"] == 0 and nodes[4].stats["gps_updates"] == 101
    assert all(nodes[a].stats["no_anchor"] == 0 for a in record.ids)
    # Vehicle 3 measures vehicle 4, which has GPS: it ends within centimetres.
    err = position_errors(record, record.trace("ekf-local"))
    assert err[-1, record.ids.index(3)] < 0.05
    # Node 3 loses vehicle 4's poses (unicast frames lost: its radio cut one way): counted, not fused.
    sc = short("oliveros-caravan-2", 2.0, **{"estimator": {"name": "ekf-local", "params": {}},
                                             "faults": [{"at": 1.0, "action": "loss", "link": [3, 4],
                                                         "probability": 1.0}]})
    _, nodes, _ = in_process(sc, "ekf-local")
    assert 45 <= nodes[3].stats["no_anchor"] <= 51, nodes[3].stats


def test_ci_stays_consistent_where_fusing_as_if_independent_does_not():
    """Side by side on the same caravan (vehicle 4 with GPS): fusing a target's estimate as if
    it were independent of one's own (ekf-local) makes the chain's vehicles overconfident by
    orders of magnitude; covariance intersection (ekf-ci on vehicles) keeps the NEES of every
    robot at or below its dimension."""
    from swarmloc.results import metrics

    nees = {}
    for est in ("ekf-local", "ekf-ci"):
        sc = short("oliveros-caravan-2", 2.0, **{"estimator": {"name": est, "params": {}}})
        record, nodes, _ = in_process(sc, est)
        agents = metrics(record, [est])["estimators"][est]["agents"]
        nees[est] = {a: agents[str(a)]["nees"]["mean"] for a in record.ids}
        if est == "ekf-ci":
            assert type(nodes[1]).__name__ == "CiVehicleNode" and nodes[1].stats["relpos_updates"] > 0
    robots = (1, 2, 3, 5, 6, 7)
    assert max(nees["ekf-local"][a] for a in (1, 5)) > 100, nees
    assert all(nees["ekf-ci"][a] < 7 * 1.5 for a in robots), nees


def test_ci_on_vehicles_keeps_the_states_it_does_not_see_bounded():
    """Every CI fusion inflates the states a relative position does not see by 1 / w; over a
    caravan without GPS (case 1), 50 fusions per vehicle per second, no covariance entry grows
    beyond what the vehicles' own drift explains, and the NEES stays at or below the state
    dimension."""
    from swarmloc.results import metrics

    sc = short("oliveros-caravan-1", 3.0, **{"estimator": {"name": "ekf-ci", "params": {}}})
    record, nodes, _ = in_process(sc, "ekf-ci")
    cov = record.trace("ekf-ci").cov
    assert np.nanmax(np.abs(cov)) < 0.1, np.nanmax(np.abs(cov))
    agents = metrics(record, ["ekf-ci"])["estimators"]["ekf-ci"]["agents"]
    assert all(agents[str(a)]["nees"]["mean"] < 1.5 * record.models[a].state_dim for a in record.ids), agents
