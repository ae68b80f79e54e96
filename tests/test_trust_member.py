"""Issue 26, finding 7: one member (it holds the swarm key) sends plausible-looking but wrong
numbers in its frames.

The first tests attack from a separate process (tests/attacker.py, `member`), rewriting agent
2's frames of a lockstep wang2019 run as they are sent and handing them to their receivers as
netsim would. Every lie is refused and counted by reason (swarmloc.filters.plausibility), no
covariance is left indefinite, and the estimates stay within the bound docs/security.md
documents ("A member's damage (finding 7)") of the unattacked run's.

The rest run in process, per estimator family that takes peers' data (the estimators are
sans-I/O nodes; benchmarks/member_damage.py, `probe`): one frame of agent 2's, captured with its
receiver's state at a tick of an honest run, is made a lie whose size is bisected to the
receiver's refusal threshold; one just inside moves the receiver by no more than the derived
bound (plausibility.step_bound), one just outside is refused and counted and leaves the
receiver as if it had never come, and no covariance the receiver holds is indefinite."""

import importlib.util
import json
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from helpers import in_process
from test_trust import attack, short

# docs/security.md, "A member's damage (finding 7)": a refused lie still costs its receiver the
# genuine frame it displaced (and, for a participant that refuses a gain, its cross-covariances);
# what the estimates may then differ from the unattacked run's by, at most, in metres.
DAMAGE_BOUND_M = 25.0


def attacked(cli, tmp_path, lie: str, size: float, limit: int = 1_000_000):
    sc, path = short(tmp_path)
    out = tmp_path / "run"
    run = cli.start_run(str(path), out)
    try:
        cli.wait_tick(5, run, timeout=240)
        report = attack(cli, "member", 20, sc.clock.steps - 20, out / "logs" / "keys", lie, size, limit)
    except AssertionError as exc:
        run.kill()
        raise AssertionError(f"{exc}\n{run.communicate()}") from None
    stdout, stderr = run.communicate(timeout=300)
    assert run.returncode == 0, stderr
    m = json.loads((out / "metrics.json").read_text())
    # No early end. A lie handed over under a delivery number netsim has not used yet (the
    # attacker guesses it from the last delivery it heard) can leave a receiver one delivery
    # ahead of netsim's count until its next delivery: a lockstep tick may then wait out its
    # timeout, counted, and go on.
    assert m["ticks"] == sc.clock.steps + 1 and m["unresponsive_agents"] == []
    assert m["tick_timeouts"] <= report["frames"]
    drops = Counter()
    for aid in sc.agent_ids:
        drops.update({r: n for r, n in m["agent_stats"][str(aid)]["node_drops"].items() if r.startswith("implausible")})
    zen = np.load(out / "estimates" / "ukf-dcl.npz")
    ref = in_process(sc)[0].trace("ukf-dcl")
    return report, drops, zen["mean"], zen["cov"], ref


def attacked_landing(cli, tmp_path, lie: str, size: float, limit: int, attempts: int = 3):
    """`attacked`, run again (at most `attempts` runs) while no lie reached a node. A lie is handed
    over racing netsim's genuine frame under the same delivery number; on a busy machine the
    genuine one can win every race (the lie then refused as a copy), and such a run tests
    nothing. Every run's damage is held to the bound."""
    for i in range(attempts):
        where = tmp_path / f"attempt-{i}"
        where.mkdir()
        got = attacked(cli, where, lie, size, limit)
        assert_within_bound(*got[2:])
        if got[1]:
            break
    return got


def assert_within_bound(mean, cov, ref) -> float:
    """No covariance indefinite (or asymmetric) on any agent-tick, and every position within
    DAMAGE_BOUND_M of the unattacked run's. Returns the largest shift."""
    ok = ~np.isnan(cov).any(axis=(-1, -2))
    C = cov[ok]
    assert np.allclose(C, np.swapaxes(C, -1, -2), rtol=1e-9, atol=1e-12)
    assert np.linalg.eigvalsh(C).min() > 0
    shift = np.linalg.norm(mean[..., :2] - ref.mean[..., :2], axis=-1)
    worst = float(np.nanmax(shift))
    assert worst <= DAMAGE_BOUND_M, worst
    return worst


@pytest.mark.slow
def test_commits_with_huge_y_and_nu_are_refused(cli, tmp_path):
    """Y = nu = 1e11 in every commit of agent 2's: the issue saw every agent 1e12 m off. Each
    lie that reaches a node is refused at once (the innovation is beyond the chi-square bound)."""
    report, drops, mean, cov, ref = attacked_landing(cli, tmp_path, "yn", 0, 20)
    assert 10 <= report["frames"] <= 20  # as many as the run had before its end
    assert drops["implausible-innovation"] >= 1 and set(drops) == {"implausible-innovation"}, drops
    assert drops["implausible-innovation"] <= report["frames"]
    assert_within_bound(mean, cov, ref)


@pytest.mark.slow
def test_commits_with_gains_x100_are_refused(cli, tmp_path):
    """Twelve of agent 2's commits (the issue: three) with every gain x100: the issue saw estimates 56 km off and
    covariances indefinite. A participant forms its own gain from its own rows and refuses one
    that differs (and becomes an orphan, so its cross-covariances are rebuilt)."""
    report, drops, mean, cov, ref = attacked_landing(cli, tmp_path, "gains", 100.0, 12)
    assert 6 <= report["frames"] <= 12  # as many as the run had before its end
    # A commit goes on down its tree before it is applied: each participant below refuses it too.
    # Not every lie reaches a node: one that comes after the genuine frame is a duplicate.
    assert 1 <= drops["implausible-gain"] <= report["frames"] * 3 and set(drops) == {"implausible-gain"}, drops
    assert_within_bound(mean, cov, ref)


@pytest.mark.slow
def test_a_range_1km_off_is_refused(cli, tmp_path):
    """Agent 2's ranges 1 km longer in its chain starts: the issue saw estimates 1,171 m off.
    The measured platform refuses each (NIS beyond the bound) and the chain runs empty."""
    report, drops, mean, cov, ref = attacked_landing(cli, tmp_path, "range", 1000.0, 20)
    assert 10 <= report["frames"] <= 20  # as many as the run had before its end
    assert drops["implausible-innovation"] >= 1 and set(drops) == {"implausible-innovation"}, drops
    assert_within_bound(mean, cov, ref)


# ------------------------------------------------------------------ in process, per family

_spec = importlib.util.spec_from_file_location(
    "member_damage", Path(__file__).resolve().parent.parent / "benchmarks" / "member_damage.py")
damage = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(damage)


@pytest.mark.parametrize("probe", damage.PROBES, ids=[p["family"] for p in damage.PROBES])
def test_a_lie_just_inside_the_bound_moves_the_receiver_at_most_the_derived_bound_one_outside_is_refused(probe):
    r = damage.run_probe(probe)
    assert r["honest_refused"] == {}, r  # the genuine frame passes every check
    assert np.isfinite(r["threshold"]), r  # some size is refused
    assert r["inside_refused"] == {}, r
    assert sum(r["outside_refused"].values()) >= 1, r
    assert set(r["outside_refused"]) <= {"implausible-innovation", "implausible-shift", "implausible-information",
                                         "implausible-covariance"}, r
    assert r["outside_unchanged"], r  # refused: as if it had never come
    assert r["min_eig"] >= 0.0, r
    if np.isfinite(r["bound"]):
        assert r["move"] <= r["bound"] * (1 + 1e-9), r


@pytest.mark.parametrize("alg,lie,size,over", [
    ("ukf-dcl", "range", 100.0, {}), ("ukf-dcl", "commit-nu", 60.0, {}), ("ukf-dcl", "token-nu", 30.0, {}),
    ("rdl", "request-x", 20.0, {"estimator.name": "rdl"}), ("rdl", "commit-x", 20.0, {"estimator.name": "rdl"}),
])
def test_a_whole_run_of_lies_inside_the_bound_leaves_no_covariance_indefinite(alg, lie, size, over):
    """Every frame of a kind agent 2 sends a lie just inside the bound, wang2019 for 30 s: every
    covariance positive definite on every agent-tick, and the shift within the largest measured
    (docs/security.md: the sweep's maxima, at 100 s)."""
    sc = damage.S.load("wang2019").with_overrides(**{"clock.duration": 30.0, **over})
    fn = next(sw["fn"] for sw in damage.SWEEPS if sw["alg"] == alg and sw["lie"] == lie)
    ref, _ = damage.run(sc, alg)
    tr, drops = damage.run(sc, alg, fn, size)
    assert damage.min_eig(tr) > 0.0
    worst, _ = damage.shifts(sc, tr, ref)
    assert worst <= MEASURED_MAX_M[(alg, lie)], worst


# The largest shift measured for each lie over its sweep (benchmarks/member_damage.py sweep,
# 100 s; docs/security.md): a whole run's damage is measured, not derived.
MEASURED_MAX_M = {("ukf-dcl", "range"): 130.0, ("ukf-dcl", "commit-nu"): 300.0, ("ukf-dcl", "token-nu"): 300.0,
                  ("rdl", "request-x"): 450.0, ("rdl", "commit-x"): 300.0}
