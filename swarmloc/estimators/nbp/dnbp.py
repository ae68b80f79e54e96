"""dNBP: dynamic nonparametric belief propagation between agent processes (Wan et al. 2014).

Each agent's belief over its position is a Gaussian mixture of M weighted samples (a kernel
density estimate, swarmloc.estimators.nbp.mixtures). One time slice per tick:

1. **Prediction** (Wan Algorithm 3): the last slice's belief through the motion model, a
   particle-filter step with the agent's own odometry (the displacement it measured and its
   process noise, as the model's `predict` gives them).
2. **A normal agent** (a GNSS fix this tick) multiplies the prediction with its fix and
   broadcasts its belief (`nbp.belief`, it = 0). It never takes messages from fault agents,
   nor needs any: the normal agents are the anchors.
3. **A fault agent** (no fix) turns each belief it hears from an agent it ranged this tick
   into that agent's message to it, a ring of the measured radius around the sender's samples
   (Algorithm 1) whose kernel is `ring_scale` times the ring's thickness, and once it holds `thresholds[0]` (3) of them, from normal agents or from
   fault agents that have sent, it forms its belief, the product of its prediction and the
   messages (mixture importance sampling, Algorithm 2), and broadcasts it. Later messages
   refine and re-send it, up to `iterations` sends per slice. When it stays below the threshold
   for `quiet` seconds without a new message, its own threshold drops to 2, then to 1
   (swarmloc.estimators.nbp.schedule: the local image of the paper's "no fault node can reach it").
4. **The slice ends** with the next tick. A fault agent that never became ready forms its
   belief then from what it holds (relaxed to the end): its estimate of the slice, and the
   prior of the next, but too late to help others in this slice. **Carried relaxation**: it
   starts the next slice at the highest threshold the messages it held would have met (2 if
   it held 2), since its neighbourhood changes little from one slice to the next; an agent
   that became ready starts the next slice at the threshold it was ready at (3 after a slice
   with 3 messages).

When an iteration is over, in both clock modes: a slice's messages are those carrying its
tick k; a belief of an earlier slice is `stale` (counted, dropped), of a later one `early`.
Lockstep: a tick's message rounds run until the swarm is quiet, so every send the thresholds
allow happens within the tick, and the quiet timer (modelled time) fires at the next tick,
i.e. relaxation within a slice takes effect at its end (step 4), and carried relaxation is
what lets a sparse neighbourhood send in the next slices. Real time: the quiet timer runs on
the clock within the slice, so a relaxed agent still sends in it; a late belief of the
previous slice is stale.

The estimate is the belief's mean and covariance. Randomness: one generator per agent from
(seed, agent id), so a run is reproducible in process and over Zenoh alike.
"""

from __future__ import annotations

import time

import numpy as np

from swarmloc.estimators.nbp import mixtures as nbp
from swarmloc.estimators.nbp.schedule import RELAX_TAG, THRESHOLDS, Schedule
from swarmloc.filters import plausibility
from swarmloc.node import Estimate, Node, NodeSpec, Send, Timer, odometry_of
from swarmloc.wire.messages import NbpBelief, Sensors

NBP_STREAM = 0xD1BB  # keeps a node's draws apart from the scenario's other streams


def ring_thickness(sender: np.ndarray, z: float, sigma: float, M: int) -> float:
    """A ring message's own thickness (std, m): the range noise and the sender's kernel, plus
    the spacing of M samples around it. The ring's kernel is `ring_scale` times this
    (docs/dnbp.md, "The ring's kernel")."""
    d = sender.shape[0]
    spacing = 2.0 * np.pi * max(z, 0.0) / M
    return float(np.sqrt(sigma**2 + np.trace(sender) / d + spacing**2 / 4.0))


class DnbpNode(Node):
    algorithm = "dnbp"

    def __init__(self, aid: int, x0, P0, model="planar-speed-heading", *, M: int = 300, iterations: int = 3,
                 quiet: float = 0.1, thresholds=THRESHOLDS, ring_scale: float = 4.0, seed: int = 0,
                 rule: str = "silverman"):
        super().__init__(aid, x0, P0, model)
        self.M, self.iterations, self.quiet = int(M), int(iterations), float(quiet)
        self.ring_scale = float(ring_scale)
        self.thresholds, self.rule = tuple(int(t) for t in thresholds), rule
        self.rng = np.random.default_rng([int(seed), NBP_STREAM, self.id])
        self.p = self.model.position_dim
        self.belief = nbp.GaussianMixture.from_samples(self.rng.multivariate_normal(self.x, self.P, self.M), rule=rule)
        self.prior: nbp.GaussianMixture | None = None  # this slice's prediction
        self.normal = True
        self.ranges: dict[int, tuple[float, float]] = {}
        self.messages: dict[int, nbp.GaussianMixture] = {}
        self.schedule = Schedule(True, ())
        self.sends = 0
        self.final = True  # the slice's belief is formed (a normal agent's at once)
        self.slice_end = 0.0  # when the slice's time is up (its tick's time plus dt)
        # Threshold level a fault agent starts a slice at: the one its last slice would have
        # needed (see the module docstring, "carried relaxation").
        self.carry = 0
        self.stats = {"slices_normal": 0, "slices_fault": 0, "fault_sent": 0, "relaxed": 0, "formed_late": 0,
                      "step_s": 0.0, "updates": 0}

    @classmethod
    def spec(cls, scenario, aid, settings=None) -> NodeSpec:
        s = settings
        return super().spec(scenario, aid).with_(
            M=getattr(s, "M", 300), iterations=getattr(s, "iterations", 3), quiet=getattr(s, "quiet", 0.1),
            thresholds=list(getattr(s, "thresholds", THRESHOLDS)), ring_scale=getattr(s, "ring_scale", 4.0),
            seed=scenario.seed)

    # ------------------------------------------------------------------ tick

    def step(self, sensors: Sensors) -> list:
        t0 = time.perf_counter()
        if sensors.k <= self.k:
            return self.drop("stale", f"own frame of tick {sensors.k}")
        if not self.final:
            self._form(late=True)
        if sensors.odometry is None:
            return self.drop("invalid", "a frame without odometry")
        gap = self.missed_motion(sensors)
        dx, _, Q = self.model.predict(np.zeros(self.p), odometry_of(sensors))
        if gap is not None:
            Q = Q + gap
        self.prior = nbp.predict(self.belief, np.eye(self.p), Q, self.rng, self.M, self.rule, u=dx)
        self.belief = self.prior
        self.k = sensors.k
        self.slice_end = sensors.t + max(sensors.odometry.dt, 1e-6)
        self.ranges = {r.target: (r.range, r.std) for r in sensors.ranges if r.target != self.id}
        self.messages, self.sends = {}, 0
        self.normal = sensors.gnss is not None
        self.schedule = Schedule(self.normal, self.ranges, self.thresholds)
        for _ in range(self.carry if not self.normal else 0):
            self.schedule.relax()
        out: list = []
        if self.normal:
            self.stats["slices_normal"] += 1
            g = sensors.gnss
            fix = nbp.gnss_message(g.position[: self.p], np.eye(self.p) * g.std**2)
            self.belief = nbp.belief_update(self.prior, [fix], self.M, self.rng, self.rule)
            self.final = True
            out.append(self._send())
        else:
            self.stats["slices_fault"] += 1
            self.final = False
            out.append(Timer(self.quiet, RELAX_TAG))
        self._estimate()
        self.stats["step_s"] += time.perf_counter() - t0
        return out

    def receive(self, src: int, msg) -> list:
        if not isinstance(msg, NbpBelief):
            return self.drop("unexpected", type(msg).__name__)
        if msg.k < self.k:
            return self.drop("stale", f"belief of slice {msg.k} from {src}")
        if msg.k > self.k:
            return self.drop("early", f"belief of slice {msg.k} from {src}")
        if self.normal:
            return self.drop("ignored", f"a normal agent takes no beliefs ({src})")
        if src not in self.ranges:
            return self.drop("not-ranged", f"belief from {src}, not ranged this slice")
        n = msg.samples.shape[0]
        if msg.samples.ndim != 2 or msg.samples.shape[1] != self.p or msg.weights.shape != (n,) or n == 0 \
                or msg.bandwidth.shape != (self.p, self.p) or not (msg.weights >= 0).all() or msg.weights.sum() <= 0:
            return self.drop("invalid", f"belief from {src}")
        # A kernel must be a covariance: a hostile or corrupt one would make the ring's thickness NaN.
        if not (np.isfinite(msg.samples).all() and np.isfinite(msg.bandwidth).all()
                and np.allclose(msg.bandwidth, msg.bandwidth.T) and np.linalg.eigvalsh(msg.bandwidth).min() >= 0):
            return self.drop("invalid", f"belief from {src}: samples or kernel not a finite covariance")
        z, sigma = self.ranges[src]
        if (why := self._implausible(msg, z, sigma)) is not None:
            return self.drop(why, f"belief from {src}")
        t0 = time.perf_counter()
        new = self.schedule.hear(src, msg.normal)
        h = self.ring_scale * ring_thickness(msg.bandwidth, z, sigma, self.M) if self.ring_scale > 0 else None
        try:
            ring = nbp.range_message(msg.samples.astype(float), msg.weights.astype(float), z, sigma, self.rng, self.M,
                                     self.rule, bandwidth=h)
        except (ValueError, np.linalg.LinAlgError):
            return self.drop("invalid", f"belief from {src}")
        self.messages[src] = ring  # a refined belief replaces the sender's earlier one
        out: list = []
        if self.schedule.ready() and self.sends < self.iterations:
            self._form()
            out.append(self._send())
        elif new and not self.schedule.ready():
            out.append(Timer(self.quiet, RELAX_TAG))  # quiet counts from the last new message
        self.stats["step_s"] += time.perf_counter() - t0
        return out

    def on_timer(self, tag: str, t: float) -> list:
        if tag != RELAX_TAG or self.final or self.schedule.ready():
            return []
        if t >= self.slice_end - 1e-9:  # lockstep: the timer fires at the next tick, the slice is over
            self._form(late=True)
            return []
        if self.schedule.relax():
            self.stats["relaxed"] += 1
        if self.schedule.ready() and self.messages and self.sends < self.iterations:
            self._form()
            return [self._send()]
        return [Timer(self.quiet, RELAX_TAG)] if self.schedule.threshold > 1 else []

    # ------------------------------------------------------------------ helpers

    def _implausible(self, msg, z: float, sigma: float) -> str | None:
        """One member's lie (issue 26, finding 7): the range we measured to the sender against
        the distance between its belief's mean and our prediction's, linearised along the line
        between them, S = u^T (P_ours + P_its) u + sigma^2, within plausibility's bound. A
        belief that puts the sender where our range cannot reach is refused before it becomes a
        ring; one within the bound moves the ring's centre by at most step_bound(S, 1) metres."""
        w = msg.weights.astype(float)
        w = w / w.sum()
        X = msg.samples.astype(float)
        m_s = w @ X
        dm = X - m_s
        P_s = (w[:, None] * dm).T @ dm + msg.bandwidth
        m_p, P_p = self.prior.mean(), self.prior.cov()
        diff = m_s - m_p
        dist = float(np.linalg.norm(diff))
        u = diff / dist if dist > 1e-9 else np.eye(self.p)[0]
        S = float(u @ (P_p + P_s) @ u) + sigma**2
        return plausibility.innovation(np.array([z - dist]), np.array([[S]]))

    def _form(self, late: bool = False) -> None:
        """The belief: this slice's prediction times the messages held (mixture importance
        sampling, guided by the last belief so refinements concentrate samples). Formed late
        (never ready in the slice) with n messages held, the next slice starts at the highest
        threshold n meets; formed in time, at the level it was formed at."""
        if not self.normal:
            held = len(self.schedule.held)
            if late and held:
                self.carry = next(i for i, t in enumerate(self.thresholds) if t <= held or i == len(self.thresholds) - 1)
            elif not late:
                self.carry = self.thresholds.index(self.schedule.threshold)
        if self.messages:
            guide = self.belief if self.sends else None
            self.belief = nbp.belief_update(self.prior, list(self.messages.values()), self.M, self.rng, self.rule,
                                            guide=guide)
            self.stats["updates"] += 1
        self.final = True
        self.stats["formed_late"] += late
        self._estimate()

    def _send(self) -> Send:
        if not self.normal:
            self.sends += 1
            self.stats["fault_sent"] += 1
        b = self.belief
        return Send(NbpBelief(self.k, self.sends, self.normal, b.means.astype(np.float32), b.weights.astype(np.float32),
                              b.bandwidth.copy()), None)

    def _estimate(self) -> None:
        self.x = self.belief.mean()
        self.P = self.belief.cov()

    def estimate(self) -> Estimate:
        return Estimate(self.k, self.x.copy(), self.P.copy())

    def resume(self, k, x, P) -> None:
        super().resume(k, x, P)
        self.belief = nbp.GaussianMixture.from_samples(self.rng.multivariate_normal(self.x, self.P, self.M),
                                                       rule=self.rule)
        self.final = True


class LeastSquaresReference:
    """The baseline of Wan section 4, offline: an agent with a GNSS fix takes it; one without
    multilaterates from the agents with a fix that it ranged this tick (at least 3, their fixes
    taken as their positions); with fewer, or a degenerate geometry, it dead-reckons from its
    last estimate on its odometry."""

    algorithm = "ls"

    def __init__(self, scenario, ids):
        from swarmloc.models.motion import MOTION_MODELS

        self.ids = list(ids)
        self.model = MOTION_MODELS[scenario.agent(self.ids[0]).model]
        self.est = {a: scenario.prior(a) for a in self.ids}
        self.k = -1
        self.stats = {"fixes": 0, "multilaterated": 0, "dead_reckoned": 0}

    @classmethod
    def from_scenario(cls, scenario, ids, settings=None):
        return cls(scenario, ids)

    def step(self, frames: dict[int, Sensors]) -> None:
        p = self.model.position_dim
        self.k = next(iter(frames.values())).k
        fixes = {a: f.gnss for a, f in frames.items() if f.gnss is not None}
        for a in self.ids:
            f = frames[a]
            if a in fixes:
                self.est[a] = (fixes[a].position[:p].copy(), np.eye(p) * fixes[a].std**2)
                self.stats["fixes"] += 1
                continue
            anchors = [(fixes[r.target].position[:p], r.range, r.std) for r in f.ranges if r.target in fixes]
            solved = None
            if len(anchors) >= p + 1:
                solved = nbp.least_squares_position(np.array([x for x, _, _ in anchors]),
                                                    np.array([z for _, z, _ in anchors]),
                                                    float(np.mean([s for _, _, s in anchors])),
                                                    x0=self.est[a][0])
            if solved is not None:
                self.est[a] = solved
                self.stats["multilaterated"] += 1
            elif f.odometry is not None:
                x, P = self.est[a]
                x, F, Q = self.model.predict(x, odometry_of(f))
                self.est[a] = (x, F @ P @ F.T + Q)
                self.stats["dead_reckoned"] += 1

    def estimate(self, aid: int) -> Estimate:
        x, P = self.est[aid]
        return Estimate(self.k, np.array(x, float), np.array(P, float))
