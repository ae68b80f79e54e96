"""Every message type swarmloc puts on the wire, in one registry (see swarmloc.wire).

Adding an estimator family means adding its radio messages here, so docs/wire.md and the
decoder's validation stay complete in one place. Each type is a msgspec Struct
(swarmloc/wire/schema.py): its annotations are the field's wire type and bounds, and a test
holds docs/wire.md's tables to them (tests/test_wire_docs.py). A default applies when a message
is constructed; on the wire every field is required.
"""

from typing import Annotated, Any

import numpy as np
from msgspec import field

from swarmloc.wire.schema import (
    PLAIN,
    Array,
    ChainKey,
    Float,
    FloatIn,
    Id,
    Int,
    ListOf,
    MapOf,
    Message,
    Named,
    Str,
    Tick,
    Version,
    message,
)

# Sensor readings: a physical quantity (m, s, m/s, rad, rad/s, m/s^2) or its std beyond this is
# no reading but a fault or a forgery; refused at decoding, so an estimator never squares it.
SENSOR = 1e6
Std = FloatIn(0.0, SENSOR)
Reading = FloatIn(-SENSOR, SENSOR)
NonNegative = FloatIn(0.0)
Vec = Annotated[np.ndarray, Array(1)]
Mat = Annotated[np.ndarray, Array(2)]
SqMat = Annotated[np.ndarray, Array(2, square=True)]
SensorVec = Annotated[np.ndarray, Array(1, bound=SENSOR)]
Blocks = Annotated[MapOf(Id, Mat), Named("Blocks")]
Plain = Annotated[Any, PLAIN]


# --------------------------------------------------------------------------- environment -> agent


@message("clock")
class Clock(Message):
    k: Tick
    t: Float
    mode: Str(16)
    dt: NonNegative
    speed: NonNegative = 1.0  # real time: modelled seconds per wall second


@message("odometry")
class OdometryMsg(Message):
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
class RangeMsg(Message):
    target: Id
    range: Std
    std: Std


@message("gnss")
class GnssMsg(Message):
    """A GNSS position fix: position (m, swarm frame), std of each horizontal coordinate and,
    for a 3D fix, of the vertical one (None: the horizontal std)."""

    position: Vec
    std: Std
    std_vertical: Std | None = None


@message("imu")
class ImuMsg(Message):
    """The IMU intervals of one tick, oldest first: each row is the mean body angular rate
    (rad/s) and mean specific force (m/s^2) over `dt` seconds, body axes FLU:
    [gx, gy, gz, ax, ay, az]."""

    dt: Std
    samples: Annotated[np.ndarray, Array(2, bound=SENSOR)]


@message("pseudoranges")
class PseudorangesMsg(Message):
    """GNSS pseudoranges of one epoch: satellite positions (rows, m, swarm ENU frame) and the
    measured pseudorange to each (m, receiver clock bias included), all with std `std`."""

    sats: Mat
    rho: Vec
    std: Std


@message("relpos")
class RelPosMsg(Message):
    """Relative position of platform `target` seen from the measurer, p_target - p_measurer
    (m, swarm ENU frame), each component with std `std`."""

    target: Id
    z: SensorVec
    std: Std


@message("target_range")
class TargetRangeMsg(Message):
    """A range from the measuring agent to target `target` (an id of the scenario's
    `world.targets`, its own id space), taken only within `sensors.target_range.max_range`
    and with probability `sensors.target_range.probability` per tick."""

    target: Id
    range: Std
    std: Std


@message("range_bearing")
class RangeBearingMsg(Message):
    """A range (m) and a bearing (rad, in the measurer's body frame: counter-clockwise from its
    heading, in [-pi, pi)) to `target`: another agent (Sensors.rb) or a landmark of the
    scenario's `world.landmarks` map (Sensors.landmarks, the landmarks' own id space)."""

    target: Id
    range: Std
    bearing: Reading
    range_std: Std
    bearing_std: Std


@message("align")
class AlignMsg(Message):
    """A UAS's pre-flight alignment, in its tick-0 frame only: its initial state estimate in
    the uas-ins model's layout and that estimate's error covariance (docs/uas.md)."""

    x: Vec
    P: SqMat


@message("vehicle")
class VehicleMsg(Message):
    """A vehicle's own readings over the last `dt` (quadrotor or ground robot, Oliveros &
    Ashrafiuon 2023): the actuator command that was in force (its flight controller reports what
    it applied), the IMU's orientation, and the relative positions it measured, each in its own
    body frame (x forward, y left, z up)."""

    dt: Std
    u: SensorVec
    attitude: SensorVec
    attitude_std: Std
    seen: ListOf(RelPosMsg, 64) = field(default_factory=list)


@message("sensors")
class Sensors(Message):
    """One agent's sensor frame for tick k; relative measurements in the order they were taken.
    A platform carries the sensors its model reads: odometry for a planar robot, imu for a UAS
    (None otherwise); gnss (a position fix) and pseudoranges are None without a receiver, in an
    outage or between GNSS epochs."""

    k: Tick
    t: Float
    odometry: OdometryMsg | None
    ranges: ListOf(RangeMsg, 64)
    gnss: GnssMsg | None = None
    imu: ImuMsg | None = None
    pseudoranges: PseudorangesMsg | None = None
    relpos: ListOf(RelPosMsg, 64) = field(default_factory=list)
    align: AlignMsg | None = None
    targets: ListOf(TargetRangeMsg, 64) = field(default_factory=list)
    rb: ListOf(RangeBearingMsg, 64) = field(default_factory=list)
    landmarks: ListOf(RangeBearingMsg, 64) = field(default_factory=list)
    vehicle: VehicleMsg | None = None


@message("truth")
class Truth(Message):
    k: Tick
    t: Float
    state: Vec


# --------------------------------------------------------------------------- agent -> anyone


@message("target_estimate")
class TargetEstimateMsg(Message):
    """An agent's estimate of target `target`: position (m, swarm frame) and its covariance."""

    target: Id
    mean: Vec
    cov: SqMat


@message("estimate")
class EstimateMsg(Message):
    k: Tick
    algorithm: Str(32)
    mean: Vec
    cov: SqMat
    # (NIS, degrees of freedom) of each innovation the estimator formed in tick k (rows).
    nis: Mat | None = None
    # The agent's estimate of each target it localizes (CSL-CTL, IL-CTL); [] otherwise.
    targets: ListOf(TargetEstimateMsg, 64) = field(default_factory=list)


@message("done")
class Done(Message):
    """Lockstep acknowledgement: tick k handled, `consumed` = last netsim delivery number handled,
    `sent` = radio frames published so far."""

    k: Int(-1, 2**40)  # -1: no tick handled yet
    consumed: Int(0)
    sent: Int(0)
    commands: Int(0) = 0  # actuator commands published so far (closed loop)


@message("command")
class Command(Message):
    """Agent -> its vehicle (netsim): the actuator command computed from the agent's estimate of
    tick k, in force from tick k+1 until the next one arrives."""

    k: Tick
    u: SensorVec


# --------------------------------------------------------------------------- radio payloads


@message("beacon")
class Beacon(Message):
    """Periodic hello: who I am, where I think I am and how sure I am of it (neighbour
    discovery, and anchors for a lost neighbour finding itself again) and, for UKF-DCL, my
    version, so a neighbour that is ahead can be asked for the commits I missed."""

    k: Tick
    position: Vec
    cov: SqMat  # covariance of position
    version: Version


@message("ci.pose")
class PoseBeacon(Message):
    """EKF-CI on planar-pose robots, broadcast every tick: the sender's pose estimate [x, y,
    heading] of tick k before any fusion of that tick, its covariance, and the sender's
    observations of other robots in tick k, so that a robot it observed can fuse them too
    (docs/ekf-ci.md, "Planar-pose robots")."""

    k: Tick
    pose: Vec
    cov: SqMat
    seen: ListOf(RangeBearingMsg, 64) = field(default_factory=list)


IdList = ListOf(Id)

# Token status: what happened to the measurement on the way. VERSION: m and n had applied
# different commits, so the pair's covariance is not known to both alike; the chain runs empty.
CHAIN_OK, CHAIN_UNREACHABLE, CHAIN_REFUSED, CHAIN_VERSION = 0, 1, 2, 3


@message("dcl.start")
class DclStart(Message):
    """UKF-DCL, measurer m -> measured n: the measurement and m's side of the pair: its mean,
    its whole covariance row (so n can form every gain), its version and whether it is an
    orphan (a node whose cross-covariances were lost, see docs/ukf-dcl.md)."""

    k: Tick
    epoch: Int(0)
    key: ChainKey
    z: Vec
    R: SqMat
    x_m: Vec
    row_m: Blocks
    version: Version
    orphan: bool
    pending: ListOf(ChainKey)
    phi: Blocks = field(default_factory=dict)  # F != I: {m: Phi_m}, m's transition product (core coordinates)


@message("dcl.token")
class DclToken(Message):
    """UKF-DCL location information travelling the chain (depth first, with backtracking).

    L is the lower Cholesky factor of the (m, n) covariance block (A11, A21, A22), Y the
    sigma-point term with Pxz_i = [P_im P_in] L^-T Y (eq. 20). n forms the gain of every node
    correlated with m or n from the two rows (`gains`); the nodes the token visits add their
    version (`versions`) and, if they are orphans, their id (`orphans`), so the measurer can
    tell who can take part. Nothing is applied until the commit.
    """

    k: Tick
    epoch: Int(0)
    key: ChainKey
    status: Int(0, 3)
    L: SqMat
    Y: Mat
    Pz: SqMat
    nu: Vec
    order: IdList
    parent: MapOf(Id, Id)
    gains: Blocks
    versions: MapOf(Id, Version)
    orphans: IdList
    pending: ListOf(ChainKey)
    phi: Blocks = field(default_factory=dict)  # F != I: Phi of m and n when n formed the gains


@message("dcl.commit")
class DclCommit(Message):
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
    epoch: Int(0)
    key: ChainKey
    seq: Int(0, 2**40)
    version: Version
    L: SqMat
    Y: Mat
    Pz: SqMat
    nu: Vec
    parent: MapOf(Id, Id)
    gains: Blocks
    participants: IdList
    removed: ListOf(ListOf(Id, length=2))
    finished: bool
    pending: ListOf(ChainKey)
    phi: Blocks = field(default_factory=dict)  # the token's: outsiders form their core gain with it


@message("dcl.sync")
class DclSync(Message):
    """UKF-DCL: "send me the commits I lack"; `version` is the asker's."""

    k: Tick
    version: Version


@message("dcl.log")
class DclLog(Message):
    """UKF-DCL: commits the receiver lacks, oldest first (an answer to dcl.sync)."""

    k: Tick
    commits: ListOf(DclCommit, 64)


# RDL (Luft et al. 2018; docs/rdl.md): a relative measurement is processed by the two platforms
# it involves and no one else. A cross-covariance is the product of two factors, one held by
# each side (sigma_ij sigma_ji^T); a factor travels as a mantissa (its largest magnitude in
# [0.5, 1)) and a binary exponent, exact both ways, because one side of a product may shrink by
# many orders of magnitude while the other stays.
# RDL commit status: the measurement was applied; rejected by the chi-square gate; refused (the
# pair's covariance not positive definite, a frame of another tick).
RDL_OK, RDL_GATED, RDL_REFUSED = 0, 1, 2


@message("rdl.meas")
class RdlMeas(Message):
    """RDL, measurer m -> measured n when n has the lower id: the measurement, which n takes up
    as its own (the lower id of a pair asks, the higher one answers, so waits cannot form a cycle)."""

    k: Tick
    key: ChainKey
    z: Vec
    R: SqMat


@message("rdl.req")
class RdlRequest(Message):
    """RDL, the pair's lower id a -> the higher id b: the measurement and a's side of the pair:
    its mean, its covariance and its factor sigma_ab of the pair's cross-covariance (empty
    when it holds none), as mantissa and exponent."""

    k: Tick
    key: ChainKey
    z: Vec
    R: SqMat
    x: Vec
    P: SqMat
    factor: MapOf(Id, Mat, 1)
    exponent: MapOf(Id, Int(-1100, 1100), 1)


@message("rdl.commit")
class RdlCommit(Message):
    """RDL, b -> a: the measurement's result: a's posterior mean and covariance and its new
    factor of the pair's cross-covariance (`cross`, the whole posterior block Sigma_ab; b's
    factor is now I). Unless `status` is RDL_OK, x and P are a's own, unchanged."""

    k: Tick
    key: ChainKey
    status: Int(0, 2)
    x: Vec
    P: SqMat
    cross: Mat
    nis: NonNegative = 0.0


# CSL-CTL and IL-CTL (Wang et al. 2022): every agent shares what it measured this tick.


@message("csl.share")
class CslShare(Message):
    """CSL-CTL, broadcast once per tick: the sender's sensor frame of tick k (odometry, ranges
    to agents, ranges to targets). Every agent runs the joint problem of the agents it hears."""

    k: Tick
    sensors: Sensors


@message("ctl.fix")
class CtlFix(Message):
    """IL-CTL, broadcast once per tick: the sender's own position estimate after tick k (its
    IL dead reckoning) and its ranges to targets, which the receivers take as exact anchors."""

    k: Tick
    mean: Vec
    cov: SqMat
    targets: ListOf(TargetRangeMsg, 64)


@message("veh.pose")
class VehiclePose(Message):
    """ekf-local (vehicles, CL without cross-covariances), broadcast every tick: the sender's
    estimate of tick k after its own sensors (command, IMU, GPS) and before any relative
    measurement of the tick, in its model's state layout (swarmloc/models/vehicles.py), and its
    covariance. raw (the paper's "without CL"): the sender's raw pose of tick k, once it has it."""

    k: Tick
    x: Vec
    P: SqMat


# EKF fusion centre (Goel et al. section 3): UAS send their inputs, the centre runs the joint EKF.


@message("fc.data")
class CentreData(Message):
    """UAS -> fusion centre, unicast, every tick: the UAS's sensor frame of tick k and, when
    the UAS does not hold the centre's answer for the previous tick (the centre is new,
    restarted or was out of reach), its own estimate of tick k after its own step (x, P), from
    which the centre takes the UAS into its joint state."""

    k: Tick
    sensors: Sensors
    x: Vec | None = None
    P: SqMat | None = None


@message("fc.estimate")
class CentreEstimate(Message):
    """Fusion centre -> UAS, unicast: the UAS's marginal of the joint estimate after tick k
    (x in the uas-ins layout, P its error covariance)."""

    k: Tick
    x: Vec
    P: SqMat


# dNBP (Wan et al. 2014): beliefs as weighted sample sets, float32 on the wire (docs/wire.md).
NBP_MAX_SAMPLES = 1000  # M: samples in one belief
NBP_MAX_DIM = 3  # d: a 2D or 3D position


@message("nbp.belief", max_bytes=20 * 1024)  # M = 1000, d = 3: at most 16265 bytes
class NbpBelief(Message):
    """dNBP, broadcast: the sender's belief over its position in time slice k after its
    `it`-th send of the slice: M weighted samples (float32) and the kernel bandwidth of the
    Gaussian mixture they define (Wan et al. 2014, Algorithms 1-2). `normal`: the sender has a
    GNSS fix in this slice (receivers that are normal ignore beliefs of fault senders)."""

    k: Tick
    it: Int(0, 255)
    normal: bool
    samples: Annotated[np.ndarray, Array(2, dtype="<f4", dims=((1, NBP_MAX_SAMPLES), (1, NBP_MAX_DIM)))]  # (M, d)
    weights: Annotated[np.ndarray, Array(1, dtype="<f4", dims=((1, NBP_MAX_SAMPLES),))]  # (M,)
    bandwidth: Annotated[np.ndarray, Array(2, square=True, dims=((1, NBP_MAX_DIM), (1, NBP_MAX_DIM)))]  # (d, d)


@message("time.echo")
class TimeEcho(Message):
    """One peer's clock stamp echoed back: `sent`, the UNIX send time its latest radio frame to
    us carried, and `received`, our UNIX time when we took that frame."""

    peer: Id
    sent: Float
    received: Float


@message("time.sync")
class TimeSync(Message):
    """Direct mode, broadcast about once a second by every agent's daemon (never its node): an
    echo for each peer it has heard; the frame's own attachment is its send time. A peer that
    finds its own stamp echoed has NTP's four timestamps and so the two clocks' offset
    (agents/timesync.py, docs/deploy.md#clock-offsets)."""

    echoes: ListOf(TimeEcho, 64)


@message("radio.nack")
class LinkNack(Message):
    """The radio could not deliver our unicast frame `seq` to `dst` (a MAC's missing ACK).

    netsim sends it on radio/rx/<sender>; a real radio driver would report the same."""

    seq: Int(0)
    dst: Id
    reason: Str(32)


# --------------------------------------------------------------------------- netsim control & monitoring


@message("control")
class Control(Message):
    """Request to netsim/control: op is one of inject, clear, faults, status (docs/wire.md)."""

    op: Str(32)
    args: Plain


@message("reply")
class Reply(Message):
    ok: bool
    error: Str(512)
    data: Plain


@message("event")
class Event(Message):
    """netsim -> launcher: something the launcher must do to the processes (kill, restart)."""

    kind: Str(16)
    node: Id
    t: Float


@message("link")
class LinkMsg(Message):
    """One pair's link as netsim sees it: physics (SNR without interference, modelled delivery
    ratio), faults (up, reason) and what actually happened (SINR of the last frame with the
    interference it met, counts, last frame heard)."""

    a: Id
    b: Id
    up: bool
    distance: float
    reason: Str(32)
    snr_db: float
    sinr_db: Float | None  # of the last frame heard (worse direction)
    pdr_model: float
    delivered: Int(0)
    dropped: Int(0)
    delivery_ratio: Float | None
    last_heard: Float | None


@message("links")
class Links(Message):
    k: Tick
    links: ListOf(LinkMsg, 4096)

