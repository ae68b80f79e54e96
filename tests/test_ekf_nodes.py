"""The UAS EKF node and the distributed EKF-CI / naive nodes (swarmloc/estimators/ekf/local.py,
ekf_ci.py; Goel, Kealy, Lohani 2016, sections 3-4), on synthetic flights from netsim/world/uas_sensors.py.

Convention of the frames built here (the one ekf.py documents): tick k's IMU intervals end at
t_k = k * TICK, the alignment is the state at t_0, GNSS and relative positions are taken at t_k.
"""

import math

import numpy as np
import pytest
import scipy.stats

from netsim.world import uas_sensors as uas
from swarmloc import wire
from swarmloc.estimators import REGISTRY
from swarmloc.estimators.ekf.ci import CiNode, NaiveNode
from swarmloc.estimators.ekf.local import EkfNode, InsEkf
from swarmloc.estimators.settings import CiSettings
from swarmloc.filters import fusion
from swarmloc.models import ins
from swarmloc.models.motion import UasIns
from swarmloc.wire.messages import AlignMsg, Beacon, GnssMsg, ImuMsg, PseudorangesMsg, RelPosMsg, Sensors

DT, ROWS = 0.01, 10  # 100 Hz IMU, 10 intervals a tick
TICK = DT * ROWS
EPOCH = 10  # ticks between GNSS epochs and relative measurements: 1 Hz
ERROR = UasIns().error
SPEC = ins.ImuSpec()


def prior_cov(spec=SPEC, clock_std=1.0) -> np.ndarray:
    """Alignment covariance: 1 m, 0.1 m/s, 0.01 rad level and 0.03 rad heading, the turn-on biases."""
    return np.diag(np.concatenate([[1.0] * 3, [0.1] * 3, [0.01, 0.01, 0.03], [spec.gyro_bias_sigma0] * 3,
                                   [spec.accel_bias_sigma0] * 3, [clock_std]]) ** 2)


class Flight:
    """One UAS's truth (the 16-vector at every t_k) and IMU rows (tick k: the intervals ending at t_k)."""

    def __init__(self, trajectory, seed, ticks: int, spec=SPEC, clock=None):
        self.seed = np.atleast_1d(seed).tolist()
        rec = uas.ImuSimulator(trajectory, DT, spec, rng=[*self.seed, 0]).run(ticks * ROWS)
        self.rows = np.column_stack([rec.gyro, rec.accel]).reshape(ticks, ROWS, 6)
        t = np.arange(ticks + 1) * TICK
        C, pos, vel = trajectory.dcm(t), trajectory.position(t), trajectory.velocity(t)
        # The biases in force at t_k are those of the interval that starts there.
        bg = np.vstack([rec.gyro_bias[::ROWS], rec.gyro_bias[-1]])
        ba = np.vstack([rec.accel_bias[::ROWS], rec.accel_bias[-1]])
        clk = [clock.advance(tk) for tk in t] if clock is not None else np.zeros(len(t))
        self.x = np.array([UasIns.pack(ins.InsState(pos[k], vel[k], ins.dcm_to_quat(C[k]), bg[k], ba[k], clk[k]))
                           for k in range(ticks + 1)])

    def align(self, P0) -> AlignMsg:
        """The truth at t_0 with an error drawn from P0, as the alignment's covariance claims (the
        same draw every call, so two estimators of one flight start alike)."""
        e = np.random.default_rng([*self.seed, 1]).standard_normal(16) * np.sqrt(np.diag(P0))
        return AlignMsg(UasIns.pack(ins.inject(UasIns.unpack(self.x[0]), -e)), P0)

    def imu(self, k) -> ImuMsg:
        return ImuMsg(DT, self.rows[k - 1])


def frame(k, **kw) -> Sensors:
    return Sensors(k, k * TICK, None, [], **kw)


def fix(rng, p, std) -> GnssMsg:
    return GnssMsg(np.asarray(p) + rng.normal(0.0, std, 3), std)


def pos_err(node, truth) -> float:
    return float(np.linalg.norm(ERROR(truth, node.x)[:3]))


def pair(phase: float, ticks: int, seed) -> list[Flight]:
    """Two UAS on figure-8s about 36 m apart, the paper's two-node setting."""
    trajs = [uas.figure8(center=(0.0, 0.0), altitude=50.0, phase=phase),
             uas.figure8(center=(30.0, 20.0), altitude=60.0, phase=phase + 0.5)]
    return [Flight(tr, [*seed, i], ticks) for i, tr in enumerate(trajs)]


def run_pair(cls, flights, ticks: int, gnss: set, seed, settings=CiSettings(), relpos_std=0.05, gnss_std=2.0,
             on_epoch=None):
    """Two nodes (ids 0 and 1) tick by tick; at every epoch the ones in `gnss` get a fix and each
    measures the other; broadcasts reach the other node after both have stepped (lockstep).
    Returns the position errors (ticks+1, 2) and position NEES (ticks+1, 2)."""
    rng = np.random.default_rng([*seed, 99])
    kw = {} if cls is EkfNode else {"criterion": settings.criterion}
    nodes = [cls(i, np.zeros(16), np.eye(16), imu=SPEC, **kw) for i in range(2)]
    for i, n in enumerate(nodes):
        n.step(frame(0, align=flights[i].align(prior_cov())))
    err, nees = np.zeros((ticks + 1, 2)), np.zeros((ticks + 1, 2))
    for k in range(1, ticks + 1):
        epoch = k % EPOCH == 0
        sent = []
        for i, n in enumerate(nodes):
            x, other = flights[i].x[k], flights[1 - i].x[k]
            rel = [RelPosMsg(1 - i, other[:3] - x[:3] + rng.normal(0.0, relpos_std, 3), relpos_std)] if epoch else []
            g = fix(rng, x[:3], gnss_std) if epoch and i in gnss else None
            sent.append(n.step(frame(k, imu=flights[i].imu(k), gnss=g, relpos=rel)))
        for i, n in enumerate(nodes):
            for s in sent[1 - i]:
                assert s.dst is None and isinstance(s.msg, Beacon)
                n.receive(1 - i, s.msg)
        for i, n in enumerate(nodes):
            e = ERROR(flights[i].x[k], n.x)
            err[k, i] = np.linalg.norm(e[:3])
            if epoch:
                nees[k, i] = fusion.nees(e[:3], n.P[:3, :3])
        if epoch and on_epoch:
            on_epoch(k, nodes)
    return err, nees


# --------------------------------------------------------------------------- the EKF


@pytest.mark.parametrize("tau", [math.inf, 300.0])
def test_batched_predict_equals_mechanize_and_error_dynamics_row_by_row(tau):
    """InsEkf.predict batches the rows for speed; it must be ins.mechanize and ins.error_dynamics."""
    rng = np.random.default_rng(3)
    spec = ins.ImuSpec(bias_tau=tau)
    s = ins.InsState([100.0, -50.0, 30.0], [8.0, -3.0, 1.0], ins.quat_from_euler(0.2, -0.1, 1.0),
                     [1e-3, -2e-3, 5e-4], [0.05, -0.02, 0.03], 12.0, 0.5)
    A = rng.normal(size=(16, 16)) * 0.1
    P0 = np.diag(rng.uniform(0.1, 2.0, 16)) + A @ A.T
    rows = np.column_stack([rng.normal(0.0, 0.3, (ROWS, 3)), rng.normal(0.0, 1.0, (ROWS, 3)) + [0.0, 0.0, 9.8]])
    f = InsEkf(UasIns.pack(s), P0, spec)
    f.state = s.copy()  # with its clock drift, which the 16-vector does not carry
    f.predict(ImuMsg(DT, rows))
    ref, P = s.copy(), P0.copy()
    for r in rows:
        sample = ins.ImuSample(r[:3], r[3:])
        F, Q = ins.error_dynamics(ref, sample, DT, spec)
        ref = ins.mechanize(ref, sample, DT, spec.bias_tau)
        P = F @ P @ F.T + Q
    np.testing.assert_allclose(ins.state_error(ref, f.state), 0.0, atol=1e-12)
    np.testing.assert_allclose(f.state.clock_bias, ref.clock_bias, rtol=1e-15)
    np.testing.assert_allclose(f.P, P, rtol=0, atol=1e-13 * np.abs(P).max())


def test_perfect_imu_without_gnss_tracks_truth():
    """(a) Hovering with a perfect IMU, the strapdown INS holds the truth to rounding; on a
    figure-8 it stays within the mechanization's O(dt^2) error."""
    perfect = ins.ImuSpec.perfect()
    for trajectory, ticks, tol in ((uas.Hover((5.0, -3.0, 40.0), yaw=0.7), 600, 1e-9), (uas.figure8(), 600, 0.05)):
        fl = Flight(trajectory, 0, ticks, spec=perfect)
        P0 = np.diag(np.full(16, 1e-6))
        node = EkfNode(1, np.zeros(16), np.eye(16), imu=perfect)
        node.step(frame(0, align=AlignMsg(fl.x[0], P0)))
        for k in range(1, ticks + 1):
            node.step(frame(k, imu=fl.imu(k)))
        assert node.k == ticks and node.nis == []
        e = ERROR(fl.x[-1], node.x)
        assert np.linalg.norm(e[:3]) < tol, e
        np.testing.assert_array_equal(node.estimate().mean, node.filter.vector())
    assert not node.drops


@pytest.mark.slow
def test_gnss_fixes_hold_the_error_at_noise_level_and_nees_is_chi_square():
    """(b) Noisy MEMS IMU and a 2 m fix at 1 Hz: 10 Monte Carlo runs of 60 s. At every epoch after
    5 s the run-averaged NEES (15 states; the clock is not observable from fixes) must lie in the
    two-sided 95% chi-square interval of 10 x 15 dof at least 85% of the time, and so must its
    mean over the epochs. The NIS of every fix is recorded and is chi-square(3) too. (Checked to
    fail for a filter told its IMU noise is half what it is, or its fixes 20% better or 30% worse
    than they are.)"""
    runs, ticks = 10, 600
    epochs = np.arange(50, ticks + 1, EPOCH)
    nees, err, nis = np.zeros((runs, len(epochs))), [], []
    for m in range(runs):
        fl = Flight(uas.figure8(phase=m), [m], ticks)
        rng = np.random.default_rng([m, 7])
        node = EkfNode(1, np.zeros(16), np.eye(16), imu=SPEC)
        node.step(frame(0, align=fl.align(prior_cov())))
        j = 0
        for k in range(1, ticks + 1):
            node.step(frame(k, imu=fl.imu(k), gnss=fix(rng, fl.x[k][:3], 2.0) if k % EPOCH == 0 else None))
            if k % EPOCH == 0:
                assert len(node.nis) == 1 and node.nis[0][1] == 3
                nis.append(node.nis[0][0])
            else:
                assert node.nis == []
            if j < len(epochs) and k == epochs[j]:
                e = ERROR(fl.x[k], node.x)
                nees[m, j] = fusion.nees(e[:15], node.P[:15, :15])
                err.append(np.linalg.norm(e[:3]))
                j += 1
    lo, hi = scipy.stats.chi2.ppf([0.025, 0.975], runs * 15) / runs
    avg = nees.mean(axis=0)
    inside = np.mean((avg >= lo) & (avg <= hi))
    assert inside >= 0.85, (inside, avg)
    assert lo <= avg.mean() <= hi, (avg.mean(), lo, hi)
    # 2 m per axis from GNSS alone is 3.5 m rms in 3D; the INS smooths it.
    rms = math.sqrt(np.mean(np.square(err)))
    assert 0.5 < rms < 3.5, rms
    nis_lo, nis_hi = scipy.stats.chi2.ppf([0.025, 0.975], 3 * len(nis)) / len(nis)
    assert nis_lo <= np.mean(nis) <= nis_hi, np.mean(nis)


def test_pseudoranges_converge_the_clock_bias():
    """(c) The receiver clock starts 150 m off the filter's guess (0, std 300 m) and drifts;
    1 m pseudoranges at 1 Hz pin it down within a few epochs, and it stays within 4 sigma."""
    ticks = 300
    constellation = uas.GnssConstellation()
    clock = uas.ReceiverClock(rng=5, bias=150.0, drift=0.3)
    fl = Flight(uas.figure8(), [1], ticks, clock=clock)
    receiver_rng = np.random.default_rng(9)
    P0 = prior_cov(clock_std=300.0)
    align = fl.align(P0)
    x0 = align.x.copy()
    x0[15] = 0.0
    node = EkfNode(1, np.zeros(16), np.eye(16), imu=SPEC)
    node.step(frame(0, align=AlignMsg(x0, P0)))
    clock_err = []
    for k in range(1, ticks + 1):
        pr = None
        if k % EPOCH == 0:
            t, p = k * TICK, fl.x[k][:3]
            _, sats, _ = constellation.visible(t, p)
            rho = np.linalg.norm(sats - p, axis=1) + fl.x[k][15] + receiver_rng.normal(0.0, 1.0, len(sats))
            pr = PseudorangesMsg(sats, rho, 1.0)
        node.step(frame(k, imu=fl.imu(k), pseudoranges=pr))
        if pr is not None:
            assert node.nis[0][1] == len(pr.rho) >= 4
            e = fl.x[k][15] - node.x[15]
            clock_err.append(e)
            if k >= 3 * EPOCH:
                assert abs(e) < 4 * math.sqrt(node.P[15, 15]) and abs(e) < 5.0, (k, e, node.P[15, 15])
    assert abs(clock_err[0]) < 20.0  # one epoch already removes most of the 150 m
    assert node.stats["pseudorange_updates"] == ticks // EPOCH
    assert pos_err(node, fl.x[-1]) < 5.0


# --------------------------------------------------------------------------- EKF-CI


@pytest.mark.slow
def test_ci_keeps_the_node_without_gnss_bounded_and_without_sharing_it_drifts():
    """(d) Node 0 has GNSS, node 1 none; both measure their relative position (5 cm) at 1 Hz.
    Node 1 alone drifts by hundreds of metres in 60 s; fusing node 0's estimate with CI it stays
    within a few metres, while node 0 is not harmed."""
    ticks = 600
    flights = pair(0.0, ticks, [0])
    alone, _ = run_pair(EkfNode, flights, ticks, gnss={0}, seed=[0])
    ci, _ = run_pair(CiNode, flights, ticks, gnss={0}, seed=[0])
    assert alone[-1, 1] > 50.0, alone[-1, 1]
    assert ci[50:, 1].max() < 8.0, ci[50:, 1].max()
    assert ci[50:, 0].max() < 8.0
    np.testing.assert_allclose(ci[:, 0], alone[:, 0], atol=1.0)  # node 1's worse estimate barely moves node 0


def test_nan_inputs_are_dropped_counted_and_change_nothing():
    """(e) A NaN in a GNSS fix, pseudoranges, an alignment, a relative position or a beacon is
    dropped and counted, and the estimate is exactly what it would have been without it; NaN
    IMU rows are replaced by the last good one and counted."""
    ticks = 20
    flights = pair(0.0, ticks, [4])
    nodes = {}
    for name in ("clean", "dirty"):
        n = CiNode(0, np.zeros(16), np.eye(16), imu=SPEC)
        n.step(frame(0, align=AlignMsg(flights[0].x[0], prior_cov())))
        for k in range(1, ticks):
            n.step(frame(k, imu=flights[0].imu(k)))
        nodes[name] = n
    clean, dirty = nodes["clean"], nodes["dirty"]
    k = ticks
    x = flights[0].x[k]
    z = flights[1].x[k][:3] - x[:3]
    clean.step(frame(k, imu=flights[0].imu(k), relpos=[RelPosMsg(1, z, 0.05)]))
    dirty.step(frame(k, imu=flights[0].imu(k), gnss=GnssMsg(np.array([x[0], np.nan, x[2]]), 2.0),
                     pseudoranges=PseudorangesMsg(np.array([[2e7, 0.0, 1e7]]), np.array([np.inf]), 1.0),
                     relpos=[RelPosMsg(1, z, 0.05), RelPosMsg(2, np.array([np.nan, 0.0, 0.0]), 0.05)]))
    assert dirty.drops["non-finite"] == 3, dirty.drops
    assert dirty.nis == [] and dirty.stats["gnss_updates"] == 0
    for a, b in ((dirty.estimate(), clean.estimate()),):
        assert a.k == b.k == k
        np.testing.assert_array_equal(a.mean, b.mean)
        np.testing.assert_array_equal(a.cov, b.cov)
    before = dirty.estimate()
    for beacon in (Beacon(k, np.array([np.nan, 0.0, 0.0]), np.eye(3), {}),
                   Beacon(k, x[:3] + z, np.full((3, 3), np.nan), {}),
                   Beacon(k, x[:3] + z, -np.eye(3), {}),
                   Beacon(k, np.zeros(2), np.eye(2), {})):
        assert dirty.receive(1, beacon) == []
    after = dirty.estimate()
    np.testing.assert_array_equal(after.mean, before.mean)
    np.testing.assert_array_equal(after.cov, before.cov)
    assert dirty.drops["non-finite"] == 5 and dirty.drops["malformed"] == 2, dirty.drops
    assert dirty.stats["fused"] == 0
    # The valid beacon after the bad ones is still used: the bad ones did not count as heard.
    dirty.receive(1, Beacon(k, x[:3] + z + 0.1, np.eye(3) * 0.01, {}))
    assert dirty.stats["fused"] == 1
    # An alignment with a NaN keeps the placeholder; NaN IMU rows are held, not propagated.
    n = EkfNode(1, np.zeros(16), np.eye(16), imu=SPEC)
    P0 = prior_cov()
    align_x = flights[0].x[0].copy()
    align_x[4] = np.nan
    n.step(frame(0, align=AlignMsg(align_x, P0)))
    assert n.drops["non-finite"] == 1 and np.all(np.isfinite(n.x))
    n.resume(0, flights[0].x[0], P0)
    twin = EkfNode(1, np.zeros(16), np.eye(16), imu=SPEC)
    twin.resume(0, flights[0].x[0], P0)
    rows = flights[0].rows[0].copy()
    rows[4] = np.nan
    held = rows.copy()
    held[4] = held[3]
    n.step(frame(1, imu=ImuMsg(DT, rows)))
    twin.step(frame(1, imu=ImuMsg(DT, held)))
    np.testing.assert_array_equal(n.x, twin.x)
    assert n.drops["non-finite"] == 2 and n.stats["imu_rows_held"] == 1
    n.step(frame(2, imu=ImuMsg(float("nan"), flights[0].rows[1])))  # unusable: coasted over, 0.1 s like tick 1
    assert n.drops["non-finite"] == 3 and n.stats["coasted_ticks"] == 1 and np.all(np.isfinite(n.x))
    np.testing.assert_allclose(n.x[:3], twin.x[:3] + twin.x[3:6] * TICK)


@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_ci_fusion_never_grows_its_criterion(criterion):
    """(f) omega = 1 (keep the prior) is always a candidate, so the fused covariance's trace
    (or determinant) never exceeds the prior's."""
    checks = []

    class Recording(CiNode):
        def fuse(self, dz, Pz):
            dx, P, omega = super().fuse(dz, Pz)
            checks.append((self.filter.P.copy(), P, omega))
            return dx, P, omega

    ticks = 200
    flights = pair(1.0, ticks, [2])
    run_pair(Recording, flights, ticks, gnss={0}, seed=[2], settings=CiSettings(criterion=criterion))
    assert len(checks) == 2 * ticks // EPOCH
    used = 0
    for prior, post, omega in checks:
        if criterion == "trace":
            assert np.trace(post) <= np.trace(prior) * (1 + 1e-12)
        else:
            assert np.linalg.slogdet(post)[1] <= np.linalg.slogdet(prior)[1] + 1e-9
            # The clock of a node without pseudoranges is left out: not inflated by 1/omega.
            assert post[15, 15] == prior[15, 15] or prior[15, :15].any()
        used += omega < 1.0
    assert used >= ticks // EPOCH // 2  # the node without GNSS takes in its neighbour's fix


@pytest.mark.slow
def test_naive_fusion_is_overconfident_and_ci_is_not():
    """The classic result behind CI: two nodes repeatedly fusing each other's estimates (node 0
    with GNSS, node 1 without). Naive fusion counts the shared information again at every
    epoch: its position covariance collapses and the run-averaged NEES leaves the 95% chi-square
    interval upward at essentially every epoch. CI's, with either criterion, does not exceed its
    upper bound (it is conservative: below the interval is what CI promises, not a failure)."""
    runs, ticks = 4, 400
    res = {}
    for name, cls, settings in (("naive", NaiveNode, CiSettings()), ("ci-trace", CiNode, CiSettings(criterion="trace")),
                                ("ci-det", CiNode, CiSettings(criterion="det"))):
        nees = []
        for m in range(runs):
            _, ne = run_pair(cls, pair(float(m), ticks, [10 + m]), ticks, gnss={0}, seed=[10 + m], settings=settings)
            nees.append(ne[100::EPOCH])  # epochs after 10 s
        res[name] = np.mean(nees, axis=0)  # (epochs, node)
    lo, hi = scipy.stats.chi2.ppf([0.025, 0.975], runs * 3) / runs
    assert np.mean(res["naive"] > hi) >= 0.9, res["naive"]
    for name in ("ci-trace", "ci-det"):
        assert np.mean(res[name] > hi) <= 0.1 and res[name].mean() <= 3.0, (name, res[name])
    print(f"\nposition NEES, mean over {runs} runs and the epochs after 10 s, nodes 0 (GNSS) and 1 "
          f"(dof 3, 95% band of the run average {lo:.2f}..{hi:.2f}): "
          + ", ".join(f"{k} {v.mean(axis=0).round(2)}" for k, v in res.items()))


def test_beacon_bookkeeping():
    """Stale beacons dropped, early ones held until their tick, duplicates and strangers
    counted, unmeasured neighbours ignored, other messages refused; the same arrivals in the same
    order give bit-identical estimates."""
    ticks = 10
    flights = pair(0.0, ticks, [5])

    def fresh():
        n = CiNode(0, np.zeros(16), np.eye(16), imu=SPEC)
        n.step(frame(0, align=AlignMsg(flights[0].x[0], prior_cov())))
        for k in range(1, ticks):
            n.step(frame(k, imu=flights[0].imu(k)))
        return n

    x1 = flights[1].x[ticks][:3]
    z = x1 - flights[0].x[ticks][:3]
    beacon = Beacon(ticks, x1, np.eye(3) * 0.04, {})
    n = fresh()
    assert n.receive(1, beacon) == [] and n.stats["held"] == 1  # early: tick 10 before our step of 10
    out = n.step(frame(ticks, imu=flights[0].imu(ticks), relpos=[RelPosMsg(1, z, 0.05), RelPosMsg(1, z, 0.05)]))
    assert n.drops["duplicate"] == 1  # a second relpos to the same target in one tick
    (send,) = out
    assert send.dst is None and send.msg.k == ticks and send.msg.version == {}
    assert n.stats["fused"] == 1 and n.fused[0][0] == 1 and 0.0 <= n.fused[0][1] < 1.0
    n.receive(1, beacon)
    assert n.drops["duplicate"] == 2 and n.stats["fused"] == 1
    n.receive(2, Beacon(ticks, x1, np.eye(3), {}))
    assert n.stats["unmeasured"] == 1
    n.receive(3, Beacon(ticks - 1, x1, np.eye(3), {}))
    assert n.drops["stale"] == 1
    n.receive(3, GnssMsg(x1, 1.0))
    assert n.drops["unexpected-type"] == 1
    assert n.receive(0, beacon) == [] and n.drops["malformed"] == 1  # our own
    # The beacon crosses the real wire codec unchanged.
    env = wire.decode(wire.encode(send.msg, 0, 1, None))
    np.testing.assert_array_equal(env.body.position, send.msg.position)
    # Determinism: same inputs, same order -> same bits; another order may differ, but is itself reproducible.
    a, b = fresh(), fresh()
    for node in (a, b):
        node.step(frame(ticks, imu=flights[0].imu(ticks), relpos=[RelPosMsg(1, z, 0.05), RelPosMsg(2, z + 1.0, 0.05)]))
        node.receive(2, Beacon(ticks, x1 + 1.0, np.eye(3) * 0.09, {}))
        node.receive(1, beacon)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.P, b.P)


def test_ranges_are_ignored_and_naive_fusion_is_plain_kalman():
    """A range gives no explicit position (section 4): the CI node ignores it. The naive node
    fuses the implied position with the Kalman update, omega meaningless."""
    from swarmloc.wire.messages import RangeMsg

    ticks = 10
    flights = pair(0.0, ticks, [6])
    nodes = []
    for cls in (CiNode, NaiveNode):
        n = cls(0, np.zeros(16), np.eye(16), imu=SPEC)
        n.step(frame(0, align=AlignMsg(flights[0].x[0], prior_cov())))
        nodes.append(n)
    z = flights[1].x[1][:3] - flights[0].x[1][:3]
    for n in nodes:
        n.step(Sensors(1, TICK, None, [RangeMsg(1, float(np.linalg.norm(z)), 0.1)], imu=flights[0].imu(1),
                       relpos=[RelPosMsg(1, z, 0.05)]))
    assert not nodes[0].drops and nodes[0].nis == []
    prior = nodes[1].P.copy()
    nodes[1].receive(1, Beacon(1, flights[1].x[1][:3], np.eye(3) * 0.01, {}))
    assert nodes[1].stats["fused"] == 1 and math.isnan(nodes[1].fused[0][1])
    S = prior[:3, :3] + np.eye(3) * (0.01 + 0.05**2)
    np.testing.assert_allclose(nodes[1].P[:3, :3], prior[:3, :3] - prior[:3, :3] @ np.linalg.solve(S, prior[:3, :3]),
                               atol=1e-12)


def test_missed_ticks_are_coasted_and_resume_restarts_the_filter():
    ticks = 30
    fl = Flight(uas.figure8(), [8], ticks)
    node = EkfNode(1, np.zeros(16), np.eye(16), imu=SPEC)
    node.step(frame(0, align=AlignMsg(fl.x[0], prior_cov())))
    for k in range(1, 11):
        node.step(frame(k, imu=fl.imu(k)))
    P10 = node.P.copy()
    node.resume(10, node.x, P10)
    node.step(frame(20, imu=fl.imu(20)))  # ticks 11..19 never seen
    assert node.k == 20 and node.stats["coasted_ticks"] == 9
    assert np.trace(node.P[:3, :3]) > np.trace(P10[:3, :3]) + 3 * (3.0 * 0.9**2 / 2) ** 2
    e = ERROR(fl.x[20], node.x)
    assert fusion.nees(e[:3], node.P[:3, :3]) < scipy.stats.chi2.ppf(0.999, 3)


def test_registry_builds_the_nodes_from_a_scenario():
    from swarmloc.experiment import scenario

    sc = scenario.parse({"version": scenario.SCENARIO_VERSION, "name": "t", "world": {"agents": [
        {"id": 1, "model": "uas-ins", "start": [0.0, 0.0, 50.0]},
        {"id": 2, "model": "uas-ins", "start": [30.0, 0.0, 50.0]}]},
        "sensors": {"imu": {"gyro_arw": 2e-4}}, "estimator": {"name": "ekf-ci", "params": {"criterion": "det"}}})
    for name, cls in (("ekf", EkfNode), ("ekf-ci", CiNode), ("ekf-naive", NaiveNode)):
        info = REGISTRY[name]
        node = info.make_node(sc, 2, info.settings(sc.estimator.params if name != "ekf" else None))
        assert type(node) is cls and node.algorithm == name and node.x.shape == (16,)
        np.testing.assert_allclose(node.x[:3], sc.prior(2)[0])
        assert node.filter.imu.gyro_arw == 2e-4
        if name != "ekf":
            assert node.criterion == "det"
    with pytest.raises(ValueError, match="criterion"):
        REGISTRY["ekf-ci"].settings({"criterion": "volume"})


def test_a_beacon_whose_position_is_a_lie_past_the_bound_is_refused():
    """Issue 26, finding 7 for EKF-CI on UAS: a beacon position 1 km off (a member's lie) is
    refused as implausible and counted, the estimate untouched; one a metre off is fused."""
    ticks = 10
    flights = pair(0.0, ticks, [5])

    def fresh():
        n = CiNode(0, np.zeros(16), np.eye(16), imu=SPEC)
        n.step(frame(0, align=AlignMsg(flights[0].x[0], prior_cov())))
        for k in range(1, ticks + 1):
            z = flights[1].x[k][:3] - flights[0].x[k][:3]
            n.step(frame(k, imu=flights[0].imu(k), relpos=[RelPosMsg(1, z, 0.05)] if k == ticks else []))
        return n

    x1 = flights[1].x[ticks][:3]
    n = fresh()
    x, P = n.x.copy(), n.P.copy()
    n.receive(1, Beacon(ticks, x1 + np.array([1000.0, 0.0, 0.0]), np.eye(3) * 0.04, {}))
    assert n.drops["implausible-innovation"] == 1 and n.stats["fused"] == 0
    np.testing.assert_array_equal(n.x, x)
    np.testing.assert_array_equal(n.P, P)
    m = fresh()
    m.receive(1, Beacon(ticks, x1 + np.array([1.0, 0.0, 0.0]), np.eye(3) * 0.04, {}))
    assert m.stats["fused"] == 1 and not m.drops
