"""Run records and their metrics: what a run recorded (truth, sensor frames, every estimator's
trace), the offline references computed from it, and the error, NEES and NIS summaries of
metrics.json (written to disk by rundir.py; format: docs/run-format.md)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.stats

from swarmloc import wire
from swarmloc.node import Estimate
from swarmloc.wire.messages import GnssMsg, OdometryMsg, RangeMsg, Sensors

FORMAT_VERSION = 1


@dataclass
class Trace:
    """One estimator's means and covariances for every agent and tick.

    A swarm may mix models of different state sizes: arrays are as wide as the largest, and
    agent i's entries beyond dims[i] are NaN."""

    ids: np.ndarray  # (N,)
    k: np.ndarray  # (T,)
    t: np.ndarray  # (T,)
    mean: np.ndarray  # (T, N, d), NaN where the agent reported nothing
    cov: np.ndarray  # (T, N, d, d)
    dims: np.ndarray | None = None  # (N,) state dimension of each agent; None: all d
    # Each agent's estimate of each target (CSL-CTL, IL-CTL), NaN where it has none; None for an
    # estimator that localizes no target.
    target_ids: np.ndarray | None = None  # (M,)
    target_mean: np.ndarray | None = None  # (T, N, M, 2)
    target_cov: np.ndarray | None = None  # (T, N, M, 2, 2)

    def __post_init__(self):
        if self.dims is None:
            self.dims = np.full(len(self.ids), self.mean.shape[-1], np.int64)

    def save(self, path: Path) -> None:
        targets = {} if self.target_ids is None else {
            "target_ids": self.target_ids, "target_mean": self.target_mean, "target_cov": self.target_cov}
        np.savez(path, ids=self.ids, k=self.k, t=self.t, mean=self.mean, cov=self.cov, dims=self.dims, **targets)

    @classmethod
    def load(cls, path: Path) -> "Trace":
        with np.load(path, allow_pickle=False) as f:
            targets = [f[n] if n in f else None for n in ("target_ids", "target_mean", "target_cov")]
            return cls(f["ids"], f["k"], f["t"], f["mean"], f["cov"], f["dims"] if "dims" in f else None, *targets)


class RunRecord:
    """Everything a run produces, gathered tick by tick (in-process runner or netsim).

    models: each localized agent's motion model (its state size, its position, its error for
    NEES), or one state size for a swarm of planar robots."""

    def __init__(self, ids: list[int], models: dict | int):
        from swarmloc.models.motion import MOTION_MODELS

        self.ids = sorted(ids)
        self.col = {a: i for i, a in enumerate(self.ids)}
        if isinstance(models, int):
            models = {a: next(m for m in MOTION_MODELS.values() if m.state_dim == models) for a in self.ids}
        self.models = {a: MOTION_MODELS[m] if isinstance(m, str) else m for a, m in models.items()}
        self.dims = np.array([self.models[a].state_dim for a in self.ids], np.int64)
        self.d = int(self.dims.max())
        self.k: list[int] = []
        self.t: list[float] = []
        self.truth: list[np.ndarray] = []
        self.sensors: list[dict[int, Sensors]] = []
        self.target_ids: list[int] = []
        self.target_truth: list[np.ndarray] = []  # per tick (M, 2)
        self.landmarks: dict[int, tuple[float, float]] = {}  # the known map, for plots
        self.ground_stations: dict[int, tuple[float, float]] = {}  # where they stand, for plots (nothing to localize)
        self.est: dict[str, dict[int, dict[int, Estimate]]] = {}
        # alg -> {(k, agent): [(nis, dof), ...]}: an agent may publish its estimate of a tick more
        # than once (a fusion-centre UAS: its own, then the centre's); the last one counts.
        self._nis: dict[str, dict[tuple[int, int], tuple]] = {}
        # The posterior Cramér-Rao bound of the run (swarmloc.experiment.bounds.Bound), once computed
        # (compute_references); bound_error: why it could not be.
        self.bound = None
        self.bound_error: str | None = None
        self.bound_time: tuple[float, float] | None = None  # (wall, CPU) seconds the bound took

    @classmethod
    def for_scenario(cls, scenario) -> "RunRecord":
        record = cls(scenario.localized_ids, {a: scenario.agent(a).model for a in scenario.localized_ids})
        record.landmarks = {m.id: tuple(m.position) for m in scenario.world.landmarks}
        record.ground_stations = {a.id: tuple(a.start[:2]) for a in scenario.world.agents if not a.localized}
        return record

    def add_tick(self, k: int, t: float, frames: dict[int, Sensors], truth: dict[int, np.ndarray],
                 targets: dict[int, np.ndarray] | None = None) -> None:
        """One tick's sensor frames and truth: every agent's state and every target's position."""
        if targets:
            if not self.target_ids:
                self.target_ids = sorted(targets)
            self.target_truth.append(np.array([targets[o] for o in self.target_ids], float))
        self.k.append(k)
        self.t.append(t)
        self.sensors.append(frames)
        row = np.full((len(self.ids), self.d), np.nan)
        for ci, a in enumerate(self.ids):
            row[ci, : self.dims[ci]] = truth[a]
        self.truth.append(row)

    def add_estimate(self, algorithm: str, aid: int, e: Estimate) -> None:
        if aid not in self.col:
            return  # a ground station: nothing to localize
        self.est.setdefault(algorithm, {}).setdefault(e.k, {})[aid] = e
        self._nis.setdefault(algorithm, {})[(e.k, aid)] = tuple((float(v), int(d)) for v, d in e.nis)

    @property
    def nis(self) -> dict[str, list[tuple[int, int, float, int]]]:
        """alg -> [(k, agent, NIS, dof)] of every innovation, ticks in order."""
        return {alg: [(k, a, v, d) for (k, a), rows in sorted(by.items()) for v, d in rows]
                for alg, by in self._nis.items()}

    def trace(self, algorithm: str) -> Trace:
        T, N, d = len(self.k), len(self.ids), self.d
        mean = np.full((T, N, d), np.nan)
        cov = np.full((T, N, d, d), np.nan)
        by_k = self.est.get(algorithm, {})
        for ti, k in enumerate(self.k):
            for a, e in by_k.get(k, {}).items():
                n = self.dims[self.col[a]]
                mean[ti, self.col[a], :n] = e.mean
                cov[ti, self.col[a], :n, :n] = e.cov
        trace = Trace(np.array(self.ids), np.array(self.k), np.array(self.t), mean, cov, self.dims.copy())
        if self.target_ids and any(e.targets for per in by_k.values() for e in per.values()):
            M, col = len(self.target_ids), {o: i for i, o in enumerate(self.target_ids)}
            tm, tc = np.full((T, N, M, 2), np.nan), np.full((T, N, M, 2, 2), np.nan)
            for ti, k in enumerate(self.k):
                for a, e in by_k.get(k, {}).items():
                    for o, m, P in e.targets:
                        if o in col:
                            tm[ti, self.col[a], col[o]], tc[ti, self.col[a], col[o]] = m, P
            trace.target_ids, trace.target_mean, trace.target_cov = np.array(self.target_ids), tm, tc
        return trace

    def truth_array(self) -> np.ndarray:
        return np.stack(self.truth)

    # ---------------------------------------------------------------- sensor stream as arrays

    def sensor_arrays(self) -> dict[str, np.ndarray]:
        """sensors.npz: every frame bit for bit (`wire`, msgpack per docs/wire.md), and the planar
        sensors also as plain columns for tools without a msgpack reader."""
        blobs, offsets = [], np.zeros((len(self.k), len(self.ids) + 1), np.int64)
        pos = 0
        for ti, frames in enumerate(self.sensors):
            offsets[ti, 0] = pos
            for ci, a in enumerate(self.ids):
                b = wire.encode(frames[a], 0, 0)
                blobs.append(b)
                pos += len(b)
                offsets[ti, ci + 1] = pos
        out = {"ids": np.array(self.ids), "k": np.array(self.k), "t": np.array(self.t),
               "wire": np.frombuffer(b"".join(blobs), np.uint8), "wire_offsets": offsets}
        planar = [a for a in self.ids if self.models[a].name == "planar-speed-heading"]
        if planar == self.ids:
            out.update(self._planar_columns())
        return out

    def _planar_columns(self) -> dict[str, np.ndarray]:
        odo = np.array([[[s.odometry.dt, s.odometry.speed, s.odometry.heading, s.odometry.speed_std, s.odometry.heading_std]
                         for s in (frames[a] for a in self.ids)] for frames in self.sensors])
        rows = [(k, m, r.target, r.range, r.std) for k, frames in zip(self.k, self.sensors)
                for m in self.ids for r in frames[m].ranges]
        rng = np.array(rows, float).reshape(-1, 5)
        gnss = np.full((len(self.k), len(self.ids), 3), np.nan)  # x, y, std; NaN: no fix
        for ti, frames in enumerate(self.sensors):
            for ci, a in enumerate(self.ids):
                g = frames[a].gnss
                if g is not None:
                    gnss[ti, ci] = [*g.position[:2], g.std]
        return {"odometry": odo, "gnss": gnss,
                "range_k": rng[:, 0].astype(np.int64), "range_m": rng[:, 1].astype(np.int64),
                "range_n": rng[:, 2].astype(np.int64), "range_z": rng[:, 3], "range_std": rng[:, 4]}


def frames_from_arrays(a: dict[str, np.ndarray]) -> list[dict[int, Sensors]]:
    """Rebuild the sensor frames of a run from sensors.npz (for references computed offline)."""
    ids = [int(i) for i in a["ids"]]
    if "wire" in a:
        data, off = a["wire"].tobytes(), a["wire_offsets"]
        return [{m: wire.decode(data[off[ti, ci]:off[ti, ci + 1]], expect=(Sensors,)).body for ci, m in enumerate(ids)}
                for ti in range(len(a["k"]))]
    out = []
    for ti, k in enumerate(a["k"]):
        sel = np.flatnonzero(a["range_k"] == k)
        frames = {}
        for ci, m in enumerate(ids):
            o = a["odometry"][ti, ci]
            ranges = [RangeMsg(int(a["range_n"][j]), float(a["range_z"][j]), float(a["range_std"][j]))
                      for j in sel if a["range_m"][j] == m]
            g = a["gnss"][ti, ci] if "gnss" in a else np.full(3, np.nan)
            gnss = None if np.isnan(g[0]) else GnssMsg(g[:2].copy(), float(g[2]))
            frames[m] = Sensors(int(k), float(a["t"][ti]), OdometryMsg(*map(float, o)), ranges, gnss)
        out.append(frames)
    return out


def compute_references(scenario, record: RunRecord, which=None, bound: bool = True) -> None:
    """The scenario's offline references from the recorded sensor stream, added in place, and
    (`bound`) the run's posterior Cramér-Rao bound (`compute_bound`)."""
    from swarmloc.estimators import REGISTRY

    for name in scenario.reference_names if which is None else which:
        ref = REGISTRY[name].make_reference(scenario, record.ids, scenario.reference_settings(name))
        for frames in record.sensors:
            ref.step(frames)
            for a in record.ids:
                record.add_estimate(name, a, ref.estimate(a))
    if bound:
        compute_bound(scenario, record)


def compute_bound(scenario, record: RunRecord) -> None:
    """record.bound: the PCRB of the run (swarmloc.experiment.bounds.pcrb), once, unless the
    scenario says `bound: false`; record.bound_time: its (wall, CPU) seconds. A run whose bound
    cannot be computed keeps its metrics: record.bound_error says why, metrics.json["pcrb"] too."""
    from swarmloc.experiment.bounds import pcrb

    if record.bound is not None or not record.k or not getattr(scenario, "bound", True):
        return
    wall, cpu = time.perf_counter(), time.process_time()
    try:
        record.bound = pcrb(scenario, record)
        record.bound_error = None
    except Exception as exc:  # the bound is beside the run's numbers: its failure must not lose them
        logging.getLogger(__name__).warning("no PCRB for this run: %s", exc, exc_info=True)
        record.bound_error = f"{type(exc).__name__}: {exc}"
    record.bound_time = (time.perf_counter() - wall, time.process_time() - cpu)


def chi2_bounds(dof: int, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided bounds of a chi-square variable with `dof` degrees of freedom. The mean of n
    consistent NEES values of d degrees of freedom each is chi2(n d) / n: call with n d and
    divide by n (as if the values were independent; values of one run are correlated in time,
    so a run's time average is a looser check than a Monte Carlo average)."""
    lo, hi = scipy.stats.chi2.ppf([(1 - confidence) / 2, (1 + confidence) / 2], dof)
    return float(lo), float(hi)


def _average_with_bounds(values: np.ndarray, dof_each: np.ndarray) -> dict | None:
    """Mean of chi-square values and the 95% two-sided bounds of that mean if consistent."""
    if values.size == 0:
        return None
    total = int(dof_each.sum())
    lo, hi = chi2_bounds(total)
    n = values.size
    return {"mean": float(values.mean()), "dof": float(total / n), "n": int(n),
            "bounds": [lo / n, hi / n], "inside": bool(lo / n <= values.mean() <= hi / n)}


def nees_series(record: RunRecord, trace: Trace) -> np.ndarray:
    """NEES per tick and agent (T, N): NaN where the agent reported nothing."""
    truth = record.truth_array()
    T, N = truth.shape[:2]
    out = np.full((T, N), np.nan)
    for ci, a in enumerate(record.ids):
        n, model = int(record.dims[ci]), record.models[a]
        if model.name in ("planar-speed-heading", "planar-pose"):
            # Their error is elementwise: every tick at once (a replay has ~10^4 ticks per robot).
            x, P = trace.mean[:, ci, :n], trace.cov[:, ci, :n, :n]
            ok = ~(np.isnan(x).any(axis=1) | np.isnan(P).any(axis=(1, 2)))
            e = model.error(truth[ok, ci, :n], x[ok])
            try:
                out[ok, ci] = np.einsum("ti,ti->t", e, np.linalg.solve(P[ok], e[..., None])[..., 0])
                continue
            except np.linalg.LinAlgError:
                pass  # a singular covariance somewhere: tick by tick, leaving that one NaN
        for ti in range(T):
            x, P = trace.mean[ti, ci, :n], trace.cov[ti, ci, :n, :n]
            if np.isnan(x).any() or np.isnan(P).any():
                continue
            e = model.error(truth[ti, ci, :n], x)
            try:
                out[ti, ci] = float(e @ np.linalg.solve(P, e))
            except np.linalg.LinAlgError:
                pass
    return out


def position_errors(record: RunRecord, trace: Trace) -> np.ndarray:
    """Position error (m) per tick and agent (T, N), each agent in its own position dimension."""
    truth = record.truth_array()
    out = np.full(truth.shape[:2], np.nan)
    for ci, a in enumerate(record.ids):
        p = record.models[a].position_dim
        out[:, ci] = np.linalg.norm(trace.mean[:, ci, :p] - truth[:, ci, :p], axis=-1)
    return out


def target_errors(record: RunRecord, trace: Trace) -> tuple[np.ndarray, np.ndarray]:
    """Each agent's target error (m) and target NEES (2 dof) per tick: (T, N, M) each, NaN
    where the agent has no estimate of the target (yet)."""
    truth = np.stack(record.target_truth)  # (T, M, 2)
    e = trace.target_mean - truth[:, None]
    err = np.linalg.norm(e, axis=-1)
    nees = np.full(err.shape, np.nan)
    ok = ~np.isnan(err) & ~np.isnan(trace.target_cov).any(axis=(-1, -2))
    if ok.any():
        P = trace.target_cov[ok]
        good = np.linalg.det(P) > 0
        sol = np.full(e[ok].shape, np.nan)
        sol[good] = np.linalg.solve(P[good], e[ok][good][..., None])[..., 0]
        nees[ok] = np.einsum("ni,ni->n", e[ok], sol)
    return err, nees


def _target_metrics(record: RunRecord, trace: Trace) -> dict:
    """Per target: the agents' mean error over the ticks they had an estimate, the final error
    (mean over agents at the last tick), the NEES average with its 95% bounds and, with the
    run's PCRB, the target's bound at the last tick (final_pcrb_m)."""
    err, nees = target_errors(record, trace)
    out = {}
    for mi, o in enumerate(record.target_ids):
        e, n = err[:, :, mi], nees[:, :, mi]
        final = e[-1][~np.isnan(e[-1])]
        per = {str(a): {"mean_error_m": float(np.nanmean(e[:, ci])) if (~np.isnan(e[:, ci])).any() else None,
                        "final_error_m": None if np.isnan(e[-1, ci]) else float(e[-1, ci]),
                        "first_tick": int(record.k[int(np.argmax(~np.isnan(e[:, ci])))]) if (~np.isnan(e[:, ci])).any() else None}
               for ci, a in enumerate(record.ids)}
        valid = n[~np.isnan(n)]
        out[str(o)] = {"agents": per,
                       "mean_error_m": float(np.nanmean(e)) if (~np.isnan(e)).any() else None,
                       "final_error_m": float(final.mean()) if final.size else None,
                       "nees": _average_with_bounds(valid, np.full(valid.size, 2))}
        b = record.bound
        if b is not None and o in b.target_ids:
            out[str(o)]["final_pcrb_m"] = _finite(b.target_position[-1, b.target_ids.index(o)])
    return out


def heading_errors(record: RunRecord, trace: Trace) -> np.ndarray:
    """Heading error (rad, wrapped) per tick and agent (T, N); NaN for agents without a heading
    in their state (a planar-pose robot has one)."""
    truth = record.truth_array()
    out = np.full(truth.shape[:2], np.nan)
    for ci, a in enumerate(record.ids):
        att = record.models[a].layout.att_idx
        if len(att) == 1:
            i = att[0]
            out[:, ci] = np.abs(np.remainder(trace.mean[:, ci, i] - truth[:, ci, i] + np.pi, 2 * np.pi) - np.pi)
    return out


def _rms(x: np.ndarray) -> float | None:
    x = x[~np.isnan(x)]
    return float(np.sqrt(np.mean(x**2))) if x.size else None


SAME_M = 1e-6  # estimates closer than this everywhere are the same estimates (float precision is ~1e-12 m)


def identical_estimates(record: RunRecord, traces: dict[str, Trace], tol: float = SAME_M) -> list[tuple[str, str, float]]:
    """Pairs of estimators whose position estimates agree on every agent and tick to within
    tol metres (and are missing on the same ticks), with their largest difference; each
    estimator paired only with the first one it equals."""
    pos = {}
    for alg, tr in traces.items():
        pos[alg] = np.concatenate([tr.mean[:, ci, :record.models[a].position_dim] for ci, a in enumerate(record.ids)],
                                  axis=1)
    pairs, matched = [], set()
    algs = list(traces)
    for i, a in enumerate(algs):
        for b in algs[i + 1:]:
            if b in matched or pos[a].shape != pos[b].shape:
                continue
            na, nb = np.isnan(pos[a]), np.isnan(pos[b])
            if (na != nb).any() or na.all():
                continue
            d = float(np.max(np.abs(pos[a][~na] - pos[b][~na])))
            if d <= tol:
                pairs.append((a, b, d))
                matched.add(b)
    return pairs


def formation_errors(record: RunRecord, trace: Trace) -> np.ndarray:
    """Per tick, the RMS over agents of the position error left once the estimated formation is
    moved and turned onto the true one (the rigid transform that fits best, Kabsch): what
    measurements among the agents alone can observe. NaN on ticks with fewer than 3 agents
    with an estimate and a truth, or agents of different position dimensions."""
    dims = {record.models[a].position_dim for a in record.ids}
    out = np.full(len(record.k), np.nan)
    if len(dims) != 1 or len(record.ids) < 3:
        return out
    p = dims.pop()
    truth, est = record.truth_array()[:, :, :p], trace.mean[:, :, :p]
    for k in range(len(out)):
        ok = ~np.isnan(est[k]).any(axis=1) & ~np.isnan(truth[k]).any(axis=1)  # a replay's truth has gaps
        if ok.sum() < 3:
            continue
        a, b = est[k][ok] - est[k][ok].mean(0), truth[k][ok] - truth[k][ok].mean(0)
        u, _, vt = np.linalg.svd(a.T @ b)
        flip = np.ones(p)
        flip[-1] = np.sign(np.linalg.det(u @ vt))
        out[k] = np.sqrt(np.mean(np.sum((a @ (u * flip) @ vt - b) ** 2, axis=1)))
    return out


def _finite(v) -> float | None:
    return float(v) if np.isfinite(v) else None


def _against_bound(err: np.ndarray, bound: np.ndarray | None) -> dict:
    """The PCRB over the cells (ticks, agents) where the estimator has an error and the bound is
    finite: its RMS (pcrb_m, the bound on rmse_m), rmse over those cells divided by it
    (rmse_over_pcrb: 1 is the best any estimator can do on average), and its final value."""
    if bound is None:
        return {}
    ok = np.isfinite(err) & np.isfinite(bound)
    p = float(np.sqrt(np.mean(bound[ok] ** 2))) if ok.any() else None
    r = float(np.sqrt(np.mean(err[ok] ** 2))) if ok.any() else None
    return {"pcrb_m": p, "rmse_over_pcrb": r / p if p else None,
            "final_pcrb_m": _finite(bound[-1]) if bound.size else None}


def gnss_covered(record: RunRecord) -> np.ndarray:
    """(T, N) bool: the agent had a GNSS fix within one epoch of the tick. The epoch is the
    shortest gap between two fixes of one agent in the run: one tick in the planar world (a fix
    every tick, so a tick counts only if it carried a fix itself), the GNSS epoch for UAS, whose
    ticks between epochs are not GNSS-denied. An agent without a receiver, or in an outage
    longer than an epoch, is not covered."""
    fixed = np.array([[frames[a].gnss is not None for a in record.ids] for frames in record.sensors], bool)
    if not fixed.any():
        return fixed
    gaps = [np.diff(np.flatnonzero(fixed[:, ci])) for ci in range(fixed.shape[1])]
    gaps = np.concatenate(gaps)
    w = int(gaps.min()) if gaps.size else 1
    # A fix in (t - w, t + w): the running count of fixes over a window of 2w - 1 ticks.
    c = np.vstack([np.zeros((1, fixed.shape[1]), np.int64), np.cumsum(fixed, axis=0)])
    T = fixed.shape[0]
    lo = np.clip(np.arange(T) - w + 1, 0, T)
    hi = np.clip(np.arange(T) + w, 0, T)
    return (c[hi] - c[lo]) > 0


def tracks_of(scenario) -> dict:
    """Each vehicle's reference (swarmloc.models.vehicles.CircleReference) by id: what its
    controller tracks, for the tracking error in `metrics`. {} in a swarm without vehicles."""
    from swarmloc.models.motion import VEHICLES
    from swarmloc.models.vehicles import CircleReference

    return {a.id: CircleReference(**a.reference_params()) for a in scenario.world.agents
            if a.model in VEHICLES and getattr(a.motion, "kind", None) == "track"}


def metrics(record: RunRecord, algorithms: list[str], since: float = 0.0, tracks: dict | None = None) -> dict:
    """Per estimator and agent: position error (mean over ticks 1.., final, max), NEES and
    NIS averages with their two-sided 95% chi-square bounds, the jitter (RMS of the tick-to-tick
    change of the position error); with GNSS in the swarm, the mean and largest error over the
    ticks and agents without a fix within an epoch (`no_gnss_mean_error_m`, `no_gnss_max_error_m`,
    `gnss_covered`); with targets, each target's errors (`targets`) and their means over the
    targets (`target_final_error_m`, `target_mean_error_m`); with `tracks` ({id:
    CircleReference}, `tracks_of`), the tracking error |true position - reference| (the run's,
    the same for every estimator).

    since (s): only the ticks with t >= since count (tick 0 never does), so a start-up transient
    can be left out; `final_error_m` is the last tick's either way."""
    covered = gnss_covered(record)
    tnow = np.asarray(record.t, float)
    rows = (np.arange(len(record.k)) >= 1) & (tnow >= since - 1e-9)
    pairs = rows[1:] & rows[:-1]  # consecutive ticks both counted: the jitter's differences
    truth = record.truth_array()
    track = None
    if tracks:
        track = np.full((len(record.k), len(record.ids)), np.nan)
        for ci, a in enumerate(record.ids):
            if a in tracks:
                want = np.array([tracks[a].derivatives(tk, 0)[0] for tk in tnow])
                track[:, ci] = np.linalg.norm(truth[:, ci, :3] - want, axis=1)
    kept_k = None if since <= 0 else {k for k, r in zip(record.k, rows) if r}
    out: dict = {"ticks": len(record.k), "agents": record.ids,
                 "models": {str(a): record.models[a].name for a in record.ids}, "estimators": {}}
    bound = record.bound.position if record.bound is not None else None
    if record.bound is not None:
        b = record.bound
        out["pcrb"] = {"rms_m": {str(a): _rms(bound[rows, ci]) for ci, a in enumerate(record.ids)},
                       "final_m": {str(a): _finite(bound[-1, ci]) for ci, a in enumerate(record.ids)},
                       **b.summary()}
        if b.target_ids:
            out["pcrb"]["targets_final_m"] = {str(o): _finite(b.target_position[-1, i]) for i, o in enumerate(b.target_ids)}
    elif record.bound_error:
        out["pcrb"] = {"error": record.bound_error}
    if "pcrb" in out and record.bound_time is not None:  # what the bound added to the run
        out["pcrb"]["wall_s"], out["pcrb"]["cpu_s"] = record.bound_time
    for alg in algorithms:
        tr = record.trace(alg)
        err = position_errors(record, tr)
        head = heading_errors(record, tr)
        nees = nees_series(record, tr)
        nis = record.nis.get(alg, [])
        if kept_k is not None:
            nis = [row for row in nis if row[0] in kept_k]
        per = {}
        all_nees, all_dof, all_jit = [], [], []
        for ci, a in enumerate(record.ids):
            col = err[rows, ci]
            valid = col[~np.isnan(col)]
            ne = nees[rows, ci]
            ne = ne[~np.isnan(ne)]
            all_nees.append(ne)
            all_dof.append(np.full(ne.size, record.dims[ci]))
            p = record.models[a].position_dim
            ev = tr.mean[:, ci, :p] - truth[:, ci, :p]
            jit = np.linalg.norm(np.diff(ev, axis=0), axis=1)[pairs]
            jit = jit[~np.isnan(jit)]
            all_jit.append(jit)
            mine = [(v, d) for (_, who, v, d) in nis if who == a]
            per[str(a)] = {
                "mean_error_m": float(valid.mean()) if valid.size else None,
                "final_error_m": float(err[-1, ci]) if len(record.k) > 1 and not np.isnan(err[-1, ci]) else None,
                "max_error_m": float(valid.max()) if valid.size else None,
                "rmse_m": _rms(col),
                "heading_rmse_rad": _rms(head[rows, ci]),
                "jitter_m": _rms(jit),
                "mean_nees": float(ne.mean()) if ne.size else None,
                "nees": _average_with_bounds(ne, np.full(ne.size, record.dims[ci])),
                "nis": _average_with_bounds(np.array([v for v, _ in mine]), np.array([d for _, d in mine], np.int64)),
                "ticks_missing": int(np.isnan(col).sum()),
                **_against_bound(col, None if bound is None else bound[rows, ci]),
            }
            if track is not None and not np.isnan(track[:, ci]).all():
                per[str(a)]["tracking_rmse_m"] = _rms(track[rows, ci])
        vals = [p["mean_error_m"] for p in per.values() if p["mean_error_m"] is not None]
        ne, dof = np.concatenate(all_nees), np.concatenate(all_dof)
        out["estimators"][alg] = {
            "agents": per, "mean_error_m": float(np.mean(vals)) if vals else None,
            "max_error_m": max((p["max_error_m"] for p in per.values() if p["max_error_m"] is not None), default=None),
            "rmse_m": _rms(err[rows].ravel()), "heading_rmse_rad": _rms(head[rows].ravel()),
            "jitter_m": _rms(np.concatenate(all_jit)),
            **({} if bound is None else {k: v for k, v in _against_bound(err[rows].ravel(), bound[rows].ravel()).items()
                                         if k != "final_pcrb_m"}),
            "nees": _average_with_bounds(ne, dof),
            "nis": _average_with_bounds(np.array([v for *_, v, _ in nis]), np.array([d for *_, d in nis], np.int64)),
        }
        if track is not None:
            out["estimators"][alg]["tracking_rmse_m"] = _rms(track[rows].ravel())
        if tr.target_ids is not None:
            targets = _target_metrics(record, tr)
            out["estimators"][alg]["targets"] = targets
            # Flat copies, mean over the targets, so a study can sweep them (netsim/study.py reads
            # only top-level numbers).
            for key in ("final_error_m", "mean_error_m"):
                vals = [t[key] for t in targets.values() if t[key] is not None]
                out["estimators"][alg][f"target_{key}"] = float(np.mean(vals)) if vals else None
        # What measurements among the agents can observe: the error once the swarm's common shift
        # and turn are taken out (formation_errors).
        out["estimators"][alg]["formation_rmse_m"] = _rms(formation_errors(record, tr)[rows])
        if covered.any():
            lost = err[rows][~covered[rows]]
            lost = lost[~np.isnan(lost)]
            out["estimators"][alg]["no_gnss_mean_error_m"] = float(lost.mean()) if lost.size else None
            out["estimators"][alg]["no_gnss_max_error_m"] = float(lost.max()) if lost.size else None
    # Estimators that gave the same position estimates (to SAME_M): a summary says so.
    out["identical"] = [{"estimators": [a, b], "max_difference_m": d}
                        for a, b, d in identical_estimates(record, {alg: record.trace(alg) for alg in algorithms})]
    return out
