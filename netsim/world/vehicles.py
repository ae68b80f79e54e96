"""The vehicles of netsim's world: quadrotors and ground robots in closed loop (Oliveros &
Ashrafiuon 2023).

`VehicleFleet` integrates each vehicle's dynamics (swarmloc/models/vehicles.py) as the world truth under
the actuator command in force, perturbed by actuator noise, and produces per tick what its
sensors report: the IMU's orientation, relative positions in its body frame (along the
scenario's measurement graph, within the proximity of the pair's types, while the pair's radio
link is up: the sensing is cooperative, so a `cut` removes the edge), and GPS fixes on the
schedule. Each frame also carries the command that was in force over the tick, so an estimator
propagates with what the vehicle really did, including when a command was lost.

Who computes the command (`world.control`): `netsim`, the vehicle's autopilot fed the true state
(the paper's validation runs, a motion-capture system in the loop); or `agents`, each agent from
its own estimate over the wire (`command`, docs/wire.md). A command applies from the next tick;
one that does not come leaves the last one in force.

Randomness: a stream per purpose and per vehicle, derived from the world seed, drawn whether or
not its measurement is delivered, so the graph, the proximity and the faults never shift another
draw, and the commands change only the truth, never the noise.
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from swarmloc.models.vehicles import MODELS, CircleReference, actuator_std, controller_for, relpos
from swarmloc.wire.messages import GnssMsg, RelPosMsg, VehicleMsg

VEHICLE_STREAM = 0x0B1C
"""First spawn-key word of every fleet stream: apart from World's and the UAS fleet's."""
PURPOSES = ("actuator", "attitude", "relpos", "gps")


def stream(seed: int, purpose: str, aid: int) -> np.random.Generator:
    ss = np.random.SeedSequence(seed, spawn_key=(VEHICLE_STREAM, PURPOSES.index(purpose), aid))
    return np.random.default_rng(ss)


def reference_of(spec) -> CircleReference:
    """The circle an agent's `track` motion names (swarmloc.experiment.scenario.TrackMotion)."""
    return CircleReference(**spec.reference_params())


class VehicleFleet:
    def __init__(self, scenario, ids: list[int], seed: int):
        self.sc = scenario
        self.cfg = scenario.sensors.vehicle
        self.ids = sorted(ids)
        self.dt = scenario.clock.dt
        specs = {a: scenario.agent(a) for a in self.ids}
        self.model = {a: MODELS[specs[a].model] for a in self.ids}
        self.reference = {a: reference_of(specs[a]) for a in self.ids}
        self.x = {a: self.model[a].initial_state(np.array(specs[a].start, float), specs[a].heading) for a in self.ids}
        self.autopilot = ({a: controller_for(self.model[a], self.reference[a]) for a in self.ids}
                          if scenario.world.control == "netsim" else {})
        self.u = {a: self.model[a].hover_input(self.x[a]) for a in self.ids}  # the command in force
        self.rng = {(p, a): stream(seed, p, a) for p in PURPOSES for a in self.ids}
        self.noise = {a: actuator_std(self.model[a], self.cfg.force_noise, self.cfg.moment_noise) for a in self.ids}
        graph = self.cfg.graph if self.cfg.graph is not None else [(b, t) for b in self.ids for t in self.ids if b != t]
        self.graph = sorted((int(b), int(t)) for b, t in graph)
        self.commands: Counter[str] = Counter()  # commands received: applied, or refused by reason
        # Closed loop: ticks each vehicle flew on an older command, none having come (or been
        # let through) since the previous tick.
        self.held = {a: 0 for a in self.ids}
        self._fresh: set[int] = set()

    def command(self, aid: int, u) -> str | None:
        """A command for vehicle aid, in force from the next tick; the reason it is refused, or None."""
        if aid not in self.model:
            self.commands["not-a-vehicle"] += 1
            return "not-a-vehicle"
        u = np.asarray(u, float)
        if u.shape != (self.model[aid].input_dim,) or not np.isfinite(u).all():
            self.commands["malformed"] += 1
            return "malformed"
        self.u[aid] = u.copy()
        self.commands["applied"] += 1
        self._fresh.add(aid)
        return None

    def positions(self) -> dict[int, np.ndarray]:
        return {a: self.model[a].position(x).copy() for a, x in self.x.items()}

    def states(self) -> dict[int, np.ndarray]:
        return {a: x.copy() for a, x in self.x.items()}

    def step(self, k: int, gnss_ok, link_ok) -> dict[int, dict]:
        """Advance to tick k (k >= 1 covers one dt under the commands in force); the Sensors
        fields of every vehicle's frame."""
        t = k * self.dt
        dt = 0.0 if k == 0 else self.dt
        if k > 0:
            if not self.autopilot:
                for a in self.ids:
                    self.held[a] += a not in self._fresh
                self._fresh.clear()
            for a in self.ids:
                if a in self.autopilot:
                    self.u[a] = self.autopilot[a].command(self.x[a], t - self.dt, self.dt)
                noise = self.noise[a] * self.rng["actuator", a].standard_normal(self.model[a].input_dim)
                self.x[a] = self.model[a].step(self.x[a], self.u[a] + noise, self.dt)
        seen = self._relpos(link_ok)
        out = {}
        gps_on = self.cfg.gps_schedule.active(t)
        for a in self.ids:
            m = self.model[a]
            att = m.orientation(self.x[a]) + self.cfg.attitude_noise * self.rng["attitude", a].standard_normal(
                m.orientation_dim)
            fix_noise = self.cfg.gps_noise * self.rng["gps", a].standard_normal(3)
            gnss = None
            if a in self.cfg.gps and gps_on and gnss_ok(a):
                gnss = GnssMsg(m.position(self.x[a]) + fix_noise, self.cfg.gps_noise)
            out[a] = {"odometry": None, "ranges": [], "gnss": gnss,
                      "vehicle": VehicleMsg(dt, self.u[a].copy(), att, self.cfg.attitude_noise, seen.get(a, []))}
        return out

    def _relpos(self, link_ok) -> dict[int, list[RelPosMsg]]:
        out: dict[int, list[RelPosMsg]] = {}
        for b, t in self.graph:
            noise = self.cfg.relpos_noise * self.rng["relpos", b].standard_normal(3)
            mb, mt = self.model[b], self.model[t]
            dist = float(np.linalg.norm(mt.position(self.x[t]) - mb.position(self.x[b])))
            if dist <= self.cfg.range_of(mb.name, mt.name) and link_ok(b, t):
                z = relpos(mb, self.x[b], mt, self.x[t]) + noise
                out.setdefault(b, []).append(RelPosMsg(t, z, self.cfg.relpos_noise))
        return {b: v[:64] for b, v in out.items()}

