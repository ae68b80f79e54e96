"""Every message type swarmloc puts on the wire, in one registry (see swarmloc.wire).

Adding an estimator family means adding its radio messages here, so docs/wire.md and the
decoder's validation stay complete in one place.
"""

from __future__ import annotations

from dataclasses import field
from typing import Annotated

import numpy as np

from swarmloc.wire import MAX_ID, Array, Bool, Float, Int, ListOf, MapOf, Nested, Optional, Plain, Str, message

Id = Annotated[int, Int(0, MAX_ID)]
Tick = Annotated[int, Int(0, 2**40)]
# Sensor readings: a physical quantity (m, s, m/s, rad, rad/s, m/s^2) or its std beyond this is
# no reading but a fault or a forgery; refused at decoding, so an estimator never squares it.
SENSOR = 1e6
Std = Annotated[float, Float(lo=0.0, hi=SENSOR)]
Reading = Annotated[float, Float(lo=-SENSOR, hi=SENSOR)]
Vec = Annotated[np.ndarray, Array(1)]
Mat = Annotated[np.ndarray, Array(2)]
SqMat = Annotated[np.ndarray, Array(2, square=True)]
Blocks = Annotated[dict, MapOf(Int(0, MAX_ID), Array(2))]
# A chain key: (measurer, kind, target, index within the tick), swarmloc.node.keyed_measurements;
# chains run in this order.
ChainKey = ListOf(Int(0, MAX_ID), length=4)


# --------------------------------------------------------------------------- environment -> agent


@message("clock")
class Clock:
    k: Tick
    t: Annotated[float, Float()]
    mode: Annotated[str, Str(16)]
    dt: Annotated[float, Float(lo=0.0)]
    speed: Annotated[float, Float(lo=0.0)] = 1.0  # real time: modelled seconds per wall second


@message("odometry")
class OdometryMsg:
    dt: Std
    speed: Reading
    heading: Reading
    speed_std: Std
    heading_std: Std
    # The gyro's turn rate over the step and its std: what a model with heading in its state
    # (planar-pose) reads instead of `heading`.
    turn_rate: Reading = 0.0
    turn_rate_std: Std = 0.0


@message("range")
class RangeMsg:
    target: Id
    range: Std
    std: Std


@message("gnss")
class GnssMsg:
    """A GNSS position fix: position (m, swarm frame), std of each horizontal coordinate and,
    for a 3D fix, of the vertical one (None: the horizontal std)."""

    position: Vec
    std: Std
    std_vertical: Annotated[float | None, Optional(Float(lo=0.0, hi=SENSOR))] = None


@message("imu")
class ImuMsg:
    """The IMU intervals of one tick, oldest first: each row is the mean body angular rate
    (rad/s) and mean specific force (m/s^2) over `dt` seconds, body axes FLU:
    [gx, gy, gz, ax, ay, az]."""

    dt: Std
    samples: Annotated[np.ndarray, Array(2, bound=SENSOR)]


@message("pseudoranges")
class PseudorangesMsg:
    """GNSS pseudoranges of one epoch: satellite positions (rows, m, swarm ENU frame) and the
    measured pseudorange to each (m, receiver clock bias included), all with std `std`."""

    sats: Mat
    rho: Vec
    std: Std


@message("relpos")
class RelPosMsg:
    """Relative position of platform `target` seen from the measurer, p_target - p_measurer
    (m, swarm ENU frame), each component with std `std`."""

    target: Id
    z: Annotated[np.ndarray, Array(1, bound=SENSOR)]
    std: Std


@message("target_range")
class TargetRangeMsg:
    """A range from the measuring agent to target `target` (an id of the scenario's
    `world.targets`, its own id space), taken only within `sensors.target_range.max_range`
    and with probability `sensors.target_range.probability` per tick."""

    target: Id
    range: Std
    std: Std


@message("range_bearing")
class RangeBearingMsg:
    """A range (m) and a bearing (rad, in the measurer's body frame: counter-clockwise from its
    heading, in [-pi, pi)) to `target`: another agent (Sensors.rb) or a landmark of the
    scenario's `world.landmarks` map (Sensors.landmarks, the landmarks' own id space)."""

    target: Id
    range: Std
    bearing: Reading
    range_std: Std
    bearing_std: Std


@message("align")
class AlignMsg:
    """A UAS's pre-flight alignment, in its tick-0 frame only: its initial state estimate in
    the uas-ins model's layout and that estimate's error covariance (docs/uas.md)."""

    x: Vec
    P: SqMat


@message("vehicle")
class VehicleMsg:
    """A vehicle's own readings over the last `dt` (quadrotor or ground robot, Oliveros &
    Ashrafiuon 2023): the actuator command that was in force (its flight controller reports what
    it applied), the IMU's orientation, and the relative positions it measured, each in its own
    body frame (x forward, y left, z up)."""

    dt: Std
    u: Annotated[np.ndarray, Array(1, bound=SENSOR)]
    attitude: Annotated[np.ndarray, Array(1, bound=SENSOR)]
    attitude_std: Std
    seen: Annotated[list, ListOf(Nested(RelPosMsg), max_len=64)] = field(default_factory=list)


@message("sensors")
class Sensors:
    """One agent's sensor frame for tick k; relative measurements in the order they were taken.
    A platform carries the sensors its model reads: odometry for a planar robot, imu for a UAS
    (None otherwise); gnss (a position fix) and pseudoranges are None without a receiver, in an
    outage or between GNSS epochs."""

    k: Tick
    t: Annotated[float, Float()]
    odometry: Annotated[OdometryMsg | None, Optional(Nested(OdometryMsg))]
    ranges: Annotated[list, ListOf(Nested(RangeMsg), max_len=64)]
    gnss: Annotated[GnssMsg | None, Optional(Nested(GnssMsg))] = None
    imu: Annotated[ImuMsg | None, Optional(Nested(ImuMsg))] = None
    pseudoranges: Annotated[PseudorangesMsg | None, Optional(Nested(PseudorangesMsg))] = None
    relpos: Annotated[list, ListOf(Nested(RelPosMsg), max_len=64)] = field(default_factory=list)
    align: Annotated[AlignMsg | None, Optional(Nested(AlignMsg))] = None
    targets: Annotated[list, ListOf(Nested(TargetRangeMsg), max_len=64)] = field(default_factory=list)
    rb: Annotated[list, ListOf(Nested(RangeBearingMsg), max_len=64)] = field(default_factory=list)
    landmarks: Annotated[list, ListOf(Nested(RangeBearingMsg), max_len=64)] = field(default_factory=list)
    vehicle: Annotated[VehicleMsg | None, Optional(Nested(VehicleMsg))] = None


@message("truth")
class Truth:
    k: Tick
    t: Annotated[float, Float()]
    state: Vec


# --------------------------------------------------------------------------- agent -> anyone


@message("target_estimate")
class TargetEstimateMsg:
    """An agent's estimate of target `target`: position (m, swarm frame) and its covariance."""

    target: Id
    mean: Vec
    cov: SqMat


@message("estimate")
class EstimateMsg:
    k: Tick
    algorithm: Annotated[str, Str(32)]
    mean: Vec
    cov: SqMat
    # (NIS, degrees of freedom) of each innovation the estimator formed in tick k (rows).
    nis: Annotated[np.ndarray | None, Optional(Array(2))] = None
    # The agent's estimate of each target it localizes (CSL-CTL, IL-CTL); [] otherwise.
    targets: Annotated[list, ListOf(Nested(TargetEstimateMsg), max_len=64)] = field(default_factory=list)


@message("done")
class Done:
    """Lockstep acknowledgement: tick k handled, `consumed` = last netsim delivery number handled,
    `sent` = radio frames published so far."""

    k: Annotated[int, Int(-1, 2**40)]  # -1: no tick handled yet
    consumed: Annotated[int, Int(0)]
    sent: Annotated[int, Int(0)]
    commands: Annotated[int, Int(0)] = 0  # actuator commands published so far (closed loop)


@message("command")
class Command:
    """Agent -> its vehicle (netsim): the actuator command computed from the agent's estimate of
    tick k, in force from tick k+1 until the next one arrives."""

    k: Tick
    u: Annotated[np.ndarray, Array(1, bound=SENSOR)]


# --------------------------------------------------------------------------- radio payloads


# How many state-changing commits of each measurer a UKF-DCL node has applied (a version
# vector, zero entries left out). Two nodes with equal versions hold equal copies of every
# cross-covariance between them.
VersionMap = MapOf(Int(0, MAX_ID), Int(1, 2**40))
Version = Annotated[dict, VersionMap]


@message("beacon")
class Beacon:
    """Periodic hello: who I am, where I think I am and how sure I am of it (neighbour
    discovery, and anchors for a lost neighbour finding itself again) and, for UKF-DCL, my
    version, so a neighbour that is ahead can be asked for the commits I missed."""

    k: Tick
    position: Vec
    cov: SqMat  # covariance of position
    version: Version


@message("ci.pose")
class PoseBeacon:
    """EKF-CI on planar-pose robots, broadcast every tick: the sender's pose estimate [x, y,
    heading] of tick k before any fusion of that tick, its covariance, and the sender's
    observations of other robots in tick k, so that a robot it observed can fuse them too
    (docs/ekf-ci.md, "Planar-pose robots")."""

    k: Tick
    pose: Vec
    cov: SqMat
    seen: Annotated[list, ListOf(Nested(RangeBearingMsg), max_len=64)] = field(default_factory=list)


IdList = Annotated[list, ListOf(Int(0, MAX_ID))]

# Token status: what happened to the measurement on the way. VERSION: m and n had applied
# different commits, so the pair's covariance is not known to both alike; the chain runs empty.
CHAIN_OK, CHAIN_UNREACHABLE, CHAIN_REFUSED, CHAIN_VERSION = 0, 1, 2, 3


@message("dcl.start")
class DclStart:
    """UKF-DCL, measurer m -> measured n: the measurement and m's side of the pair: its mean,
    its whole covariance row (so n can form every gain), its version and whether it is an
    orphan (a node whose cross-covariances were lost, see docs/ukf-dcl.md)."""

    k: Tick
    epoch: Annotated[int, Int(0)]
    key: Annotated[list, ChainKey]
    z: Vec
    R: SqMat
    x_m: Vec
    row_m: Blocks
    version: Version
    orphan: Annotated[bool, Bool()]
    pending: Annotated[list, ListOf(ChainKey)]
    phi: Blocks = field(default_factory=dict)  # F != I: {m: Phi_m}, m's transition product (core coordinates)


@message("dcl.token")
class DclToken:
    """UKF-DCL location information travelling the chain (depth first, with backtracking).

    L is the lower Cholesky factor of the (m, n) covariance block (A11, A21, A22), Y the
    sigma-point term with Pxz_i = [P_im P_in] L^-T Y (eq. 20). n forms the gain of every node
    correlated with m or n from the two rows (`gains`); the nodes the token visits add their
    version (`versions`) and, if they are orphans, their id (`orphans`), so the measurer can
    tell who can take part. Nothing is applied until the commit.
    """

    k: Tick
    epoch: Annotated[int, Int(0)]
    key: Annotated[list, ChainKey]
    status: Annotated[int, Int(0, 3)]
    L: SqMat
    Y: Mat
    Pz: SqMat
    nu: Vec
    order: IdList
    parent: Annotated[dict, MapOf(Int(0, MAX_ID), Int(0, MAX_ID))]
    gains: Blocks
    versions: Annotated[dict, MapOf(Int(0, MAX_ID), VersionMap)]
    orphans: IdList
    pending: Annotated[list, ListOf(ChainKey)]
    phi: Blocks = field(default_factory=dict)  # F != I: Phi of m and n when n formed the gains


@message("dcl.commit")
class DclCommit:
    """UKF-DCL commit, flooded down the chain's tree from the measurer and replayed to nodes
    that missed it (`dcl.log`).

    A commit with `seq` > 0 changes state: it is measurer m's `seq`-th such commit, computed at
    version `version` (m's, which every participant shared), and every node applies it once, in
    an order that respects `version` (its causal history). It either applies the measurement
    (`gains` for every node correlated with m or n; `participants` update their mean and own
    block, everyone else only the cross-covariances with the participants), or removes orphans
    (`removed`: [group size, orphan id] pairs). A commit with `seq` = 0 changes nothing but the
    chain's epoch. `finished` says whether the measurement is done (applied or dropped) or will
    be retried in the next epoch.
    """

    k: Tick
    epoch: Annotated[int, Int(0)]
    key: Annotated[list, ChainKey]
    seq: Annotated[int, Int(0, 2**40)]
    version: Version
    L: SqMat
    Y: Mat
    Pz: SqMat
    nu: Vec
    parent: Annotated[dict, MapOf(Int(0, MAX_ID), Int(0, MAX_ID))]
    gains: Blocks
    participants: IdList
    removed: Annotated[list, ListOf(ListOf(Int(0, MAX_ID), length=2))]
    finished: Annotated[bool, Bool()]
    pending: Annotated[list, ListOf(ChainKey)]
    phi: Blocks = field(default_factory=dict)  # the token's: outsiders form their core gain with it


@message("dcl.sync")
class DclSync:
    """UKF-DCL: "send me the commits I lack"; `version` is the asker's."""

    k: Tick
    version: Version


@message("dcl.log")
class DclLog:
    """UKF-DCL: commits the receiver lacks, oldest first (an answer to dcl.sync)."""

    k: Tick
    commits: Annotated[list, ListOf(Nested(DclCommit), max_len=64)]


# CSL-CTL and IL-CTL (Wang et al. 2022): every agent shares what it measured this tick.


@message("csl.share")
class CslShare:
    """CSL-CTL, broadcast once per tick: the sender's sensor frame of tick k (odometry, ranges
    to agents, ranges to targets). Every agent runs the joint problem of the agents it hears."""

    k: Tick
    sensors: Annotated[Sensors, Nested(Sensors)]


@message("ctl.fix")
class CtlFix:
    """IL-CTL, broadcast once per tick: the sender's own position estimate after tick k (its
    IL dead reckoning) and its ranges to targets, which the receivers take as exact anchors."""

    k: Tick
    mean: Vec
    cov: SqMat
    targets: Annotated[list, ListOf(Nested(TargetRangeMsg), max_len=64)]


@message("veh.pose")
class VehiclePose:
    """ekf-local (vehicles, no CL), broadcast every tick: the sender's estimate of tick k after
    its own sensors (command, IMU, GPS) and before any relative measurement of the tick, in its
    model's state layout (swarmloc/vehicles.py), and its covariance."""

    k: Tick
    x: Vec
    P: SqMat


# EKF fusion centre (Goel et al. section 3): UAS send their inputs, the centre runs the joint EKF.


@message("fc.data")
class CentreData:
    """UAS -> fusion centre, unicast, every tick: the UAS's sensor frame of tick k and, when
    the UAS does not hold the centre's answer for the previous tick (the centre is new,
    restarted or was out of reach), its own estimate of tick k after its own step (x, P), from
    which the centre takes the UAS into its joint state."""

    k: Tick
    sensors: Annotated[Sensors, Nested(Sensors)]
    x: Annotated[np.ndarray | None, Optional(Array(1))] = None
    P: Annotated[np.ndarray | None, Optional(Array(2, square=True))] = None


@message("fc.estimate")
class CentreEstimate:
    """Fusion centre -> UAS, unicast: the UAS's marginal of the joint estimate after tick k
    (x in the uas-ins layout, P its error covariance)."""

    k: Tick
    x: Vec
    P: SqMat


# dNBP (Wan et al. 2014): beliefs as weighted sample sets, float32 on the wire (docs/wire.md).
NBP_MAX_SAMPLES = 1000  # M: samples in one belief
NBP_MAX_DIM = 3  # d: a 2D or 3D position


@message("nbp.belief", max_bytes=20 * 1024)  # M = 1000, d = 3: at most 16265 bytes
class NbpBelief:
    """dNBP, broadcast: the sender's belief over its position in time slice k after its
    `it`-th send of the slice: M weighted samples (float32) and the kernel bandwidth of the
    Gaussian mixture they define (Wan et al. 2014, Algorithms 1-2). `normal`: the sender has a
    GNSS fix in this slice (receivers that are normal ignore beliefs of fault senders)."""

    k: Tick
    it: Annotated[int, Int(0, 255)]
    normal: Annotated[bool, Bool()]
    samples: Annotated[np.ndarray, Array(2, dtype="<f4", dims=((1, NBP_MAX_SAMPLES), (1, NBP_MAX_DIM)))]  # (M, d)
    weights: Annotated[np.ndarray, Array(1, dtype="<f4", dims=((1, NBP_MAX_SAMPLES),))]  # (M,)
    bandwidth: Annotated[np.ndarray, Array(2, square=True, dims=((1, NBP_MAX_DIM), (1, NBP_MAX_DIM)))]  # (d, d)


@message("radio.nack")
class LinkNack:
    """The radio could not deliver our unicast frame `seq` to `dst` (a MAC's missing ACK).

    netsim sends it on radio/rx/<sender>; a real radio driver would report the same."""

    seq: Annotated[int, Int(0)]
    dst: Id
    reason: Annotated[str, Str(32)]


# --------------------------------------------------------------------------- netsim control & monitoring


@message("control")
class Control:
    """Request to netsim/control: op is one of inject, clear, faults, status (docs/wire.md)."""

    op: Annotated[str, Str(32)]
    args: Annotated[dict, Plain()]


@message("reply")
class Reply:
    ok: Annotated[bool, Bool()]
    error: Annotated[str, Str(512)]
    data: Annotated[dict, Plain()]


@message("event")
class Event:
    """netsim -> launcher: something the launcher must do to the processes (kill, restart)."""

    kind: Annotated[str, Str(16)]
    node: Id
    t: Annotated[float, Float()]


@message("link")
class LinkMsg:
    """One pair's link as netsim sees it: physics (SNR without interference, modelled delivery
    ratio), faults (up, reason) and what actually happened (SINR of the last frame with the
    interference it met, counts, last frame heard)."""

    a: Id
    b: Id
    up: Annotated[bool, Bool()]
    distance: Annotated[float, Float(finite=False)]
    reason: Annotated[str, Str(32)]
    snr_db: Annotated[float, Float(finite=False)]
    sinr_db: Annotated[float | None, Optional(Float())]  # of the last frame heard (worse direction)
    pdr_model: Annotated[float, Float(finite=False)]
    delivered: Annotated[int, Int(0)]
    dropped: Annotated[int, Int(0)]
    delivery_ratio: Annotated[float | None, Optional(Float())]
    last_heard: Annotated[float | None, Optional(Float())]


@message("links")
class Links:
    k: Tick
    links: Annotated[list, ListOf(Nested(LinkMsg), max_len=4096)]

