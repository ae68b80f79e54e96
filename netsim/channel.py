"""Radio physics of netsim: which receivers get each frame, when, or why not.

The module is transport-free and deterministic given a ``numpy.random.Generator``:
the emulator feeds it positions (:meth:`RadioMedium.set_positions`), frames
(:meth:`RadioMedium.offer`) and the clock (:meth:`RadioMedium.advance`), and it
returns one :class:`Outcome` per (frame, receiver).

Two channel models implement :class:`ChannelModel`:

* :class:`UnitDisk` - delivered iff within range; no airtime, no interference,
  draws nothing from the rng unless jitter is enabled.
* :class:`LogDistance` - log-distance path loss with correlated log-normal
  shadowing, thermal noise, SINR with worst-case interference over the airtime,
  DBPSK (or noncoherent BFSK) bit errors, per-sender FIFO queue, optional
  carrier sense and unicast retries.

The formulas, defaults and their sources are documented in ``docs/radio.md``.
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Annotated, Literal, Protocol, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

__all__ = [
    "SPEED_OF_LIGHT_M_S",
    "THERMAL_NOISE_DBM_PER_HZ",
    "DROP_REASONS",
    "Reason",
    "Modulation",
    "TxFrame",
    "Outcome",
    "LinkInfo",
    "Jammer",
    "RxBatch",
    "ChannelModel",
    "UnitDisk",
    "LogDistance",
    "ChannelConfig",
    "RadioMedium",
    "dbm_to_mw",
    "mw_to_dbm",
    "friis_reference_loss_db",
    "log_distance_path_loss_db",
    "noise_floor_dbm",
    "ber",
    "per",
]

SPEED_OF_LIGHT_M_S = 299_792_458.0
# kT at T0 = 290 K, the reference temperature of the noise-figure definition.
THERMAL_NOISE_DBM_PER_HZ = -174.0

Reason = Literal["distance", "sinr", "collision", "half-duplex", "queue", "jammed"]
DROP_REASONS: tuple[Reason, ...] = ("distance", "sinr", "collision", "half-duplex", "queue", "jammed")
Modulation = Literal["dbpsk", "ncfsk"]

# "distance" means no frame of any size is receivable with better than this
# probability; the sensitivity derived from it is where PER(header-only) = 1 - 1e-6.
_DISTANCE_SUCCESS_PROBABILITY = 1e-6

FloatArray = NDArray[np.float64]


# --------------------------------------------------------------------------- #
# Pure physics functions
# --------------------------------------------------------------------------- #
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


def _ebn0(sinr_linear: FloatArray, bandwidth_hz: float, bitrate_bps: float) -> FloatArray:
    # Eb/N0 = (S / (N0 B)) * (B / R): the noise is integrated over B, a bit lasts 1/R.
    return sinr_linear * (bandwidth_hz / bitrate_bps)


def _ber_from_ebn0(ebn0: FloatArray, modulation: Modulation) -> FloatArray:
    if modulation == "dbpsk":
        return 0.5 * np.exp(-ebn0)
    if modulation == "ncfsk":
        return 0.5 * np.exp(-0.5 * ebn0)
    raise ValueError(f"unknown modulation {modulation!r}")


def _per_from_ber(bit_error: FloatArray, bits: ArrayLike) -> FloatArray:
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
    return _as_result(_ber_from_ebn0(_ebn0(sinr, bandwidth_hz, bitrate_bps), modulation))


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
    return _as_result(_per_from_ber(np.asarray(b, dtype=float), bits))


# --------------------------------------------------------------------------- #
# Value types
# --------------------------------------------------------------------------- #
@dataclass(frozen=True)
class TxFrame:
    """A frame handed to the radio of ``src``. ``dst=None`` is a broadcast."""

    uid: int
    src: int
    dst: int | None
    size: int  # payload bytes; the model adds its MAC header

    def __post_init__(self) -> None:
        if self.size < 0:
            raise ValueError(f"frame size must be >= 0, got {self.size}")
        if self.dst is not None and self.dst == self.src:
            raise ValueError(f"frame {self.uid}: dst equals src ({self.src})")


@dataclass(frozen=True)
class Outcome:
    """Fate of one frame at one receiver.

    ``t`` is the arrival time when delivered, else the time the drop was decided
    (end of the airtime; the offer time for ``"queue"``). ``sinr_db`` is the
    worst-case SINR over the airtime (nan for :class:`UnitDisk` and queue drops).
    """

    uid: int
    src: int
    receiver: int
    delivered: bool
    t: float
    reason: Reason | None
    sinr_db: float


@dataclass(frozen=True)
class LinkInfo:
    """Mean (interference-free) quality of the directed link ``src -> dst``.

    ``pdr`` is the predicted single-attempt delivery ratio of a frame of
    ``size`` payload bytes; ``up`` is ``pdr >= 0.5``. Power and SNR are nan for
    :class:`UnitDisk`.
    """

    src: int
    dst: int
    distance_m: float
    rx_power_dbm: float
    snr_db: float
    pdr: float
    up: bool
    size: int


def _pos3(p: ArrayLike) -> FloatArray:
    a = np.asarray(p, dtype=float).reshape(-1)
    if a.shape == (2,):
        return np.array([a[0], a[1], 0.0])
    if a.shape == (3,):
        return a.copy()
    raise ValueError(f"position must be 2D or 3D, got shape {np.shape(p)}")


@dataclass(frozen=True)
class Jammer:
    """An emitter of noise-like power, active on the half-open interval [t_start, t_end).

    ``power_dbm`` is the EIRP. With ``band_hz`` wider than the receiver
    bandwidth only the fraction B / band_hz falls in band; ``None`` puts all of
    the power in band. Received power uses the model's path loss without shadowing.
    """

    position: tuple[float, ...]
    power_dbm: float
    t_start: float
    t_end: float
    band_hz: float | None = None

    def __post_init__(self) -> None:
        # Stored as a tuple so the dataclass stays hashable and comparable.
        object.__setattr__(self, "position", tuple(float(v) for v in _pos3(self.position)))
        if self.t_end < self.t_start:
            raise ValueError("jammer t_end must be >= t_start")
        if self.band_hz is not None and self.band_hz <= 0:
            raise ValueError("jammer band_hz must be > 0")

    def active_during(self, t0: float, t1: float) -> bool:
        """Whether [t_start, t_end) intersects the half-open interval [t0, t1)."""
        return self.t_start < t1 and self.t_end > t0


@dataclass(frozen=True)
class RxBatch:
    """Everything a model needs to judge one frame at k receivers (arrays of length k).

    Interference is the worst case (maximum over the airtime) of the summed
    power of overlapping transmissions only (``interference_tx_mw``) and of
    transmissions plus jammers (``interference_all_mw``).
    """

    distance_m: FloatArray
    shadow_db: FloatArray
    bits: int
    half_duplex: NDArray[np.bool_]
    interference_tx_mw: FloatArray
    interference_all_mw: FloatArray


Verdicts = tuple[NDArray[np.bool_], list[Reason | None], FloatArray]


# --------------------------------------------------------------------------- #
# Channel models
# --------------------------------------------------------------------------- #
class ChannelModel(Protocol):
    """What :class:`RadioMedium` needs from a channel model.

    The medium owns time, queues, positions, shadowing state and the bookkeeping
    of which transmissions overlap; the model owns the physics (airtime, power,
    PER, delays, backoff).
    """

    @property
    def models_interference(self) -> bool: ...
    @property
    def queue_size(self) -> int | None: ...
    @property
    def unicast_retries(self) -> int: ...
    @property
    def shadowing_sigma_db(self) -> float: ...
    @property
    def shadowing_decorrelation_m(self) -> float: ...
    @property
    def cca_threshold_dbm(self) -> float | None: ...
    @property
    def reference_frame_bytes(self) -> int: ...

    def airtime_s(self, size: int) -> float: ...
    def frame_bits(self, size: int) -> int: ...
    def rx_power_dbm(self, distance_m: FloatArray, shadow_db: FloatArray) -> FloatArray: ...
    def jammer_rx_power_dbm(self, jammer: Jammer, distance_m: FloatArray) -> FloatArray: ...
    def decide(self, batch: RxBatch, rng: np.random.Generator) -> Verdicts: ...
    def delivery_delay_s(self, distance_m: FloatArray, rng: np.random.Generator) -> FloatArray: ...
    def backoff_s(self, stage: int, rng: np.random.Generator) -> float: ...
    def link_quality(self, distance_m: float, shadow_db: float, size: int) -> tuple[float, float, float, bool]: ...


def _uniform_jitter(jitter_s: float, n: int, rng: np.random.Generator) -> FloatArray:
    # Drawing nothing when jitter is off keeps jitter-free runs independent of the rng.
    if jitter_s <= 0.0 or n == 0:
        return np.zeros(n)
    return rng.uniform(0.0, jitter_s, size=n)


class UnitDisk(BaseModel):
    """Idealised channel: a frame is delivered iff the receiver is within ``range_m``.

    No airtime, no interference, no half-duplex, unbounded queue, no retries and
    no propagation delay: arrival = offer time + latency + U[0, jitter). With
    ``jitter_s == 0`` it never touches the rng.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    model: Literal["unit-disk"] = Field("unit-disk", description="Discriminator for config files.")
    range_m: float = Field(math.inf, gt=0, description="Delivery radius (m); inclusive.")
    latency_s: float = Field(0.0, ge=0, description="Fixed one-hop latency (s).")
    jitter_s: float = Field(0.0, ge=0, description="Extra latency drawn from U[0, jitter_s) (s).")

    @property
    def models_interference(self) -> bool:
        return False

    @property
    def queue_size(self) -> int | None:
        return None

    @property
    def unicast_retries(self) -> int:
        return 0

    @property
    def shadowing_sigma_db(self) -> float:
        return 0.0

    @property
    def shadowing_decorrelation_m(self) -> float:
        return math.inf

    @property
    def cca_threshold_dbm(self) -> float | None:
        return None

    @property
    def reference_frame_bytes(self) -> int:
        return 0

    def airtime_s(self, size: int) -> float:
        return 0.0

    def frame_bits(self, size: int) -> int:
        return 8 * size

    def rx_power_dbm(self, distance_m: FloatArray, shadow_db: FloatArray) -> FloatArray:
        return np.full(np.shape(distance_m), np.nan)

    def jammer_rx_power_dbm(self, jammer: Jammer, distance_m: FloatArray) -> FloatArray:
        return np.full(np.shape(distance_m), np.nan)

    def decide(self, batch: RxBatch, rng: np.random.Generator) -> Verdicts:
        far = batch.distance_m > self.range_m
        busy = batch.half_duplex & ~far
        delivered = ~far & ~busy
        reasons: list[Reason | None] = [
            "distance" if f else ("half-duplex" if b else None) for f, b in zip(far.tolist(), busy.tolist())
        ]
        return delivered, reasons, np.full(len(reasons), np.nan)

    def delivery_delay_s(self, distance_m: FloatArray, rng: np.random.Generator) -> FloatArray:
        n = len(distance_m)
        return self.latency_s + _uniform_jitter(self.jitter_s, n, rng)

    def backoff_s(self, stage: int, rng: np.random.Generator) -> float:
        return 0.0

    def link_quality(self, distance_m: float, shadow_db: float, size: int) -> tuple[float, float, float, bool]:
        up = distance_m <= self.range_m
        return math.nan, math.nan, 1.0 if up else 0.0, up


class LogDistance(BaseModel):
    """Log-distance path loss + correlated log-normal shadowing + SINR-driven PER.

    Received power: P_rx = P_tx + G_tx + G_rx - PL(d0) - 10 eta log10(d/d0) - X,
    X ~ N(0, sigma) per node pair, symmetric, evolving with the Gudmundson (1991)
    AR(1) model as either end moves. A frame is judged at each receiver from its
    SINR (worst-case interference over the airtime) through ``per``. Every
    default is justified in the field description and in ``docs/radio.md``.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    model: Literal["log-distance"] = Field("log-distance", description="Discriminator for config files.")

    # --- propagation ------------------------------------------------------
    carrier_hz: float = Field(2.4e9, gt=0, description="Carrier frequency (Hz); 2.4 GHz ISM band.")
    tx_power_dbm: float = Field(
        20.0, description="Transmit power (dBm); 100 mW, the 2.4 GHz EIRP limit of ETSI EN 300 328."
    )
    tx_gain_dbi: float = Field(0.0, description="Transmit antenna gain (dBi); isotropic.")
    rx_gain_dbi: float = Field(0.0, description="Receive antenna gain (dBi); isotropic.")
    reference_distance_m: float = Field(
        1.0, gt=0, description="d0 (m) of the free-space reference loss 20 log10(4 pi d0 f / c) (Friis)."
    )
    path_loss_exponent: float = Field(
        3.0,
        gt=0,
        description="eta; 2 is free space, 2.7-3.5 urban/obstructed (Rappaport, Wireless Communications, Table 4.2).",
    )
    shadowing_sigma_db: float = Field(
        4.0,
        ge=0,
        description="Log-normal shadowing std (dB); measurements span 4-13 dB (Goldsmith, Wireless "
        "Communications, 2005, sec. 2.7); 4 dB is a mildly cluttered outdoor site.",
    )
    shadowing_decorrelation_m: float = Field(
        20.0,
        gt=0,
        description="Gudmundson (1991) decorrelation distance (m): rho = exp(-delta_d / d_corr). "
        "Goldsmith sec. 2.7: the size of the blocking objects, tens of metres outdoors.",
    )

    # --- receiver ---------------------------------------------------------
    bandwidth_hz: float = Field(
        1e6,
        gt=0,
        description="Noise bandwidth (Hz). Equal to the bitrate = matched filter without spreading gain, "
        "so co-channel interference is not suppressed. Set it above the bitrate to model DSSS processing gain.",
    )
    noise_figure_db: float = Field(
        6.0, description="Receiver noise figure (dB); typical 2.4 GHz transceiver (ns-3 WifiPhy uses 7 dB)."
    )
    modulation: Modulation = Field(
        "dbpsk", description="'dbpsk' (802.11b 1 Mbit/s basic rate) or 'ncfsk' (noncoherent BFSK, GFSK-like radios)."
    )
    sensitivity_dbm: float | None = Field(
        None,
        description="Below this mean received power frames are dropped as 'distance'. None derives it: the "
        "power at which even a header-only frame has PER = 1 - 1e-6.",
    )

    # --- PHY / MAC framing --------------------------------------------------
    bitrate_bps: float = Field(1e6, gt=0, description="PHY bitrate (bit/s); 802.11b basic rate 1 Mbit/s.")
    preamble_s: float = Field(
        192e-6,
        ge=0,
        description="Preamble + PHY header (s); 802.11b long PLCP preamble 144 us + header 48 us.",
    )
    mac_header_bytes: int = Field(
        28, ge=0, description="MAC overhead per frame (bytes); 802.11 data header 24 B + FCS 4 B."
    )
    processing_delay_s: float = Field(
        200e-6, ge=0, description="Per-hop stack/driver latency added to every delivery (s); assumption."
    )
    processing_jitter_s: float = Field(
        100e-6, ge=0, description="Extra per-delivery latency drawn from U[0, jitter) (s); assumption."
    )
    queue_size: int = Field(
        16, ge=0, description="Frames that may wait at a sender behind the one in service; more are dropped."
    )
    unicast_retries: int = Field(
        3,
        ge=0,
        description="Retransmissions of a failed unicast (802.11 default retry limit is 7; stale "
        "localisation data loses value quickly, so fewer).",
    )
    carrier_sense: bool = Field(
        True, description="Defer while a transmission is sensed above the CCA threshold (CSMA, no RTS/CTS)."
    )
    carrier_sense_dbm: float | None = Field(
        None, description="CCA threshold (dBm); None = the receiver sensitivity (802.11 CCA mode 1)."
    )
    slot_s: float = Field(20e-6, gt=0, description="Backoff slot (s); 802.11b DSSS aSlotTime.")
    difs_s: float = Field(50e-6, ge=0, description="Idle time before any backoff (s); 802.11b DIFS.")
    cw_min: int = Field(31, ge=0, description="Initial contention window (slots); 802.11b aCWmin.")
    cw_max: int = Field(1023, ge=0, description="Maximum contention window (slots); 802.11b aCWmax.")
    reference_frame_bytes: int = Field(
        100, ge=0, description="Payload used by RadioMedium.link() to predict delivery ratio."
    )

    # --- derived quantities -------------------------------------------------
    @cached_property
    def reference_loss_db(self) -> float:
        """Free-space loss at d0 (dB)."""
        return friis_reference_loss_db(self.carrier_hz, self.reference_distance_m)

    @cached_property
    def noise_floor_dbm(self) -> float:
        """-174 dBm/Hz + 10 log10(B) + NF."""
        return noise_floor_dbm(self.bandwidth_hz, self.noise_figure_db)

    @cached_property
    def _noise_mw(self) -> float:
        return float(dbm_to_mw(self.noise_floor_dbm))

    @cached_property
    def derived_sensitivity_dbm(self) -> float:
        """Power at which a header-only frame has PER = 1 - 1e-6 (no interference)."""
        bits = max(self.frame_bits(0), 1)
        target_ber = -math.expm1(math.log(_DISTANCE_SUCCESS_PROBABILITY) / bits)
        ratio = min(2.0 * target_ber, 1.0)
        if ratio >= 1.0:  # even Eb/N0 = 0 leaves a chance: nothing is hopeless
            return -math.inf
        ebn0 = -math.log(ratio) * (1.0 if self.modulation == "dbpsk" else 2.0)
        snr_db = 10.0 * math.log10(ebn0 * self.bitrate_bps / self.bandwidth_hz)
        return self.noise_floor_dbm + snr_db

    @property
    def effective_sensitivity_dbm(self) -> float:
        """The threshold actually used for 'distance' drops."""
        return self.derived_sensitivity_dbm if self.sensitivity_dbm is None else self.sensitivity_dbm

    # --- ChannelModel -------------------------------------------------------
    @property
    def models_interference(self) -> bool:
        return True

    @property
    def cca_threshold_dbm(self) -> float | None:
        if not self.carrier_sense:
            return None
        return self.effective_sensitivity_dbm if self.carrier_sense_dbm is None else self.carrier_sense_dbm

    def path_loss_db(self, distance_m: ArrayLike) -> float | FloatArray:
        """Mean path loss without shadowing (dB)."""
        return log_distance_path_loss_db(
            distance_m,
            carrier_hz=self.carrier_hz,
            exponent=self.path_loss_exponent,
            reference_distance_m=self.reference_distance_m,
        )

    def airtime_s(self, size: int) -> float:
        """preamble + (payload + MAC header) * 8 / bitrate."""
        return self.preamble_s + self.frame_bits(size) / self.bitrate_bps

    def frame_bits(self, size: int) -> int:
        """Bits protected by the FCS: payload + MAC header (the preamble is not counted)."""
        return 8 * (size + self.mac_header_bytes)

    def per(self, sinr_db: ArrayLike, bits: ArrayLike) -> float | FloatArray:
        """:func:`per` with this model's bandwidth, bitrate and modulation."""
        return per(
            sinr_db,
            bits,
            bandwidth_hz=self.bandwidth_hz,
            bitrate_bps=self.bitrate_bps,
            modulation=self.modulation,
        )

    def _per_linear(self, sinr: FloatArray, bits: int) -> FloatArray:
        ebn0 = _ebn0(sinr, self.bandwidth_hz, self.bitrate_bps)
        return _per_from_ber(_ber_from_ebn0(ebn0, self.modulation), bits)

    def rx_power_dbm(self, distance_m: FloatArray, shadow_db: FloatArray) -> FloatArray:
        eirp = self.tx_power_dbm + self.tx_gain_dbi
        return np.asarray(eirp + self.rx_gain_dbi - self.path_loss_db(distance_m) - shadow_db, dtype=float)

    def jammer_rx_power_dbm(self, jammer: Jammer, distance_m: FloatArray) -> FloatArray:
        in_band_db = 0.0
        if jammer.band_hz is not None and jammer.band_hz > self.bandwidth_hz:
            in_band_db = 10.0 * math.log10(self.bandwidth_hz / jammer.band_hz)
        return np.asarray(jammer.power_dbm + in_band_db + self.rx_gain_dbi - self.path_loss_db(distance_m), dtype=float)

    def decide(self, batch: RxBatch, rng: np.random.Generator) -> Verdicts:
        signal_dbm = self.rx_power_dbm(batch.distance_m, batch.shadow_db)
        signal_mw = np.power(10.0, signal_dbm / 10.0)
        noise = self._noise_mw
        sinr_all = signal_mw / (noise + batch.interference_all_mw)
        with np.errstate(divide="ignore"):
            sinr_db = 10.0 * np.log10(sinr_all)

        k = len(signal_dbm)
        delivered = np.zeros(k, dtype=bool)
        reasons: list[Reason | None] = [None] * k
        far = signal_dbm < self.effective_sensitivity_dbm
        busy = batch.half_duplex & ~far
        for i in np.flatnonzero(far):
            reasons[i] = "distance"
        for i in np.flatnonzero(busy):
            reasons[i] = "half-duplex"

        idx = np.flatnonzero(~far & ~busy)
        if idx.size:
            # One uniform per reception, compared against nested PERs, so the
            # drop is attributed to the weakest impairment that explains it.
            u = rng.random(idx.size)
            s = signal_mw[idx]
            p_all = self._per_linear(sinr_all[idx], batch.bits)
            p_tx = self._per_linear(s / (noise + batch.interference_tx_mw[idx]), batch.bits)
            p_snr = self._per_linear(s / noise, batch.bits)
            ok = u >= p_all
            delivered[idx] = ok
            for j, i in enumerate(idx.tolist()):
                if ok[j]:
                    continue
                if u[j] >= p_tx[j]:
                    reasons[i] = "jammed"
                elif u[j] >= p_snr[j]:
                    reasons[i] = "collision"
                else:
                    reasons[i] = "sinr"
        return delivered, reasons, sinr_db

    def delivery_delay_s(self, distance_m: FloatArray, rng: np.random.Generator) -> FloatArray:
        n = len(distance_m)
        prop = np.asarray(distance_m, dtype=float) / SPEED_OF_LIGHT_M_S
        return prop + self.processing_delay_s + _uniform_jitter(self.processing_jitter_s, n, rng)

    def backoff_s(self, stage: int, rng: np.random.Generator) -> float:
        """DIFS + U{0..CW} slots with CW = min((cw_min + 1) 2^stage - 1, cw_max) (binary exponential)."""
        cw = min((self.cw_min + 1) * (2 ** min(stage, 30)) - 1, self.cw_max)
        return self.difs_s + self.slot_s * int(rng.integers(0, cw + 1))

    def link_quality(self, distance_m: float, shadow_db: float, size: int) -> tuple[float, float, float, bool]:
        rx = float(self.rx_power_dbm(np.asarray(distance_m), np.asarray(shadow_db)))
        snr_db = rx - self.noise_floor_dbm
        if rx < self.effective_sensitivity_dbm:
            pdr = 0.0
        else:
            pdr = 1.0 - float(self.per(snr_db, self.frame_bits(size)))
        return rx, snr_db, pdr, pdr >= 0.5


ChannelConfig = Annotated[Union[UnitDisk, LogDistance], Field(discriminator="model")]
"""Config-file union: ``{"model": "log-distance", ...}`` or ``{"model": "unit-disk", ...}``."""


# --------------------------------------------------------------------------- #
# Shadowing state
# --------------------------------------------------------------------------- #
class _ShadowField:
    """Symmetric per-pair shadowing, advanced on every position update.

    delta_d for a pair is the sum of both ends' displacements: the environment a
    link sees changes when either end moves. Because exp(-a) exp(-b) = exp(-(a+b)),
    updating every tick is equivalent to one update over the summed path, so the
    result does not depend on the tick rate.
    """

    def __init__(self, sigma_db: float, decorrelation_m: float) -> None:
        self._sigma = sigma_db
        self._dcorr = decorrelation_m
        self._index: dict[int, int] = {}
        self._pos = np.zeros((0, 3))
        self._s = np.zeros((0, 0))

    def update(self, positions: Mapping[int, FloatArray], rng: np.random.Generator) -> None:
        ids = sorted(positions)
        n = len(ids)
        pos = np.array([positions[i] for i in ids], dtype=float).reshape(n, 3)
        if self._sigma == 0.0:
            self._index = {node: k for k, node in enumerate(ids)}
            self._pos = pos
            return
        old = np.array([self._index.get(node, -1) for node in ids], dtype=int)
        kept = old >= 0
        moved = np.zeros(n)
        if kept.any():
            moved[kept] = np.linalg.norm(pos[kept] - self._pos[old[kept]], axis=1)
        iu, ju = np.triu_indices(n, 1)
        both = kept[iu] & kept[ju]
        prev = np.zeros(iu.size)
        prev[both] = self._s[old[iu[both]], old[ju[both]]]
        rho = np.where(both, np.exp(-(moved[iu] + moved[ju]) / self._dcorr), 0.0)
        z = rng.standard_normal(iu.size)
        values = rho * prev + np.sqrt(1.0 - rho * rho) * self._sigma * z
        s = np.zeros((n, n))
        s[iu, ju] = values
        s[ju, iu] = values
        self._s = s
        self._pos = pos
        self._index = {node: k for k, node in enumerate(ids)}

    def pair(self, a: int, b: int) -> float:
        """Shadowing (dB) between ``a`` and ``b``; 0 if either is unknown."""
        if self._sigma == 0.0:
            return 0.0
        ia, ib = self._index.get(a), self._index.get(b)
        return 0.0 if ia is None or ib is None else float(self._s[ia, ib])

    def get(self, a: int, others: Sequence[int]) -> FloatArray:
        """Shadowing (dB) between ``a`` and each of ``others``; 0 for unknown nodes."""
        out = np.zeros(len(others))
        ia = self._index.get(a)
        if self._sigma == 0.0 or ia is None:
            return out
        idx = np.array([self._index.get(b, -1) for b in others], dtype=int)
        known = idx >= 0
        out[known] = self._s[ia, idx[known]]
        return out


# --------------------------------------------------------------------------- #
# Medium
# --------------------------------------------------------------------------- #
# At equal times, ends are handled before new attempts so that the order is fixed.
_END = 0
_TRY = 1


@dataclass(eq=False)
class _Tx:
    frame: TxFrame
    start: float
    end: float
    pos: FloatArray  # sender position when the transmission started

    @property
    def src(self) -> int:
        return self.frame.src


@dataclass
class _Sender:
    queue: deque[TxFrame] = field(default_factory=deque)
    current: TxFrame | None = None
    retry: int = 0


class RadioMedium:
    """Discrete-event radio medium shared by all nodes.

    Usage per tick: :meth:`set_positions`, any number of :meth:`offer`, then
    :meth:`advance` to the tick time. Time never runs backwards: offers dated
    before the last ``advance`` are treated as offered at that time.

    Each sender transmits one frame at a time (FIFO; overflow is dropped as
    ``"queue"``). With carrier sense, a sender that senses another transmission
    above the CCA threshold defers until it ends plus DIFS and a random backoff;
    after each frame it performs a post-backoff. A failed unicast attempt (the
    sender is assumed to learn this instantly; ACKs use no airtime) is retried
    after a binary-exponential backoff, and only the final attempt is reported.
    """

    def __init__(self, model: ChannelModel, rng: np.random.Generator) -> None:
        self._model = model
        self._rng = rng
        self._pos: dict[int, FloatArray] = {}
        self._shadow = _ShadowField(model.shadowing_sigma_db, model.shadowing_decorrelation_m)
        self._jammers: tuple[Jammer, ...] = ()
        self._senders: dict[int, _Sender] = {}
        self._events: list[tuple[float, int, int, object]] = []
        self._pending: list[tuple[float, int, Outcome]] = []
        self._txs: list[_Tx] = []
        self._on_air: dict[int, _Tx] = {}
        self._seq = itertools.count()
        self._now = -math.inf

    # --- inputs ---------------------------------------------------------------
    @property
    def model(self) -> ChannelModel:
        """The channel model this medium was built with."""
        return self._model

    @property
    def now(self) -> float:
        """Time of the last :meth:`advance` (-inf before the first)."""
        return self._now

    def set_positions(self, positions: Mapping[int, ArrayLike]) -> None:
        """Replace the set of known nodes and their 2D/3D positions (m).

        Nodes absent from ``positions`` are forgotten (frames to them drop as
        ``"distance"``); a node that reappears gets fresh shadowing.
        """
        self._pos = {int(k): _pos3(v) for k, v in positions.items()}
        self._shadow.update(self._pos, self._rng)

    def set_jammers(self, jammers: Sequence[Jammer]) -> None:
        """Replace the jammer list; each acts on frames whose airtime meets [t_start, t_end)."""
        self._jammers = tuple(jammers)

    def offer(self, frame: TxFrame, t: float) -> list[Outcome]:
        """Queue ``frame`` at its sender at time ``t``; returns the immediate ``"queue"`` drops."""
        t = max(t, self._now)
        sender = self._senders.setdefault(frame.src, _Sender())
        if sender.current is None:
            sender.current = frame
            sender.retry = 0
            self._push(t, _TRY, frame.src)
            return []
        cap = self._model.queue_size
        if cap is not None and len(sender.queue) >= cap:
            return [
                Outcome(frame.uid, frame.src, r, False, t, "queue", math.nan) for r in self._receivers(frame)
            ]
        sender.queue.append(frame)
        return []

    # --- time -----------------------------------------------------------------
    def advance(self, t: float) -> list[Outcome]:
        """Resolve every event up to ``t``; return outcomes with ``outcome.t <= t`` in time order."""
        while self._events and self._events[0][0] <= t:
            time, kind, _, payload = heapq.heappop(self._events)
            self._now = max(self._now, time)
            if kind == _END:
                assert isinstance(payload, _Tx)
                self._end(payload, time)
            else:
                assert isinstance(payload, int)
                self._try(payload, time)
        self._now = max(self._now, t)
        out: list[Outcome] = []
        while self._pending and self._pending[0][0] <= t:
            out.append(heapq.heappop(self._pending)[2])
        return out

    def next_event_time(self) -> float | None:
        """Earliest time at which :meth:`advance` could change state or return an outcome."""
        times = []
        if self._events:
            times.append(self._events[0][0])
        if self._pending:
            times.append(self._pending[0][0])
        return min(times) if times else None

    # --- queries --------------------------------------------------------------
    def link(self, a: int, b: int, size: int | None = None) -> LinkInfo:
        """Mean interference-free quality of ``a -> b`` with the current shadowing."""
        d = float(np.linalg.norm(self._pos[a] - self._pos[b]))
        size = self._model.reference_frame_bytes if size is None else size
        rx, snr, pdr, up = self._model.link_quality(d, self.shadowing_db(a, b), size)
        return LinkInfo(a, b, d, rx, snr, pdr, up, size)

    def shadowing_db(self, a: int, b: int) -> float:
        """Current shadowing loss (dB) between ``a`` and ``b``; symmetric."""
        return self._shadow.pair(a, b)

    # --- internals ------------------------------------------------------------
    def _push(self, t: float, kind: int, payload: object) -> None:
        heapq.heappush(self._events, (t, kind, next(self._seq), payload))

    def _receivers(self, frame: TxFrame) -> list[int]:
        if frame.dst is not None:
            return [frame.dst]
        return sorted(n for n in self._pos if n != frame.src)

    def _try(self, src: int, t: float) -> None:
        sender = self._senders[src]
        frame = sender.current
        if frame is None:
            return
        pos = self._pos.get(src)
        if pos is None:
            # A sender that left the world cannot radiate; its frame reaches nobody.
            self._report(
                [Outcome(frame.uid, src, r, False, t, "distance", math.nan) for r in self._receivers(frame)]
            )
            self._finish(src, t)
            return
        cca = self._model.cca_threshold_dbm
        if cca is not None:
            busy_until = self._sensed_busy_until(src, pos, t, cca)
            if busy_until is not None:
                self._push(busy_until + self._model.backoff_s(sender.retry, self._rng), _TRY, src)
                return
        tx = _Tx(frame, t, t + self._model.airtime_s(frame.size), pos.copy())
        self._txs.append(tx)
        self._on_air[id(tx)] = tx
        self._push(tx.end, _END, tx)

    def _sensed_busy_until(self, src: int, pos: FloatArray, t: float, cca_dbm: float) -> float | None:
        heard = [x for x in self._txs if x.src != src and x.start <= t < x.end]
        if not heard:
            return None
        dist = np.linalg.norm(np.array([x.pos for x in heard]) - pos, axis=1)
        shadow = np.array([self._shadow.pair(x.src, src) for x in heard])
        power = self._model.rx_power_dbm(dist, shadow)
        ends = [x.end for x, p in zip(heard, power.tolist()) if p >= cca_dbm]
        return max(ends) if ends else None

    def _end(self, tx: _Tx, t: float) -> None:
        outcomes = self._resolve(tx, t)
        del self._on_air[id(tx)]
        sender = self._senders[tx.src]
        failed_unicast = tx.frame.dst is not None and not outcomes[0].delivered
        if failed_unicast and sender.retry < self._model.unicast_retries:
            sender.retry += 1
            self._push(t + self._model.backoff_s(sender.retry, self._rng), _TRY, tx.src)
        else:
            self._report(outcomes)
            self._finish(tx.src, t)
        self._prune()

    def _finish(self, src: int, t: float) -> None:
        sender = self._senders[src]
        sender.current = sender.queue.popleft() if sender.queue else None
        sender.retry = 0
        if sender.current is not None:
            # Post-backoff keeps a sender with a full queue from hogging a CSMA channel.
            wait = self._model.backoff_s(0, self._rng) if self._model.cca_threshold_dbm is not None else 0.0
            self._push(t + wait, _TRY, src)

    def _report(self, outcomes: Sequence[Outcome]) -> None:
        for o in outcomes:
            heapq.heappush(self._pending, (o.t, next(self._seq), o))

    def _prune(self) -> None:
        # Nothing unresolved starts before the earliest on-air start, and nothing
        # new starts before now, so older transmissions can no longer interfere.
        horizon = min((x.start for x in self._on_air.values()), default=self._now)
        horizon = min(horizon, self._now)
        self._txs = [x for x in self._txs if x.end > horizon]

    def _resolve(self, tx: _Tx, t: float) -> list[Outcome]:
        frame = tx.frame
        receivers = self._receivers(frame)
        known = [r for r in receivers if r in self._pos]
        by_receiver: dict[int, Outcome] = {
            r: Outcome(frame.uid, frame.src, r, False, t, "distance", math.nan)
            for r in receivers
            if r not in self._pos
        }
        if known:
            rpos = np.array([self._pos[r] for r in known])
            dist = np.linalg.norm(rpos - tx.pos, axis=1)
            overlapping = [x for x in self._txs if x is not tx and x.start < tx.end and x.end > tx.start]
            transmitting = {x.src for x in overlapping}
            i_tx, i_all = self._interference(tx, overlapping, known, rpos)
            batch = RxBatch(
                distance_m=dist,
                shadow_db=self._shadow.get(frame.src, known),
                bits=self._model.frame_bits(frame.size),
                half_duplex=np.array([r in transmitting for r in known], dtype=bool),
                interference_tx_mw=i_tx,
                interference_all_mw=i_all,
            )
            delivered, reasons, sinr_db = self._model.decide(batch, self._rng)
            arrival = np.full(len(known), t)
            arrival[delivered] = t + self._model.delivery_delay_s(dist[delivered], self._rng)
            for k, r in enumerate(known):
                by_receiver[r] = Outcome(
                    frame.uid, frame.src, r, bool(delivered[k]), float(arrival[k]), reasons[k], float(sinr_db[k])
                )
        return [by_receiver[r] for r in receivers]

    def _interference(
        self, tx: _Tx, overlapping: Sequence[_Tx], known: Sequence[int], rpos: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        k = len(known)
        if not self._model.models_interference:
            return np.zeros(k), np.zeros(k)
        jams = [j for j in self._jammers if j.active_during(tx.start, tx.end)]
        if not overlapping and not jams:
            return np.zeros(k), np.zeros(k)
        # The interference is piecewise constant between these edges; the frame
        # is judged on its worst piece.
        edges = {tx.start, tx.end}
        for x in overlapping:
            edges.update((max(x.start, tx.start), min(x.end, tx.end)))
        for j in jams:
            edges.update((max(j.t_start, tx.start), min(j.t_end, tx.end)))
        e = np.array(sorted(edges))
        lo, hi = e[:-1], e[1:]
        keep = hi > lo
        if not keep.any():
            return np.zeros(k), np.zeros(k)
        mid = 0.5 * (lo[keep] + hi[keep])
        i_tx = np.zeros((mid.size, k))
        for x in overlapping:
            active = (x.start <= mid) & (mid < x.end)
            p = self._model.rx_power_dbm(np.linalg.norm(rpos - x.pos, axis=1), self._shadow.get(x.src, known))
            i_tx += np.outer(active, np.power(10.0, p / 10.0))
        i_jam = np.zeros_like(i_tx)
        for j in jams:
            active = (j.t_start <= mid) & (mid < j.t_end)
            p = self._model.jammer_rx_power_dbm(j, np.linalg.norm(rpos - np.array(j.position), axis=1))
            i_jam += np.outer(active, np.power(10.0, p / 10.0))
        return i_tx.max(axis=0), (i_tx + i_jam).max(axis=0)
