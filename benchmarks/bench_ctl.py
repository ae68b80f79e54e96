"""Cost of the CTL step of CSL-CTL (Wang et al. 2022) against the number of agents N.

Usage: python benchmarks/bench_ctl.py [--sizes 4 8 16] [--budget 2.0] [--min-reps 30] [--seed 1] [--out PATH]

One synthetic, realistic problem per N, one target at the origin: N planar-pose agents
(x, y, heading) at 250-350 m from it (within the 400 m detection range), bearings spread over
120 deg, heading at it; a joint prior over the 3N agent states and the target from a
correlated covariance (position std 2-5 m, heading std 0.05 rad, target std 3 m, random
correlations from a rank-3 common factor plus an independent part), the prior mean drawn
around the truth from it; round(0.8 N) agents range the target (std 10 m).

Timed, each as the median over repetitions (at least --min-reps, more until --budget seconds
per cell) of a fresh copy of the same problem, with `ut_noise` True (sigma points over prior
and range noise: 2 (2(N+1) + E) + 1 majorizations) and False (prior only, the paper's
4(N+1) + 1):
  - `ctl.estimate` alone, on the problem `JointCslCtl.localize_targets` hands it (positions of
    the agents and the target, their marginal covariance, the target ranges);
  - `JointCslCtl.localize_targets` (that plus building the problem, the NIS of the target
    ranges, and carrying the headings along by regression: `_with_rest`);
  - `JointCslCtl.step`: a whole tick, UKF time update of the 3N + 2 state, one range between
    two agents (std 5 m), then the CTL step.
Two cases for the target: `tracked` (already in the joint state with a prior, the steady
state: every tick after the first fix) and `first fix` (no prior: started by trilateration;
estimate/localize_targets only). Also: iterations of the central majorization, the number of
majorization runs, sigma-point runs that hit max_iter (the estimator's max_iter 100, tol 1e-9).
Markdown to stdout (and --out). One BLAS thread. Not a test.
"""

from __future__ import annotations

from swarmloc.process import pin_blas

pin_blas()  # before numpy loads

import argparse  # noqa: E402
import copy  # noqa: E402
import os  # noqa: E402
import shlex  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from datetime import datetime, timezone  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from machine import code_version, cpu_model  # noqa: E402  benchmarks/machine.py

from swarmloc.estimators.ctl import majorization as ctl  # noqa: E402
from swarmloc.estimators.ctl.csl_ctl import JointCslCtl, trilaterate  # noqa: E402
from swarmloc.wire.messages import OdometryMsg, RangeMsg, Sensors, TargetRangeMsg  # noqa: E402

TARGET_STD, RANGE_STD, AGENT_RANGE_STD = 10.0, 10.0, 5.0
DT, SPEED = 0.5, 1.0
MAX_ITER, TOL = 100, 1e-9  # JointCslCtl's defaults (csl-ctl settings)


def log(msg: str) -> None:
    print(f"[{datetime.now():%H:%M:%S}] {msg}", file=sys.stderr, flush=True)


class Problem:
    """Truth, the joint prior (agents' planar-pose blocks, then the target's position) and the
    tick's frames for N agents."""

    def __init__(self, n: int, seed: int):
        rng = np.random.default_rng([seed, n])
        self.n = n
        bearing = np.pi + rng.uniform(-np.pi / 3, np.pi / 3, n)
        dist = rng.uniform(250.0, 350.0, n)
        pos = dist[:, None] * np.c_[np.cos(bearing), np.sin(bearing)]
        head = bearing - np.pi  # at the target (origin)
        self.truth = np.c_[pos, head]  # (n, 3)
        self.target = np.zeros(2)
        dim = 3 * n + 2
        std = np.concatenate([np.r_[rng.uniform(2.0, 5.0, 2), 0.05] for _ in range(n)] + [np.full(2, 3.0)])
        F = rng.normal(size=(dim, 3))
        C = F @ F.T + np.diag(rng.uniform(1.0, 3.0, dim))
        s = np.sqrt(np.diag(C))
        C = C / np.outer(s, s)
        self.P = C * np.outer(std, std)
        truth_vec = np.r_[self.truth.ravel(), self.target]
        self.x = truth_vec + np.linalg.cholesky(self.P) @ rng.normal(size=dim)
        m = max(3, int(round(0.8 * n)))
        self.rangers = sorted(rng.choice(n, m, replace=False).tolist())
        self.z = {i: float(np.linalg.norm(pos[i] - self.target) + RANGE_STD * rng.normal()) for i in self.rangers}
        self.z12 = float(np.linalg.norm(pos[0] - pos[1]) + AGENT_RANGE_STD * rng.normal())
        self.ids = list(range(1, n + 1))

    def frames(self, k: int, with_odometry: bool, agent_range: bool, target_ranges: bool = True) -> dict[int, Sensors]:
        out = {}
        for i, a in enumerate(self.ids):
            odo = OdometryMsg(DT, SPEED, 0.0, 0.5, 0.0, 0.0, 0.05) if with_odometry else None
            ranges = [RangeMsg(2, self.z12, AGENT_RANGE_STD)] if agent_range and a == 1 else []
            targets = [TargetRangeMsg(0, self.z[i], RANGE_STD)] if target_ranges and i in self.rangers else []
            out[a] = Sensors(k, k * DT, odo, ranges, targets=targets)
        return out

    def joint(self, ut_noise: bool, tracked: bool) -> JointCslCtl:
        """A JointCslCtl whose state is this prior (tracked: with the target; else agents only)."""
        j = JointCslCtl({a: self.x[3 * i:3 * i + 3] for i, a in enumerate(self.ids)}, np.eye(3), "planar-pose",
                        tol=TOL, max_iter=MAX_ITER, ut_noise=ut_noise)
        n3 = 3 * self.n
        if tracked:
            j.x, j.P = self.x.copy(), self.P.copy()
            j.offset[("target", 0)], j.size[("target", 0)] = n3, 2
            j.targets.append(0)
        else:
            j.x, j.P = self.x[:n3].copy(), self.P[:n3, :n3].copy()
        j.k = 10
        j.nis = {a: [] for a in self.ids}  # step() sets it before localize_targets
        return j

    def ctl_problem(self, tracked: bool):
        """What localize_targets passes to ctl.estimate: node order agents, then the target."""
        n = self.n
        pos_idx = np.r_[np.concatenate([np.arange(3 * i, 3 * i + 2) for i in range(n)]),
                        np.arange(3 * n, 3 * n + 2) if tracked else np.zeros(0, int)]
        prior = np.full((n + 1, 2), np.nan)
        prior[: pos_idx.size // 2] = self.x[pos_idx].reshape(-1, 2)
        Ppp = self.P[np.ix_(pos_idx, pos_idx)]
        x0 = prior.copy()
        if not tracked:
            x0[n] = trilaterate(prior[self.rangers], np.array([self.z[i] for i in self.rangers]))
        edges = ctl.Edges(np.array(self.rangers), np.full(len(self.rangers), n), np.array([self.z[i] for i in self.rangers]),
                          np.full(len(self.rangers), RANGE_STD))
        has_prior = np.arange(n + 1) < (n + 1 if tracked else n)
        return prior, Ppp, edges, x0, has_prior


def timed(make, call, budget: float, min_reps: int) -> tuple[np.ndarray, object]:
    """Median-ready times (s) of call(make()) over fresh inputs; the last result."""
    times, start, out = [], time.perf_counter(), None
    while len(times) < min_reps or (time.perf_counter() - start < budget and len(times) < 5000):
        arg = make()
        t0 = time.perf_counter()
        out = call(arg)
        times.append(time.perf_counter() - t0)
    return np.array(times), out


def ms(t: np.ndarray) -> str:
    return f"{np.median(t) * 1e3:.2f}"


def bench(n: int, seed: int, budget: float, min_reps: int) -> list[dict]:
    pb = Problem(n, seed)
    rows = []
    for tracked in (True, False):
        prior, Ppp, edges, x0, has_prior = pb.ctl_problem(tracked)
        for ut_noise in (True, False):
            t_est, res = timed(lambda: None, lambda _: ctl.estimate(prior, Ppp, edges, x0, has_prior=has_prior, noise=ut_noise,
                                                                     tol=TOL, max_iter=MAX_ITER), budget, min_reps)
            frames = pb.frames(11, False, False)
            base = pb.joint(ut_noise, tracked)

            def loc(j):
                j.localize_targets(frames)
                return j
            t_loc, j = timed(lambda: copy.deepcopy(base), loc, budget, min_reps)
            row = {"n": n, "case": "tracked" if tracked else "first fix", "ut_noise": ut_noise, "E": len(edges),
                   "dim": int(Ppp.shape[0]), "est": t_est, "loc": t_loc, "iters": res.majorized.iterations,
                   "converged": res.majorized.converged, "runs": res.runs, "sigma_unconv": res.sigma_unconverged,
                   "loc_stats": dict(j.stats), "err": float(np.linalg.norm(res.x[n] - pb.target)),
                   "sd": float(np.sqrt(np.trace(res.cov[2 * n:, 2 * n:]))), "step": None, "step0": None}
            if tracked:
                fr = pb.frames(11, True, True)

                def step(jj):
                    jj.step(fr, 11)
                    return jj
                t_step, js = timed(lambda: copy.deepcopy(base), step, budget, min_reps)
                row["step"], row["step_stats"] = t_step, dict(js.stats)
                fr0 = pb.frames(11, True, True, target_ranges=False)

                def step0(jj):
                    jj.step(fr0, 11)
                    return jj
                row["step0"] = timed(lambda: copy.deepcopy(base), step0, budget, min_reps)[0]
            rows.append(row)
            log(f"  N={n} {row['case']} ut_noise={ut_noise}: estimate {ms(t_est)} ms, localize_targets {ms(t_loc)} ms"
                + (f", step {ms(row['step'])} ms" if row["step"] is not None else "") + f" ({len(t_loc)} reps)")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[4, 8, 16])
    ap.add_argument("--budget", type=float, default=2.0, help="seconds of repetitions per timed cell (beyond --min-reps)")
    ap.add_argument("--min-reps", type=int, default=30)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    command = "python " + " ".join(shlex.quote(x) for x in sys.argv)
    started_at, t0, load0 = datetime.now(timezone.utc), time.perf_counter(), os.getloadavg()
    rows = []
    for n in a.sizes:
        log(f"N = {n}")
        rows += bench(n, a.seed, a.budget, a.min_reps)
    load1 = os.getloadavg()
    md = ["## CSL-CTL: cost of the CTL step against the number of agents", "",
          f"Machine: {cpu_model()}, {os.cpu_count()} CPUs, Python {sys.version.split()[0]}, numpy {np.__version__}, "
          f"one BLAS thread; code {code_version()}; {started_at:%Y-%m-%d %H:%M} UTC.  ",
          f"Command: `{command}`; whole benchmark {time.perf_counter() - t0:.0f} s; load average 1/5/15 min "
          f"{load0[0]:.2f}/{load0[1]:.2f}/{load0[2]:.2f} at start, {load1[0]:.2f}/{load1[1]:.2f}/{load1[2]:.2f} at end.", "",
          "One target; N planar-pose agents 250-350 m from it, round(0.8 N) of them range it (std 10 m); correlated "
          "joint prior (position std 2-5 m, heading 0.05 rad, target 3 m). Times are medians (ms) over repetitions on "
          "fresh copies. `estimate`: `ctl.estimate` alone; `localize_targets`: `JointCslCtl.localize_targets` (problem "
          "set-up, NIS, estimate, headings by regression); `step`: `JointCslCtl.step`, a whole tick (UKF time update of "
          "the 3N + 2 state, one range between two agents, CTL); `step w/o CTL`: the same tick without target ranges (KF-CSL alone). dim: prior dimensions of the CTL problem (2 per node "
          "with a prior); E: target ranges; runs: majorizations (central + sigma points); iters: accepted steps of the "
          "central majorization (tol 1e-9, max_iter 100); unconv: sigma-point runs that hit max_iter. "
          "err / sd: the target's error (m) and sqrt(trace cov) (m) of this one draw.", "",
          "| N | target | ut_noise | dim | E | runs | iters | unconv | estimate ms | localize_targets ms | step ms | step w/o CTL ms | "
          "ms per majorization | err m | sd m | ctl_failed |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r['n']} | {r['case']} | {r['ut_noise']} | {r['dim']} | {r['E']} | {r['runs']} | {r['iters']}"
                  f"{'' if r['converged'] else ' (max)'} | {r['sigma_unconv']} | {ms(r['est'])} | {ms(r['loc'])} | "
                  f"{ms(r['step']) if r['step'] is not None else '-'} | "
                  f"{ms(r['step0']) if r['step0'] is not None else '-'} | {np.median(r['est']) * 1e3 / r['runs']:.3f} | "
                  f"{r['err']:.2f} | {r['sd']:.2f} | {r['loc_stats']['ctl_failed']} |")
    text = "\n".join(md) + "\n"
    print(text)
    if a.out is not None:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(text)


if __name__ == "__main__":
    main()
