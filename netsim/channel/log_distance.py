"""The log-distance channel: path loss with log-normal shadowing, thermal noise, SINR with
interference over the airtime, bit errors, per-sender queues, carrier sense and unicast retries."""

from __future__ import annotations

import math
from functools import cached_property
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from netsim.channel.frames import (
    CODE_COLLISION,
    CODE_DISTANCE,
    CODE_HALF_DUPLEX,
    CODE_JAMMED,
    CODE_SINR,
    uniform_jitter,
)
from netsim.channel.jammer import Jammer
from netsim.channel.physics import (
    SPEED_OF_LIGHT_M_S,
    FloatArray,
    Modulation,
    ber_from_ebn0,
    dbm_to_mw,
    ebn0_of,
    friis_reference_loss_db,
    log_distance_path_loss_db,
    noise_floor_dbm,
    per,
    per_from_ber,
)

# "distance" means no frame of any size is receivable with better than this
# probability; the sensitivity derived from it is where PER(header-only) = 1 - 1e-6.
_DISTANCE_SUCCESS_PROBABILITY = 1e-6


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
        ebn0 = ebn0_of(sinr, self.bandwidth_hz, self.bitrate_bps)
        return per_from_ber(ber_from_ebn0(ebn0, self.modulation), bits)

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
        signal_mw, sinr_all, sinr_db, far = self._sinr(signal_dbm, interference_all_mw)
        noise = self._noise_mw
        code = np.where(far, CODE_DISTANCE, np.where(half_duplex, CODE_HALF_DUPLEX, 0)).astype(np.int8)
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
            code[idx] = np.where(u >= p_tx, CODE_JAMMED, np.where(u >= p_snr, CODE_COLLISION, CODE_SINR))
        return code, sinr_db

    def _sinr(self, signal_dbm: FloatArray, interference_mw: FloatArray) -> tuple[FloatArray, ...]:
        signal_mw = np.power(10.0, signal_dbm / 10.0)
        sinr = signal_mw / (self._noise_mw + interference_mw)
        with np.errstate(divide="ignore"):
            sinr_db = 10.0 * np.log10(sinr)
        return signal_mw, sinr, sinr_db, signal_dbm < self.effective_sensitivity_dbm

    def judge_alone(self, distance_m: FloatArray, signal_dbm: FloatArray,
                    bits: NDArray[np.int64]) -> tuple[NDArray[np.int8], FloatArray, FloatArray, int]:
        """:meth:`judge` of receptions nothing interferes with, all but its draw: the codes before
        it, the SINR (dB), each reception's loss probability and the code of a loss. judge()
        would draw one uniform per code-0 reception and lose it below that probability: with no
        interference the three nested PERs are one, so every loss is "sinr"."""
        _, sinr, sinr_db, far = self._sinr(signal_dbm, np.zeros(len(signal_dbm)))
        code = np.where(far, CODE_DISTANCE, 0).astype(np.int8)
        return code, sinr_db, self._per_linear(sinr, bits), CODE_SINR

    def delivery_delay_s(self, distance_m: FloatArray, rng: np.random.Generator) -> FloatArray:
        n = len(distance_m)
        prop = np.asarray(distance_m, dtype=float) / SPEED_OF_LIGHT_M_S
        return prop + self.processing_delay_s + uniform_jitter(self.processing_jitter_s, n, rng)

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
