"""What the channel models and the medium exchange: a frame offered, the outcome at each receiver
(one by one or as arrays), the state of a link, and the protocol a channel model implements."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from netsim.channel.jammer import Jammer
from netsim.channel.physics import FloatArray

Reason = Literal["distance", "sinr", "collision", "half-duplex", "queue", "jammed"]
DROP_REASONS: tuple[Reason, ...] = ("distance", "sinr", "collision", "half-duplex", "queue", "jammed")


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
CODE_DISTANCE, CODE_SINR, CODE_COLLISION, CODE_HALF_DUPLEX, CODE_QUEUE, CODE_JAMMED = (REASON_CODE[r] for r in DROP_REASONS)
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


def uniform_jitter(jitter_s: float, n: int, rng: np.random.Generator) -> FloatArray:
    # Drawing nothing when jitter is off keeps jitter-free runs independent of the rng.
    if jitter_s <= 0.0 or n == 0:
        return np.zeros(n)
    return rng.uniform(0.0, jitter_s, size=n)
