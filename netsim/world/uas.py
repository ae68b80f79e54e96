"""The UAS part of netsim's world: truth and sensor frames of a scenario's ``uas-ins`` agents.

`UasFleet` flies each UAS along the trajectory its motion spec names (netsim/world/uas_sensors.py), placed so
that it passes through the agent's `start` at t = 0, and produces per tick what its sensors
report: a tick's IMU intervals, and at every GNSS epoch (``sensors.epoch``) a position fix or
pseudoranges, relative positions and inter-UAV ranges. Tick 0 carries each UAS's pre-flight
alignment (`AlignMsg`). The planar `netsim.world.World` delegates its UAS to this class.

Truth is what swarmloc/models/ins.py's filter estimates: `states` packs the true `InsState` with
`UasIns.pack`, its biases those in force for the next IMU interval and its clock bias that of the
receiver clock behind the pseudoranges, so a perfect filter tracks it exactly.

Randomness: every draw comes from a stream of its own per purpose and per agent, derived from
the world seed (`stream`), so enabling relative positions never changes the IMU noise, and the
order of the agents changes nothing. Draws happen whether or not their measurement is delivered
(a GNSS outage, a peer out of range), so what is delivered never shifts another draw.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from netsim.world.uas_sensors import (
    GnssConstellation,
    GnssReceiver,
    ImuSimulator,
    ReceiverClock,
    Trajectory,
    circle,
    figure8,
    random_smooth,
)
from swarmloc.models import ins
from swarmloc.models.motion import UasIns
from swarmloc.wire.messages import AlignMsg, GnssMsg, ImuMsg, PseudorangesMsg, RangeMsg, RelPosMsg

UAS_STREAM = 0x0A5F
"""First spawn-key word of every fleet stream: keeps them apart from World's streams (spawn keys
of length one) and from the scenario's prior."""
PURPOSES = ("trajectory", "imu", "clock", "gnss", "relpos", "range", "align")

ALIGN_VELOCITY_STD = 0.1
"""m/s: pre-flight alignment, velocity std (on the ground or a hand launch, velocity is known)."""
ALIGN_ATTITUDE_STD = math.radians(0.5)
"""rad: pre-flight alignment, std of each attitude-error component (levelling and a compass)."""
CLOCK_STD = 10.0
"""m: std of a receiver's clock bias at turn-on (the truth's) and of the alignment's clock error."""
CHUNK_SECONDS = 2.0
"""Simulated seconds of IMU and trajectory computed per batch: one vectorised trajectory
evaluation per batch instead of one per tick. The batches depend only on the agent id, dt and
this constant, so a run is reproducible bit for bit; another batching would change the numbers by
rounding only (ImuSimulator accumulates its interval start times batch by batch)."""


def stream(seed: int, purpose: str, aid: int) -> np.random.Generator:
    """The generator of one purpose (`PURPOSES`) for one agent."""
    ss = np.random.SeedSequence(seed, spawn_key=(UAS_STREAM, PURPOSES.index(purpose), aid))
    return np.random.default_rng(ss)


def _whole(x: float, what: str) -> int:
    n = round(x)
    if n < 1 or abs(x - n) > 1e-9 * max(1.0, abs(x)):
        raise ValueError(f"{what} must be a whole number >= 1, got {x:.12g}")
    return int(n)


def trajectory_of(motion, start, rng) -> Trajectory:
    """The trajectory of a uas-ins agent's motion spec, translated to pass through `start` (ENU
    m) at t = 0. Only the constant term moves, so velocity, attitude and IMU are unchanged."""
    if motion.kind == "figure8":
        traj = figure8(width=motion.width, height=motion.height, period=motion.period, phase=motion.phase,
                       heading=motion.heading, climb=motion.climb)
    elif motion.kind == "orbit":
        traj = circle(radius=motion.radius, speed=motion.speed, phase=motion.phase, clockwise=motion.clockwise)
    elif motion.kind == "random3d":
        traj = random_smooth(rng, radius=motion.radius, speed=motion.speed, wander=motion.wander,
                             vertical=motion.vertical)
    else:
        raise ValueError(f"motion {motion.kind!r} is not a UAS trajectory")
    traj.origin = traj.origin + (np.asarray(start, float) - traj.position(0.0))
    return traj


def align_covariance(initial_std: float, spec: ins.ImuSpec) -> np.ndarray:
    """P of the pre-flight alignment, in the error-state order of swarmloc/models/ins.py."""
    d = np.concatenate([np.full(3, initial_std**2), np.full(3, ALIGN_VELOCITY_STD**2),
                        np.full(3, ALIGN_ATTITUDE_STD**2),
                        np.full(3, spec.gyro_bias_sigma0**2), np.full(3, spec.accel_bias_sigma0**2), [CLOCK_STD**2]])
    return np.diag(d)


class _SharedSky(GnssConstellation):
    """The constellation with the last epoch's satellite positions kept: every receiver asks for
    the same epoch, and the orbits cost more than the rest of a pseudorange epoch."""

    _t, _enu = None, None

    def enu(self, t: float) -> np.ndarray:
        if t != self._t:
            self._t, self._enu = t, super().enu(t)
        return self._enu


class _Uas:
    """One UAS: trajectory, IMU, clock, receiver, its streams and the current batch."""

    def __init__(self, fleet: "UasFleet", spec, seed: int, first_batch: int):
        aid = spec.id
        self.id = aid
        self.rng = {p: stream(seed, p, aid) for p in PURPOSES}
        self.traj = trajectory_of(spec.motion, spec.start, self.rng["trajectory"])
        self.imu = ImuSimulator(self.traj, fleet.imu_dt, fleet.imu_spec, rng=self.rng["imu"])
        # Drift 0: the 16-state filter carries the drift as a known constant, 0 at the start (ClockSpec).
        clock_rng = self.rng["clock"]
        self.clock = ReceiverClock(fleet.clock_spec, rng=clock_rng, bias=CLOCK_STD * clock_rng.standard_normal())
        self.receiver = None
        if fleet.constellation is not None and fleet.has_receiver(aid):
            self.receiver = GnssReceiver(fleet.constellation, rng=self.rng["gnss"], sigma=fleet.gnss.pseudorange_noise,
                                         mask_deg=fleet.gnss.mask_deg, clock=self.clock)
        self.n, self.dt = fleet.imu_per_tick, fleet.dt
        # The batch: the IMU of ticks k0 .. k0 + m - 1 (n rows each) and the truth at ticks
        # k0 - 1 .. k0 + m - 1 (row k - k0 + 1). Bias row j is the bias in force for interval j,
        # so tick k's truth bias (the one for the next interval) is row n (k - k0 + 1). The
        # first batch is computed here, so tick 0 reads row 0 of it and ticks pay only refills.
        self.refill(1, first_batch)
        self.row = 0

    def refill(self, k0: int, ticks: int):
        n = self.n
        rec = self.imu.run(ticks * n)
        t = self.dt * np.arange(k0 - 1, k0 + ticks)
        self.k0, self.m = k0, ticks
        self.pos, self.vel, self.dcm = self.traj.position(t), self.traj.velocity(t), self.traj.dcm(t)
        self.samples = np.concatenate([rec.gyro, rec.accel], axis=1)
        self.bg = np.vstack([rec.gyro_bias, self.imu.gyro_bias])
        self.ba = np.vstack([rec.accel_bias, self.imu.accel_bias])

    def advance(self, k: int, batch: int) -> np.ndarray:
        """Move to tick k >= 1; return its IMU samples (n, 6)."""
        if k >= self.k0 + self.m:
            self.refill(k, batch)
        j = k - self.k0
        self.row = j + 1
        self.clock.advance(k * self.dt)
        return self.samples[self.n * j: self.n * (j + 1)].copy()

    def position(self) -> np.ndarray:
        return self.pos[self.row]

    def true_ins(self) -> ins.InsState:
        r, b = self.row, self.n * self.row
        return ins.InsState(self.pos[r], self.vel[r], ins.dcm_to_quat(self.dcm[r]), self.bg[b], self.ba[b],
                            self.clock.bias, self.clock.drift)


class UasFleet:
    """Truth and sensors of the scenario's uas-ins agents `ids`, with streams from `seed` (the
    world seed).

    Call `step(0)`, `step(1)`, ... in order: tick 0 is the start (no motion, the alignment),
    tick k >= 1 covers [t_{k-1}, t_k] with t_k = k dt. `positions` and `states` are the truth at
    the last tick stepped (t = 0 before any)."""

    def __init__(self, scenario, ids: list[int], seed: int):
        self.sc = scenario
        self.dt = float(scenario.clock.dt)
        self.ids = sorted(ids)
        sensors = scenario.sensors
        imu = sensors.imu
        self.imu_spec = imu.spec()
        self.imu_dt = 1.0 / imu.rate_hz
        self.imu_per_tick = _whole(self.dt * imu.rate_hz, f"clock.dt * sensors.imu.rate_hz (IMU intervals per tick: "
                                   f"{self.dt} s * {imu.rate_hz} Hz)")
        self.epoch_ticks = _whole(sensors.epoch / self.dt, f"sensors.epoch / clock.dt (ticks per GNSS epoch: "
                                  f"{sensors.epoch} s / {self.dt} s)")
        rel_epoch = sensors.epoch if sensors.relative_epoch is None else sensors.relative_epoch
        self.relative_ticks = _whole(rel_epoch / self.dt, f"sensors.relative_epoch / clock.dt (ticks between relative "
                                     f"measurements: {rel_epoch} s / {self.dt} s)")
        self.batch = max(1, round(CHUNK_SECONDS / self.dt))
        self.clock_spec = ins.ClockSpec()
        self.gnss = sensors.gnss
        self.constellation = _SharedSky() if self.gnss.enabled and self.gnss.kind == "pseudorange" else None
        self.P0 = align_covariance(scenario.estimation.initial_std, self.imu_spec)
        specs = {a.id: a for a in scenario.world.agents}
        bad = [a for a in self.ids if a not in specs or specs[a].model != UasIns.name]
        if bad:
            raise ValueError(f"agents {bad} are not uas-ins agents of the scenario")
        # Staggered first batches spread the refills over the ticks instead of stalling every
        # `batch`-th tick. By id, not by place in the fleet, so an agent's numbers are the same
        # in any fleet.
        self.uas = {a: _Uas(self, specs[a], seed, 1 + a % self.batch) for a in self.ids}
        self.k = -1

    def has_receiver(self, aid: int) -> bool:
        return self.gnss.enabled and (self.gnss.agents is None or aid in self.gnss.agents)

    def positions(self) -> dict[int, np.ndarray]:
        return {a: u.position().copy() for a, u in self.uas.items()}

    def true_ins(self, aid: int) -> ins.InsState:
        """The true navigation state of one UAS, clock drift included (`states` has no drift)."""
        return self.uas[aid].true_ins()

    def states(self) -> dict[int, np.ndarray]:
        return {a: UasIns.pack(u.true_ins()) for a, u in self.uas.items()}

    def step(self, k: int, gnss_ok: Callable[[int], bool] = lambda a: True) -> dict[int, dict]:
        """Advance to tick k (the next one) and return each UAS's Sensors fields (module
        docstring); gnss_ok(a) False is an outage of a's receiver."""
        if k != self.k + 1:
            raise ValueError(f"UasFleet.step: expected tick {self.k + 1}, got {k}")
        self.k = k
        out = {a: {"imu": None, "gnss": None, "pseudoranges": None, "relpos": [], "ranges": [], "align": None}
               for a in self.ids}
        if k == 0:
            for a, u in self.uas.items():
                out[a]["align"] = self._align(u)
            return out
        for a, u in self.uas.items():
            out[a]["imu"] = ImuMsg(self.imu_dt, u.advance(k, self.batch))
        gnss, relative = k % self.epoch_ticks == 0, k % self.relative_ticks == 0
        if gnss or relative:
            self._epoch(k * self.dt, out, gnss_ok, gnss, relative)
        return out

    def _align(self, u: _Uas) -> AlignMsg:
        true = u.true_ins()
        draw = np.sqrt(np.diag(self.P0)) * u.rng["align"].standard_normal(ins.ERROR_DIM)
        if not self.sc.estimation.initial_error:
            draw[:] = 0.0
        # inject(true, -draw) is the exact inverse of state_error: additive parts give back
        # draw up to rounding, and the attitude, q_est = exp(-draw) (x) q_true, gives
        # q_true (x) conj(q_est) = exp(draw) exactly, so state_error(true, est) = draw.
        est = ins.inject(true, -draw)
        return AlignMsg(UasIns.pack(est), self.P0.copy())

    def _epoch(self, t: float, out: dict, gnss_ok, gnss: bool = True, relative: bool = True):
        P = np.stack([u.position() for u in self.uas.values()])
        D = np.linalg.norm(P[None, :, :] - P[:, None, :], axis=-1)  # D[i, j] = |p_j - p_i|
        cfg = self.gnss
        nv = cfg.noise_vertical if cfg.noise_vertical is not None else cfg.noise
        rel, rng_cfg = self.sc.sensors.relpos, self.sc.sensors.range
        for i, (a, u) in enumerate(self.uas.items()):
            if gnss and self.has_receiver(a):
                if cfg.kind == "position":
                    e = u.rng["gnss"].standard_normal(3) * [cfg.noise, cfg.noise, nv]
                    if gnss_ok(a):
                        out[a]["gnss"] = GnssMsg(P[i] + e, cfg.noise, nv)
                else:
                    prs = u.receiver.measure(t, P[i])
                    if gnss_ok(a):
                        out[a]["pseudoranges"] = PseudorangesMsg(prs.sat_positions, prs.pseudoranges, prs.sigma)
            if rel.enabled and relative:
                # A full block per epoch, one row per fleet member, so who is in range never
                # shifts the draws.
                z = P - P[i] + u.rng["relpos"].standard_normal((len(self.ids), 3)) * rel.noise
                out[a]["relpos"] = [RelPosMsg(b, z[j], rel.noise)
                                    for j, b in enumerate(self.ids) if j != i and D[i, j] <= rel.max_range]
            if rng_cfg.all_pairs and relative:
                # Clipped at 0 as World does: the wire rejects a negative range. A full row is
                # drawn either way, so measuring each pair once shifts no draw.
                r = np.maximum(D[i] + u.rng["range"].standard_normal(len(self.ids)) * rng_cfg.noise, 0.0).tolist()
                out[a]["ranges"] = [RangeMsg(b, r[j], rng_cfg.noise)
                                    for j, b in enumerate(self.ids)
                                    if j != i and D[i, j] <= rng_cfg.max_range and (rng_cfg.both_ends or j > i)]
