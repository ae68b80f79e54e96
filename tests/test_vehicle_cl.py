"""The vehicle estimators as radio roles (swarmloc/estimators/vehicles/cl.py), in process.

EKF-CL over the radio, step by step side by side with the centralized joint EKF run offline on
the same frames (the shape of FilterPy's UKF tests); the centre out of reach; the controller's
command idempotent within a tick; EKF without CL fusing against the poses of the tick."""

import copy

import numpy as np
import pytest
from helpers import in_process

from swarmloc.estimators.vehicles.cl import LocalNode
from swarmloc.estimators.vehicles.filters import JointVehicleEkf, VehicleEkf
from swarmloc.experiment import scenario as S
from swarmloc.experiment.results import position_errors
from swarmloc.models.vehicles import MODELS


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


@pytest.mark.slow
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


@pytest.mark.slow
def test_ci_stays_consistent_where_fusing_as_if_independent_does_not():
    """Side by side on the same caravan (vehicle 4 with GPS): fusing a target's estimate as if
    it were independent of one's own (ekf-local) makes the chain's vehicles overconfident by
    orders of magnitude; covariance intersection (ekf-ci on vehicles) keeps the NEES of every
    robot at or below its dimension."""
    from swarmloc.experiment.results import metrics

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


@pytest.mark.slow
def test_ci_on_vehicles_keeps_the_states_it_does_not_see_bounded():
    """Every CI fusion inflates the states a relative position does not see by 1 / w; over a
    caravan without GPS (case 1), 50 fusions per vehicle per second, no covariance entry grows
    beyond what the vehicles' own drift explains, and the NEES stays at or below the state
    dimension."""
    from swarmloc.experiment.results import metrics

    sc = short("oliveros-caravan-1", 3.0, **{"estimator": {"name": "ekf-ci", "params": {}}})
    record, nodes, _ = in_process(sc, "ekf-ci")
    cov = record.trace("ekf-ci").cov
    assert np.nanmax(np.abs(cov)) < 0.1, np.nanmax(np.abs(cov))
    agents = metrics(record, ["ekf-ci"])["estimators"]["ekf-ci"]["agents"]
    assert all(agents[str(a)]["nees"]["mean"] < 1.5 * record.models[a].state_dim for a in record.ids), agents


def test_a_pose_of_a_later_tick_waits_for_it():
    """Real time on the swarm clock: a peer whose flight controller's samples come a little
    earlier steps first, and its pose of tick k may arrive while this node is still at k - 1.
    It is held, and fused once the node steps to k (a pose of a past tick is stale)."""
    from swarmloc.wire.messages import RelPosMsg, Sensors, VehicleMsg, VehiclePose

    m = MODELS["ground-robot"]
    me, other = m.initial_state([0.0, 0.0, 0.0], 0.0), m.initial_state([2.0, 0.0, 0.0], 0.0)
    P = np.diag([0.2**2] * 3 + [1e-4] * 4)
    node = LocalNode(2, me + [0.3, 0, 0, 0, 0, 0, 0], P, "ground-robot", [0.3, 3e-3],
                     roster=[(1, "ground-robot"), (2, "ground-robot")])
    frame = lambda k, seen: Sensors(k, 0.05 * k, None, [], vehicle=VehicleMsg(0.05 if k else 0.0, np.zeros(2),
                                                                              np.array([0.0]), 0.01, seen))
    node.step(frame(0, []))
    pose = VehiclePose(1, other, np.eye(7) * 1e-6)
    assert node.receive(1, pose) == [] and node.stats["held"] == 1 and node.stats["relpos_updates"] == 0
    node.step(frame(1, [RelPosMsg(1, np.array([2.0, 0.0, 0.0]), 0.01)]))
    assert node.stats["relpos_updates"] == 1 and node.stats["no_anchor"] == 0
    assert abs(node.x[0]) < 0.05  # pulled from 0.3 m off to the sighting
    node.receive(1, VehiclePose(0, other, np.eye(7) * 1e-6))
    assert node.drops["stale"] == 1


def _raw_chain(seconds=2.0, **over):
    sc = short("oliveros-chain-control", seconds, **{"estimator": {"name": "raw", "params": {}}, **over})
    return sc, *in_process(sc, "raw")[:2]


def test_raw_feeds_back_the_gps_fix_and_chains_relative_positions_from_it():
    """The paper's closed loop without CL: vehicle 4 steers on its GPS fix, 3 on 4's position
    less its own measurement of 4 rotated by its IMU's orientation, 2 on 3's, 1 on 2's."""
    sc, record, nodes = _raw_chain()
    tr = record.trace("raw")
    col = {a: i for i, a in enumerate(record.ids)}
    for ti, frames in enumerate(record.sensors):
        q = {a: np.asarray(frames[a].vehicle.attitude) / np.linalg.norm(frames[a].vehicle.attitude) for a in col}
        est = {a: tr.mean[ti, col[a], :13] for a in col}
        np.testing.assert_allclose(est[4][:3], frames[4].gnss.position, atol=1e-12)
        for a in col:
            np.testing.assert_allclose(est[a][3:7], q[a], atol=1e-12)
        for b, t in ((3, 4), (2, 3), (1, 2)):
            (z,) = [r.z for r in frames[b].vehicle.seen if r.target == t]
            R = MODELS["quadrotor"].rotation(est[b])
            np.testing.assert_allclose(est[b][:3], est[t][:3] - R @ np.asarray(z), atol=1e-9)
    ticks = len(record.k)
    assert nodes[4].stats["raw_gps"] == ticks and sum(nodes[a].stats["raw_chain"] for a in (1, 2, 3)) == 3 * ticks


def test_raw_without_gps_steers_on_its_own_ekf_and_the_chain_on_it():
    sc, record, nodes = _raw_chain(**{"sensors.vehicle.gps_schedule": {"start": 1.0}})
    before = sum(1 for t in record.t if t < 1.0)
    assert nodes[4].stats["raw_none"] == before and nodes[4].stats["raw_gps"] == len(record.k) - before
    assert all(nodes[a].stats["raw_chain"] == len(record.k) for a in (1, 2, 3))


@pytest.mark.slow
def test_cl_removes_the_noise_that_raw_feedback_accumulates_down_the_chain():
    """Without CL each hop adds a relative position's noise and the rotation error of a raw
    orientation over the lever arm, so the raw error grows with the hops from vehicle 4; EKF-CL's
    estimates of the vehicles without GPS are far smoother (section 6.3: CL "significantly
    reduces the noise")."""
    from swarmloc.experiment.results import metrics

    sc, record, _ = _raw_chain(4.0)
    raw = metrics(record, ["raw"])["estimators"]["raw"]["agents"]
    cl_sc = short("oliveros-chain-control", 4.0)
    cl_record, _, _ = in_process(cl_sc, "ekf-cl")
    cl = metrics(cl_record, ["ekf-cl"])["estimators"]["ekf-cl"]["agents"]
    rms = [raw[str(a)]["rmse_m"] for a in (1, 2, 3, 4)]
    assert rms[0] > rms[1] > rms[2] > rms[3], rms
    for a in ("1", "2", "3"):
        assert cl[a]["jitter_m"] < 0.2 * raw[a]["jitter_m"], (a, cl[a], raw[a])


def test_the_papers_filter_assumptions_reach_every_vehicle_filter():
    """Section 6.1: a constant Q = 0.1 I and an orientation std of 0.1, whatever the world's."""
    from swarmloc.estimators import make_nodes
    from swarmloc.estimators.vehicles.filters import process_noise

    quad = MODELS["quadrotor"]
    x = quad.initial_state([0.0, 0.0, 1.0])
    np.testing.assert_array_equal(process_noise(quad, x, 0.02, np.full(4, 0.1), q=0.1), 0.1 * np.eye(13))
    f = VehicleEkf(quad, x, np.eye(13) * 1e-4, np.full(4, 0.1), q=0.1)
    F = quad.transition(x, quad.hover_input(), 0.02)[1]
    P = F @ f.P @ F.T + 0.1 * np.eye(13)
    f.predict(quad.hover_input(), 0.02)
    np.testing.assert_allclose(f.P, 0.5 * (P + P.T), atol=1e-15)
    sc = short("oliveros-chain-control", 1.0, **{"estimation.process_noise": 0.1, "estimation.attitude_std": 0.2})
    for name in ("ekf-cl", "raw", "ekf-local", "ekf-ci"):
        nodes = make_nodes(name, sc)
        assert all(n.filter.q == 0.1 and n.attitude_std == 0.2 for a, n in nodes.items() if a != 10), name
    assert make_nodes("ekf-cl", sc)[10].process_q == 0.1 and make_nodes("ekf-cl", sc)[10].attitude_std == 0.2
    with pytest.raises(ValueError, match="q must be"):
        process_noise(quad, x, 0.02, np.full(4, 0.1), q=float("nan"))
    # The assumed orientation std replaces the one the IMU reports in the attitude update.
    record, nodes, _ = in_process(short("oliveros-chain-control", 0.1, **{"estimation.attitude_std": 0.2,
                                                                        "estimator": {"name": "ekf-local", "params": {}}}),
                                  "ekf-local")
    own = VehicleEkf(quad, *sc.prior(4), nodes[4].actuator_std)
    v = record.sensors[0][4].vehicle
    own.update_attitude(v.attitude, 0.2)
    if record.sensors[0][4].gnss is not None:
        own.update_gps(record.sensors[0][4].gnss.position, record.sensors[0][4].gnss.std)
    np.testing.assert_allclose(record.trace("ekf-local").cov[0, 3, :13, :13], own.P, atol=1e-15)


@pytest.mark.slow
def test_case_4_estimates_are_noisier_than_case_1s():
    """Table 1: joining the caravans through the two quadrotors (case 4, 4 -> 8) instead of two
    robots (case 1, 1 -> 5) leaves the estimates noisier (benchmarks/studies/
    oliveros-case4-orientation.yaml, orientation noise 0.01: the swarm's jitter 1.04-1.43 times
    case 1's and robot 1's 1.35-2.1 times, in each of 10 seeds)."""
    from swarmloc.experiment.results import metrics

    jitter = {}
    for case in (1, 4):
        sc = short(f"oliveros-caravan-{case}", 3.0)
        record, _, _ = in_process(sc, "ekf-cl")
        jitter[case] = metrics(record, ["ekf-cl"])["estimators"]["ekf-cl"]
    assert jitter[4]["agents"]["1"]["jitter_m"] > 1.2 * jitter[1]["agents"]["1"]["jitter_m"]
    assert jitter[4]["jitter_m"] > jitter[1]["jitter_m"]


@pytest.mark.slow
def test_with_the_papers_filter_noise_case_4_is_far_noisier_than_case_1():
    """Section 6.1's filter assumptions (Q = 0.1 I per tick, orientation 0.1) over an IMU of that
    noise: the filter follows its measurements, and the link between the caravans through two
    quadrotors (case 4), whose relative position carries a 3-D orientation error, shakes every
    estimate more than the link through two robots (case 1): the swarm's jitter 1.5-1.7 times
    case 1's, quadrotor 4's 1.35-1.6 times, in every one of 10 seeds
    (benchmarks/studies/oliveros-case4-filter-q.yaml)."""
    from swarmloc.experiment.results import metrics

    paper = {"estimation.process_noise": 0.1, "sensors.vehicle.attitude_noise": 0.1}
    out = {}
    for case in (1, 4):
        record, _, _ = in_process(short(f"oliveros-caravan-{case}", 3.0, **paper), "ekf-cl")
        out[case] = metrics(record, ["ekf-cl"])["estimators"]["ekf-cl"]
    assert out[4]["jitter_m"] > 1.3 * out[1]["jitter_m"], (out[4]["jitter_m"], out[1]["jitter_m"])
    assert out[4]["agents"]["4"]["jitter_m"] > 1.2 * out[1]["agents"]["4"]["jitter_m"]


@pytest.mark.slow
def test_with_noisy_quadrotors_case_4_is_the_less_noisy():
    """Filters matched to a world whose quadrotors are the noisy vehicles (moment noise 0.1 N m):
    case 4's link gives quadrotor 4 a neighbour, which outweighs robot 1's lost one; the swarm's
    jitter about 0.7 times case 1's in each of 5 seeds (benchmarks/studies/oliveros-case4-actuator.yaml)."""
    from swarmloc.experiment.results import metrics

    world = {"sensors.vehicle.attitude_noise": 0.1, "sensors.vehicle.force_noise": 0.1,
             "sensors.vehicle.moment_noise": 0.1}
    out = {}
    for case in (1, 4):
        # 10 s, as the study: the quadrotors' noise takes seconds to outgrow the start.
        record, _, _ = in_process(short(f"oliveros-caravan-{case}", 10.0, **world), "ekf-cl")
        out[case] = metrics(record, ["ekf-cl"])["estimators"]["ekf-cl"]
    assert out[4]["jitter_m"] < 0.85 * out[1]["jitter_m"], (out[4]["jitter_m"], out[1]["jitter_m"])
    assert out[4]["agents"]["1"]["jitter_m"] > out[1]["agents"]["1"]["jitter_m"]  # robot 1 still loses
