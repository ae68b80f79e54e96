"""Radio physics of netsim: which receivers get each frame, when, or why not.

The module is transport-free and deterministic given a ``numpy.random.Generator``:
the emulator feeds it positions (:meth:`RadioMedium.set_positions`), frames
(:meth:`RadioMedium.offer`) and the clock (:meth:`RadioMedium.advance`), and it
returns one :class:`Outcome` per (frame, receiver), or the same as :class:`Outcomes`
arrays (``offer_arrays``, ``advance_arrays``, ``run_to_idle``).

The medium works on arrays: positions and everything that follows from them alone
(distances, received powers, who senses whom) are computed once per
:meth:`RadioMedium.set_positions`; a transmission is judged at all its receivers at once,
and the broadcasts that end within one ``advance`` are judged together.

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

import math
from bisect import bisect_left
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from operator import attrgetter
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
    "Outcomes",
    "LinkInfo",
    "Jammer",
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


# Reasons as small integers, so a batch of receptions carries them in one array:
# 0 is "delivered", k > 0 is DROP_REASONS[k - 1].
REASON_CODE: dict[Reason | None, int] = {None: 0, **{r: k + 1 for k, r in enumerate(DROP_REASONS)}}
_DISTANCE, _SINR, _COLLISION, _HALF_DUPLEX, _QUEUE, _JAMMED = (REASON_CODE[r] for r in DROP_REASONS)
_REASON_OF_CODE: tuple[Reason | None, ...] = (None, *DROP_REASONS)


@dataclass(frozen=True)
class Outcomes:
    """Many :class:`Outcome` as parallel arrays (one entry per frame and receiver).

    ``reason`` holds codes (0 delivered, k > 0 ``DROP_REASONS[k - 1]``).
    """

    uid: NDArray[np.int64]
    src: NDArray[np.int64]
    receiver: NDArray[np.int64]
    t: FloatArray
    reason: NDArray[np.int8]
    sinr_db: FloatArray

    def __len__(self) -> int:
        return len(self.uid)

    @property
    def delivered(self) -> NDArray[np.bool_]:
        return self.reason == 0

    @staticmethod
    def empty() -> Outcomes:
        i, f = np.zeros(0, np.int64), np.zeros(0)
        return Outcomes(i, i, i, f, np.zeros(0, np.int8), f)

    @staticmethod
    def concat(parts: Sequence[Outcomes]) -> Outcomes:
        if len(parts) == 1:
            return parts[0]
        if not parts:
            return Outcomes.empty()
        return Outcomes(*(np.concatenate([getattr(o, f) for o in parts]) for f in _OUTCOME_FIELDS))

    def take(self, idx: NDArray[np.intp]) -> Outcomes:
        return Outcomes(*(getattr(self, f)[idx] for f in _OUTCOME_FIELDS))

    def to_list(self) -> list[Outcome]:
        reasons = [_REASON_OF_CODE[c] for c in self.reason.tolist()]
        return [
            Outcome(u, s, r, why is None, t, why, q)
            for u, s, r, t, why, q in zip(
                self.uid.tolist(), self.src.tolist(), self.receiver.tolist(), self.t.tolist(), reasons,
                self.sinr_db.tolist(),
            )
        ]


_OUTCOME_FIELDS = ("uid", "src", "receiver", "t", "reason", "sinr_db")


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
    def delivery_delay_s(self, distance_m: FloatArray, rng: np.random.Generator) -> FloatArray: ...
    def backoff_s(self, stage: int, rng: np.random.Generator) -> float: ...
    def backoff_window(self, stage: int) -> tuple[float, float, int]: ...
    def link_quality(self, distance_m: float, shadow_db: float, size: int) -> tuple[float, float, float, bool]: ...
    def link_quality_arrays(
        self, distance_m: FloatArray, shadow_db: FloatArray, size: int
    ) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]: ...
    def judge(
        self,
        distance_m: FloatArray,
        signal_dbm: FloatArray,
        interference_tx_mw: FloatArray,
        interference_all_mw: FloatArray,
        half_duplex: NDArray[np.bool_],
        bits: NDArray[np.int64],
        rng: np.random.Generator,
    ) -> tuple[NDArray[np.int8], FloatArray]: ...


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

    def judge(
        self,
        distance_m: FloatArray,
        signal_dbm: FloatArray,
        interference_tx_mw: FloatArray,
        interference_all_mw: FloatArray,
        half_duplex: NDArray[np.bool_],
        bits: NDArray[np.int64],
        rng: np.random.Generator,
    ) -> tuple[NDArray[np.int8], FloatArray]:
        """Reason codes (0 = delivered) and SINR (nan: no notion of power) for each reception."""
        far = distance_m > self.range_m
        code = np.where(far, _DISTANCE, np.where(half_duplex, _HALF_DUPLEX, 0)).astype(np.int8)
        return code, np.full(len(code), np.nan)

    def delivery_delay_s(self, distance_m: FloatArray, rng: np.random.Generator) -> FloatArray:
        n = len(distance_m)
        return self.latency_s + _uniform_jitter(self.jitter_s, n, rng)

    def backoff_s(self, stage: int, rng: np.random.Generator) -> float:
        return 0.0

    def backoff_window(self, stage: int) -> tuple[float, float, int]:
        return 0.0, 0.0, 0

    def link_quality(self, distance_m: float, shadow_db: float, size: int) -> tuple[float, float, float, bool]:
        up = distance_m <= self.range_m
        return math.nan, math.nan, 1.0 if up else 0.0, up

    def link_quality_arrays(
        self, distance_m: FloatArray, shadow_db: FloatArray, size: int
    ) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
        up = distance_m <= self.range_m
        nan = np.full(np.shape(distance_m), np.nan)
        return nan, nan.copy(), up.astype(float), up


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

    def _per_linear(self, sinr: FloatArray, bits: ArrayLike) -> FloatArray:
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

    def judge(
        self,
        distance_m: FloatArray,
        signal_dbm: FloatArray,
        interference_tx_mw: FloatArray,
        interference_all_mw: FloatArray,
        half_duplex: NDArray[np.bool_],
        bits: NDArray[np.int64],
        rng: np.random.Generator,
    ) -> tuple[NDArray[np.int8], FloatArray]:
        """Reason codes (0 = delivered) and worst-case SINR (dB) for each reception."""
        signal_mw = np.power(10.0, signal_dbm / 10.0)
        noise = self._noise_mw
        sinr_all = signal_mw / (noise + interference_all_mw)
        with np.errstate(divide="ignore"):
            sinr_db = 10.0 * np.log10(sinr_all)
        far = signal_dbm < self.effective_sensitivity_dbm
        code = np.where(far, _DISTANCE, np.where(half_duplex, _HALF_DUPLEX, 0)).astype(np.int8)
        idx = np.flatnonzero(code == 0)
        if idx.size:
            # One uniform per reception, compared against nested PERs, so the
            # drop is attributed to the weakest impairment that explains it.
            u = rng.random(idx.size)
            lost = u < self._per_linear(sinr_all[idx], bits[idx])
            idx, u = idx[lost], u[lost]
            s, b = signal_mw[idx], bits[idx]
            p_tx = self._per_linear(s / (noise + interference_tx_mw[idx]), b)
            p_snr = self._per_linear(s / noise, b)
            code[idx] = np.where(u >= p_tx, _JAMMED, np.where(u >= p_snr, _COLLISION, _SINR))
        return code, sinr_db

    def delivery_delay_s(self, distance_m: FloatArray, rng: np.random.Generator) -> FloatArray:
        n = len(distance_m)
        prop = np.asarray(distance_m, dtype=float) / SPEED_OF_LIGHT_M_S
        return prop + self.processing_delay_s + _uniform_jitter(self.processing_jitter_s, n, rng)

    def backoff_s(self, stage: int, rng: np.random.Generator) -> float:
        """DIFS + U{0..CW} slots with CW = min((cw_min + 1) 2^stage - 1, cw_max) (binary exponential)."""
        fixed, slot, cw = self.backoff_window(stage)
        return fixed + slot * int(rng.integers(0, cw + 1))

    def backoff_window(self, stage: int) -> tuple[float, float, int]:
        """(DIFS, slot, CW) of :meth:`backoff_s`: the backoff is DIFS + U{0..CW} slots."""
        return self.difs_s, self.slot_s, min((self.cw_min + 1) * (2 ** min(stage, 30)) - 1, self.cw_max)

    def link_quality(self, distance_m: float, shadow_db: float, size: int) -> tuple[float, float, float, bool]:
        rx = float(self.rx_power_dbm(np.asarray(distance_m), np.asarray(shadow_db)))
        snr_db = rx - self.noise_floor_dbm
        if rx < self.effective_sensitivity_dbm:
            pdr = 0.0
        else:
            pdr = 1.0 - float(self.per(snr_db, self.frame_bits(size)))
        return rx, snr_db, pdr, pdr >= 0.5

    def link_quality_arrays(
        self, distance_m: FloatArray, shadow_db: FloatArray, size: int
    ) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
        """:meth:`link_quality` over arrays of links: (rx dBm, SNR dB, PDR, up)."""
        rx = self.rx_power_dbm(distance_m, shadow_db)
        snr_db = rx - self.noise_floor_dbm
        pdr = np.where(rx < self.effective_sensitivity_dbm, 0.0,
                       1.0 - np.asarray(self.per(snr_db, self.frame_bits(size)), dtype=float))
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

    def matrix(self) -> FloatArray:
        """Shadowing (dB) between every two known nodes, in ascending id order."""
        n = len(self._index)
        return np.zeros((n, n)) if self._sigma == 0.0 else self._s

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
@dataclass(eq=False, slots=True)
class _Tx:
    frame: TxFrame
    start: float
    end: float
    pos: FloatArray  # sender position when the transmission started
    gen: int  # the geometry (set_positions call) it started under
    row: int  # its sender's row in that geometry

    @property
    def src(self) -> int:
        return self.frame.src


@dataclass
class _Sender:
    slot: int  # index into the medium's per-sender arrays
    queue: deque[TxFrame] = field(default_factory=deque)
    current: TxFrame | None = None


@dataclass(frozen=True)
class _Geometry:
    """Positions and what follows from them alone; fixed until the next set_positions.

    Rows and columns are the known nodes in ascending id order. ``rx_dbm[i, j]`` is the
    mean received power at j of a frame from i (shadowing included), ``hears[i, j]``
    whether j senses i's transmissions above the CCA threshold (never itself; an extra
    last column of False, so that ``hears[i, -1]`` asks about a node not in the world).
    """

    ids: NDArray[np.int64]
    index: dict[int, int]
    xyz: FloatArray
    distance: FloatArray
    shadow: FloatArray
    rx_dbm: FloatArray
    rx_mw: FloatArray
    hears: NDArray[np.bool_]


def _distances(a: FloatArray, b: FloatArray) -> FloatArray:
    diff = a[:, None, :] - b[None, :, :]
    return np.sqrt(np.add.reduce(diff * diff, axis=2))


_END_TIME = attrgetter("end")


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

    :meth:`offer_arrays`, :meth:`advance_arrays` and :meth:`run_to_idle` return the
    same outcomes as :class:`Outcomes` arrays; :meth:`offer` and :meth:`advance` as
    :class:`Outcome` objects.
    """

    def __init__(self, model: ChannelModel, rng: np.random.Generator) -> None:
        self._model = model
        self._rng = rng
        self._pos: dict[int, FloatArray] = {}
        self._shadow = _ShadowField(model.shadowing_sigma_db, model.shadowing_decorrelation_m)
        self._geo = self._geometry()
        self._gen = 0
        self._links: dict[int, tuple[FloatArray, ...]] = {}
        self._jammers: tuple[Jammer, ...] = ()
        self._senders: dict[int, _Sender] = {}
        # Per sender slot: its node, the time of its next attempt (inf: none), the retries of
        # the frame in service and its row in the geometry (-1: not in the world).
        self._sender_ids: list[int] = []
        self._try_at = np.zeros(0)
        self._stage = np.zeros(0, np.int64)
        self._retrying = 0  # senders whose stage is not 0
        self._slot_row = np.zeros(0, np.int64)
        self._windows: list[tuple[float, float, int]] = []  # the model's backoff window per retry stage
        self._spare = np.zeros(0)  # uniforms drawn for backoffs and not used yet
        self._first_stage = np.zeros(0)  # stage-0 backoffs drawn and not used yet
        self._frame_bits: dict[int, int] = {}  # by payload size
        self._airtime: dict[int, float] = {}  # by payload size
        self._on_air: list[_Tx] = []  # in start order
        self._txs: list[_Tx] = []  # on air or ended recently enough to overlap one on air
        self._unjudged: list[tuple[_Tx, list[_Tx]]] = []  # ended broadcasts and what overlapped them
        self._pending: list[tuple[Outcomes, NDArray[np.int64]]] = []  # (outcomes, order reported)
        self._reported = 0
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
        self._geo = self._geometry()
        self._gen += 1
        self._links = {}
        self._slot_row = np.array([self._geo.index.get(a, -1) for a in self._sender_ids], np.int64)

    def set_jammers(self, jammers: Sequence[Jammer]) -> None:
        """Replace the jammer list; each acts on frames whose airtime meets [t_start, t_end)."""
        self._jammers = tuple(jammers)

    def offer(self, frame: TxFrame, t: float) -> list[Outcome]:
        """Queue ``frame`` at its sender at time ``t``; returns the immediate ``"queue"`` drops."""
        out = self.offer_arrays(frame, t)
        return [] if out is None else out.to_list()

    def offer_arrays(self, frame: TxFrame, t: float) -> Outcomes | None:
        """:meth:`offer`, the drops (if any) as arrays."""
        t = max(t, self._now)
        sender = self._senders.get(frame.src) or self._new_sender(frame.src)
        if sender.current is None:
            sender.current = frame  # its stage is 0: _finish left it so
            self._try_at[sender.slot] = t
            return None
        cap = self._model.queue_size
        if cap is not None and len(sender.queue) >= cap:
            return self._drops(frame, t, _QUEUE)
        sender.queue.append(frame)
        return None

    # --- time -----------------------------------------------------------------
    def advance(self, t: float) -> list[Outcome]:
        """Resolve every event up to ``t``; return outcomes with ``outcome.t <= t`` in time order."""
        return self.advance_arrays(t).to_list()

    def advance_arrays(self, t: float) -> Outcomes:
        """:meth:`advance`, the outcomes as arrays."""
        self._run(t)
        self._now = max(self._now, t)
        return self._take_pending(t)

    def run_to_idle(self) -> Outcomes:
        """Resolve everything offered; the clock stops at the last event or arrival, not at infinity."""
        self._run(math.inf)
        out = self._take_pending(math.inf)
        if len(out):
            self._now = max(self._now, float(out.t[-1]))
        return out

    def next_event_time(self) -> float | None:
        """Earliest time at which :meth:`advance` could change state or return an outcome."""
        times = [min(x.end for x in self._on_air)] if self._on_air else []
        if self._try_at.size:
            times.append(float(self._try_at.min()))
        times += [float(o.t.min()) for o, _ in self._pending]
        t = min(times, default=math.inf)
        return None if t == math.inf else t

    # --- queries --------------------------------------------------------------
    def link(self, a: int, b: int, size: int | None = None) -> LinkInfo:
        """Mean interference-free quality of ``a -> b`` with the current shadowing."""
        ia, ib = self._geo.index[a], self._geo.index[b]
        d = float(self._geo.distance[ia, ib])
        size = self._model.reference_frame_bytes if size is None else size
        rx, snr, pdr, up = self._model.link_quality(d, float(self._geo.shadow[ia, ib]), size)
        return LinkInfo(a, b, d, rx, snr, pdr, up, size)

    def link_arrays(self, size: int | None = None) -> tuple[NDArray[np.int64], FloatArray, FloatArray, FloatArray,
                                                            FloatArray, NDArray[np.bool_]]:
        """:meth:`link` for every ordered pair: (ids, distance, rx dBm, SNR dB, PDR, up), matrices by id order."""
        size = self._model.reference_frame_bytes if size is None else size
        if size not in self._links:
            geo = self._geo
            self._links[size] = (geo.distance, *self._model.link_quality_arrays(geo.distance, geo.shadow, size))
        return (self._geo.ids, *self._links[size])  # type: ignore[return-value]

    def shadowing_db(self, a: int, b: int) -> float:
        """Current shadowing loss (dB) between ``a`` and ``b``; symmetric."""
        return self._shadow.pair(a, b)

    # --- geometry -------------------------------------------------------------
    def _geometry(self) -> _Geometry:
        ids = sorted(self._pos)
        n = len(ids)
        xyz = np.array([self._pos[i] for i in ids], dtype=float).reshape(n, 3)
        dist = _distances(xyz, xyz)
        shadow = self._shadow.matrix()
        rx = np.asarray(self._model.rx_power_dbm(dist, shadow), dtype=float).reshape(n, n)
        cca = self._model.cca_threshold_dbm
        hears = np.zeros((n, n + 1), dtype=bool)  # the last column answers for row -1: nobody there
        if cca is not None:
            hears[:, :n] = rx >= cca
        np.fill_diagonal(hears, False)
        return _Geometry(np.array(ids, dtype=np.int64), {a: k for k, a in enumerate(ids)}, xyz, dist, shadow, rx,
                         np.power(10.0, rx / 10.0), hears)

    def _rows(self, txs: Sequence[_Tx]) -> tuple[FloatArray, FloatArray]:
        """Distance and received power (dBm) from each transmission to every known node."""
        geo = self._geo
        rows = np.array([x.row if x.gen == self._gen else -1 for x in txs], dtype=np.int64)
        dist, dbm = geo.distance[rows], geo.rx_dbm[rows]
        for i in np.flatnonzero(rows < 0).tolist():
            # Started before the last set_positions: from where it started, with today's shadowing.
            x = txs[i]
            dist[i] = np.linalg.norm(geo.xyz - x.pos, axis=1)
            dbm[i] = self._model.rx_power_dbm(dist[i], self._shadow.get(x.src, geo.ids.tolist()))
        return dist, dbm

    # --- senders --------------------------------------------------------------
    def _new_sender(self, node: int) -> _Sender:
        sender = self._senders[node] = _Sender(len(self._sender_ids))
        self._sender_ids.append(node)
        self._try_at = np.append(self._try_at, math.inf)
        self._stage = np.append(self._stage, 0)
        self._slot_row = np.append(self._slot_row, self._geo.index.get(node, -1))
        return sender

    def _receivers(self, frame: TxFrame) -> NDArray[np.int64]:
        if frame.dst is not None:
            return np.array([frame.dst], dtype=np.int64)
        return self._geo.ids[self._geo.ids != frame.src]

    def _drops(self, frame: TxFrame, t: float, code: int) -> Outcomes:
        r = self._receivers(frame)
        k = len(r)
        return Outcomes(np.full(k, frame.uid, np.int64), np.full(k, frame.src, np.int64), r, np.full(k, t),
                        np.full(k, code, np.int8), np.full(k, np.nan))

    # --- the event loop -------------------------------------------------------
    def _run(self, limit: float) -> None:
        # Events in time order, ends before attempts at equal times. Attempts between two
        # ends that only defer are handled together (_attempts): nothing they do changes
        # what the others sense.
        while True:
            ending = min(self._on_air, key=_END_TIME) if self._on_air else None
            t_end = ending.end if ending is not None else math.inf
            first = int(np.argmin(self._try_at)) if self._try_at.size else -1  # ties in slot order
            t_try = float(self._try_at[first]) if first >= 0 else math.inf
            if ending is not None and t_end <= t_try:
                if t_end > limit:
                    break
                self._now = max(self._now, t_end)
                self._on_air.remove(ending)
                self._end(ending, t_end)
            elif t_try <= limit and t_try < math.inf:
                self._attempts(first, t_end, limit)
            else:
                break
        if self._unjudged:
            self._report(self._judge(self._unjudged))
            self._unjudged = []

    def _attempts(self, first: int, horizon: float, limit: float) -> None:
        """Attempts before ``horizon`` (the next end) and ``limit``, ``first`` the earliest.

        The usual case after an end: the channel is free, the earliest attempt transmits and
        every attempt during its airtime senses it and defers. Anything else is left to
        :meth:`_attempts_in_order`.
        """
        sensing = self._model.cca_threshold_dbm is not None
        if self._on_air and sensing:
            self._attempts_in_order(horizon, limit)
            return
        try_at = self._try_at
        tx = self._start(first, float(try_at[first]))
        if tx is None or not sensing:
            return
        cand = np.flatnonzero(try_at < min(horizon, tx.end, math.nextafter(limit, math.inf)))
        if not cand.size:
            return
        if self._geo.hears[tx.row, self._slot_row[cand]].all():
            try_at[cand] = tx.end + self._backoffs(cand)
        else:
            self._attempts_in_order(min(horizon, tx.end), limit)

    def _attempts_in_order(self, horizon: float, limit: float) -> None:
        """Every attempt before ``horizon`` (the next end) and ``limit``, in time order.

        A sender that senses a transmission defers past its end, hence past the next end:
        deferring never changes what anyone else senses, so the deferrals are drawn together
        at the end. Each attempt that finds the channel free starts a transmission, which
        those after it then sense, and which may bring the next end forward.
        """
        try_at = self._try_at
        cand = np.flatnonzero(try_at < min(horizon, math.nextafter(limit, math.inf)))
        if cand.size > 1:
            cand = cand[np.argsort(try_at[cand], kind="stable")]  # ties in slot order
        times = try_at[cand].tolist()
        sensing = self._model.cca_threshold_dbm is not None
        rows = self._slot_row[cand]
        busy = self._busy_until(rows) if sensing and self._on_air else None  # None: nothing sensed yet
        n, k = len(cand), 0
        deferred: list[slice] = []
        while k < n:
            i = k
            if busy is not None:
                free = np.flatnonzero(busy[k:n] == -math.inf)
                i = k + int(free[0]) if free.size else n
            if i > k:
                deferred.append(slice(k, i))
            if i == n:
                break
            tx = self._start(int(cand[i]), times[i])
            k = i + 1
            if tx is None:  # nothing went on air, but the sender may try again before horizon
                break
            if tx.end < horizon:
                horizon = tx.end
                n = max(k, bisect_left(times, horizon))
            if sensing and k < n:
                heard = self._geo.hears[tx.row, rows[k:n]]
                if busy is None:
                    busy = np.full(len(cand), -math.inf)
                busy[k:n] = np.where(heard, np.maximum(busy[k:n], tx.end), busy[k:n])
        if deferred:
            at = np.r_[tuple(deferred)] if len(deferred) > 1 else np.arange(deferred[0].start, deferred[0].stop)
            slots = cand[at]
            try_at[slots] = busy[at] + self._backoffs(slots)  # type: ignore[index]

    def _backoffs(self, slots: NDArray[np.intp]) -> FloatArray:
        """Backoffs of these senders at their retry stages, U{0..CW} slots each."""
        k = len(slots)
        stage = self._stage[slots] if self._retrying else None
        top = int(stage.max()) if stage is not None else 0
        while len(self._windows) <= top:
            self._windows.append(self._model.backoff_window(len(self._windows)))
        if top == 0:  # the usual case: drawn ahead, in blocks
            if self._first_stage.size < k:
                self._first_stage = np.concatenate([self._first_stage, self._backoff(0, self._uniforms(max(k, 1024)))])
            b, self._first_stage = self._first_stage[:k], self._first_stage[k:]
            return b
        fixed, slot, cw = (np.array(v)[stage] for v in zip(*self._windows[: top + 1]))
        return fixed + slot * np.floor(self._uniforms(k) * (cw + 1))

    def _backoff(self, stage: int, u: FloatArray) -> FloatArray:
        # Floats hold these windows exactly (far below 2^53), so the slot count is uniform on 0..CW.
        fixed, slot, cw = self._windows[stage]
        return fixed + slot * np.floor(u * (cw + 1))

    def _uniforms(self, k: int) -> FloatArray:
        # Drawn in blocks: deferrals take a few at a time, thousands of times per second.
        if self._spare.size < k:
            self._spare = np.concatenate([self._spare, self._rng.random(max(k, 1024))])
        u, self._spare = self._spare[:k], self._spare[k:]
        return u

    def _busy_until(self, rows: NDArray[np.int64]) -> FloatArray:
        """Per listener (row, -1 if gone), the latest end of what it senses now (-inf: the channel is free)."""
        geo, gen = self._geo, self._gen
        busy = np.full(len(rows), -math.inf)
        for x in self._on_air:
            heard = geo.hears[x.row, rows] if x.gen == gen else self._heard_stale(x, rows)
            busy = np.where(heard, np.maximum(busy, x.end), busy)
        return busy

    def _heard_stale(self, x: _Tx, rows: NDArray[np.int64]) -> NDArray[np.bool_]:
        geo = self._geo
        dist = np.linalg.norm(geo.xyz[rows] - x.pos, axis=1)
        listeners = geo.ids[rows]
        power = self._model.rx_power_dbm(dist, self._shadow.get(x.src, listeners.tolist()))
        cca = self._model.cca_threshold_dbm
        return (power >= cca) & (listeners != x.src) & (rows >= 0)

    def _start(self, slot: int, t: float) -> _Tx | None:
        # Deferrals need not move the clock: a deferred sender always has a later event.
        self._now = max(self._now, t)
        self._try_at[slot] = math.inf
        sender = self._senders[self._sender_ids[slot]]
        frame = sender.current
        if frame is None:
            return None
        row = int(self._slot_row[slot])
        if row < 0:
            # A sender that left the world cannot radiate; its frame reaches nobody.
            self._report(self._drops(frame, t, _DISTANCE))
            self._finish(sender, t)
            return None
        airtime = self._airtime.get(frame.size)
        if airtime is None:
            airtime = self._airtime[frame.size] = self._model.airtime_s(frame.size)
        tx = _Tx(frame, t, t + airtime, self._geo.xyz[row], self._gen, row)
        self._txs.append(tx)
        self._on_air.append(tx)
        return tx

    def _end(self, tx: _Tx, t: float) -> None:
        overlapping = [x for x in self._txs if x is not tx and x.start < tx.end and x.end > tx.start]
        sender = self._senders[tx.src]
        if tx.frame.dst is None:
            # A broadcast's fate changes nothing at its sender: judge it later, with others.
            self._unjudged.append((tx, overlapping))
            self._finish(sender, t)
        else:
            out = self._judge([(tx, overlapping)])
            slot = sender.slot
            if out.reason[0] != 0 and self._stage[slot] < self._model.unicast_retries:
                self._retrying += int(self._stage[slot] == 0)
                self._stage[slot] += 1
                self._try_at[slot] = t + self._model.backoff_s(int(self._stage[slot]), self._rng)
            else:
                self._report(out)
                self._finish(sender, t)
        self._prune()

    def _finish(self, sender: _Sender, t: float) -> None:
        sender.current = sender.queue.popleft() if sender.queue else None
        if self._stage[sender.slot]:
            self._retrying -= 1
            self._stage[sender.slot] = 0
        if sender.current is not None:
            # Post-backoff keeps a sender with a full queue from hogging a CSMA channel.
            wait = self._model.backoff_s(0, self._rng) if self._model.cca_threshold_dbm is not None else 0.0
            self._try_at[sender.slot] = t + wait

    def _report(self, out: Outcomes) -> None:
        if len(out):
            self._pending.append((out, np.arange(self._reported, self._reported + len(out))))
            self._reported += len(out)

    def _take_pending(self, limit: float) -> Outcomes:
        if not self._pending:
            return Outcomes.empty()
        out = Outcomes.concat([o for o, _ in self._pending])
        seq = np.concatenate([s for _, s in self._pending]) if len(self._pending) > 1 else self._pending[0][1]
        due = out.t <= limit
        self._pending = [] if due.all() else [(out.take(~due), seq[~due])]
        idx = np.flatnonzero(due)
        return out.take(idx[np.lexsort((seq[idx], out.t[idx]))])

    def _prune(self) -> None:
        # Nothing unresolved starts before the earliest on-air start, and nothing
        # new starts before now, so older transmissions can no longer interfere.
        horizon = min((x.start for x in self._on_air), default=self._now)
        horizon = min(horizon, self._now)
        self._txs = [x for x in self._txs if x.end > horizon]

    # --- judging --------------------------------------------------------------
    def _judge(self, items: Sequence[tuple[_Tx, list[_Tx]]]) -> Outcomes:
        """Outcomes of ended transmissions (each with those that overlapped it), all at once."""
        geo = self._geo
        n = len(geo.ids)
        txs = [tx for tx, _ in items]
        frames = [x.frame for x in txs]
        uid = np.array([f.uid for f in frames], dtype=np.int64)
        src = np.array([f.src for f in frames], dtype=np.int64)
        src_row = self._row_of(src)
        cols = np.arange(n)
        wanted = cols != src_row[:, None]
        unicast = np.array([f.dst is not None for f in frames], dtype=bool)
        dst, dst_row = src, np.full(len(txs), -1)
        if unicast.any():
            dst = np.array([src[i] if f.dst is None else f.dst for i, f in enumerate(frames)], dtype=np.int64)
            dst_row = np.where(unicast, self._row_of(dst), -1)
            wanted[unicast] = cols == dst_row[unicast, None]
        rx_tx, rx_row = np.nonzero(wanted)
        at = rx_tx * n + rx_row  # into the flattened (transmission, node) matrices
        dist, dbm = self._rows(txs)
        d = dist.reshape(-1)[at]
        i_tx, i_all, half_duplex = self._interference(items, n)
        if half_duplex is None:
            i_tx = i_all = np.zeros(len(at))
            half_duplex = np.zeros(len(at), bool)
        else:
            i_tx, i_all, half_duplex = (m.reshape(-1)[at] for m in (i_tx, i_all, half_duplex))
        bits = np.array([self._bits(f.size) for f in frames], dtype=np.int64)[rx_tx]
        code, sinr_db = self._model.judge(d, dbm.reshape(-1)[at], i_tx, i_all, half_duplex, bits, self._rng)
        end = np.array([x.end for x in txs])
        t = end[rx_tx]
        ok = code == 0
        if ok.any():
            t[ok] += self._model.delivery_delay_s(d[ok], self._rng)
        out = Outcomes(uid[rx_tx], src[rx_tx], geo.ids[rx_row], t, code, sinr_db)
        lost = np.flatnonzero(unicast & (dst_row < 0))  # to a node not in the world
        if lost.size:
            k = lost.size
            gone = Outcomes(uid[lost], src[lost], dst[lost], end[lost], np.full(k, _DISTANCE, np.int8),
                            np.full(k, np.nan))
            out = Outcomes.concat([out, gone])
            out = out.take(np.argsort(np.concatenate([rx_tx, lost]), kind="stable"))
        return out

    def _row_of(self, ids: NDArray[np.int64]) -> NDArray[np.int64]:
        """Each node's row in the geometry, -1 for nodes not in the world."""
        # A dict look-up per id: a round has a few transmissions, and numpy's fixed cost per
        # call (searchsorted, where) was most of this for them.
        index = self._geo.index
        return np.array([index.get(i, -1) for i in ids.tolist()], dtype=np.int64)

    def _bits(self, size: int) -> int:
        bits = self._frame_bits.get(size)
        if bits is None:
            bits = self._frame_bits[size] = self._model.frame_bits(size)
        return bits

    def _interference(
        self, items: Sequence[tuple[_Tx, list[_Tx]]], n: int
    ) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]] | tuple[None, None, None]:
        """Per transmission and node: worst-case interference (transmissions only, and with
        jammers) over the airtime, in mW, and whether the node was itself transmitting;
        all None if nothing overlapped any of the transmissions."""
        T = len(items)
        others: dict[int, int] = {}
        sources: list[_Tx] = []
        pair_tx: list[int] = []
        pair_src: list[int] = []
        for i, (_, overlapping) in enumerate(items):
            for x in overlapping:
                k = others.get(id(x))
                if k is None:
                    k = others[id(x)] = len(sources)
                    sources.append(x)
                pair_tx.append(i)
                pair_src.append(k)
        start = np.array([tx.start for tx, _ in items])
        end = np.array([tx.end for tx, _ in items])
        jams = [j for j in self._jammers if np.any((j.t_start < end) & (j.t_end > start))] \
            if self._model.models_interference else []
        if not sources and not jams:
            return None, None, None  # nothing overlapped: no interference, nobody half-duplex
        half_duplex = np.zeros((T, n), dtype=bool)
        zeros = np.zeros((T, n))
        if sources:
            row = np.array([self._geo.index.get(x.src, -1) for x in sources], dtype=np.int64)[pair_src]
            half_duplex[np.asarray(pair_tx)[row >= 0], row[row >= 0]] = True
        if not self._model.models_interference:
            return zeros, zeros, half_duplex
        # Interference only rises when a source starts, so its worst piece of the airtime
        # begins at the frame's start or at one of the overlapping starts.
        k, J = len(sources), len(jams)
        s_start = np.array([x.start for x in sources] + [j.t_start for j in jams])
        s_end = np.array([x.end for x in sources] + [j.t_end for j in jams])
        overlaps = np.zeros((T, k + J), dtype=bool)
        overlaps[pair_tx, pair_src] = True
        for m, j in enumerate(jams):
            overlaps[:, k + m] = (j.t_start < end) & (j.t_end > start)
        oi, os_ = np.nonzero(overlaps)
        pt_tx = np.concatenate([np.arange(T), oi])
        pt_t = np.concatenate([start, np.maximum(s_start[os_], start[oi])])
        order = np.argsort(pt_tx, kind="stable")
        pt_tx, pt_t = pt_tx[order], pt_t[order]
        active = (overlaps[pt_tx] & (s_start <= pt_t[:, None]) & (pt_t[:, None] < s_end)
                  & (pt_t < end[pt_tx])[:, None]).astype(float)
        groups = np.searchsorted(pt_tx, np.arange(T))
        if k:
            _, dbm = self._rows(sources)
            from_tx = active[:, :k] @ np.power(10.0, dbm / 10.0)
        else:
            from_tx = np.zeros((len(pt_t), n))
        from_all = from_tx
        if J:
            jam_mw = np.array([np.power(10.0, self._model.jammer_rx_power_dbm(
                j, np.linalg.norm(self._geo.xyz - np.array(j.position), axis=1)) / 10.0) for j in jams])
            from_all = from_tx + active[:, k:] @ jam_mw
        return (np.maximum.reduceat(from_tx, groups, axis=0), np.maximum.reduceat(from_all, groups, axis=0),
                half_duplex)
