"""Tests for netsim.channel: hand-computed physics, statistics and MAC behaviour."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import TypeAdapter, ValidationError

from netsim.channel import (
    SPEED_OF_LIGHT_M_S,
    ChannelConfig,
    Jammer,
    LogDistance,
    Outcome,
    RadioMedium,
    TxFrame,
    UnitDisk,
    ber,
    friis_reference_loss_db,
    noise_floor_dbm,
    per,
)

C = 299_792_458.0
Z999 = 3.2905  # two-sided 99.9 % normal quantile


def quiet(**kw: object) -> LogDistance:
    """LogDistance with every source of randomness or MAC behaviour not under test switched off."""
    base: dict[str, object] = dict(
        shadowing_sigma_db=0.0,
        processing_delay_s=0.0,
        processing_jitter_s=0.0,
        carrier_sense=False,
        unicast_retries=0,
    )
    base.update(kw)
    return LogDistance(**base)  # type: ignore[arg-type]


def mw(dbm: float) -> float:
    return 10.0 ** (dbm / 10.0)


def hand_rx_dbm(d: float, eta: float = 3.0, ptx: float = 20.0) -> float:
    pl0 = 20.0 * math.log10(4.0 * math.pi * 1.0 * 2.4e9 / C)
    return ptx - (pl0 + 10.0 * eta * math.log10(d))


def run(medium: RadioMedium, frames: list[tuple[TxFrame, float]], until: float) -> list[Outcome]:
    out: list[Outcome] = []
    for frame, t in sorted(frames, key=lambda ft: ft[1]):
        out += medium.advance(t)
        out += medium.offer(frame, t)
    out += medium.advance(until)
    return out


def for_uid(outcomes: list[Outcome], uid: int, receiver: int) -> Outcome:
    (o,) = [o for o in outcomes if o.uid == uid and o.receiver == receiver]
    return o


# --------------------------------------------------------------------------- #
# Link budget by hand
# --------------------------------------------------------------------------- #
def test_free_space_reference_loss_at_2_4_ghz() -> None:
    assert friis_reference_loss_db(2.4e9) == pytest.approx(40.05, abs=0.01)
    assert LogDistance().reference_loss_db == pytest.approx(20 * math.log10(4 * math.pi * 2.4e9 / C), abs=1e-12)
    # 5.8 GHz is 20 log10(5.8/2.4) = 7.66 dB worse.
    assert friis_reference_loss_db(5.8e9) - friis_reference_loss_db(2.4e9) == pytest.approx(7.665, abs=1e-3)


@pytest.mark.parametrize(("eta", "d", "expected"), [(3.0, 10.0, 70.05), (3.0, 100.0, 100.05), (2.0, 100.0, 80.05)])
def test_path_loss_at_10_and_100_m(eta: float, d: float, expected: float) -> None:
    assert LogDistance(path_loss_exponent=eta).path_loss_db(d) == pytest.approx(expected, abs=0.01)


def test_path_loss_clamped_below_reference_distance() -> None:
    m = LogDistance()
    assert m.path_loss_db(0.0) == pytest.approx(m.reference_loss_db)
    assert m.path_loss_db(0.5) == pytest.approx(m.reference_loss_db)


def test_noise_floor_20_mhz_nf_6() -> None:
    expected = -174.0 + 10 * math.log10(20e6) + 6.0
    assert expected == pytest.approx(-174 + 73.01 + 6, abs=0.01)
    assert noise_floor_dbm(20e6, 6.0) == pytest.approx(expected, abs=1e-9)
    assert LogDistance(bandwidth_hz=20e6, noise_figure_db=6.0).noise_floor_dbm == pytest.approx(-94.99, abs=0.01)


def test_airtime_from_size_and_bitrate() -> None:
    m = LogDistance(bitrate_bps=1e6, preamble_s=192e-6, mac_header_bytes=28)
    assert m.airtime_s(100) == pytest.approx(192e-6 + (100 + 28) * 8 / 1e6, abs=1e-15)
    assert LogDistance(bitrate_bps=250e3, preamble_s=0.0, mac_header_bytes=0).airtime_s(125) == pytest.approx(4e-3)


def test_arrival_time_is_airtime_plus_propagation() -> None:
    m = quiet()
    med = RadioMedium(m, np.random.default_rng(0))
    med.set_positions({0: [0.0, 0.0], 1: [300.0, 0.0, 0.0]})
    (o,) = run(med, [(TxFrame(1, 0, 1, 50), 2.0)], until=3.0)
    assert o.delivered
    assert o.t == pytest.approx(2.0 + m.airtime_s(50) + 300.0 / C, abs=1e-12)


def test_processing_delay_and_jitter_bounds() -> None:
    m = LogDistance(shadowing_sigma_db=0.0, processing_delay_s=1e-3, processing_jitter_s=2e-3, carrier_sense=False)
    med = RadioMedium(m, np.random.default_rng(3))
    med.set_positions({0: [0.0, 0.0], 1: [10.0, 0.0]})
    frames = [(TxFrame(k, 0, None, 10), k * 0.1) for k in range(200)]
    out = run(med, frames, until=30.0)
    lat = np.array([o.t - k * 0.1 - m.airtime_s(10) - 10.0 / C for k, o in enumerate(sorted(out, key=lambda o: o.uid))])
    assert lat.min() >= 1e-3 - 1e-12 and lat.max() < 3e-3
    assert lat.std() > 3e-4  # the jitter really is drawn


# --------------------------------------------------------------------------- #
# PER curve
# --------------------------------------------------------------------------- #
def test_per_hand_values() -> None:
    g = 10 * math.log10(3.0)
    assert ber(g) == pytest.approx(0.5 * math.exp(-3.0), rel=1e-12)
    assert per(g, 100) == pytest.approx(1 - (1 - 0.5 * math.exp(-3.0)) ** 100, rel=1e-12)
    assert per(g, 100, modulation="ncfsk") == pytest.approx(1 - (1 - 0.5 * math.exp(-1.5)) ** 100, rel=1e-12)
    # Spreading gain B/R multiplies Eb/N0.
    assert per(g, 100, bandwidth_hz=2e6) == pytest.approx(1 - (1 - 0.5 * math.exp(-6.0)) ** 100, rel=1e-12)
    assert per(g, 0) == 0.0


def test_per_monotone_in_sinr_and_length() -> None:
    sinr = np.linspace(-10, 20, 301)
    bits = np.array([8, 64, 512, 4096, 32768])
    grid = np.asarray(per(sinr[None, :], bits[:, None]))
    assert np.all(np.diff(grid, axis=1) <= 0)  # more SINR never hurts
    assert np.all(np.diff(grid, axis=0) >= 0)  # longer frames never help
    # Strictly, wherever float64 can still resolve PER from 0 and 1.
    inner = (grid > 1e-12) & (grid < 1 - 1e-12)
    both = inner[:-1] & inner[1:]
    assert both.sum() > 100 and np.all(np.diff(grid, axis=0)[both] > 0)
    both = inner[:, :-1] & inner[:, 1:]
    assert both.sum() > 100 and np.all(np.diff(grid, axis=1)[both] < 0)
    assert grid[-1, 0] == pytest.approx(1.0) and grid[0, -1] < 1e-40


def test_per_method_matches_pure_function() -> None:
    m = LogDistance(bandwidth_hz=2e6, modulation="ncfsk")
    assert m.per(5.0, 800) == per(5.0, 800, bandwidth_hz=2e6, modulation="ncfsk")


def test_derived_sensitivity_makes_header_only_frames_hopeless() -> None:
    m = LogDistance()
    snr = m.derived_sensitivity_dbm - m.noise_floor_dbm
    assert m.per(snr, m.frame_bits(0)) == pytest.approx(1 - 1e-6, abs=1e-12)


# --------------------------------------------------------------------------- #
# SINR and interference
# --------------------------------------------------------------------------- #
def _sinr_setup() -> tuple[LogDistance, RadioMedium]:
    m = quiet()
    med = RadioMedium(m, np.random.default_rng(0))
    # Receiver 0 at the origin; signal from 1 at 100 m, interferers at 150 m and 200 m.
    med.set_positions({0: [0.0, 0.0], 1: [100.0, 0.0], 2: [0.0, 150.0], 3: [0.0, -200.0]})
    return m, med


def test_sinr_one_interferer() -> None:
    m, med = _sinr_setup()
    out = run(med, [(TxFrame(1, 1, None, 100), 0.0), (TxFrame(2, 2, None, 100), 0.0)], until=1.0)
    noise = mw(-174 + 60 + 6)
    expected = 10 * math.log10(mw(hand_rx_dbm(100)) / (noise + mw(hand_rx_dbm(150))))
    assert for_uid(out, 1, 0).sinr_db == pytest.approx(expected, abs=1e-9)


def test_sinr_two_interferers_add_in_mw() -> None:
    m, med = _sinr_setup()
    frames = [(TxFrame(1, 1, None, 100), 0.0), (TxFrame(2, 2, None, 100), 0.0), (TxFrame(3, 3, None, 100), 0.0)]
    out = run(med, frames, until=1.0)
    noise = mw(-174 + 60 + 6)
    interference = mw(hand_rx_dbm(150)) + mw(hand_rx_dbm(200))
    expected = 10 * math.log10(mw(hand_rx_dbm(100)) / (noise + interference))
    assert for_uid(out, 1, 0).sinr_db == pytest.approx(expected, abs=1e-9)


def test_sinr_uses_worst_instant_not_sum_of_disjoint_interferers() -> None:
    m, med = _sinr_setup()
    # Frame 1 lasts 1.216 ms; 2 covers [0, 0.416 ms), 3 covers [0.6, 1.016 ms): never together.
    frames = [(TxFrame(1, 1, None, 100), 0.0), (TxFrame(2, 2, None, 0), 0.0), (TxFrame(3, 3, None, 0), 0.6e-3)]
    out = run(med, frames, until=1.0)
    noise = mw(-174 + 60 + 6)
    worst = max(mw(hand_rx_dbm(150)), mw(hand_rx_dbm(200)))
    expected = 10 * math.log10(mw(hand_rx_dbm(100)) / (noise + worst))
    assert for_uid(out, 1, 0).sinr_db == pytest.approx(expected, abs=1e-9)


def test_overlapping_frames_collide_where_each_alone_delivers() -> None:
    m = quiet()
    med = RadioMedium(m, np.random.default_rng(1))
    med.set_positions({0: [0.0, 0.0], 1: [-100.0, 0.0], 2: [100.0, 0.0]})
    alone = [(TxFrame(k, 1 + k % 2, 0, 100), 0.01 * k) for k in range(40)]
    out_alone = run(med, alone, until=1.0)
    assert len(out_alone) == 40 and all(o.delivered for o in out_alone)
    both = [(TxFrame(100 + k, 1 + k % 2, 0, 100), 2.0 + 0.01 * (k // 2)) for k in range(40)]
    out_both = run(med, both, until=3.0)
    assert len(out_both) == 40
    assert all(not o.delivered and o.reason == "collision" for o in out_both)
    assert all(o.sinr_db == pytest.approx(0.0, abs=0.01) for o in out_both)  # equal powers, noise negligible


def test_carrier_sense_serialises_senders_that_hear_each_other() -> None:
    m = quiet(carrier_sense=True)
    med = RadioMedium(m, np.random.default_rng(2))
    med.set_positions({0: [0.0, 0.0], 1: [-100.0, 0.0], 2: [100.0, 0.0]})
    frames = [(TxFrame(100 + k, 1 + k % 2, 0, 100), 0.01 * (k // 2)) for k in range(40)]
    out = run(med, frames, until=2.0)
    assert len(out) == 40 and all(o.delivered for o in out)


def test_hidden_terminals_still_collide_with_carrier_sense() -> None:
    m = quiet(carrier_sense=True, carrier_sense_dbm=-60.0)  # 1 and 2 (200 m apart, -89 dBm) cannot hear each other
    med = RadioMedium(m, np.random.default_rng(2))
    med.set_positions({0: [0.0, 0.0], 1: [-100.0, 0.0], 2: [100.0, 0.0]})
    frames = [(TxFrame(k, 1 + k % 2, 0, 100), 0.01 * (k // 2)) for k in range(20)]
    out = run(med, frames, until=2.0)
    assert all(o.reason == "collision" for o in out)


# --------------------------------------------------------------------------- #
# Statistics
# --------------------------------------------------------------------------- #
def _mid_range(m: LogDistance, size: int) -> tuple[float, float]:
    d = 440.0
    p = float(m.per(hand_rx_dbm(d) - m.noise_floor_dbm, m.frame_bits(size)))
    assert 0.1 < p < 0.9, p  # really a mid-range link
    return d, p


def test_delivery_ratio_matches_per_within_binomial_bound() -> None:
    m = quiet()
    d, p = _mid_range(m, 100)
    med = RadioMedium(m, np.random.default_rng(42))
    med.set_positions({0: [0.0, 0.0], 1: [d, 0.0]})
    n = 2000
    out = run(med, [(TxFrame(k, 0, None, 100), 0.01 * k) for k in range(n)], until=n * 0.01 + 1)
    assert len(out) == n
    delivered = sum(o.delivered for o in out)
    assert abs(delivered - n * (1 - p)) <= Z999 * math.sqrt(n * p * (1 - p))
    assert {o.reason for o in out if not o.delivered} == {"sinr"}


def test_unicast_retries_raise_delivery_ratio() -> None:
    n = 1000
    ratios = {}
    for retries in (0, 3):
        m = quiet(unicast_retries=retries)
        d, p = _mid_range(m, 100)
        med = RadioMedium(m, np.random.default_rng(7))
        med.set_positions({0: [0.0, 0.0], 1: [d, 0.0]})
        out = run(med, [(TxFrame(k, 0, 1, 100), 0.05 * k) for k in range(n)], until=n * 0.05 + 1)
        assert sorted(o.uid for o in out) == list(range(n))  # one final outcome per frame
        ratios[retries] = sum(o.delivered for o in out) / n
        q = p ** (retries + 1)
        assert abs(ratios[retries] - (1 - q)) <= Z999 * math.sqrt(q * (1 - q) / n)
    assert ratios[3] > ratios[0] + 0.2


def test_far_receiver_dropped_for_distance_without_drawing() -> None:
    m = quiet()
    rng = np.random.default_rng(0)
    med = RadioMedium(m, rng)
    med.set_positions({0: [0.0, 0.0], 1: [5000.0, 0.0]})
    med.offer(TxFrame(1, 0, None, 10), 0.0)
    state = rng.bit_generator.state
    (o,) = med.advance(1.0)
    assert (o.delivered, o.reason) == (False, "distance")
    assert hand_rx_dbm(5000.0) < m.derived_sensitivity_dbm
    assert rng.bit_generator.state == state


# --------------------------------------------------------------------------- #
# Jammers, half duplex, queue
# --------------------------------------------------------------------------- #
def test_jammer_cuts_links_exactly_while_active() -> None:
    m = quiet()
    med = RadioMedium(m, np.random.default_rng(5))
    med.set_positions({0: [0.0, 0.0], 1: [100.0, 0.0], 2: [-100.0, 0.0]})
    med.set_jammers([Jammer((105.0, 0.0), power_dbm=0.0, t_start=1.0, t_end=2.0)])
    frames = [(TxFrame(k, 0, None, 100), 0.002 + 0.01 * k) for k in range(300)]
    out = run(med, frames, until=4.0)
    near = {o.uid: o for o in out if o.receiver == 1}
    far = [o for o in out if o.receiver == 2]
    jammed = {uid for uid, o in near.items() if not o.delivered}
    assert jammed == set(range(100, 200))  # frames on air in [1, 2)
    assert all(near[uid].reason == "jammed" for uid in jammed)
    assert all(o.delivered for o in far)  # the jammer is local


def test_jammer_boundaries_are_half_open() -> None:
    # 128 B at 8192 bit/s with no preamble or header: exactly 0.125 s on air.
    m = quiet(bitrate_bps=8192.0, bandwidth_hz=8192.0, preamble_s=0.0, mac_header_bytes=0)
    assert m.airtime_s(128) == 0.125
    med = RadioMedium(m, np.random.default_rng(5))
    med.set_positions({0: [0.0, 0.0], 1: [100.0, 0.0]})
    med.set_jammers([Jammer((105.0, 0.0), power_dbm=0.0, t_start=1.0, t_end=2.0)])
    starts = {1: 0.875, 2: 0.9375, 3: 1.875, 4: 2.0}  # ends at t_start / straddles / ends at 2.0 / starts at t_end
    out = run(med, [(TxFrame(u, 0, None, 128), t) for u, t in starts.items()], until=3.0)
    result = {o.uid: o.delivered for o in out}
    assert result == {1: True, 2: False, 3: False, 4: True}


def test_wideband_jammer_only_counts_in_band_fraction() -> None:
    m = quiet()
    j = Jammer((10.0, 0.0, 0.0), power_dbm=10.0, t_start=0.0, t_end=1.0, band_hz=20e6)
    d = np.array([10.0])
    narrow = Jammer((10.0, 0.0), power_dbm=10.0, t_start=0.0, t_end=1.0)
    assert m.jammer_rx_power_dbm(narrow, d)[0] - m.jammer_rx_power_dbm(j, d)[0] == pytest.approx(
        10 * math.log10(20.0), abs=1e-9
    )


def test_half_duplex() -> None:
    m = quiet()
    med = RadioMedium(m, np.random.default_rng(0))
    med.set_positions({0: [0.0, 0.0], 1: [100.0, 0.0]})
    frames = [
        (TxFrame(1, 1, None, 1000), 0.0),  # 1 on air for 8.2 ms
        (TxFrame(2, 0, 1, 100), 0.001),  # 0 sends to 1 while 1 transmits
        (TxFrame(3, 0, 1, 100), 0.020),  # after 1 has finished
    ]
    out = run(med, frames, until=1.0)
    assert for_uid(out, 2, 1).reason == "half-duplex"
    assert for_uid(out, 1, 0).reason == "half-duplex"  # 0 was transmitting during 1's frame
    assert for_uid(out, 3, 1).delivered


def test_queue_overflow() -> None:
    m = quiet(queue_size=2)
    med = RadioMedium(m, np.random.default_rng(0))
    med.set_positions({0: [0.0, 0.0], 1: [10.0, 0.0], 2: [20.0, 0.0]})
    immediate = [med.offer(TxFrame(k, 0, 1, 100), 0.5) for k in range(5)]
    assert [len(x) for x in immediate] == [0, 0, 0, 1, 1]
    assert [(o.uid, o.receiver, o.reason, o.t) for x in immediate for o in x] == [
        (3, 1, "queue", 0.5),
        (4, 1, "queue", 0.5),
    ]
    bcast = med.offer(TxFrame(9, 0, None, 100), 0.5)
    assert sorted(o.receiver for o in bcast) == [1, 2] and all(o.reason == "queue" for o in bcast)
    out = med.advance(1.0)
    assert [o.uid for o in out] == [0, 1, 2] and all(o.delivered for o in out)
    a = m.airtime_s(100)
    # Frames leave one at a time, back to back.
    assert [o.t for o in out] == pytest.approx([0.5 + (k + 1) * a + 10.0 / C for k in range(3)], abs=1e-12)


# --------------------------------------------------------------------------- #
# Shadowing
# --------------------------------------------------------------------------- #
def _shadow_matrix(med: RadioMedium, n: int) -> np.ndarray:
    iu, ju = np.triu_indices(n, 1)
    return np.array([med.shadowing_db(int(a), int(b)) for a, b in zip(iu, ju)])


def test_shadowing_symmetric_and_distributed() -> None:
    m = quiet(shadowing_sigma_db=4.0)
    med = RadioMedium(m, np.random.default_rng(11))
    rng = np.random.default_rng(0)
    n = 40
    med.set_positions({i: rng.uniform(0, 500, 2) for i in range(n)})
    for a in range(n):
        for b in range(a + 1, n):
            assert med.shadowing_db(a, b) == med.shadowing_db(b, a)
    assert med.link(3, 17).rx_power_dbm == med.link(17, 3).rx_power_dbm
    s = _shadow_matrix(med, n)
    assert 3.5 < s.std() < 4.5 and abs(s.mean()) < 0.5


def test_shadowing_correlated_in_distance_moved() -> None:
    m = quiet(shadowing_sigma_db=4.0, shadowing_decorrelation_m=20.0)
    med = RadioMedium(m, np.random.default_rng(12))
    rng = np.random.default_rng(1)
    n = 40
    pos = rng.uniform(0, 500, (n, 2))
    med.set_positions(dict(enumerate(pos)))
    s0 = _shadow_matrix(med, n)

    med.set_positions(dict(enumerate(pos)))  # nobody moved: unchanged
    assert np.array_equal(_shadow_matrix(med, n), s0)

    step = rng.normal(size=(n, 2))
    step *= 0.1 / np.linalg.norm(step, axis=1, keepdims=True)
    med.set_positions(dict(enumerate(pos + step)))  # 10 cm each: rho = exp(-0.2 / 20)
    s1 = _shadow_matrix(med, n)
    assert np.corrcoef(s0, s1)[0, 1] > 0.95
    assert (s1 - s0).std() < 1.0  # theory: 4 sqrt(2 (1 - rho)) = 0.56 dB

    med.set_positions(dict(enumerate(pos + 500.0)))  # far beyond d_corr: fresh draw
    s2 = _shadow_matrix(med, n)
    assert abs(np.corrcoef(s1, s2)[0, 1]) < 0.2
    assert 3.5 < s2.std() < 4.5


def test_link_info_consistent_with_model() -> None:
    m = quiet()
    med = RadioMedium(m, np.random.default_rng(0))
    med.set_positions({0: [0.0, 0.0], 1: [300.0, 400.0], 2: [5000.0, 0.0]})
    li = med.link(0, 1)
    assert li.distance_m == pytest.approx(500.0)
    assert li.rx_power_dbm == pytest.approx(hand_rx_dbm(500.0), abs=1e-9)
    assert li.snr_db == pytest.approx(hand_rx_dbm(500.0) + 108.0, abs=1e-9)
    assert li.pdr == pytest.approx(1 - m.per(li.snr_db, m.frame_bits(100)), abs=1e-12)
    assert li.up == (li.pdr >= 0.5)
    assert med.link(0, 1, size=10).pdr > li.pdr  # shorter frames survive better
    far = med.link(0, 2)
    assert far.pdr == 0.0 and not far.up


# --------------------------------------------------------------------------- #
# Unit disk
# --------------------------------------------------------------------------- #
def test_unit_disk_delivers_iff_within_range_and_draws_nothing() -> None:
    rng = np.random.default_rng(123)
    state = rng.bit_generator.state
    med = RadioMedium(UnitDisk(range_m=100.0, latency_s=0.01), rng)
    med.set_positions({0: [0.0, 0.0], 1: [50.0, 0.0], 2: [60.0, 80.0], 3: [100.0 + 1e-9, 0.0], 4: [0.0, 0.0, 150.0]})
    frames = [(TxFrame(1, 0, None, 100), 1.0), (TxFrame(2, 0, 4, 100), 1.0), (TxFrame(3, 1, None, 100), 1.0)]
    out = run(med, frames, until=2.0)
    got = {(o.uid, o.receiver): (o.delivered, o.reason) for o in out}
    assert got == {
        (1, 1): (True, None),
        (1, 2): (True, None),  # exactly at range
        (1, 3): (False, "distance"),
        (1, 4): (False, "distance"),
        (2, 4): (False, "distance"),
        (3, 0): (True, None),
        (3, 2): (True, None),
        (3, 3): (True, None),
        (3, 4): (False, "distance"),
    }
    assert all(o.t == (1.01 if o.delivered else 1.0) for o in out)
    assert all(math.isnan(o.sinr_db) for o in out)
    assert rng.bit_generator.state == state


def test_unit_disk_never_collides() -> None:
    med = RadioMedium(UnitDisk(), np.random.default_rng(0))
    med.set_positions({i: [float(i), 0.0] for i in range(5)})
    out = run(med, [(TxFrame(i, i, None, 1000), 0.0) for i in range(5)], until=0.0)
    assert len(out) == 20 and all(o.delivered and o.t == 0.0 for o in out)


def test_unit_disk_jitter() -> None:
    rng = np.random.default_rng(5)
    state = rng.bit_generator.state
    med = RadioMedium(UnitDisk(latency_s=0.01, jitter_s=0.005), rng)
    med.set_positions({0: [0.0, 0.0], 1: [1.0, 0.0]})
    out = run(med, [(TxFrame(k, 0, 1, 10), float(k)) for k in range(50)], until=100.0)
    lat = np.array([o.t - o.uid for o in out])
    assert np.all((lat >= 0.01) & (lat < 0.015)) and lat.std() > 5e-4
    assert rng.bit_generator.state != state


# --------------------------------------------------------------------------- #
# Medium mechanics and config
# --------------------------------------------------------------------------- #
def test_advance_in_time_order_and_next_event_time() -> None:
    m = LogDistance(shadowing_sigma_db=0.0)
    med = RadioMedium(m, np.random.default_rng(9))
    assert med.next_event_time() is None
    med.set_positions({i: [10.0 * i, 0.0] for i in range(6)})
    for i in range(6):
        med.offer(TxFrame(i, i, None, 50), 0.0)
    assert med.next_event_time() == 0.0
    out: list[Outcome] = []
    while (t := med.next_event_time()) is not None:
        out += med.advance(t)
    assert len(out) == 30
    times = [o.t for o in out]
    assert times == sorted(times)
    assert med.advance(100.0) == []


def test_partial_advance_holds_back_future_arrivals() -> None:
    m = quiet(processing_delay_s=0.5)
    med = RadioMedium(m, np.random.default_rng(0))
    med.set_positions({0: [0.0, 0.0], 1: [10.0, 0.0]})
    med.offer(TxFrame(1, 0, 1, 10), 0.0)
    assert med.advance(0.1) == []
    assert med.next_event_time() == pytest.approx(0.5 + m.airtime_s(10) + 10.0 / C)
    (o,) = med.advance(1.0)
    assert o.delivered


def test_unknown_receiver_and_departed_sender_drop_as_distance() -> None:
    m = quiet()
    med = RadioMedium(m, np.random.default_rng(0))
    med.set_positions({0: [0.0, 0.0], 1: [10.0, 0.0]})
    out = run(med, [(TxFrame(1, 0, 7, 10), 0.0)], until=1.0)
    assert [(o.receiver, o.reason) for o in out] == [(7, "distance")]
    med.offer(TxFrame(2, 1, 0, 10), 1.0)
    med.set_positions({0: [0.0, 0.0]})  # 1 leaves before its frame goes out
    (o,) = med.advance(2.0)
    assert (o.uid, o.reason) == (2, "distance")


def test_same_seed_same_outcomes() -> None:
    def once() -> list[Outcome]:
        med = RadioMedium(LogDistance(), np.random.default_rng(2024))
        rng = np.random.default_rng(0)
        med.set_positions({i: rng.uniform(0, 600, 2) for i in range(8)})
        frames = [(TxFrame(k, k % 8, None if k % 3 else (k + 1) % 8, 60), 0.001 * k) for k in range(100)]
        return run(med, frames, until=5.0)

    first = once()
    assert first == once()
    assert len({o.reason for o in first}) >= 2


def test_config_rejects_unknown_fields_and_parses_discriminated_union() -> None:
    with pytest.raises(ValidationError):
        LogDistance(pathloss=3.0)  # type: ignore[call-arg]
    with pytest.raises(ValidationError):
        UnitDisk(range_m=-1.0)
    cfg = TypeAdapter(ChannelConfig).validate_python({"model": "log-distance", "path_loss_exponent": 2.5})
    assert isinstance(cfg, LogDistance) and cfg.path_loss_exponent == 2.5
    assert isinstance(TypeAdapter(ChannelConfig).validate_python({"model": "unit-disk"}), UnitDisk)
    assert SPEED_OF_LIGHT_M_S == C


def test_frame_validation() -> None:
    with pytest.raises(ValueError):
        TxFrame(1, 0, 0, 10)
    with pytest.raises(ValueError):
        TxFrame(1, 0, None, -1)
