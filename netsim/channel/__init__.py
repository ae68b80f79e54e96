"""Radio physics of netsim: which receivers get each frame, when, or why not.

The room: physics.py (link budget, BER and PER), frames.py (frames, outcomes, link state, the
channel-model protocol), jammer.py, one module per channel model (unit_disk.py,
log_distance.py) and medium.py (RadioMedium, which applies a model to every frame). This module
is the front door: import from `netsim.channel`.

The package is transport-free and deterministic given a ``numpy.random.Generator``:
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

from netsim.channel.frames import (
                                    DROP_REASONS,
                                    REASON_CODE,
                                    ChannelModel,
                                    LinkInfo,
                                    Outcome,
                                    Outcomes,
                                    Reason,
                                    TxFrame,
)
from netsim.channel.jammer import Jammer
from netsim.channel.log_distance import LogDistance
from netsim.channel.medium import ChannelConfig, RadioMedium
from netsim.channel.physics import (
                                    SPEED_OF_LIGHT_M_S,
                                    THERMAL_NOISE_DBM_PER_HZ,
                                    Modulation,
                                    ber,
                                    dbm_to_mw,
                                    friis_reference_loss_db,
                                    log_distance_path_loss_db,
                                    mw_to_dbm,
                                    noise_floor_dbm,
                                    per,
)
from netsim.channel.unit_disk import UnitDisk

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
    "REASON_CODE",
    "dbm_to_mw",
    "mw_to_dbm",
    "friis_reference_loss_db",
    "log_distance_path_loss_db",
    "noise_floor_dbm",
    "ber",
    "per",
]
