"""The run summary says what is good and what is not: the columns' roles, identical estimators,
an estimator worse than the baseline and whether its formation says why, drops in words (at the
end, and live while a real-time run goes), the ground station; complete in a pipe. And the
metrics behind it (identical_estimates, formation_errors)."""

import io
import json
import queue
import sys
import time
from types import SimpleNamespace

import numpy as np
import pytest

from agents import launcher, summary
from swarmloc.experiment.results import RunRecord, Trace, formation_errors, identical_estimates


def agent(mean, final):
    return {"mean_error_m": mean, "final_error_m": final, "max_error_m": final, "rmse_m": mean,
            "heading_rmse_rad": 0.1, "nees": {"mean": 3.2, "bounds": [2.9, 3.1], "inside": False}}


def estimator(mean, formation=None, **agents):
    return {"agents": {a: agent(*v) for a, v in agents.items()}, "mean_error_m": mean, "rmse_m": mean,
            "heading_rmse_rad": 0.2, "formation_rmse_m": formation,
            "nees": {"mean": 3.2, "bounds": [2.9, 3.1], "inside": False}, "nis": None}


def metrics(**changes) -> dict:
    m = {"scenario": "wang2022", "seed": 11, "ticks": 601, "agents": [1, 2], "estimator": "csl-ctl",
         "wall_time_s": 6.0, "ticks_per_s": 100.0, "transport": "zenoh-lockstep",
         "estimators": {"il": estimator(25.2, 26.4, **{"1": (20.0, 40.0), "2": (30.4, 50.0)}),
                        "ukf-ccl": estimator(36.9, 7.4, **{"1": (35.0, 60.0), "2": (38.8, 70.0)}),
                        "csl-ctl": estimator(14.7, 5.0, **{"1": (14.0, 16.0), "2": (15.4, 17.0)}),
                        "il-ctl": estimator(25.2, 26.4, **{"1": (20.0, 40.0), "2": (30.4, 50.0)})},
         "identical": [{"estimators": ["il", "il-ctl"], "max_difference_m": 0.0}],
         "radio": {"delivered": 7212, "dropped": {"distance": 18177, "collision": 3}}, "ground_stations": [],
         "agent_stats": {}}
    m.update(changes)
    return m


def printed(tmp_path, monkeypatch, m: dict) -> str:
    """print_summary as a pipe receives it: stdout is not a terminal."""
    (tmp_path / "metrics.json").write_text(json.dumps(m))
    out = io.StringIO()
    monkeypatch.setattr(sys, "stdout", out)
    from swarmloc.process import console

    summary.print_summary(tmp_path, [], console())
    return out.getvalue()


def test_the_summary_marks_roles_and_says_what_is_good(tmp_path, monkeypatch):
    text = printed(tmp_path, monkeypatch, metrics())
    assert "…" not in text
    header = [line for line in text.splitlines() if "┃" in line]
    assert "baseline" in header[1] and "reference" in header[1] and "agents" in header[1]
    assert "il and il-ctl gave the same position estimates (exactly)" in text
    # the reference is worse than dead reckoning: said in words, with the formation that explains it
    assert "ukf-ccl (reference) is worse than the baseline il here: 36.9 m against 25.2 m" in text
    assert "Its formation is better (7.4 m against 26.4 m" in text
    assert "csl-ctl (agents) is worse" not in text  # it is better than both baselines
    assert "il-ctl" not in text.split("il and il-ctl gave")[1].split("\n", 1)[1]  # the copy is not a second baseline
    assert "18180 dropped (18177 out of radio range, 3 collided)" in text and "{" not in text
    assert "position RMSE (m)" in text and "heading RMSE (rad)" in text  # the per-agent rows are named


def test_a_worse_estimator_whose_formation_is_not_better_gets_no_explanation():
    m = metrics()
    m["estimators"]["ukf-ccl"]["formation_rmse_m"] = 30.0
    notes = summary.summary_notes(m, ["il", "ukf-ccl", "csl-ctl", "il-ctl"])
    worse = [n for n in notes if n.startswith("ukf-ccl")]
    assert len(worse) == 1 and "formation" not in worse[0]


def test_the_ground_station_is_named():
    notes = summary.summary_notes(metrics(ground_stations=[4]), ["il"])
    assert any(n.startswith("agent 4: ground station") for n in notes)


@pytest.mark.parametrize("transport, warned", [("zenoh-realtime", True), ("zenoh-lockstep", False)])
def test_dropped_measurements_are_summarized_and_warned_in_real_time(transport, warned):
    stats = {"1": {"measurements_dropped": 900, "measurements_used": 100},
             "2": {"measurements_dropped": 100, "measurements_used": 900}}
    notes = summary.measurement_drops(metrics(agent_stats=stats, transport=transport))
    assert len(notes) == 1 and "dropped 1000 of their 2000 measurements (50%)" in notes[0]
    assert ("not keeping up" in notes[0]) == warned


def test_a_few_drops_are_counted_not_warned():
    stats = {"1": {"measurements_dropped": 5, "measurements_used": 995}}
    notes = summary.measurement_drops(metrics(agent_stats=stats, transport="zenoh-realtime"))
    assert "(0%)" in notes[0] or "(1%)" in notes[0]
    assert "not keeping up" not in notes[0]
    assert summary.measurement_drops(metrics(agent_stats={"1": {"measurements_dropped": 0}})) == []


def test_the_live_drop_warning_says_when_the_agents_fall_behind(monkeypatch):
    """_DropWatch, the warning on the console while a real-time run goes: each round is the
    agents' counters so far, as ControlClient.agents() returns them (here fed by the test);
    it speaks when a large share of what came since the last round was dropped."""
    feed: queue.Queue = queue.Queue()

    class Agents:
        def __init__(self, swarm, connect):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def agents(self):
            stats = feed.get(timeout=10)
            if stats is None:
                raise ConnectionError("the session closed")
            return SimpleNamespace(stats=stats)

    monkeypatch.setattr("agents.control.ControlClient", Agents)
    monkeypatch.setattr(launcher._DropWatch, "EVERY_S", 0.0)
    watch = launcher._DropWatch("s", "tcp/127.0.0.1:7447")

    def poll(stats: dict) -> str | None:
        feed.put(stats)
        end = time.monotonic() + 10
        while watch.rounds.empty():
            assert time.monotonic() < end, "the watch's thread took no round"
            time.sleep(0.005)
        return watch.check()

    def counters(**agents):  # agent: (dropped, used) so far
        return {a: {"measurements_dropped": d, "measurements_used": u, "k": 10} for a, (d, u) in agents.items()}

    try:
        assert watch.check() is None  # no round yet
        assert poll({"1": {"k": 10}}) is None  # agents that drop nothing by design (no chains) report no drops
        assert poll(counters(a=(0, 50), b=(1, 49))) is None  # 1 %
        assert poll(counters(a=(5, 52), b=(6, 50))) is None  # 10 of 13 since: too few to judge
        warning = poll(counters(a=(65, 72), b=(66, 70)))  # 120 dropped and 40 used since the last round
        assert warning is not None and "dropped 75% of their measurements" in warning
        assert "--speed" in warning and "lockstep" in warning  # what to do about it
        assert poll(counters(a=(200, 80), b=(200, 80))) is None  # as bad, but it said so a moment ago
        monkeypatch.setattr(launcher._DropWatch, "QUIET_S", 0.0)
        assert "dropped 100%" in poll(counters(a=(300, 80), b=(300, 80)))
    finally:
        feed.put(None)  # the client fails: the watch ends quietly, the run does not depend on it
        watch.close()
    assert not watch.thread.is_alive()


# ------------------------------------------------------------------ the metrics behind it


def record_with(truth: np.ndarray, estimates: dict[str, np.ndarray]) -> tuple[RunRecord, dict]:
    """A record of N planar agents over T ticks with the given truth (T, N, 2) and estimates."""
    T, N, _ = truth.shape
    r = RunRecord(list(range(1, N + 1)), {a: "planar-speed-heading" for a in range(1, N + 1)})
    r.k, r.t = list(range(T)), [float(k) for k in range(T)]
    r.truth = [np.pad(truth[k], ((0, 0), (0, r.d - 2)), constant_values=0.0) for k in range(T)]
    traces = {}
    for alg, mean in estimates.items():
        m = np.full((T, N, r.d), np.nan)
        m[:, :, :2] = mean
        traces[alg] = Trace(np.array(r.ids), np.array(r.k), np.array(r.t), m, np.full((T, N, r.d, r.d), np.nan),
                            np.array(r.dims))
    return r, traces


def test_the_formation_error_leaves_out_the_common_shift_and_turn():
    rng = np.random.default_rng(1)
    truth = rng.uniform(-100, 100, (20, 5, 2))
    c, s = np.cos(0.3), np.sin(0.3)
    moved = truth @ np.array([[c, s], [-s, c]]) + [40.0, -25.0]  # the whole swarm turned and shifted
    bent = truth + rng.normal(0, 2.0, truth.shape)  # each agent off on its own
    r, traces = record_with(truth, {"moved": moved, "bent": bent})
    assert np.nanmax(formation_errors(r, traces["moved"])) < 1e-9
    position = np.linalg.norm(moved - truth, axis=-1).mean()
    assert position > 20  # far off, yet the shape is exact
    f = formation_errors(r, traces["bent"])
    assert 1.0 < np.nanmean(f) < 3.0  # the agents' own errors are what is left (2 m each, less what a fit absorbs)


def test_identical_estimates_are_found_and_near_ones_are_not():
    rng = np.random.default_rng(2)
    truth = rng.uniform(-10, 10, (10, 3, 2))
    a = truth + rng.normal(0, 1, truth.shape)
    r, traces = record_with(truth, {"a": a, "b": a + 1e-12, "c": a + 1e-3, "d": a.copy()})
    pairs = identical_estimates(r, traces)
    assert [(x, y) for x, y, _ in pairs] == [("a", "b"), ("a", "d")]  # d is paired with a, not again with b
    assert max(d for *_, d in pairs) < 1e-9


def test_ticks_without_truth_leave_that_agent_out_of_the_formation():
    rng = np.random.default_rng(3)
    truth = rng.uniform(-50, 50, (6, 4, 2))
    est = truth + rng.normal(0, 1.0, truth.shape)
    r, traces = record_with(truth, {"a": est})
    r.truth[2][1, :2] = np.nan  # a replay's Vicon gap
    f = formation_errors(r, traces["a"])
    assert np.isfinite(f).all()
