"""plots/links.png: readable at 7 and 16 agents, with either radio model and faults close together;
the run plots a reader can read: identical lines dashed, jumps of an estimate left as gaps, an
inset on small target ellipses."""

import itertools

import matplotlib.image
import matplotlib.pyplot as plt
import numpy as np
import pytest
from helpers import in_process

from swarmloc.experiment import plots
from swarmloc.experiment import scenario as S

# Close together on purpose, several in one tick: their labels would overlap unless stacked.
FAULTS = [
    {"at": 5.0, "action": "cut", "link": [1, 2], "duration": 5},
    {"at": 5.0, "action": "loss", "probability": 0.3, "node": 3},
    {"at": 5.5, "action": "radio-off", "node": 4, "duration": 2},
    {"at": 6.0, "action": "partition", "groups": [[1, 2, 3]], "duration": 3},
    {"at": 6.0, "action": "jammer", "name": "j1", "position": [0, 0], "radius_m": 40, "duration": 3},
    {"at": 6.5, "action": "clear-loss", "node": 3},
]
RADIOS = {"unit-disk": {"model": "unit-disk", "range_m": 150},
          "log-distance": {"model": "log-distance", "tx_power_dbm": 10}}


def scenario(n: int, radio: str):
    """n agents on a grid 60 m apart, 15 s: some links out of range (16 agents), all in range (7)."""
    agents = [{"id": i + 1, "start": [60.0 * (i % 4), 60.0 * (i // 4)], "heading": 0.7 * i,
               "motion": {"kind": "random", "speed": 1.0, "turn_rate_std": 0.08}} for i in range(n)]
    return S.parse({"version": 1, "name": f"plots{n}", "seed": 3, "clock": {"dt": 0.5, "duration": 15},
                    "world": {"agents": agents}, "radio": RADIOS[radio], "estimators": ["ukf-dcl"],
                    "sensors": {"range": {"probability": 0.5, "max_per_step": 2, "max_range": 200}},
                    "faults": FAULTS})


@pytest.fixture(scope="module")
def runs():
    cache = {}

    def get(n, radio):
        if (n, radio) not in cache:
            cache[n, radio] = in_process(scenario(n, radio))[2].radio_arrays()
        return cache[n, radio]

    return get


@pytest.fixture
def figure(runs):
    made = []

    def make(n, radio):
        made.append(plots.links_figure(runs(n, radio)))
        made[-1].canvas.draw()
        return made[-1]

    yield make
    for fig in made:
        plt.close(fig)


def overlapping(boxes) -> list:
    return [(a, b) for a, b in itertools.combinations(boxes, 2) if a.overlaps(b)]


CASES = [(n, radio) for n in (7, 16) for radio in RADIOS]


@pytest.mark.parametrize("n,radio", CASES)
def test_links_png_written(tmp_path, runs, n, radio):
    path = plots.plot_links(tmp_path, runs(n, radio))
    assert path == tmp_path / "plots" / "links.png"
    height, width, _ = matplotlib.image.imread(path).shape
    assert width == 11 * plots.DPI and height < 20 * plots.DPI  # 16 agents: bounded rows, not 120


@pytest.mark.parametrize("n,radio", CASES)
def test_snr_panel_only_when_the_model_has_snr(figure, n, radio):
    fig = figure(n, radio)
    names = [ax.get_label() for ax in fig.axes]
    assert ("snr" in names) == (radio == "log-distance")
    assert {"faults", "links", "link rows", "receptions"} <= set(names)
    if radio == "unit-disk":
        assert "no SNR recorded" in fig.get_suptitle()


@pytest.mark.parametrize("n,radio", CASES)
def test_fault_labels_do_not_overlap(runs, figure, n, radio):
    fig = figure(n, radio)
    labels = [t for t in fig.findobj(plt.Text) if t.get_gid() == "fault-label"]
    assert sorted(int(t.get_text()) for t in labels) == list(range(1, runs(n, radio)["fault_t"].size + 1))
    boxes = [t.get_window_extent() for t in labels]
    assert not overlapping(boxes)
    # They are that close: side by side on one line, some would overlap.
    assert overlapping([b.translated(0, -b.y0) for b in boxes])


@pytest.mark.parametrize("n,radio", CASES)
def test_link_rows_readable(figure, n, radio):
    fig = figure(n, radio)
    ax = next(ax for ax in fig.axes if ax.get_label() == "link rows")
    ticks = ax.get_yticklabels()
    assert 0 < len(ticks) <= plots.MAX_LINK_ROWS
    assert min(t.get_fontsize() for t in ticks) >= 7
    assert not overlapping([t.get_window_extent() for t in ticks])
    legend = next(ax.get_legend() for ax in fig.axes if ax.get_label() == "links")
    assert [t.get_text() for t in legend.get_texts()] == ["up", "down (channel)", "down (fault)"]


def test_link_state_tells_faults_from_the_channel(runs):
    h = plots.LinkHistory(runs(16, "unit-disk"))
    pair = {tuple(p): j for j, p in enumerate(h.pairs.tolist())}
    cut = h.state[:, pair[1, 2]]
    during = (h.t >= 5.0) & (h.t < 10.0)  # the cut, and the partition inside it
    assert (cut[during] == plots.FAULT_DOWN).all() and (cut[~during] == plots.UP).all()
    # 1 at (0, 0) and 16 at (180, 180): 255 m apart, beyond the 150 m range, whatever the faults.
    assert (h.state[:, pair[1, 16]] == plots.DOWN).all()
    assert (h.state[:, pair[5, 6]] == plots.UP).all()  # 60 m apart, in none of the faults


def test_stagger_stacks_only_what_overlaps():
    assert plots.stagger([0, 1, 2.5, 0.5], [2, 3, 4, 5]) == [0, 2, 0, 1]  # placed in order of left edge
    assert plots.stagger([0, 2], [1, 3], pad=0.5) == [0, 0]
    assert plots.stagger([0, 2], [1, 3], pad=1.5) == [0, 1]


def test_a_burst_of_faults_is_grouped_within_the_level_limit():
    t = np.r_[np.full(30, 10.0), 50.0]  # 30 faults in one tick, then one alone
    labels = plots.fault_labels(t, width=lambda s: 0.5 * len(s), pad=0.1, max_levels=4)
    assert max(level for _, _, level, _ in labels) < 4
    assert sorted(i for *_, members in labels for i in members) == list(range(31))
    assert ("31", 50.0, 0, [30]) in labels
    assert any("-" in text for text, *_ in labels)


# ------------------------------------------------------------------ run plots a reader can read


@pytest.fixture(scope="module")
def quiet_run():
    """wang2019 for 10 s: no fault, infinite range, every frame delivered; ukf-dcl equals ukf-ccl."""
    from swarmloc.experiment.results import compute_references

    sc = S.load("wang2019").with_overrides(**{"clock.duration": 10.0})
    record, _, sim = in_process(sc)
    compute_references(sc, record, ["il", "ukf-ccl"])
    return record, sim.radio_arrays()


def test_identical_estimators_are_dashed_and_said_to_be(quiet_run):
    record, _ = quiet_run
    traces = {a: record.trace(a) for a in ("il", "ukf-dcl", "ukf-ccl")}
    styles = plots._line_styles(record, traces)
    assert styles["ukf-ccl"]["ls"] != "-" and "identical to UKF-DCL" in styles["ukf-ccl"]["label"]
    assert styles["ukf-dcl"]["ls"] == "-" and styles["il"]["ls"] == "-" and "identical" not in styles["il"]["label"]


def test_a_fault_free_links_plot_shows_its_traffic_not_blank_panels(quiet_run):
    _, radio = quiet_run
    fig = plots.links_figure(radio)
    names = [ax.get_label() for ax in fig.axes]
    plt.close(fig)
    assert names == ["traffic"] and "every frame delivered, no fault" in fig.get_suptitle()


def test_receptions_are_binned_so_sparse_beacons_leave_no_empty_bins():
    h = plots.LinkHistory.__new__(plots.LinkHistory)
    h.t = np.arange(601) * 0.1
    h.edges = np.r_[h.t, 60.1]
    h.outcomes = np.zeros((1, 601))
    h.outcomes[0, 10::10] = 2  # beacons once a second, ticks of 0.1 s
    counts, edges, width = h.binned_outcomes()
    assert width == pytest.approx(1.0) and (counts[0, 1:] == 2).all() and edges.size == counts.shape[1] + 1


def test_data_over_decades_get_a_log_axis():
    assert plots._wide([np.r_[np.full(50, 900.0), np.linspace(0.5, 3, 500)]])
    assert not plots._wide([np.linspace(0.5, 3, 500)])


def test_many_agents_are_one_panel_of_their_spread(tmp_path):
    from swarmloc.experiment.results import RunRecord

    n = 20
    r = RunRecord(list(range(1, n + 1)), {a: "planar-speed-heading" for a in range(1, n + 1)})
    t = np.arange(30.0)
    errors = {"dnbp": np.r_[np.full((3, n), 600.0), np.random.default_rng(0).uniform(1, 5, (27, n))]}
    path = plots._per_agent(tmp_path / "e.png", r, t, errors, "position error (m)")
    height, width, _ = matplotlib.image.imread(path).shape
    assert height < 7 * plots.DPI  # not 20 panels 2294 px high


@pytest.mark.parametrize("n", [4, 20])
def test_the_bound_is_drawn_in_each_panel_and_in_the_spread(tmp_path, monkeypatch, n):
    from swarmloc.experiment.results import RunRecord

    r = RunRecord(list(range(1, n + 1)), {a: "planar-speed-heading" for a in range(1, n + 1)})
    t = np.arange(30.0)
    rng = np.random.default_rng(1)
    errors, floor = {"il": rng.uniform(1, 5, (30, n))}, rng.uniform(0.5, 1, (30, n))
    closed = []
    monkeypatch.setattr(plots.plt, "close", closed.append)
    plots._per_agent(tmp_path / "e.png", r, t, errors, "position error (m)", floor=floor)
    (fig,) = closed
    drawn = [(ax, line) for ax in fig.axes for line in ax.get_lines() if line.get_label().startswith(plots.PCRB_LABEL)]
    if n <= plots.MAX_PANELS:  # each agent's own bound in its own panel
        assert len(drawn) == n
        for ci, (_, line) in enumerate(drawn):
            np.testing.assert_array_equal(line.get_ydata(), floor[:, ci])
    else:  # one panel: the median bound over the agents
        ((_, line),) = drawn
        np.testing.assert_allclose(line.get_ydata(), np.median(floor, axis=1))
    monkeypatch.undo()
    plt.close(fig)


def test_a_jump_of_an_estimate_breaks_its_line_and_a_jump_of_the_truth_does_not():
    truth = np.c_[np.arange(10.0), np.zeros(10)]  # 1 m a tick
    est = truth + 0.2
    est[6:] += [0.0, 400.0]  # a lost agent found again: 400 m in one tick
    drawn = plots._without_jumps(est, truth)
    assert drawn.shape == (11, 2) and np.isnan(drawn[6]).all()  # the break, between ticks 5 and 6
    np.testing.assert_array_equal(np.delete(drawn, 6, axis=0), est)  # the track itself untouched
    np.testing.assert_array_equal(plots._without_jumps(truth + 0.2, truth), truth + 0.2)
    teleported = truth.copy()
    teleported[6:] += [0.0, 400.0]  # the agent itself moved so (a replay's Vicon after a gap): followed, not cut
    assert not np.isnan(plots._without_jumps(teleported + 0.2, teleported)).any()


def target_axes(spread: float):
    """A 1 km map of platform tracks along its left and bottom edges and a target near its
    middle, estimated within `spread` m; the inset's draw callback and what it was called with."""
    fig, ax = plt.subplots(figsize=(6, 6))
    s = np.linspace(0, 1000, 50)
    platforms = np.stack([np.c_[np.zeros(50), s], np.c_[s, np.zeros(50)]], axis=1)  # (T, 2 platforms, 2)
    ax.plot(platforms[:, :, 0], platforms[:, :, 1], "k-")
    rng = np.random.default_rng(0)
    covered = np.array([420.0, 380.0]) + rng.uniform(-spread / 2, spread / 2, (200, 2))
    ax.plot(covered[:, 0], covered[:, 1], "r.")
    ax.set_aspect("equal", adjustable="datalim")
    calls = []

    def draw(inset, labels):
        calls.append(labels)
        inset.plot(covered[:, 0], covered[:, 1], "r.")

    return fig, ax, platforms, covered, draw, calls


def test_small_target_ellipses_get_an_inset_beside_them():
    fig, ax, platforms, covered, draw, calls = target_axes(spread=4.0)
    plots._target_inset(ax, np.r_[covered, [[np.nan, np.nan]]], platforms, draw)
    fig.canvas.draw()
    (inset,) = ax.child_axes
    assert calls == [False]  # drawn again inside, without a second legend's labels
    (x0, x1), (y0, y1) = inset.get_xlim(), inset.get_ylim()
    assert x0 < covered[:, 0].min() and covered[:, 0].max() < x1 and y0 < covered[:, 1].min() < covered[:, 1].max() < y1
    assert x1 - x0 < 20  # a zoom: the 4 m spread fills it, not the 1 km map
    # Where it sits hides neither the target it zooms on nor any platform track.
    box = inset.get_window_extent()
    assert not box.contains(*ax.transData.transform(covered.mean(0)))
    assert not any(box.contains(x, y) for x, y in ax.transData.transform(platforms.reshape(-1, 2)))
    plt.close(fig)


def test_targets_large_enough_to_read_on_the_map_get_no_inset():
    fig, ax, platforms, covered, draw, calls = target_axes(spread=300.0)
    plots._target_inset(ax, covered, platforms, draw)
    assert ax.child_axes == [] and calls == []
    plt.close(fig)
