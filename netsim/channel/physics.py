"""Link-budget physics: unit conversions, log-distance path loss, thermal noise, and bit and
packet error rates of the two modulations (formulas and sources: docs/radio.md)."""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

SPEED_OF_LIGHT_M_S = 299_792_458.0
# kT at T0 = 290 K, the reference temperature of the noise-figure definition.
THERMAL_NOISE_DBM_PER_HZ = -174.0

Modulation = Literal["dbpsk", "ncfsk"]

FloatArray = NDArray[np.float64]


def _as_result(x: NDArray[np.float64]) -> float | FloatArray:
    return float(x) if x.ndim == 0 else x


def dbm_to_mw(dbm: ArrayLike) -> float | FloatArray:
    """Convert dBm to mW (element-wise)."""
    return _as_result(np.power(10.0, np.asarray(dbm, dtype=float) / 10.0))


def mw_to_dbm(mw: ArrayLike) -> float | FloatArray:
    """Convert mW to dBm (element-wise); 0 mW maps to -inf dBm."""
    with np.errstate(divide="ignore"):
        return _as_result(10.0 * np.log10(np.asarray(mw, dtype=float)))


def friis_reference_loss_db(carrier_hz: float, reference_distance_m: float = 1.0) -> float:
    """Free-space path loss at the reference distance: 20 log10(4 pi d0 f / c) (Friis, 1946)."""
    return 20.0 * math.log10(4.0 * math.pi * reference_distance_m * carrier_hz / SPEED_OF_LIGHT_M_S)


def log_distance_path_loss_db(
    distance_m: ArrayLike,
    *,
    carrier_hz: float,
    exponent: float,
    reference_distance_m: float = 1.0,
) -> float | FloatArray:
    """PL(d) = PL(d0) + 10 eta log10(d / d0) (Rappaport, Wireless Communications, eq. 4.68).

    Distances below d0 are clamped to d0: the far-field formula would otherwise
    predict a gain as d -> 0.
    """
    d = np.maximum(np.asarray(distance_m, dtype=float), reference_distance_m)
    pl0 = friis_reference_loss_db(carrier_hz, reference_distance_m)
    return _as_result(pl0 + 10.0 * exponent * np.log10(d / reference_distance_m))


def noise_floor_dbm(bandwidth_hz: float, noise_figure_db: float) -> float:
    """Thermal noise power: -174 dBm/Hz + 10 log10(B) + NF."""
    return THERMAL_NOISE_DBM_PER_HZ + 10.0 * math.log10(bandwidth_hz) + noise_figure_db


def ebn0_of(sinr_linear: FloatArray, bandwidth_hz: float, bitrate_bps: float) -> FloatArray:
    # Eb/N0 = (S / (N0 B)) * (B / R): the noise is integrated over B, a bit lasts 1/R.
    return sinr_linear * (bandwidth_hz / bitrate_bps)


def ber_from_ebn0(ebn0: FloatArray, modulation: Modulation) -> FloatArray:
    if modulation == "dbpsk":
        return 0.5 * np.exp(-ebn0)
    if modulation == "ncfsk":
        return 0.5 * np.exp(-0.5 * ebn0)
    raise ValueError(f"unknown modulation {modulation!r}")


def per_from_ber(bit_error: FloatArray, bits: ArrayLike) -> FloatArray:
    # 1 - (1 - BER)^bits, via log1p/expm1 so tiny BERs do not round PER to 0.
    return -np.expm1(np.asarray(bits, dtype=float) * np.log1p(-bit_error))


def ber(
    sinr_db: ArrayLike,
    *,
    bandwidth_hz: float = 1e6,
    bitrate_bps: float = 1e6,
    modulation: Modulation = "dbpsk",
) -> float | FloatArray:
    """Bit error rate for an AWGN-like SINR.

    DBPSK: BER = 1/2 exp(-Eb/N0); noncoherent orthogonal BFSK ("ncfsk"):
    BER = 1/2 exp(-Eb/(2 N0)) (Proakis & Salehi, Digital Communications, 5th ed.).
    Eb/N0 = SINR * B / R. The DBPSK form is the one ns-3 uses for 802.11b 1 Mbit/s
    (``DsssErrorRateModel::GetDsssDbpskSuccessRate``).
    """
    sinr = np.power(10.0, np.asarray(sinr_db, dtype=float) / 10.0)
    return _as_result(ber_from_ebn0(ebn0_of(sinr, bandwidth_hz, bitrate_bps), modulation))


def per(
    sinr_db: ArrayLike,
    bits: ArrayLike,
    *,
    bandwidth_hz: float = 1e6,
    bitrate_bps: float = 1e6,
    modulation: Modulation = "dbpsk",
) -> float | FloatArray:
    """Packet error rate PER = 1 - (1 - BER(SINR))^bits, independent bit errors.

    Pure and vectorised. Non-increasing in ``sinr_db``, non-decreasing in ``bits``.
    The keyword defaults equal :class:`LogDistance`'s defaults.
    """
    b = ber(sinr_db, bandwidth_hz=bandwidth_hz, bitrate_bps=bitrate_bps, modulation=modulation)
    return _as_result(per_from_ber(np.asarray(b, dtype=float), bits))
