"""swarmloc.datasets.mrclam: the UTIAS MR.CLAM loader (Leung et al., IJRR 2011) and each quirk it handles.

tests/data/mrclam_excerpt is Dataset6 cut by write_excerpt as the union of three short windows
of absolute time (the format needs no continuity; see its README.md):
  A 1248444340.5-343.5  Robot4: 3 rows with unknown barcode 50, and a 0.555 s truth gap
  B 1248444870.9-873.3  Robot4: the 2.03 s truth gap
  C 1248444946.5-947.5  Robot1: its ground truth ends at 946.976 while its odometry goes on
"""

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest

from swarmloc.datasets import mrclam as M

ROOT = Path(__file__).resolve().parents[1]
EXCERPT = ROOT / "tests" / "data" / "mrclam_excerpt"
FULL = ROOT.parent / "shared" / "data" / "mrclam" / "MRCLAM_Dataset6"
WINDOWS = [(1248444340.5, 1248444343.5), (1248444870.9, 1248444873.3), (1248444946.5, 1248444947.5)]
R4_GAPS = [(1248444341.583, 1248444342.138), (1248444871.044, 1248444873.074)]
R1_TRUTH_END = 1248444946.976


def data_rows(path: Path) -> list[list[float]]:
    return [[float(x) for x in line.split()] for line in path.read_text().splitlines()
            if line.strip() and not line.startswith("#")]


@pytest.fixture(scope="module")
def rec():
    return M.load(EXCERPT)


def copy_excerpt(tmp_path) -> Path:
    d = tmp_path / "ds"
    shutil.copytree(EXCERPT, d)
    return d


# --- the excerpt loads -------------------------------------------------------------------------

def test_excerpt_loads_every_file(rec):
    assert rec.robots == (1, 2, 3, 4, 5)
    assert rec.source == EXCERPT
    assert rec.barcodes[1] == 5 and rec.barcodes[4] == 32 and rec.barcodes[20] == 25
    assert all(rec.subject_of_barcode[b] == s for s, b in rec.barcodes.items()) and len(rec.barcodes) == 20
    assert sorted(rec.landmarks) == list(range(6, 21))
    assert rec.landmarks[6].xy == (0.58831396, -4.28264845) and rec.landmarks[6].std == (0.00004570, 0.00027395)
    for r in rec.robots:
        o, g, m = rec.odometry[r], rec.groundtruth[r], rec.measurements[r]
        raw_o = np.array(data_rows(EXCERPT / f"Robot{r}_Odometry.dat"))
        raw_g = np.array(data_rows(EXCERPT / f"Robot{r}_Groundtruth.dat"))
        assert np.array_equal(np.c_[o.t, o.v, o.w], raw_o)
        assert np.array_equal(np.c_[g.t, g.x, g.y, g.heading], raw_g)
        assert o.t.dtype == np.float64 and m.subject.dtype == np.int64
        assert set(m.subject.tolist()) <= set(range(1, 21)) - {r}
        for t in (o.t, g.t, m.t):
            assert (np.diff(t) >= 0).all()
            assert all(any(a <= x <= b for a, b in WINDOWS) for x in t)
    # t0/t_end: the span in which every robot has odometry
    assert rec.t0 == max(rec.odometry[r].t[0] for r in rec.robots)
    assert rec.t_end == min(rec.odometry[r].t[-1] for r in rec.robots)
    assert rec.relative(rec.t0) == 0.0 and rec.duration == rec.t_end - rec.t0
    assert np.spacing(1.25e9) < 0.25e-6  # float64 keeps ~0.24 us at these absolute times


def test_recording_is_frozen(rec):
    with pytest.raises(dataclasses.FrozenInstanceError):
        rec.t0 = 0.0
    with pytest.raises(ValueError):
        rec.odometry[1].v[0] = 1.0


# --- quirk 1: unknown barcodes, self measurements ---------------------------------------------

def test_unknown_barcodes_are_dropped_and_counted(rec):
    raw = data_rows(EXCERPT / "Robot4_Measurement.dat")
    unknown = [row for row in raw if int(row[1]) not in rec.subject_of_barcode]
    assert [int(row[1]) for row in unknown] == [50, 50, 50]  # the excerpt does hold them
    assert rec.dropped == {"unknown barcode": 3, "self measurement": 0}
    assert rec.dropped_by_robot[4] == {"unknown barcode": 3, "self measurement": 0}
    m = rec.measurements[4]
    assert len(m) == len(raw) - 3
    # the kept rows carry subject ids, translated from their barcodes, in file order
    kept = [row for row in raw if int(row[1]) in rec.subject_of_barcode]
    assert m.subject.tolist() == [rec.subject_of_barcode[int(row[1])] for row in kept]
    assert np.array_equal(np.c_[m.t, m.range, m.bearing], np.array(kept)[:, [0, 2, 3]])
    # at 1248444341.315 Robot4 saw barcode 7 (landmark 8, kept) and barcode 50 (dropped)
    assert m.subject[m.t == 1248444341.315].tolist() == [8]


def test_a_robot_measuring_itself_is_dropped(tmp_path):
    d = copy_excerpt(tmp_path)
    with open(d / "Robot2_Measurement.dat", "a") as f:
        f.write("1248444342.000 \t  14 \t  0.500 \t  0.100 \n")  # 14 is Robot2's own barcode
    rec = M.load(d)
    assert rec.dropped == {"unknown barcode": 3, "self measurement": 1}
    assert rec.dropped_by_robot[2]["self measurement"] == 1
    assert 2 not in rec.measurements[2].subject


# --- quirk 2: truth gaps (Robot4) --------------------------------------------------------------

def test_truth_is_nan_inside_robot4_gaps_longer_than_max_gap(rec):
    g = rec.groundtruth[4]
    for a, b in R4_GAPS:
        assert a in g.t and b in g.t and not ((g.t > a) & (g.t < b)).any()
        inside = np.linspace(a, b, 7)[1:-1]
        assert np.isnan(rec.truth_at(4, inside)).all()
        assert not rec.truth_valid(4, inside).any()
        assert np.isfinite(rec.truth_at(4, [a, b])).all()  # the samples bounding the gap are valid
        assert np.isfinite(rec.truth_at(4, [a - 0.01, b + 0.01])).all()
    # 0.555 s is only just over the 0.5 s default: a looser max_gap interpolates across it
    a, b = R4_GAPS[0]
    assert np.isfinite(rec.truth_at(4, (a + b) / 2, max_gap=0.6)).all()
    assert np.isnan(rec.truth_at(4, (R4_GAPS[1][0] + R4_GAPS[1][1]) / 2, max_gap=0.6)).all()
    # between the excerpt's windows there is no truth at all
    assert np.isnan(rec.truth_at(2, 1248444600.0)).all()


def test_truth_at_samples_and_midpoints(rec):
    g = rec.groundtruth[3]
    p = rec.truth_at(3, g.t[:50])
    assert p.shape == (50, 3)
    assert np.allclose(p, np.c_[g.x[:50], g.y[:50], g.heading[:50]], atol=1e-12)
    mid = (g.t[10] + g.t[11]) / 2
    assert np.allclose(rec.truth_at(3, mid)[:2], [(g.x[10] + g.x[11]) / 2, (g.y[10] + g.y[11]) / 2])
    assert rec.truth_at(3, mid).shape == (3,)


def synthetic(t, x, y, heading, odo_t=None, odo_v=None) -> M.Recording:
    t = np.asarray(t, float)
    odo_t = np.asarray(t if odo_t is None else odo_t, float)
    odo_v = np.zeros(odo_t.size) if odo_v is None else np.asarray(odo_v, float)
    return M.Recording(source=Path("synthetic"), robots=(1,), barcodes={1: 5}, subject_of_barcode={5: 1},
                       landmarks={}, odometry={1: M.Odometry(odo_t, odo_v, np.zeros(odo_t.size))},
                       measurements={1: M.Measurements(np.zeros(0), np.zeros(0, np.int64), np.zeros(0), np.zeros(0))},
                       groundtruth={1: M.Groundtruth(t, np.asarray(x, float), np.asarray(y, float),
                                                     np.asarray(heading, float))},
                       t0=float(odo_t[0]), t_end=float(odo_t[-1]))


def test_truth_interpolation_synthetic_heading_across_pi():
    rec = synthetic([0.0, 1.0, 2.0, 4.0], [0.0, 1.0, 3.0, 3.0], [0.0, -2.0, -2.0, 0.0], [3.0, -3.0, -2.9, 2.8])
    p = rec.truth_at(1, [0.25, 0.6, 0.75, 1.5, 2.0], max_gap=1.5)  # samples 1 s apart here
    # 3.0 -> -3.0 is +0.2832 rad the short way round (through pi), not -6 rad
    step = 2 * np.pi - 6.0
    expected_h = M.wrap([3.0 + step / 4, 3.0 + 0.6 * step, 3.0 + 3 * step / 4, -2.95, -2.9])
    assert np.allclose(p[:, 2], expected_h, atol=1e-12)
    assert p[2, 2] < 0 and p[0, 2] > 3.0  # wrapped to (-pi, pi]
    assert np.all((p[:, 2] > -np.pi) & (p[:, 2] <= np.pi))
    assert np.allclose(p[:, 0], [0.25, 0.6, 0.75, 2.0, 3.0]) and np.allclose(p[:, 1], [-0.5, -1.2, -1.5, -2.0, -2.0])
    # at the 0.5 s default every 1 s interval is a gap; the samples themselves stay valid
    assert np.isnan(rec.truth_at(1, [0.5, 1.5, 3.0])).all() and np.isfinite(rec.truth_at(1, [0.0, 1.0, 2.0, 4.0])).all()
    # the 2 s interval (2 -> 4) is a gap at max_gap 1.5, filled at max_gap 2
    assert np.isnan(rec.truth_at(1, 3.0, max_gap=1.5)).all()
    # -2.9 -> 2.8 goes the short way through -pi (-0.583 rad): the midpoint is -3.19, i.e. +3.09
    assert np.allclose(rec.truth_at(1, 3.0, max_gap=2.0), [3.0, -1.0, -2.9 - (2 * np.pi - 5.7) / 2 + 2 * np.pi])
    # no extrapolation either side
    assert np.isnan(rec.truth_at(1, [-0.01, 4.01], max_gap=10.0)).all()
    assert np.isfinite(rec.truth_at(1, [0.0, 4.0])).all()
    assert M.wrap(np.pi) == np.pi and M.wrap(-np.pi) == np.pi


# --- quirk 3: Robot1's truth ends early --------------------------------------------------------

def test_robot1_truth_ends_and_is_not_extrapolated(rec):
    a, b = rec.truth_span(1)
    assert b == R1_TRUTH_END
    o = rec.odometry[1]
    after = o.t[o.t > b]
    assert after.size > 50  # the excerpt holds Robot1 odometry past its truth end
    assert np.isnan(rec.truth_at(1, after)).all()
    assert np.isnan(rec.truth_at(1, b + 1e-3)).all()
    assert np.isfinite(rec.truth_at(1, [b - 0.01, b])).all()
    assert all(rec.truth_span(r)[1] > b for r in (2, 3, 4, 5))


# --- quirk 4: odometry leads the truth ---------------------------------------------------------

def test_lag_estimator_recovers_a_known_shift():
    rng = np.random.default_rng(3)
    lag = 0.3
    # odometry rows every 10 ms, commands held for random 0.5-3 s, speeds like MR.CLAM's
    odo_t = np.arange(0.0, 120.0, 0.01)
    change = np.cumsum(rng.uniform(0.5, 3.0, 100))
    level = rng.choice([0.0, 0.067, 0.086, 0.1, -0.05], 101)
    odo_v = level[np.searchsorted(change, odo_t)]
    # truth: the robot drives with the command delayed by `lag`, turning slowly, Vicon at ~62 Hz
    tg = np.arange(-2.0, 122.0, 0.016)
    fine = np.arange(-2.0, 122.0, 0.001)
    v_true = np.where(fine - lag < 0, 0.0, level[np.searchsorted(change, fine - lag)])
    heading = 0.05 * fine + 3.0
    x = np.cumsum(v_true * np.cos(heading)) * 0.001
    y = np.cumsum(v_true * np.sin(heading)) * 0.001
    rec = synthetic(tg, np.interp(tg, fine, x), np.interp(tg, fine, y), M.wrap(np.interp(tg, fine, heading)),
                    odo_t, odo_v)
    est = M.estimate_odometry_lag(rec, 1)
    assert est == pytest.approx(lag, abs=0.01)
    shifted = dataclasses.replace(rec, odometry={1: rec.odometry_shifted(1, est)})
    assert shifted.odometry[1].t[0] == pytest.approx(est) and np.array_equal(shifted.odometry[1].v, odo_v)
    assert M.estimate_odometry_lag(shifted, 1) == pytest.approx(0.0, abs=0.01)


def test_lag_on_the_excerpt_is_positive(rec):
    """Robot5 starts and stops within the excerpt's windows (0 -> 0.067 m/s at 342.01, 0.086 ->
    0 at 872.80): enough to see its odometry lead the truth by ~0.2 s (Dataset6 overall: 0.22)."""
    assert 0.1 < M.estimate_odometry_lag(rec, 5) < 0.4


# --- errors ------------------------------------------------------------------------------------

def one_line_error(path, *needles):
    with pytest.raises(M.MrclamError) as e:
        M.load(path)
    msg = str(e.value)
    assert "\n" not in msg and isinstance(e.value, ValueError)
    for n in needles:
        assert n in msg, msg
    return msg


def test_errors_name_the_path_and_what_is_wrong(tmp_path):
    one_line_error(tmp_path / "nope", str(tmp_path / "nope"), "no such directory")
    (tmp_path / "file").write_text("x")
    one_line_error(tmp_path / "file", "not a directory")
    empty = tmp_path / "empty"
    empty.mkdir()
    one_line_error(empty, str(empty), "Barcodes.dat is missing")

    d = copy_excerpt(tmp_path)
    (d / "Landmark_Groundtruth.dat").unlink()
    one_line_error(d, str(d), "Landmark_Groundtruth.dat is missing")
    shutil.rmtree(d)

    d = copy_excerpt(tmp_path)
    for p in d.glob("Robot*_*.dat"):
        p.unlink()
    one_line_error(d, str(d), "no RobotN_")
    shutil.rmtree(d)

    d = copy_excerpt(tmp_path)
    (d / "Robot3_Groundtruth.dat").unlink()
    one_line_error(d, "Robot3_Groundtruth.dat is missing")
    shutil.rmtree(d)


def test_parse_errors_name_the_file_and_line(tmp_path):
    d = copy_excerpt(tmp_path)
    p = d / "Robot2_Odometry.dat"
    lines = p.read_text().splitlines(keepends=True)
    lines[9] = "1248444341.5 \t 0.067\n"  # line 10: two columns instead of three
    p.write_text("".join(lines))
    one_line_error(d, f"{p}:10:", "expected 3 columns, found 2")

    lines[9] = "1248444341.5 \t 0.067 \t abc\n"
    p.write_text("".join(lines))
    one_line_error(d, f"{p}:10:", "'abc'")

    p.write_text("".join(lines[:4] + ["1 2 3 4\n"] * 3))  # every row has the wrong count
    one_line_error(d, f"{p}:5:", "expected 3 columns, found 4")

    shutil.copy(EXCERPT / "Robot2_Odometry.dat", p)
    b = d / "Barcodes.dat"
    b.write_text(b.read_text().replace("  4 \t  32 \n", "  4 \t  32 \t 7\n"))
    one_line_error(d, f"{b}:", "expected 2 columns, found 3")


# --- excerpts ----------------------------------------------------------------------------------

def test_write_excerpt_round_trip(rec, tmp_path):
    out = M.write_excerpt(rec, tmp_path / "cut", *WINDOWS[0])
    cut = M.load(out)
    assert cut.dropped["unknown barcode"] == 3  # raw lines are copied, dropped rows included
    for r in rec.robots:
        for kind in M.KINDS:
            text = (out / f"Robot{r}_{kind}.dat").read_text().splitlines()
            assert text[:4] == (EXCERPT / f"Robot{r}_{kind}.dat").read_text().splitlines()[:4]
            assert all(line.startswith("#") for line in text[:4])
        o = rec.odometry[r]
        keep = (o.t >= WINDOWS[0][0]) & (o.t <= WINDOWS[0][1])
        assert np.array_equal(cut.odometry[r].t, o.t[keep]) and np.array_equal(cut.odometry[r].w, o.w[keep])
    assert (out / "Barcodes.dat").read_bytes() == (EXCERPT / "Barcodes.dat").read_bytes()
    # the union of two windows, from a path
    out2 = M.write_excerpt(EXCERPT, tmp_path / "cut2", [WINDOWS[0][0], WINDOWS[2][0]], [WINDOWS[0][1], WINDOWS[2][1]])
    two = M.load(out2)
    assert len(two.groundtruth[1]) == sum(((rec.groundtruth[1].t >= a) & (rec.groundtruth[1].t <= b)).sum()
                                          for a, b in (WINDOWS[0], WINDOWS[2]))


def test_the_excerpt_stays_small():
    assert sum(p.stat().st_size for p in EXCERPT.iterdir()) < 250_000


# --- the whole shared dataset -----------------------------------------------------------------

@pytest.mark.skipif(not FULL.is_dir(), reason="the shared MR.CLAM Dataset6 is not beside the repository")
def test_full_dataset6():
    rec = M.load(FULL)
    assert rec.robots == (1, 2, 3, 4, 5) and len(rec.landmarks) == 15
    rows = {1: (61785, 1941, 49241), 2: (65005, 4031, 59705), 3: (61158, 5625, 56977),
            4: (52916, 2396, 61714), 5: (60567, 5378, 57467)}  # odometry, kept measurements, truth
    for r, (no, nm, ng) in rows.items():
        assert (len(rec.odometry[r]), len(rec.measurements[r]), len(rec.groundtruth[r])) == (no, nm, ng)
    assert rec.dropped == {"unknown barcode": 6, "self measurement": 0}
    assert {r: d["unknown barcode"] for r, d in rec.dropped_by_robot.items()} == {1: 1, 2: 0, 3: 2, 4: 3, 5: 0}
    assert rec.t0 == 1248444191.043 and rec.t_end == 1248445075.086
    assert rec.duration == pytest.approx(884.043, abs=1e-3)
    assert rec.truth_span(1)[1] == R1_TRUTH_END
    assert rec.odometry[1].t[-1] - R1_TRUTH_END == pytest.approx(128.127, abs=1e-3)
    g4 = rec.groundtruth[4]
    gaps = np.diff(g4.t)
    assert np.round(np.sort(gaps[gaps > 0.5]), 3).tolist() == [0.555, 2.03]
    assert max(np.diff(rec.groundtruth[r].t).max() for r in (1, 2, 3, 5)) < 0.5
    assert 0.15 < M.estimate_odometry_lag(rec, 4) < 0.3
