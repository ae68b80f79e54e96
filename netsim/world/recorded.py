"""A recorded world: netsim plays an MR.CLAM recording instead of simulating truth.

`ReplayWorld` has the interface of `netsim.world.World`: each tick it hands every robot the
sensor frame its recording holds for that tick (swarmloc.datasets.mrclam.ticked: odometry as the mean
command over the tick, shifted by the robot's odometry lag; range-bearing observations of the
other replayed robots and of the landmarks taken during the tick, carried to its end), and
its Vicon poses are the truth the run is scored against and the positions that drive the
radio model, so link faults and a lossy channel apply to a replay as to a simulation. Where
Vicon has no pose (a gap, Robot1's early end on Dataset6) truth is NaN and the radio keeps the
robot at its last tracked position.

With a noise model (`world.noise`, swarmloc.datasets.calibrate.NoiseModel, which `swarmloc replay`
fits on a part of the recording it does not score) the world is the robots' calibrated sensor
driver: each robot's odometry is ticked with its own speed and turn-rate lags and corrected by
its command table, each range and bearing by its camera's bias model for landmarks or robots,
and every frame states that robot's fitted stds (a range's in proportion to it). Without one,
the readings go out as recorded with the scenario's noise (`sensors.odometry`,
`sensors.range_bearing`). Nothing here draws a random number: a replay is the same for every
seed, except for what the radio does.
"""

from __future__ import annotations

import numpy as np

from swarmloc.datasets import mrclam
from swarmloc.experiment.scenario import Scenario, recording
from swarmloc.wire.messages import OdometryMsg, RangeBearingMsg, Sensors

MAX_PER_FRAME = 64  # relative measurements one frame carries (docs/wire.md)


class ReplayWorld:
    def __init__(self, scenario: Scenario, seed: int | None = None):
        self.sc = scenario
        w = scenario.world
        self.rec = recording(w.path)
        self.dt = scenario.clock.dt
        self.ids = scenario.agent_ids
        self.start = self.rec.t0 + w.offset
        self.steps = scenario.clock.steps
        self.k = -1
        self.t = 0.0
        lags, self.noise = scenario.world.odometry_lag, w.noise
        if self.noise is not None:
            odo = {r: self.noise.robots[r].odometry for r in self.ids}
            self.lags = {r: odo[r].speed_lag for r in self.ids}
            turn_lags = {r: odo[r].turn_rate_lag for r in self.ids}
        else:
            self.lags = {r: (mrclam.estimate_odometry_lag(self.rec, r) if lags is None else float(lags)) for r in self.ids}
            turn_lags = self.lags
        self.ticks = {r: mrclam.ticked(self.rec, r, self.start, self.dt, self.steps, self.lags[r], turn_lags[r])
                      for r in self.ids}
        self.landmark_ids = {m.id for m in w.landmarks}
        self._readings = {r: self._calibrated(r, tk) for r, tk in self.ticks.items()}
        self.dropped = {"subject not replayed": 0, "over frame capacity": 0, "negative range": 0}
        self._rows = {r: self._by_tick(tk) for r, tk in self.ticks.items()}
        first = {a.id: np.array(a.start, float) for a in w.agents}
        self.pos = {r: first[r] for r in self.ids}
        self._positions_at(0)

    def _calibrated(self, r: int, tk: mrclam.Ticked):
        """Robot r's (v, w, speed std, turn-rate std, range, bearing, range std, bearing std),
        through its noise model if there is one; the stds None: the scenario's."""
        if self.noise is None:
            return tk.v, tk.w, None, None, tk.range, tk.bearing, None, None
        model = self.noise.robots[r]
        v, w = model.odometry.correct(tk.v, tk.w)
        v[0] = w[0] = 0.0  # tick 0 is the start: no motion
        rng, bearing = tk.range.copy(), tk.bearing.copy()
        rng_std, bearing_std = np.zeros(rng.shape), np.zeros(rng.shape)
        robot = np.isin(tk.subject, self.ids)
        rb = self.sc.sensors.range_bearing
        for sel, cam, other in ((robot, model.robots, model.landmarks), (~robot, model.landmarks, model.robots)):
            if not sel.any():
                continue
            if cam is None and other is not None:
                # Nothing of this kind in the calibration windows: the same camera's stds for the
                # other kind, without its bias (fitted on other targets). A zero std would be a drop.
                cam = other.model_copy(update={"range_bias": (0.0,) * 4, "bearing_bias": (0.0,) * 3})
            if cam is not None:
                rng[sel], bearing[sel], rng_std[sel], bearing_std[sel] = cam.correct(tk.range[sel], tk.bearing[sel])
            else:
                rng_std[sel], bearing_std[sel] = rb.range_noise, rb.bearing_noise
        return v, w, model.odometry.speed_std, model.odometry.turn_rate_std, rng, bearing, rng_std, bearing_std

    def _by_tick(self, tk: mrclam.Ticked) -> dict[int, np.ndarray]:
        """Row indices of each tick's measurements, in recorded order."""
        order = np.argsort(tk.tick, kind="stable")
        ticks, starts = np.unique(tk.tick[order], return_index=True)
        return dict(zip(ticks.tolist(), np.split(order, starts[1:])))

    def _positions_at(self, k: int) -> None:
        for r in self.ids:
            p = self.ticks[r].truth[k, :2]
            if np.isfinite(p).all():
                self.pos[r] = p.copy()

    def targets(self) -> dict[int, np.ndarray]:
        return {}

    def positions(self) -> dict[int, np.ndarray]:
        return {a: p.copy() for a, p in self.pos.items()}

    def states(self) -> dict[int, np.ndarray]:
        """Vicon poses at the current tick (NaN where Vicon has none)."""
        return {r: self.ticks[r].truth[max(self.k, 0)].copy() for r in self.ids}

    def step(self, gnss_ok=lambda a: True, link_ok=lambda a, b: True) -> dict[int, Sensors]:
        self.k += 1
        self.t = self.k * self.dt
        k = self.k
        self._positions_at(k)
        odo = self.sc.sensors.odometry
        rb_cfg = self.sc.sensors.range_bearing
        out = {}
        for r in self.ids:
            tk = self.ticks[r]
            v, w, sv, sw, rng, bearing, sr, sb = self._readings[r]
            odometry = OdometryMsg(self.dt if k else 0.0, float(v[k]), 0.0, odo.speed_noise if sv is None else sv, 0.0,
                                   float(w[k]), odo.turn_rate_noise if sw is None else sw)
            robots, marks = [], []
            for i in self._rows[r].get(k, ()):
                s = int(tk.subject[i])
                # The loader refuses non-finite numbers; the wire refuses a negative range (or a
                # zero std, which a corrected range of zero would state).
                if rng[i] < 0 or (sr is not None and not sr[i] > 0):
                    self.dropped["negative range"] += 1
                    continue
                msg = RangeBearingMsg(s, float(rng[i]), float(bearing[i]),
                                      rb_cfg.range_noise if sr is None else float(sr[i]),
                                      rb_cfg.bearing_noise if sb is None else float(sb[i]))
                if s in self.pos and s != r:
                    if rb_cfg.robots:
                        robots.append(msg)
                elif s in self.landmark_ids:
                    if rb_cfg.landmarks:
                        marks.append(msg)
                else:
                    self.dropped["subject not replayed"] += 1
            for lst in (robots, marks):
                if len(lst) > MAX_PER_FRAME:
                    self.dropped["over frame capacity"] += len(lst) - MAX_PER_FRAME
                    del lst[MAX_PER_FRAME:]
            out[r] = Sensors(k, self.t, odometry, [], rb=robots, landmarks=marks)
        return out


class McapWorld:
    """A world played from a run's run.mcap (`swarmloc rerun`): each tick hands every agent the
    sensor frame netsim recorded for it (published, or withheld while its process was down),
    decoded from the recorded bytes, so a node receives bit for bit what it received in the run;
    truth and targets are the recorded ones, and the recorded positions drive the radio. The
    world is open loop: a vehicle's actuator commands no longer move it (they are refused as
    `not-a-vehicle`), so a closed-loop run reruns exactly only with the estimator that flew it.

    A tick without a recorded frame for an agent (an agent's own recording with gaps) yields
    None for it: netsim publishes nothing to it that tick, as the platform stepped on nothing."""

    def __init__(self, scenario: Scenario, seed: int | None = None):
        from swarmloc.experiment.recording import load_world
        from swarmloc.models.motion import MOTION_MODELS

        self.sc = scenario
        self.rec, _ = load_world(scenario.world.path)
        self.dt = scenario.clock.dt
        self.ids = scenario.agent_ids
        self.k = -1
        self.t = 0.0
        if not self.rec.ticks:
            raise ValueError(f"{scenario.world.path}: the recording holds no tick")
        self.steps = self.rec.ticks[-1]
        self.dims = {a.id: MOTION_MODELS[a.model] for a in scenario.world.agents}
        self.pos = {a.id: np.array(a.start, float) for a in scenario.world.agents}
        self._positions_at(0)

    def _positions_at(self, k: int) -> None:
        for a, x in self.rec.truth.get(k, {}).items():
            m = self.dims.get(a)
            if m is not None and m.state_dim and len(x) == m.state_dim and np.isfinite(x[:m.position_dim]).all():
                self.pos[a] = np.array(x[:m.position_dim], float)

    def targets(self) -> dict[int, np.ndarray]:
        return {o: p.copy() for o, p in self.rec.targets.get(max(self.k, 0), {}).items()}

    def positions(self) -> dict[int, np.ndarray]:
        return {a: p.copy() for a, p in self.pos.items()}

    def states(self) -> dict[int, np.ndarray]:
        truth = self.rec.truth.get(max(self.k, 0), {})
        return {a: np.array(truth[a], float) if a in truth else np.full(self.dims[a].state_dim, np.nan)
                for a in self.ids}

    def step(self, gnss_ok=lambda a: True, link_ok=lambda a, b: True) -> dict[int, Sensors | None]:
        self.k += 1
        self.t = self.rec.t.get(self.k, self.k * self.dt)
        self._positions_at(self.k)
        frames = self.rec.sensors.get(self.k, {})
        return {a: frames.get(a) for a in self.ids}
