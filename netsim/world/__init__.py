"""World truth and sensors: how the platforms really move and what their sensors report.

Every random draw comes from the scenario seed through independent streams (motion, odometry,
ranging, radio), so changing the radio model never changes the trajectories or the noise.
Tick 0 is the start: platforms at their known start points, an empty sensor frame; ticks
1..steps each cover one dt of motion.
"""

from __future__ import annotations

import math

import numpy as np

from swarmloc.experiment.scenario import CircleMotion, Scenario
from swarmloc.models.motion import VEHICLES
from swarmloc.wire.messages import GnssMsg, OdometryMsg, RangeBearingMsg, RangeMsg, Sensors, TargetRangeMsg

PLANAR_MODELS = ("planar-speed-heading", "planar-pose")


def streams(seed: int) -> dict[str, np.random.Generator]:
    names = ("motion", "odometry", "range", "radio", "loss", "gnss", "target", "gnss_state", "bearing")
    children = np.random.SeedSequence(seed).spawn(len(names))
    return {n: np.random.default_rng(c) for n, c in zip(names, children)}


class World:
    """Planar robots are simulated here; UAS by netsim.world.uas.UasFleet; ground stations
    stand still. One sensor frame per agent and tick whatever its kind."""

    def __init__(self, scenario: Scenario, seed: int | None = None):
        self.sc = scenario
        seed = scenario.seed if seed is None else seed
        self.seed = seed
        self.rng = streams(seed)
        self.dt = scenario.clock.dt
        self.ids = scenario.agent_ids
        self.k = -1
        self.t = 0.0
        self.planar = [a for a in scenario.world.agents if a.model in PLANAR_MODELS]
        self.planar_ids = sorted(a.id for a in self.planar)
        uas = sorted(a.id for a in scenario.world.agents if a.model == "uas-ins")
        self.fleet = None
        if uas:
            from netsim.world.uas import UasFleet

            self.fleet = UasFleet(scenario, uas, seed)
        vehicles = sorted(a.id for a in scenario.world.agents if a.model in VEHICLES)
        self.vehicles = None
        if vehicles:
            from netsim.world.vehicles import VehicleFleet

            self.vehicles = VehicleFleet(scenario, vehicles, seed)
        self.pos = {a.id: np.array(a.start, float) for a in scenario.world.agents}
        if self.fleet is not None:
            self.pos.update(self.fleet.positions())
        if self.vehicles is not None:
            self.pos.update(self.vehicles.positions())
        self.heading = {a.id: float(a.heading) for a in self.planar}
        self.turn = {a.id: self._initial_turn(a.motion) for a in self.planar}
        # The odometry's own heading: the integral of the measured turn rate from the known start.
        self.heading_est = dict(self.heading)
        self.heading_var = {a: 0.0 for a in self.planar_ids}
        self.target_ids = sorted(t.id for t in scenario.world.targets)
        self.target_pos = {t.id: np.array(t.position, float) for t in scenario.world.targets}
        self.target_vel = {t.id: np.array(t.velocity, float) for t in scenario.world.targets}
        self._steps: int | None = None
        # GNSS state of each planar receiver, a two-state Markov chain when it switches.
        g = scenario.sensors.gnss
        self.receivers = [a for a in self.planar_ids if g.agents is None or a in g.agents] if g.enabled else []
        self.switching = g.to_fault + g.to_normal > 0
        stationary = g.to_normal / (g.to_fault + g.to_normal) if self.switching else 1.0
        draws = self.rng["gnss_state"].random(len(self.receivers)) if self.switching else np.zeros(len(self.receivers))
        self.gnss_normal = {a: bool(u < stationary) for a, u in zip(self.receivers, draws)}
        if not self.switching and g.normal_share is not None:
            keep = set(self.rng["gnss_state"].permutation(self.receivers)[:round(g.normal_share * len(self.receivers))])
            self.gnss_normal = {a: a in keep for a in self.receivers}

    @staticmethod
    def _initial_turn(motion) -> float:
        return motion.turn_rate if isinstance(motion, CircleMotion) else 0.0

    @property
    def steps(self) -> int:
        """The last tick: clock.duration / dt, or earlier, the first tick at which an agent is
        within world.stop_distance of a target. Truth does not depend on the estimates, so a
        dry run of the same world (same seed) finds it before the run starts."""
        if self._steps is None:
            self._steps = self.sc.clock.steps
            stop = self.sc.world.stop_distance
            if stop is not None:
                dry = World(self.sc, self.seed)
                dry.step()  # tick 0, the start
                for k in range(1, self.sc.clock.steps + 1):
                    dry.step()
                    if dry.nearest_target() <= stop:
                        self._steps = k
                        break
        return self._steps

    def nearest_target(self) -> float:
        """Distance (m) from the closest agent to the closest target; inf without targets."""
        if not self.target_ids:
            return math.inf
        at = np.array([self.pos[a] for a in self.planar_ids]).reshape(-1, 2)
        to = np.array([self.target_pos[o] for o in self.target_ids])
        return float(np.linalg.norm(at[:, None] - to[None], axis=-1).min(initial=math.inf))

    def targets(self) -> dict[int, np.ndarray]:
        """Each target's true position now."""
        return {o: p.copy() for o, p in self.target_pos.items()}

    def positions(self) -> dict[int, np.ndarray]:
        return {a: p.copy() for a, p in self.pos.items()}

    def states(self) -> dict[int, np.ndarray]:
        """Each agent's true state in its model's layout (a ground station's is empty)."""
        out = {a: np.zeros(0) for a in self.ids}
        out.update({a.id: self.pos[a.id].copy() if a.model == "planar-speed-heading"
                    else np.r_[self.pos[a.id], self.heading[a.id]] for a in self.planar})
        if self.fleet is not None:
            out.update(self.fleet.states())
        if self.vehicles is not None:
            out.update(self.vehicles.states())
        return out

    def step(self, gnss_ok=lambda a: True, link_ok=lambda a, b: True) -> dict[int, Sensors]:
        """Advance to the next tick; return every agent's sensor frame for it.

        gnss_ok(a) False means agent a's GNSS is out (a fault): its frame carries no fix.
        link_ok(a, b) False: the radio link a -> b is blocked by a fault, and so is the
        cooperative sensing of a vehicle's relative position."""
        self.k += 1
        self.t = self.k * self.dt
        out = {a: Sensors(self.k, self.t, None, []) for a in self.ids}
        if self.fleet is not None:
            for a, fields in self.fleet.step(self.k, gnss_ok).items():
                out[a] = Sensors(self.k, self.t, None, **fields)
            self.pos.update(self.fleet.positions())
        if self.vehicles is not None:
            for a, fields in self.vehicles.step(self.k, gnss_ok, link_ok).items():
                out[a] = Sensors(self.k, self.t, **fields)
            self.pos.update(self.vehicles.positions())
        if self.planar:
            out.update(self._step_planar(gnss_ok))
        return out

    def _step_planar(self, gnss_ok) -> dict[int, Sensors]:
        if self.k == 0:
            return {a: Sensors(0, 0.0, OdometryMsg(0.0, 0.0, self.heading_est[a], 0.0, 0.0), []) for a in self.planar_ids}
        odo_cfg = self.sc.sensors.odometry
        odometry = {}
        for spec in self.planar:
            a, m = spec.id, spec.motion
            speed = m.speed
            # Odometry over this step uses the heading the platform believes it had at its start.
            v_meas = speed + self.rng["odometry"].normal(0.0, odo_cfg.speed_noise)
            heading_est, heading_std = self.heading_est[a], math.sqrt(self.heading_var[a])
            h = self.heading[a]
            self.pos[a] = self.pos[a] + self.dt * speed * np.array([math.cos(h), math.sin(h)])
            w_meas = self.turn[a] + self.rng["odometry"].normal(0.0, odo_cfg.turn_rate_noise)
            odometry[a] = OdometryMsg(self.dt, float(v_meas), heading_est, odo_cfg.speed_noise, heading_std,
                                      float(w_meas), odo_cfg.turn_rate_noise)
            self.heading[a] = h + self.dt * self.turn[a]
            self.heading_est[a] += self.dt * w_meas
            self.heading_var[a] += (self.dt * odo_cfg.turn_rate_noise) ** 2
            if not isinstance(m, CircleMotion):
                decay = math.exp(-self.dt / m.turn_rate_tau)
                self.turn[a] = decay * self.turn[a] + m.turn_rate_std * math.sqrt(1 - decay**2) * self.rng["motion"].normal()
        ranges = self._ranges()
        gnss = self._gnss(gnss_ok)
        seen = self._target_ranges()
        rb, marks = self._range_bearing()
        return {a: Sensors(self.k, self.t, odometry[a], ranges.get(a, []), gnss.get(a), targets=seen.get(a, []),
                           rb=rb.get(a, []), landmarks=marks.get(a, []))
                for a in self.planar_ids}

    def _range_bearing(self) -> tuple[dict[int, list[RangeBearingMsg]], dict[int, list[RangeBearingMsg]]]:
        """Every planar-pose agent's range and body-frame bearing to every other agent, then to
        every landmark, within max_range. Noise is drawn for every pair in range or not (agents
        first, then landmarks, in id order), so what is delivered never shifts another draw."""
        cfg = self.sc.sensors.range_bearing
        if not cfg.enabled:
            return {}, {}
        ids = [a for a in self.planar_ids if self.sc.agent(a).model == "planar-pose"]
        marks = sorted(self.sc.world.landmarks, key=lambda m: m.id)
        at = np.array([self.pos[a] for a in ids]).reshape(len(ids), 2)
        heading = np.array([self.heading[a] for a in ids])
        rng = self.rng["bearing"]
        out: list[dict[int, list[RangeBearingMsg]]] = []
        for targets, ok in ((at, cfg.robots), (np.array([m.position for m in marks]).reshape(-1, 2), cfg.landmarks)):
            d = targets[None, :, :] - at[:, None, :]
            r = np.linalg.norm(d, axis=-1)
            b = np.arctan2(d[..., 1], d[..., 0]) - heading[:, None]
            noise = rng.standard_normal((2,) + r.shape)
            r_meas = np.maximum(r + cfg.range_noise * noise[0], 0.0)
            b_meas = (b + cfg.bearing_noise * noise[1] + np.pi) % (2 * np.pi) - np.pi
            names = ids if targets is at else [m.id for m in marks]
            seen: dict[int, list[RangeBearingMsg]] = {}
            for i, a in enumerate(ids):
                for j, o in enumerate(names):
                    if ok and r[i, j] <= cfg.max_range and not (targets is at and i == j):
                        seen.setdefault(a, []).append(RangeBearingMsg(o, float(r_meas[i, j]), float(b_meas[i, j]),
                                                                      cfg.range_noise, cfg.bearing_noise))
            out.append({a: v[:64] for a, v in seen.items()})  # what a frame carries (docs/wire.md)
        return out[0], out[1]

    def _target_ranges(self) -> dict[int, list[TargetRangeMsg]]:
        """Targets move first (constant velocity); then each agent within the detection range
        of a target ranges it with the detection probability. Draws are made for every pair,
        seen or not, so moving a target never shifts another pair's noise."""
        if not self.target_ids:
            return {}
        cfg = self.sc.sensors.target_range
        for o in self.target_ids:
            self.target_pos[o] = self.target_pos[o] + self.dt * self.target_vel[o]
        rng = self.rng["target"]
        out: dict[int, list[TargetRangeMsg]] = {}
        for a in self.planar_ids:
            for o in self.target_ids:
                detect, noise = rng.random(), rng.normal(0.0, cfg.noise)
                dist = float(np.linalg.norm(self.pos[a] - self.target_pos[o]))
                if dist <= cfg.max_range and detect < cfg.probability:
                    out.setdefault(a, []).append(TargetRangeMsg(o, max(dist + noise, 0.0), cfg.noise))
        return out

    def _gnss(self, gnss_ok) -> dict[int, GnssMsg]:
        cfg = self.sc.sensors.gnss
        if not cfg.enabled:
            return {}
        noise = {a: self.rng["gnss"].normal(0.0, cfg.noise, size=2) for a in self.planar_ids}  # drawn even in outage
        if self.switching and self.k > 1:  # the chain moves between ticks; tick 1 keeps the initial states
            u = self.rng["gnss_state"].random(len(self.receivers))
            for a, x in zip(self.receivers, u):
                self.gnss_normal[a] = x >= cfg.to_fault if self.gnss_normal[a] else x < cfg.to_normal
        return {a: GnssMsg(self.pos[a] + noise[a], cfg.noise) for a in self.receivers
                if self.gnss_normal[a] and gnss_ok(a)}

    def _ranges(self) -> dict[int, list[RangeMsg]]:
        """Up to max_per_step measurements among distinct ordered pairs within sensing range,
        or (all_pairs) one for every ordered pair within it, in (measurer, measured) order."""
        cfg = self.sc.sensors.range
        rng = self.rng["range"]
        if cfg.all_pairs:
            ids = self.planar_ids
            at = np.array([self.pos[a] for a in ids]).reshape(len(ids), -1)
            dist = np.linalg.norm(at[:, None, :] - at[None, :, :], axis=-1)
            noise = rng.normal(0.0, cfg.noise, size=dist.shape)  # drawn for every pair, in range or not
            out: dict[int, list[RangeMsg]] = {}
            for i, m in enumerate(ids):
                seen = [RangeMsg(n, max(float(dist[i, j] + noise[i, j]), 0.0), cfg.noise)
                        for j, n in enumerate(ids) if j != i and dist[i, j] <= cfg.max_range]
                if seen:
                    out[m] = seen[:64]  # what a frame carries (docs/wire.md)
            return out
        ids = self.planar_ids
        # Every ordered pair at once (row-major: the order of the nested loop the picks index);
        # a norm per pair was most of netsim's tick() at 64 agents.
        at = np.array([self.pos[a] for a in ids]).reshape(len(ids), -1)
        near = np.linalg.norm(at[:, None, :] - at[None, :, :], axis=-1) <= cfg.max_range
        np.fill_diagonal(near, False)
        pairs = [(ids[i], ids[j]) for i, j in zip(*(x.tolist() for x in np.nonzero(near)))]
        out: dict[int, list[RangeMsg]] = {}
        for _ in range(cfg.max_per_step):
            happens = rng.random() < cfg.probability
            pick = rng.integers(len(pairs)) if pairs else 0
            noise = rng.normal(0.0, cfg.noise)
            if not (happens and pairs):
                continue
            m, n = pairs.pop(pick)
            dist = float(np.linalg.norm(self.pos[m] - self.pos[n]))
            out.setdefault(m, []).append(RangeMsg(n, max(dist + noise, 0.0), cfg.noise))
        return out
