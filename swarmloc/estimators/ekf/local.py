"""One UAS's INS/GNSS error-state EKF (Goel, Kealy, Lohani 2016, sections 2-3, one node of
the joint filter), and the node that runs it alone: the "no sharing" baseline.

The filter keeps the nominal navigation state as an `ins.InsState`, propagated by strapdown
mechanization of every IMU sample, and the 16x16 covariance of the error state
dx = [dp, dv, dtheta, dbg, dba, dclk] of swarmloc/models/ins.py (eq. 1 with a multiplicative attitude
error). A measurement update estimates dx from the innovation (an EKF update about dx = 0 with
the Jacobians of swarmloc/models/measurements.py evaluated at the nominal state, which for the
rotation-vector layout are exactly the error-state Jacobians) and folds it into the nominal
state with `ins.inject`: the error state is reset to zero after every update.

Time convention: the IMU intervals of the frame of tick k are the ones that end at t_k, so
after `step` the estimate is the state at t_k, like the truth recorded for tick k. The
alignment (`AlignMsg`, tick 0 only) is the state at its frame's time: that frame's IMU
intervals, if any, precede it and are not applied.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from swarmloc.estimators.ekf.common import RejectedInput, checked, checked_covariance, checked_std, guarded
from swarmloc.filters import fusion
from swarmloc.models import ins
from swarmloc.models.measurements import PositionFix, Pseudorange
from swarmloc.models.motion import MOTION_MODELS, UasIns
from swarmloc.node import Node, NodeSpec, Send

log = logging.getLogger(__name__)

MODEL = MOTION_MODELS["uas-ins"]
LAYOUT = MODEL.layout  # StateLayout.uas16("rotation-vector"): the error state's slots
DIM = ins.ERROR_DIM

# Missing IMU data (ticks the node never saw, an unusable IMU message) is coasted at constant
# velocity. What the vehicle did meanwhile is unknown; these bound it, a little above what the
# scenarios' trajectories do (a default figure-8 peaks near 2.2 m/s^2 and 0.4 rad/s).
GAP_ACCEL_STD = 3.0  # m/s^2, taken as an unknown constant acceleration over the gap
GAP_RATE_STD = 0.5  # rad/s, likewise for the body rate

# Placeholder prior, replaced by the tick-0 alignment (the scenario's prior is a position only).
PLACEHOLDER_VEL_STD = 10.0  # m/s
PLACEHOLDER_ATT_STD = 0.5  # rad
PLACEHOLDER_CLOCK_STD = 1e3  # m


class InsEkf:
    """One UAS's error-state EKF: strapdown prediction (eqs. 2-12 in the flat ENU frame of
    swarmloc/models/ins.py) and GNSS updates (a position fix, or pseudoranges, eq. 14).

    `state` is the nominal `ins.InsState`, `P` the error-state covariance. Every method that
    takes a measurement raises `RejectedInput` for a malformed or non-finite one and then leaves
    state and P as they were; an update whose arithmetic fails (numpy.linalg.LinAlgError) also
    leaves them. P is never modified in place, only replaced.
    """

    def __init__(self, x0, P0, imu: ins.ImuSpec = ins.ImuSpec(), clock: ins.ClockSpec = ins.ClockSpec()):
        self.imu, self.clock = imu, clock
        self.W = np.diag(ins.noise_intensity(imu, clock)).copy()  # diagonal: see ins.noise_intensity
        self.last_sample: np.ndarray | None = None  # the last finite IMU row, held over bad ones
        self.state: ins.InsState
        self.P: np.ndarray
        self.set(x0, P0)

    # ------------------------------------------------------------------ state

    def set(self, x, P) -> None:
        """Replace the estimate: x in the uas-ins layout (UasIns.pack), P its error covariance.
        The clock drift, a known constant to this filter, is kept."""
        x = checked(x, (DIM,), "state")
        P = checked_covariance(P, DIM, "covariance")
        drift = self.state.clock_drift if hasattr(self, "state") else 0.0
        self.state = UasIns.unpack(x, drift)
        self.P = P

    def vector(self) -> np.ndarray:
        return UasIns.pack(self.state)

    def correct(self, dx: np.ndarray, P: np.ndarray) -> None:
        """Fold an error-state estimate dx into the nominal state (ins.inject) and take P as
        the covariance after it; refused (nothing changes) if either is not finite."""
        if not (np.all(np.isfinite(dx)) and np.all(np.isfinite(P))):
            raise np.linalg.LinAlgError("non-finite correction")
        self.state = ins.inject(self.state, dx)
        self.P = P

    # ------------------------------------------------------------------ time update

    def predict(self, imu_msg) -> int:
        """Mechanize every IMU interval of the message and propagate P <- F P F^T + Q per
        interval, with F and Q of `ins.error_dynamics` (eq. 10-12: F = I + A dt at the start of
        each interval, Q its exact first-order noise covariance).

        Returns how many rows were not finite: each is replaced by the last finite row (the
        previous interval's rates and specific force, 10 ms old at 100 Hz, are a far better
        guess than none), or by a constant-velocity coast if there never was one.

        Five times faster than calling ins.mechanize and ins.error_dynamics per row (medians for
        a 10-row tick: 0.18-0.22 ms against 0.96-1.03 ms): the rows are independent of the state except
        through the attitude, so only the quaternion chain runs row by row; the rotations,
        velocities, positions and every row's F and Q are computed for all rows at once, with
        the same formulas. tests/test_ekf_nodes.py checks the two agree.
        """
        try:
            dt = float(imu_msg.dt)
        except (TypeError, ValueError):
            raise RejectedInput("malformed", f"imu dt {imu_msg.dt!r}") from None
        if not (math.isfinite(dt) and dt > 0.0):
            raise RejectedInput("non-finite" if not math.isfinite(dt) else "malformed", f"imu dt {dt!r}")
        try:
            rows = np.array(imu_msg.samples, dtype=float)
        except (TypeError, ValueError):
            raise RejectedInput("malformed", "imu samples: not numeric") from None
        if rows.ndim != 2 or rows.shape[1] != 6:
            raise RejectedInput("malformed", f"imu samples: shape {rows.shape}, want (n, 6)")
        n = rows.shape[0]
        if n == 0:
            return 0
        bad = ~np.all(np.isfinite(rows), axis=1)
        for i in np.flatnonzero(bad):
            previous = rows[i - 1] if i > 0 else self.last_sample  # rows[i - 1] is finite by now
            rows[i] = previous if previous is not None else self._coast_sample()
        self.last_sample = rows[-1].copy()
        self._propagate(rows, dt)
        return int(bad.sum())

    def _coast_sample(self) -> np.ndarray:
        """The reading of an IMU at constant velocity (zero rate, the specific force that
        cancels gravity), with the estimated biases it would carry."""
        s = self.state
        return np.concatenate([s.gyro_bias, s.dcm.T @ -ins.GRAVITY + s.accel_bias])

    def _propagate(self, rows: np.ndarray, dt: float) -> None:
        self.state, F, Qd = ins.propagate_rows(self.state, rows, dt, self.imu, self.clock)
        P = self.P
        for i in range(rows.shape[0]):
            P = F[i] @ P @ F[i].T + Qd[i]
        self.P = 0.5 * (P + P.T)

    def coast(self, duration: float) -> None:
        """Time passes without IMU data (ticks never received, an unusable IMU message):
        constant velocity, and the covariance grows by an unknown constant acceleration
        (GAP_ACCEL_STD) and body rate (GAP_RATE_STD) over the gap, on top of the random walks
        of the biases and the clock."""
        T = float(duration)
        if not (math.isfinite(T) and T > 0.0):
            return
        s = self.state
        F = np.eye(DIM)
        F[ins.POS, ins.VEL] = np.eye(3) * T
        G = np.diag(self.W) * T
        a2, r2 = GAP_ACCEL_STD**2, GAP_RATE_STD**2
        G[ins.POS, ins.POS] += np.eye(3) * a2 * T**4 / 4
        G[ins.POS, ins.VEL] += np.eye(3) * a2 * T**3 / 2
        G[ins.VEL, ins.POS] += np.eye(3) * a2 * T**3 / 2
        G[ins.VEL, ins.VEL] += np.eye(3) * a2 * T**2
        G[ins.ATT, ins.ATT] += np.eye(3) * r2 * T**2
        P = F @ self.P @ F.T + G
        self.state = ins.InsState(s.position + s.velocity * T, s.velocity, s.quaternion, s.gyro_bias, s.accel_bias,
                                  s.clock_bias + s.clock_drift * T, s.clock_drift)
        self.P = 0.5 * (P + P.T)
        self.last_sample = None  # the attitude moved on: an old sample is no longer a good guess

    # ------------------------------------------------------------------ measurement updates

    def update(self, z, h, H, R) -> tuple[float, int]:
        """Generic error-state update: z measured, h its prediction at the nominal state, H the
        error-state Jacobian there, R its noise. fusion.ekf_update about dx = 0 (Joseph form)
        gives dx = K (z - h), which `correct` injects. Returns (NIS, dof)."""
        dx, P, nu, S = fusion.ekf_update(np.zeros(DIM), self.P, z, np.asarray(h, float), H, R)
        value = fusion.nis(nu, S)
        self.correct(dx, P)
        return value, int(nu.shape[0])

    def update_fix(self, gnss) -> tuple[float, int]:
        """A GNSS position fix: horizontal std `std`, vertical `std_vertical` (default `std`)."""
        z = checked(gnss.position, (3,), "gnss position")
        sh = checked_std(gnss.std, "gnss std")
        sv = checked_std(gnss.std_vertical, "gnss std_vertical", optional=True)
        model = PositionFix(LAYOUT, std=[sh, sh, sh if sv is None else sv])
        x = self.vector()
        return self.update(z, model.h(x), model.jacobians(x)[0], model.R)

    def update_pseudoranges(self, msg) -> tuple[float, int]:
        """One epoch of pseudoranges (eq. 14), all satellites at once."""
        sats = checked(msg.sats, (None, 3), "pseudorange satellites")
        rho = checked(msg.rho, (sats.shape[0],), "pseudoranges")
        std = checked_std(msg.std, "pseudorange std")
        if rho.shape[0] == 0:
            raise RejectedInput("malformed", "no pseudoranges")
        model = Pseudorange(LAYOUT, sats, std=std)
        x = self.vector()
        return self.update(rho, model.h(x), model.jacobians(x)[0], model.R)

    # ------------------------------------------------------------------ views

    def position(self) -> np.ndarray:
        return self.state.position.copy()

    def position_cov(self) -> np.ndarray:
        return self.P[ins.POS, ins.POS].copy()


def imu_spec(scenario) -> ins.ImuSpec:
    """The filter's IMU model: the scenario's IMU (the world draws its errors from the same)."""
    return scenario.sensors.imu.spec()


def placeholder_prior(x, P, imu: ins.ImuSpec) -> tuple[np.ndarray, np.ndarray]:
    """A 16-state prior from the scenario's (a position and its covariance, or already 16):
    at rest, level, facing east, no biases, with wide uncertainty. Only a placeholder: the
    tick-0 alignment replaces it."""
    x, P = np.asarray(x, float), np.asarray(P, float)
    if x.shape == (DIM,):
        return x, P
    x16, P16 = np.zeros(DIM), np.zeros((DIM, DIM))
    x16[ins.POS] = x
    P16[ins.POS, ins.POS] = P
    P16[ins.VEL, ins.VEL] = np.eye(3) * PLACEHOLDER_VEL_STD**2
    P16[ins.ATT, ins.ATT] = np.eye(3) * PLACEHOLDER_ATT_STD**2
    P16[ins.GYRO_BIAS, ins.GYRO_BIAS] = np.eye(3) * imu.gyro_bias_sigma0**2
    P16[ins.ACCEL_BIAS, ins.ACCEL_BIAS] = np.eye(3) * imu.accel_bias_sigma0**2
    P16[ins.CLOCK, ins.CLOCK] = PLACEHOLDER_CLOCK_STD**2
    return x16, P16


class EkfNode(Node):
    """Each UAS's own INS/GNSS EKF, nothing shared (the paper's "no information sharing" case).

    A tick: the alignment if the frame has one (tick 0), else the time update with the frame's
    IMU intervals (after coasting over any ticks never received), then the GNSS fix and/or the
    pseudoranges of the frame. Relative measurements (ranges, relpos) are ignored. `nis` holds
    the (NIS, dof) of this tick's updates; `x`, `P` always equal the filter's vector and
    covariance. A rejected input is counted in `drops` and changes nothing.
    """

    algorithm = "ekf"

    def __init__(self, aid, x0, P0, imu: ins.ImuSpec = ins.ImuSpec(), clock: ins.ClockSpec = ins.ClockSpec()):
        super().__init__(aid, x0, P0, MODEL)
        self.filter = InsEkf(self.x, self.P, imu, clock)
        self.nis: list[tuple[float, int]] = []
        self.tick: float | None = None  # duration of the last tick with usable IMU data, s
        self.stats = {"gnss_updates": 0, "pseudorange_updates": 0, "imu_rows_held": 0, "coasted_ticks": 0}
        self._sync()

    @classmethod
    def spec(cls, scenario, aid, settings=None) -> NodeSpec:
        agent = scenario.agent(aid)
        if agent.model != MODEL.name:
            raise ValueError(f"{cls.algorithm} runs on {MODEL.name} platforms; agent {aid} is {agent.model}")
        imu = imu_spec(scenario)
        x0, P0 = placeholder_prior(*scenario.prior(aid), imu)
        return NodeSpec.of(cls, aid=aid, x0=x0, P0=P0, imu=imu)

    def _sync(self) -> None:
        self.x = self.filter.vector()
        self.P = self.filter.P

    def resume(self, k, x, P) -> None:
        """Continue from a checkpoint: the filter restarts from (x, P) at tick k; ticks missed
        since are coasted over at the next frame."""
        self.filter.set(x, P)
        self.filter.last_sample = None
        self.k = int(k)
        self._sync()

    def step(self, sensors) -> list[Send]:
        if sensors.k <= self.k:
            return self.drop("stale-tick", f"sensors k={sensors.k} at k={self.k}")
        self.nis = []
        missed = sensors.k - self.k - 1 if self.k >= 0 else 0
        self.k = sensors.k
        if sensors.align is not None:
            self._guard("align", self.filter.set, sensors.align.x, sensors.align.P)
        else:
            self._time_update(sensors.imu, missed)
        # A receiver reports one or the other; given both, both are applied, fix first.
        for what, msg, update in (("gnss", sensors.gnss, self.filter.update_fix),
                                  ("pseudorange", sensors.pseudoranges, self.filter.update_pseudoranges)):
            if msg is not None and (result := self._guard(what, update, msg)) is not None:
                self.nis.append(result)
                self.stats[f"{what}_updates"] += 1
        self._sync()
        return []

    def _time_update(self, imu, missed: int) -> None:
        if imu is None:
            return  # no IMU on this platform or in this frame: no time passes for the filter
        try:
            tick = float(imu.dt) * np.shape(imu.samples)[0]
        except (TypeError, ValueError, IndexError):
            tick = math.nan
        if not (math.isfinite(tick) and tick > 0.0):
            tick = self.tick  # the message cannot say how long the tick was: as long as the last
        if missed > 0 and tick is not None:
            self.filter.coast(missed * tick)
            self.stats["coasted_ticks"] += missed
        try:
            held = self.filter.predict(imu)
        except RejectedInput as exc:
            self.drop(exc.reason, f"imu: {exc.detail}")
            if tick is not None:
                self.filter.coast(tick)
                self.stats["coasted_ticks"] += 1
            return
        self.tick = tick
        if held:
            self.stats["imu_rows_held"] += held
            self.drop("non-finite", f"imu: {held} rows held")

    def _guard(self, what: str, action, *args):
        return guarded(self, what, action, *args)
