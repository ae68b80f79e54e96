"""Run records and the run directory (format: docs/run-format.md).

A run directory is plain files: YAML, JSON and .npz archives without pickled objects, so any
tool with numpy can read it without importing swarmloc.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from swarmloc.messages import GnssMsg, OdometryMsg, RangeMsg, Sensors
from swarmloc.node import Estimate

FORMAT_VERSION = 1


@dataclass
class Trace:
    """One estimator's means and covariances for every agent and tick."""

    ids: np.ndarray  # (N,)
    k: np.ndarray  # (T,)
    t: np.ndarray  # (T,)
    mean: np.ndarray  # (T, N, d), NaN where the agent reported nothing
    cov: np.ndarray  # (T, N, d, d)

    def save(self, path: Path) -> None:
        np.savez(path, ids=self.ids, k=self.k, t=self.t, mean=self.mean, cov=self.cov)

    @classmethod
    def load(cls, path: Path) -> "Trace":
        with np.load(path, allow_pickle=False) as f:
            return cls(f["ids"], f["k"], f["t"], f["mean"], f["cov"])


class RunRecord:
    """Everything a run produces, gathered tick by tick (in-process runner or netsim)."""

    def __init__(self, ids: list[int], d: int):
        self.ids = sorted(ids)
        self.col = {a: i for i, a in enumerate(self.ids)}
        self.d = d
        self.k: list[int] = []
        self.t: list[float] = []
        self.truth: list[np.ndarray] = []
        self.sensors: list[dict[int, Sensors]] = []
        self.est: dict[str, dict[int, dict[int, Estimate]]] = {}

    def add_tick(self, k: int, t: float, frames: dict[int, Sensors], truth: dict[int, np.ndarray]) -> None:
        self.k.append(k)
        self.t.append(t)
        self.sensors.append(frames)
        self.truth.append(np.stack([truth[a] for a in self.ids]))

    def add_estimate(self, algorithm: str, aid: int, e: Estimate) -> None:
        self.est.setdefault(algorithm, {}).setdefault(e.k, {})[aid] = e

    def trace(self, algorithm: str) -> Trace:
        T, N, d = len(self.k), len(self.ids), self.d
        mean = np.full((T, N, d), np.nan)
        cov = np.full((T, N, d, d), np.nan)
        by_k = self.est.get(algorithm, {})
        for ti, k in enumerate(self.k):
            for a, e in by_k.get(k, {}).items():
                mean[ti, self.col[a]] = e.mean
                cov[ti, self.col[a]] = e.cov
        return Trace(np.array(self.ids), np.array(self.k), np.array(self.t), mean, cov)

    def truth_array(self) -> np.ndarray:
        return np.stack(self.truth)

    # ---------------------------------------------------------------- sensor stream as arrays

    def sensor_arrays(self) -> dict[str, np.ndarray]:
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
        return {"ids": np.array(self.ids), "k": np.array(self.k), "t": np.array(self.t), "odometry": odo, "gnss": gnss,
                "range_k": rng[:, 0].astype(np.int64), "range_m": rng[:, 1].astype(np.int64),
                "range_n": rng[:, 2].astype(np.int64), "range_z": rng[:, 3], "range_std": rng[:, 4]}


def frames_from_arrays(a: dict[str, np.ndarray]) -> list[dict[int, Sensors]]:
    """Rebuild the sensor frames of a run from sensors.npz (for references computed offline)."""
    ids = [int(i) for i in a["ids"]]
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


def compute_references(scenario, record: RunRecord, which=("il", "ukf-ccl")) -> None:
    """IL and UKF-CCL from the recorded sensor stream, added to the record in place."""
    from swarmloc.estimators import CentralizedUKF
    from swarmloc.runner import make_nodes

    if "il" in which:
        nodes = make_nodes("il", scenario, record.ids)
        for frames in record.sensors:
            for a, node in nodes.items():
                node.step(frames[a])
                record.add_estimate("il", a, node.estimate())
    if "ukf-ccl" in which:
        x0 = {a: scenario.prior(a)[0] for a in record.ids}
        P0 = scenario.prior(record.ids[0])[1]
        ccl = CentralizedUKF(x0, P0, scenario.agent(record.ids[0]).model, scenario.estimation.spread)
        for frames in record.sensors:
            ccl.step(frames)
            for a in record.ids:
                record.add_estimate("ukf-ccl", a, ccl.estimate(a))


def metrics(record: RunRecord, algorithms: list[str]) -> dict:
    """Position error per estimator and agent: mean over ticks 1.., final, and mean NEES."""
    truth = record.truth_array()
    out: dict = {"ticks": len(record.k), "agents": record.ids, "estimators": {}}
    for alg in algorithms:
        tr = record.trace(alg)
        err = np.linalg.norm(tr.mean[..., :2] - truth[..., :2], axis=-1)  # (T, N)
        e = tr.mean - truth
        with np.errstate(invalid="ignore"):
            nees = np.einsum("tni,tnij,tnj->tn", e, np.linalg.inv(np.where(np.isnan(tr.cov), np.eye(record.d), tr.cov)), e)
        nees[np.isnan(err)] = np.nan
        per = {}
        for ci, a in enumerate(record.ids):
            col = err[1:, ci]
            valid = col[~np.isnan(col)]
            per[str(a)] = {
                "mean_error_m": float(valid.mean()) if valid.size else None,
                "final_error_m": float(col[-1]) if col.size and not np.isnan(col[-1]) else None,
                "mean_nees": float(np.nanmean(nees[1:, ci])) if valid.size else None,
                "ticks_missing": int(np.isnan(col).sum()),
            }
        vals = [p["mean_error_m"] for p in per.values() if p["mean_error_m"] is not None]
        out["estimators"][alg] = {"agents": per, "mean_error_m": float(np.mean(vals)) if vals else None}
    return out


def write_run(out: Path, scenario, record: RunRecord, algorithms: list[str], extra: dict | None = None,
              plots: bool = True, radio: dict[str, np.ndarray] | None = None) -> dict:
    """Write the run directory; returns the metrics written to metrics.json."""
    out = Path(out)
    (out / "estimates").mkdir(parents=True, exist_ok=True)
    (out / "scenario.yaml").write_text(scenario.to_yaml())
    np.savez(out / "truth.npz", ids=np.array(record.ids), k=np.array(record.k), t=np.array(record.t),
             state=record.truth_array())
    np.savez(out / "sensors.npz", **record.sensor_arrays())
    for alg in algorithms:
        record.trace(alg).save(out / "estimates" / f"{alg}.npz")
    m = metrics(record, algorithms)
    m["format_version"] = FORMAT_VERSION
    m["scenario"] = scenario.name
    m["seed"] = scenario.seed
    m.update(extra or {})
    (out / "metrics.json").write_text(json.dumps(m, indent=2, default=_jsonable))
    if radio is not None:
        np.savez(out / "radio.npz", **radio)
    if plots:
        from swarmloc.plots import plot_links, plot_run

        plot_run(out, record, algorithms)
        if radio is not None and radio["link_k"].size:
            plot_links(out, radio)
    return m


def _jsonable(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)
