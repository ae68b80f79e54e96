"""A recorded world: netsim plays an MR.CLAM recording instead of simulating truth.

`ReplayWorld` has the interface of `netsim.world.World`: each tick it hands every robot the
sensor frame its recording holds for that tick (swarmloc.mrclam.ticked: odometry as the mean
command over the tick, shifted by the robot's odometry lag; range-bearing observations of the
other replayed robots and of the landmarks taken during the tick, carried to its end), and
its Vicon poses are the truth the run is scored against and the positions that drive the
radio model, so link faults and a lossy channel apply to a replay as to a simulation. Where
Vicon has no pose (a gap, Robot1's early end on Dataset6) truth is NaN and the radio keeps the
robot at its last tracked position.

The noise a frame states is the scenario's (`sensors.odometry`, `sensors.range_bearing`), which
`swarmloc replay` fits to the recording (swarmloc.mrclam.fit_noise); the recording's own noise
is whatever it is. Nothing here draws a random number: a replay is the same for every seed,
except for what the radio does.
"""

from __future__ import annotations

import numpy as np

from swarmloc import mrclam
from swarmloc.messages import OdometryMsg, RangeBearingMsg, Sensors
from swarmloc.scenario import Scenario, recording

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
        lags = scenario.world.odometry_lag
        self.lags = {r: (mrclam.estimate_odometry_lag(self.rec, r) if lags is None else float(lags)) for r in self.ids}
        self.ticks = {r: mrclam.ticked(self.rec, r, self.start, self.dt, self.steps, self.lags[r]) for r in self.ids}
        self.landmark_ids = {m.id for m in w.landmarks}
        self.dropped = {"subject not replayed": 0, "over frame capacity": 0, "negative range": 0}
        self._rows = {r: self._by_tick(tk) for r, tk in self.ticks.items()}
        first = {a.id: np.array(a.start, float) for a in w.agents}
        self.pos = {r: first[r] for r in self.ids}
        self._positions_at(0)

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
            odometry = OdometryMsg(self.dt if k else 0.0, float(tk.v[k]), 0.0, odo.speed_noise, 0.0, float(tk.w[k]),
                                   odo.turn_rate_noise)
            robots, marks = [], []
            for i in self._rows[r].get(k, ()):
                s = int(tk.subject[i])
                if tk.range[i] < 0:  # the loader refuses non-finite numbers; the wire refuses this
                    self.dropped["negative range"] += 1
                    continue
                msg = RangeBearingMsg(s, float(tk.range[i]), float(tk.bearing[i]), rb_cfg.range_noise,
                                      rb_cfg.bearing_noise)
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
