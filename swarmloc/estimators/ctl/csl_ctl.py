"""CSL-CTL and IL-CTL: localizing a target together with the swarm (Wang et al. 2022).

CSL-CTL ("csl-ctl"): a Kalman cooperative self-localization (KF-CSL, here the centralized UKF
of `ukf_ccl` over the agents' positions, with the targets joining the joint state as static
blocks) whose estimate, every tick in which agents range a target, is re-estimated together
with the targets by majorization, with the covariance from the unscented transform
(`swarmloc.estimators.ctl.majorization`, docs/csl-ctl.md). The re-estimate replaces the KF-CSL state, so the next
tick's KF-CSL starts from it: the paper's "parallel integration".

Distributed by replication: every agent broadcasts its sensor frame of tick k (`csl.share`:
odometry, ranges to agents, ranges to targets) and runs the whole joint problem on the shares
it holds, its own included. With every share delivered, every agent's replica is the same
arithmetic on the same numbers as the offline reference (`JointCslCtl` on every frame), so they agree bit
for bit. A share that does not come is a gap in that replica only: the sender's position is
carried over with the covariance of the farthest it could have gone, its measurements are not
used; replicas then differ, and each stays a consistent estimate of what it was told.

IL-CTL ("il-ctl"), the baseline: every agent dead-reckons alone (IL), broadcasts its estimate
and its target ranges (`ctl.fix`), and localizes each target by least squares from the
positions it was sent, taken as exact: the serial mode the paper improves on.

A tick is run when the shares of every agent it expects have come, when the `wait` timer set
at its own frame fires, or when its next frame arrives (in lockstep, the start of the next
tick). Expected: every agent during the first `forget_after` ticks, then those heard from in
the last `forget_after` ticks. Shares of a tick already run are `late`: counted, dropped.
"""

from __future__ import annotations

import numpy as np

from swarmloc.estimators.ctl import majorization as ctl
from swarmloc.estimators.il import IndependentNode
from swarmloc.estimators.ukf.ccl import CentralizedUKF
from swarmloc.filters import fusion, kalman, plausibility
from swarmloc.node import Estimate, Node, NodeSpec, Send, Timer, odometry_of
from swarmloc.wire.messages import CslShare, CtlFix, Sensors

RUN = "ctl.run"
MAX_AHEAD = 4  # ticks of early shares kept (real time: a peer may run ahead); beyond: dropped


class FirstFix:
    """A new target's first position, from ranges to anchors taken as exact, decided over ticks.

    Agents that drive at a target side by side lie nearly on a line across the line of sight,
    and the ranges of one tick fit the target and its mirror image across that line almost
    alike, the more so when the anchors' positions have drifted. So both images are kept: the
    trilateration of the first tick and its mirror across the anchors' principal axis, each
    refined by least squares and then carried tick by tick with its covariance (its earlier
    estimate as the prior). Each image scores the tick's ranges at its position before the tick
    (squared normalised residuals); once one image's total is lower by `margin`, or the two have
    met, it is the fix. A lone image (the other failed to converge) wins at once."""

    def __init__(self, margin: float = 25.0):
        self.margin = margin
        self.images: dict[int, list[list]] = {}  # target -> [[x, cov, score], ...]

    def update(self, o: int, anchors: np.ndarray, z: np.ndarray, sigma: np.ndarray):
        """(x, cov) once decided, else None; ValueError if the anchors cannot start a fix."""
        images = self.images.get(o)
        if images is None:
            start = trilaterate(anchors, z)
            centre = anchors.mean(axis=0)
            axis = np.linalg.svd(anchors - centre)[2][0]
            d = start - centre
            images = []
            for x0 in (start, centre + 2 * (d @ axis) * axis - d):
                try:
                    x, P = ctl.ls_target(anchors, z, sigma, x0)
                except ValueError:
                    continue
                r = (np.linalg.norm(x - anchors, axis=1) - z) / sigma
                images.append([x, P, float(r @ r)])
            if not images:
                raise ValueError("first fix: no least-squares solution")
        else:
            for im in images:
                r = (np.linalg.norm(im[0] - anchors, axis=1) - z) / sigma
                im[2] += float(r @ r)
                im[0], im[1] = ctl.ls_target(anchors, z, sigma, im[0], (im[0], im[1]))
        images.sort(key=lambda im: im[2])
        if len(images) == 1 or images[1][2] - images[0][2] >= self.margin or \
                np.linalg.norm(images[1][0] - images[0][0]) < 3.0 * float(sigma.max()):
            self.images.pop(o, None)
            return images[0][0], images[0][1]
        self.images[o] = images
        return None


def trilaterate(anchors: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Closed-form start for a target from >= 3 ranges: the linear least squares of the range
    equations minus their mean (exact for exact ranges); ValueError for collinear anchors."""
    a = np.asarray(anchors, float)
    if len(a) < 3 or np.linalg.matrix_rank(a - a.mean(axis=0)) < 2:
        raise ValueError("trilaterate: needs 3 anchors not on one line")
    # |x - a_i|^2 = z_i^2  ->  2 (a_i - abar) . x = |a_i|^2 - mean|a|^2 - (z_i^2 - mean z^2)
    sq, zz = (a**2).sum(axis=1), np.asarray(z, float) ** 2
    A = 2.0 * (a - a.mean(axis=0))
    b = (sq - sq.mean()) - (zz - zz.mean())
    return np.linalg.lstsq(A, b, rcond=None)[0]


class JointCslCtl(CentralizedUKF):
    """KF-CSL plus CTL over every agent and every target localized so far: one replica.

    Targets take position blocks after the agents, keyed ("target", id), in the order they were
    first localized. The CTL step re-estimates positions; whatever else an agent's state holds
    (planar-pose: its heading) follows through its correlation with the positions. A target joins when `min_ranges` agents range it in one tick (fewer cannot fix
    a point in the plane); until then its ranges are counted (`unused_target_ranges`)."""

    algorithm = "csl-ctl"

    def __init__(self, x0: dict[int, np.ndarray], P0: np.ndarray, model="planar-speed-heading",
                 spread: float | None = None, *, tol: float = 1e-9, max_iter: int = 100, ut_noise: bool = True,
                 target_process_noise: float = 0.0, min_ranges: int = 3):
        super().__init__(x0, P0, model, spread)
        self.agents = list(self.ids)
        self.targets: list[int] = []
        self.tol, self.max_iter, self.ut_noise = tol, max_iter, ut_noise
        self.q_target, self.min_ranges = target_process_noise, min_ranges
        self.p = self.model.position_dim
        self.last_odometry: dict[int, tuple] = {}  # a -> (dt, |speed|, speed std, |turn rate|, its std)
        self.stats = {"ctl_ticks": 0, "majorizations": 0, "unconverged": 0, "unused_target_ranges": 0,
                      "ctl_failed": 0, "missing_frames": 0, "undecided_first_fix": 0}
        self.first_fix = FirstFix()

    @classmethod
    def from_scenario(cls, scenario, ids, settings=None):
        return cls({a: scenario.prior(a)[0] for a in ids}, scenario.prior(ids[0])[1], scenario.agent(ids[0]).model,
                   scenario.estimation.spread, **_ctl_kwargs(settings))

    def step(self, frames: dict[int, Sensors], k: int | None = None) -> None:
        """One tick on the frames at hand (every agent's, for the reference; a replica's may
        lack some): time update, ranges among agents in key order, then CTL."""
        k = next(iter(frames.values())).k if k is None else k
        gap = max(k - self.k - 1, 0)
        Fs, Qs = [], []
        for a in self.agents:
            b = self.block(a)
            f = frames.get(a)
            if f is not None and f.odometry is not None:
                o = f.odometry
                self.last_odometry[a] = (o.dt, abs(o.speed), o.speed_std, abs(o.turn_rate), o.turn_rate_std)
                x, F, Q = self.model.predict(self.x[b], odometry_of(f))
                self.x[b] = x
                steps = gap
            else:
                # Not told how a moved: it stays, with the covariance of the farthest it could go.
                self.stats["missing_frames"] += 1
                F, Q, steps = np.eye(self.d), np.zeros((self.d, self.d)), gap + 1
            dt, v, sv, w, sw = self.last_odometry.get(a, (0.0,) * 5)
            reach = np.full(self.d, steps * dt * (w + 3.0 * sw))  # beyond the position: a heading
            reach[: self.p] = steps * dt * (v + 3.0 * sv)
            Fs.append(F)
            Qs.append(Q + np.diag(reach**2))
        dt = next((f.odometry.dt for f in frames.values() if f.odometry is not None), 0.0) * (gap + 1)
        for _ in self.targets:
            Fs.append(np.eye(self.p))
            Qs.append(np.eye(self.p) * self.q_target * dt)
        F, Q = kalman.block_diag(Fs), kalman.block_diag(Qs)
        self.x, self.P = kalman.predict(self.x, self.P, F, Q)
        self.k = k
        self.nis = {a: [] for a in self.agents}
        for m, n, z, R in self.measurements(frames):
            if n in self.offset and m in self.offset:
                self.nis[m].append(self.update(m, n, z, R))
        self.localize_targets(frames)

    def localize_targets(self, frames: dict[int, Sensors]) -> None:
        """The CTL step of this tick: majorize the joint cost of agents and targets."""
        rows = [(a, r.target, r.range, r.std) for a in sorted(frames) if a in self.offset for r in frames[a].targets]
        if not rows:
            return
        p = self.p
        keys = self.agents + [("target", o) for o in self.targets]
        fixes = {}  # new target -> its first position, from the agents' positions taken as exact
        for o in sorted({r[1] for r in rows} - set(self.targets)):
            mine = [r for r in rows if r[1] == o]
            if len({r[0] for r in mine}) < self.min_ranges:
                continue
            try:
                fix = self.first_fix.update(o, np.array([self.x[self.offset[a]:self.offset[a] + p] for a, *_ in mine]),
                                            np.array([r[2] for r in mine]), np.array([r[3] for r in mine]))
            except ValueError:
                fix = None
            if fix is None:
                self.stats["undecided_first_fix"] += 1
            else:
                fixes[o] = fix[0]
        new = list(fixes)
        used = [r for r in rows if r[1] in self.targets or r[1] in fixes]
        self.stats["unused_target_ranges"] += len(rows) - len(used)
        if not used:
            return
        p_idx = np.concatenate([np.arange(self.offset[key], self.offset[key] + p) for key in keys])
        r_idx = np.setdiff1d(np.arange(self.x.size), p_idx)  # headings, if the model has them
        node_of = {key: i for i, key in enumerate(keys)}
        for o in new:
            node_of[("target", o)] = len(node_of)
        K = len(node_of)
        prior = np.full((K, p), np.nan)
        prior[: len(keys)] = self.x[p_idx].reshape(-1, p)
        Ppp = self.P[np.ix_(p_idx, p_idx)]
        x0 = prior.copy()
        for o, x in fixes.items():
            x0[node_of[("target", o)]] = x
        try:
            implausible = []
            for a, o, z, s in used:  # NIS of the ranges to targets already in the state (linearised)
                if o in self.targets:
                    ia, io = node_of[a], node_of[("target", o)]
                    diff = prior[ia] - prior[io]
                    u = diff / max(np.linalg.norm(diff), 1e-9)
                    H = np.zeros(p_idx.size)
                    H[ia * p:(ia + 1) * p], H[io * p:(io + 1) * p] = u, -u
                    nu = np.array([z - np.linalg.norm(diff)])
                    # A member's range to a target past the innovation bound (issue 26, finding
                    # 7) takes no part in the re-estimate.
                    reason = plausibility.innovation(nu, np.array([[H @ Ppp @ H + s**2]]))
                    if reason is not None:
                        implausible.append((a, o, z, s))
                        self.refused[reason] = self.refused.get(reason, 0) + 1
                        if self.on_refused is not None:
                            self.on_refused(reason, f"range of {a} to target {o}")
                        continue
                    self.nis.setdefault(a, []).append((fusion.nis(nu, np.array([[H @ Ppp @ H + s**2]])), 1))
            if implausible:
                used = [r for r in used if r not in implausible]
                if not used:
                    return
            edges = ctl.Edges(np.array([node_of[a] for a, *_ in used]), np.array([node_of[("target", o)] for _, o, *_ in used]),
                              np.array([r[2] for r in used]), np.array([r[3] for r in used]))
            res = ctl.estimate(prior, Ppp, edges, x0, has_prior=np.arange(K) < len(keys), noise=self.ut_noise,
                               tol=self.tol, max_iter=self.max_iter)
            x, P = self._with_rest(res, p_idx, r_idx, len(new))
            np.linalg.cholesky(P)  # the next KF-CSL update factors it
        except (ValueError, np.linalg.LinAlgError):
            self.stats["ctl_failed"] += 1
            return
        self.stats["ctl_ticks"] += 1
        self.stats["majorizations"] += res.runs
        self.stats["unconverged"] += res.sigma_unconverged + (not res.majorized.converged)
        for o in new:
            self.offset[("target", o)], self.size[("target", o)] = self.x.size, p
            self.targets.append(o)
            self.x = np.r_[self.x, np.zeros(p)]
        self.x, self.P = x, P

    def _with_rest(self, res, p_idx: np.ndarray, r_idx: np.ndarray, new: int) -> tuple[np.ndarray, np.ndarray]:
        """The joint state after CTL: positions (and new targets, appended) from the
        re-estimate; the rest r moved by its regression on the positions, G = P_rp P_pp^-1:
        x_r += G dx_p, P_rr = P_rr - G P_pr + G C_pp G^T, P_r,all = G C_p,all (the Gaussian update
        of a state whose position marginal was replaced by N(x_p*, C), exact for linear models)."""
        n_old, n_p, grow = self.x.size, p_idx.size, new * self.p
        all_p = np.r_[p_idx, np.arange(n_old, n_old + grow)]
        x, P = np.r_[self.x, np.zeros(grow)], np.zeros((n_old + grow,) * 2)
        C = res.cov
        x[all_p] = res.x.ravel()
        P[np.ix_(all_p, all_p)] = C
        if r_idx.size:
            Ppp = self.P[np.ix_(p_idx, p_idx)]
            Prp = self.P[np.ix_(r_idx, p_idx)]
            G = np.linalg.solve(Ppp, Prp.T).T
            x[r_idx] = self.x[r_idx] + G @ (x[p_idx] - self.x[p_idx])
            P[np.ix_(r_idx, r_idx)] = self.P[np.ix_(r_idx, r_idx)] - G @ Prp.T + G @ C[:n_p, :n_p] @ G.T
            P[np.ix_(r_idx, all_p)] = G @ C[:n_p]
            P[np.ix_(all_p, r_idx)] = P[np.ix_(r_idx, all_p)].T
        return x, 0.5 * (P + P.T)

    def target_estimates(self) -> tuple:
        return tuple((o, self.x[self.block(("target", o))].copy(), self.P[self.block(("target", o)), self.block(("target", o))].copy())
                     for o in self.targets)

    def estimate(self, a: int) -> Estimate:
        e = super().estimate(a)
        return Estimate(e.k, e.mean, e.cov, e.nis, self.target_estimates())


class TickGather:
    """What every agent broadcast in one tick, for the nodes that run a tick on everyone's frames
    (the module docstring: which agents are expected, late, early and duplicate broadcasts)."""

    def __init__(self, me: int, ids: list[int], forget_after: int):
        self.me, self.ids, self.forget_after = me, ids, forget_after
        self.held: dict[int, dict[int, object]] = {}  # tick -> sender -> what it sent
        self.pending: int | None = None  # the tick being gathered
        self.done = -1  # the last tick run
        self.heard: dict[int, int] = {}
        self.first: int | None = None

    def open(self, k: int, own) -> None:
        self.first = k if self.first is None else self.first
        self.pending = k
        self.held.setdefault(k, {})[self.me] = own

    def offer(self, src: int, k: int, item) -> str | None:
        """Hold a neighbour's broadcast of tick k; the drop reason if it is not taken."""
        if src not in self.ids or src == self.me:
            return "invalid"
        self.heard[src] = max(self.heard.get(src, k), k)
        if k <= self.done:
            return "late"
        if k > (self.pending if self.pending is not None else self.done) + MAX_AHEAD:
            return "early"
        tick = self.held.setdefault(k, {})
        if src in tick:
            return "duplicate"
        tick[src] = item
        return None

    def expected(self, k: int) -> set[int]:
        start = self.first if self.first is not None else k
        return {a for a in self.ids if a == self.me or k - self.heard.get(a, start) <= self.forget_after}

    def ready(self) -> bool:
        return self.pending is not None and self.expected(self.pending) <= set(self.held.get(self.pending, {}))

    def close(self) -> tuple[int, dict, bool]:
        """The pending tick, what was held for it, and whether every expected agent's is there."""
        complete = self.ready()
        k, self.pending, self.done = self.pending, None, self.pending
        items = self.held.pop(k, {})
        for old in [t for t in self.held if t <= k]:
            del self.held[old]
        return k, items, complete


class CslCtlNode(Node):
    """One agent's CSL-CTL: its replica of the joint problem, fed by everyone's shares."""

    algorithm = "csl-ctl"
    joint = JointCslCtl

    def __init__(self, aid: int, x0, P0, model="planar-speed-heading", *, ids: list[int], priors,
                 spread: float | None = None, tol: float = 1e-9, max_iter: int = 100, ut_noise: bool = True,
                 target_process_noise: float = 0.0, min_ranges: int = 3, wait: float = 0.1, forget_after: int = 10):
        super().__init__(aid, x0, P0, model)
        self.ids = [int(a) for a in ids]
        self.priors = np.asarray(priors, float)
        self.settings = dict(spread=spread, tol=tol, max_iter=max_iter, ut_noise=ut_noise,
                             target_process_noise=target_process_noise, min_ranges=min_ranges)
        self.replica = self._replica({a: self.priors[i] for i, a in enumerate(self.ids)}, P0)
        self.wait, self.forget_after = float(wait), int(forget_after)
        self.gather = TickGather(self.id, self.ids, self.forget_after)  # the shares, Sensors each
        self._stats = {"incomplete_runs": 0}  # ticks run without every expected share

    @property
    def stats(self) -> dict:
        """The node's counters and its replica's (the agent's `stats` query reports both)."""
        return {**self._stats, **self.replica.stats}

    def _replica(self, x0: dict, P0) -> JointCslCtl:
        s = self.settings
        replica = self.joint(x0, P0, self.model, s["spread"], tol=s["tol"], max_iter=s["max_iter"], ut_noise=s["ut_noise"],
                             target_process_noise=s["target_process_noise"], min_ranges=s["min_ranges"])
        replica.on_refused = self.drop  # a share's implausible measurement (issue 26, finding 7), counted here
        return replica

    @classmethod
    def spec(cls, scenario, aid, settings=None) -> NodeSpec:
        ids = scenario.localized_ids
        priors = np.array([scenario.prior(a)[0] for a in ids])
        kw = _ctl_kwargs(settings)
        return super().spec(scenario, aid).with_(ids=ids, priors=priors, spread=scenario.estimation.spread, **kw,
                                                 wait=getattr(settings, "wait", 0.1),
                                                 forget_after=getattr(settings, "forget_after", 10))

    # ------------------------------------------------------------------ tick

    def step(self, sensors: Sensors) -> list[Send]:
        if self.gather.pending is not None:
            self._run()
        k = sensors.k
        if k <= self.k:
            return self.drop("stale", f"own frame of tick {k}")
        # The frame is handled (lockstep's `done` says so) though the tick runs when the shares are in.
        self.k = k
        self.nis = []
        self.gather.open(k, sensors)
        out: list = [Send(CslShare(k, sensors), None)]
        if self.gather.ready():
            self._run()
        else:
            out.append(Timer(self.wait, RUN))
        return out

    def on_timer(self, tag: str, t: float) -> list:
        if tag == RUN and self.gather.pending is not None:
            self._run()
        return []

    def receive(self, src: int, msg) -> list[Send]:
        if not isinstance(msg, CslShare):
            return self.drop("unexpected", type(msg).__name__)
        if msg.sensors.k != msg.k:
            return self.drop("invalid", f"share from {src}")
        reason = self.gather.offer(src, msg.k, msg.sensors)
        if reason is not None:
            return self.drop(reason, f"share of tick {msg.k} from {src}")
        if self.gather.ready():
            self._run()
        return []

    def _run(self) -> None:
        k, frames, complete = self.gather.close()
        self._stats["incomplete_runs"] += not complete
        self.replica.step(frames, k)
        b = self.replica.block(self.id)
        self.x, self.P = self.replica.x[b].copy(), self.replica.P[b, b].copy()
        self.nis = self.replica.nis.get(self.id, [])

    def estimate(self) -> Estimate:
        """After the tick has run, this agent's block and the targets of the replica. While the
        tick waits for shares, its own prediction on its own odometry (no NIS)."""
        targets = self.replica.target_estimates()
        k = self.gather.pending
        frame = self.gather.held.get(k, {}).get(self.id) if k is not None else None
        if frame is not None and frame.odometry is not None and k > self.replica.k:
            x, F, Q = self.model.predict(self.x, odometry_of(frame))
            return Estimate(k, x, F @ self.P @ F.T + Q, (), targets)
        return Estimate(self.replica.k, self.x.copy(), self.P.copy(), (), targets)

    def resume(self, k, x, P) -> None:
        """A restart keeps only this agent's own estimate: the others come back into the replica
        with a wide prior (1 km std) at its own position, and the targets are localized anew."""
        super().resume(k, x, P)
        self.replica = self._replica({a: np.asarray(x, float) for a in self.ids}, np.eye(self.model.state_dim) * 1e6)
        b = self.replica.block(self.id)
        self.replica.P[b, b] = np.asarray(P, float)
        self.replica.k = int(k)
        self.gather = TickGather(self.id, self.ids, self.forget_after)
        self.gather.done = int(k)


class IlCtlNode(IndependentNode):
    """IL-CTL: own dead reckoning, targets by least squares from the positions agents report."""

    algorithm = "il-ctl"

    def __init__(self, aid: int, x0, P0, model="planar-speed-heading", *, ids: list[int], min_ranges: int = 3,
                 target_process_noise: float = 0.0, wait: float = 0.1, forget_after: int = 10):
        super().__init__(aid, x0, P0, model)
        self.ids = [int(a) for a in ids]
        self.min_ranges, self.q_target = int(min_ranges), float(target_process_noise)
        self.wait, self.forget_after = float(wait), int(forget_after)
        self.gather = TickGather(self.id, self.ids, self.forget_after)  # the fixes, CtlFix each
        self.targets: dict[int, tuple[np.ndarray, np.ndarray, int]] = {}  # o -> (mean, cov, tick)
        self.dt = 0.0  # the clock's tick length, from the odometry: a static target's process noise
        self.stats = {"incomplete_runs": 0, "ls_failed": 0, "unused_target_ranges": 0, "undecided_first_fix": 0}
        self.first_fix = FirstFix()

    @classmethod
    def spec(cls, scenario, aid, settings=None) -> NodeSpec:
        return super().spec(scenario, aid).with_(
            ids=scenario.localized_ids, min_ranges=getattr(settings, "min_ranges", 3),
            target_process_noise=getattr(settings, "target_process_noise", 0.0),
            wait=getattr(settings, "wait", 0.1), forget_after=getattr(settings, "forget_after", 10))

    def step(self, sensors) -> list[Send]:
        if self.gather.pending is not None:
            self._run()
        if sensors.k <= self.gather.done:
            return self.drop("stale", f"own frame of tick {sensors.k}")
        super().step(sensors)
        k = sensors.k
        self.dt = sensors.odometry.dt if sensors.odometry is not None else self.dt
        p = self.model.position_dim
        fix = CtlFix(k, self.x[:p].copy(), self.P[:p, :p].copy(), list(sensors.targets))
        self.gather.open(k, fix)
        out: list = [Send(fix, None)]
        if self.gather.ready():
            self._run()
        else:
            out.append(Timer(self.wait, RUN))
        return out

    def on_timer(self, tag: str, t: float) -> list:
        if tag == RUN and self.gather.pending is not None:
            self._run()
        return []

    def receive(self, src: int, msg) -> list[Send]:
        if not isinstance(msg, CtlFix):
            return self.drop("unexpected", type(msg).__name__)
        if msg.mean.shape != (self.model.position_dim,):
            return self.drop("invalid", f"fix from {src}")
        reason = self.gather.offer(src, msg.k, msg)
        if reason is not None:
            return self.drop(reason, f"fix of tick {msg.k} from {src}")
        if self.gather.ready():
            self._run()
        return []

    def _plausible(self, m, P, anchor, C, r) -> bool:
        diff = m - anchor
        u = diff / max(np.linalg.norm(diff), 1e-9)
        nu = np.array([r.range - np.linalg.norm(diff)])
        reason = plausibility.innovation(nu, np.array([[u @ (P + C) @ u + r.std**2]]))
        if reason is None:
            return True
        self.drop(reason, f"range to target {r.target} from an anchor at {anchor}")
        return False

    def _run(self) -> None:
        k, fixes, complete = self.gather.close()
        self.stats["incomplete_runs"] += not complete
        rows = [(f.mean, f.cov, r) for _, f in sorted(fixes.items()) for r in f.targets]
        for o in sorted({r.target for *_, r in rows}):
            mine = [(p, C, r) for p, C, r in rows if r.target == o]
            if o in self.targets:
                # A range past the innovation bound against the target we hold, from the anchor
                # its sender reports (issue 26, finding 7): left out of the least squares.
                m, P, _ = self.targets[o]
                mine = [row for row in mine if self._plausible(m, P, *row)]
            mine = [(p, r) for p, _, r in mine]
            anchors = np.array([p for p, _ in mine])
            z, s = np.array([r.range for _, r in mine]), np.array([r.std for _, r in mine])
            if o not in self.targets and len(mine) < self.min_ranges:
                self.stats["unused_target_ranges"] += len(mine)
                continue
            try:
                if o in self.targets:
                    m, P, seen = self.targets[o]
                    P = P + np.eye(2) * self.q_target * (k - seen) * self.dt
                    fix = ctl.ls_target(anchors, z, s, m, (m, P))
                else:
                    fix = self.first_fix.update(o, anchors, z, s)
            except ValueError:
                self.stats["ls_failed"] += 1
                continue
            if fix is None:
                self.stats["undecided_first_fix"] += 1
                continue
            self.targets[o] = (fix[0], fix[1], k)

    def estimate(self) -> Estimate:
        return Estimate(self.k, self.x.copy(), self.P.copy(), (),
                        tuple((o, m.copy(), P.copy()) for o, (m, P, _) in sorted(self.targets.items())))


class BroadcastReference:
    """An estimator whose agents share by broadcast, computed offline: its nodes, each on its
    own frames, with every broadcast handed to every other node at once (a radio that loses
    nothing and reaches everyone: what the agents compute when every frame arrives)."""

    def __init__(self, nodes: dict[int, Node]):
        self.nodes = nodes

    @classmethod
    def of(cls, node_cls):
        def make(scenario, ids, settings=None):
            return cls({a: node_cls.spec(scenario, a, settings).build() for a in ids})
        return make

    def step(self, frames: dict[int, Sensors]) -> None:
        sent = [(a, s.msg) for a, node in self.nodes.items() for s in node.step(frames[a]) if isinstance(s, Send)]
        for src, msg in sent:
            for a, node in self.nodes.items():
                if a != src:
                    node.receive(src, msg)

    def estimate(self, aid: int) -> Estimate:
        return self.nodes[aid].estimate()


il_ctl_reference = BroadcastReference.of(IlCtlNode)


def _ctl_kwargs(settings) -> dict:
    return dict(tol=getattr(settings, "tol", 1e-9), max_iter=getattr(settings, "max_iter", 100),
                ut_noise=getattr(settings, "ut_noise", True),
                target_process_noise=getattr(settings, "target_process_noise", 0.0),
                min_ranges=getattr(settings, "min_ranges", 3))

