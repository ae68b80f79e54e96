"""The unit-disk channel: delivered iff within range; no airtime, no interference."""

from __future__ import annotations

import math
from typing import ClassVar, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from netsim.channel.frames import CODE_DISTANCE, CODE_HALF_DUPLEX, uniform_jitter
from netsim.channel.jammer import Jammer
from netsim.channel.physics import FloatArray


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
        code = np.where(far, CODE_DISTANCE, np.where(half_duplex, CODE_HALF_DUPLEX, 0)).astype(np.int8)
        return code, np.full(len(code), np.nan)

    judge_alone_ignores_size: ClassVar[bool] = True  # judge_alone's answer is the same for every size

    def judge_alone(self, distance_m: FloatArray, signal_dbm: FloatArray,
                    bits: NDArray[np.int64]) -> tuple[NDArray[np.int8], FloatArray, None, int]:
        """:meth:`judge` of receptions nothing overlaps: it draws nothing, so no loss probability."""
        code = np.where(distance_m > self.range_m, CODE_DISTANCE, 0).astype(np.int8)
        return code, np.full(len(code), np.nan), None, 0

    def delivery_delay_s(self, distance_m: FloatArray, rng: np.random.Generator) -> FloatArray:
        n = len(distance_m)
        return self.latency_s + uniform_jitter(self.jitter_s, n, rng)

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
