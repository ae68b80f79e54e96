"""ROS 2 over Zenoh without a ROS install: what rmw_zenoh puts on Zenoh, as plain code.

rmw_zenoh (ROS 2's Zenoh middleware) maps a ROS 2 topic to one Zenoh key expression, sends each
message CDR-encoded with a 33-byte attachment, and makes every node, publisher and subscription
visible to `ros2 topic list` through a liveliness token whose key expression spells out the
entity. An agent or netsim that publishes on those keys, with that attachment and those tokens,
is a ROS 2 publisher to every rmw_zenoh node on the same Zenoh network: no bridge, no ROS
install here. Formats (docs/ros2.md says where each comes from):

    topic key        <domain_id>/<fully qualified name without its leading />/<DDS type name>/<type hash>
    node token       @ros2_lv/<domain_id>/<session id>/<node id>/<node id>/NN/<enclave>/<namespace>/<node name>
    entity token     @ros2_lv/<domain_id>/<session id>/<node id>/<entity id>/<MP|MS>/<enclave>/<namespace>/
                     <node name>/<qualified name>/<DDS type name>/<type hash>/<qos>
    attachment       int64 sequence number, int64 source timestamp (ns since the UNIX epoch), both
                     little-endian, one byte 16, the 16-byte GID of the publisher

where a name in a token is mangled (every `/` replaced by `%`, an empty one is `%`), the DDS type
name of `pkg/msg/Type` is `pkg::msg::dds_::Type_` and the type hash is REP-2016's `RIHS01_<sha256>`
(Jazzy and later; Humble has none and writes `TypeHashNotSupported`). Type hashes and CDR come
from rosbags' type store, which holds the message definitions of the named distribution.

No Zenoh here: `Ros2Publisher` and `odometry_key` are given a session (zenoh.Session) by the
process that owns it (the agent daemon, netsim).
"""

from __future__ import annotations

import functools
import hashlib
import math
import re
import struct
from dataclasses import dataclass

import numpy as np

DISTROS = ("jazzy", "humble")
HUMBLE_TYPE_HASH = "TypeHashNotSupported"
POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
# The default QoS profile (reliability, durability, liveliness and deadlines the system's
# defaults, history keep-last 10) in rmw_zenoh's compact form, as its design document's
# examples write it for a keep-last-10 entity.
QOS_DEFAULT = "::,10:,:,:,,"
ATTACHMENT = struct.Struct("<qqB16s")  # 33 bytes
GID_SIZE = 16
UNKNOWN_VARIANCE = 1e6
"""Variance (m², rad², m²/s², rad²/s²) a covariance gets for a coordinate the estimator does
not estimate (a planar robot's height, roll and pitch): large enough that no consumer fuses it."""

NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


class Ros2Error(ValueError):
    pass


def check_namespace(ns: str) -> str:
    """A ROS 2 namespace, absolute: "/" or "/a/b" (each part a ROS name)."""
    if ns in ("", "/"):
        return "/"
    parts = ns.strip("/").split("/") if ns.startswith("/") else None
    if not parts or not all(NAME.fullmatch(p) for p in parts) or ns.endswith("/"):
        raise Ros2Error(f"{ns!r} is not a ROS 2 namespace like /swarmloc or /robot1 (absolute, parts of letters, "
                        "digits and _ not starting with a digit)")
    return ns


def check_domain(domain_id: int) -> int:
    if not isinstance(domain_id, int) or not 0 <= domain_id <= 232:
        raise Ros2Error(f"ROS_DOMAIN_ID {domain_id!r}: an integer from 0 to 232")
    return domain_id


def qualified(namespace: str, name: str) -> str:
    """The fully qualified name of `name` in `namespace`: /ns/name."""
    return f"{check_namespace(namespace).rstrip('/')}/{name}"


def mangle(name: str) -> str:
    """A name as a liveliness token carries it: every / replaced by %, an empty name %."""
    return name.replace("/", "%") if name not in ("", "/") else "%"


def dds_type_name(ros_type: str) -> str:
    """pkg/msg/Type -> pkg::msg::dds_::Type_ (the name a CDR type has in DDS)."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


@functools.lru_cache(maxsize=None)
def typestore(distro: str = "jazzy"):
    """rosbags' store of the message definitions of `distro` (serializer and type hashes)."""
    from rosbags.typesys import Stores, get_typestore

    if distro not in DISTROS:
        raise Ros2Error(f"ROS 2 distribution {distro!r}: one of {', '.join(DISTROS)}")
    return get_typestore(Stores.ROS2_JAZZY if distro == "jazzy" else Stores.ROS2_HUMBLE)


@functools.lru_cache(maxsize=None)
def type_hash(ros_type: str, distro: str = "jazzy") -> str:
    """REP-2016's hash of the type (RIHS01_...), or Humble's placeholder."""
    if distro == "humble":
        return HUMBLE_TYPE_HASH
    return typestore(distro).hash_rihs01(ros_type)


def topic_key(domain_id: int, fqn: str, ros_type: str, distro: str = "jazzy") -> str:
    """The Zenoh key expression rmw_zenoh publishes topic `fqn` of type `ros_type` on."""
    return f"{check_domain(domain_id)}/{fqn.strip('/')}/{dds_type_name(ros_type)}/{type_hash(ros_type, distro)}"


def node_token(domain_id: int, session_id: str, node_id: int, namespace: str, node: str, enclave: str = "") -> str:
    return (f"@ros2_lv/{check_domain(domain_id)}/{session_id}/{node_id}/{node_id}/NN/{mangle(enclave)}/"
            f"{mangle(check_namespace(namespace))}/{node}")


def entity_token(domain_id: int, session_id: str, node_id: int, entity_id: int, kind: str, namespace: str, node: str,
                 fqn: str, ros_type: str, distro: str = "jazzy", qos: str = QOS_DEFAULT, enclave: str = "") -> str:
    """A publisher's (kind MP) or subscription's (MS) liveliness token."""
    if kind not in ("MP", "MS"):
        raise Ros2Error(f"entity kind {kind!r}: MP (publisher) or MS (subscription)")
    return (f"@ros2_lv/{check_domain(domain_id)}/{session_id}/{node_id}/{entity_id}/{kind}/{mangle(enclave)}/"
            f"{mangle(check_namespace(namespace))}/{node}/{mangle(fqn)}/{dds_type_name(ros_type)}/"
            f"{type_hash(ros_type, distro)}/{qos}")


def encode_attachment(seq: int, stamp_ns: int, gid: bytes) -> bytes:
    if len(gid) != GID_SIZE:
        raise Ros2Error(f"a GID is {GID_SIZE} bytes, got {len(gid)}")
    return ATTACHMENT.pack(seq, stamp_ns, GID_SIZE, gid)


def decode_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, GID) of an rmw_zenoh attachment."""
    if data is None or len(data) != ATTACHMENT.size:
        raise Ros2Error(f"an rmw_zenoh attachment is {ATTACHMENT.size} bytes, got {None if data is None else len(data)}")
    seq, stamp, n, gid = ATTACHMENT.unpack(data)
    if n != GID_SIZE:
        raise Ros2Error(f"GID length byte {n}, want {GID_SIZE}")
    return seq, stamp, gid


def gid_of(session_id: str, entity_id: int) -> bytes:
    """A publisher's GID: unique per session and entity (rmw_zenoh leaves its choice to the RMW)."""
    return hashlib.sha256(f"{session_id}/{entity_id}".encode()).digest()[:GID_SIZE]


# --------------------------------------------------------------------------- CDR


def _stamp(ts, t: float):
    sec = math.floor(t)
    nsec = min(999_999_999, int(round((t - sec) * 1e9)))
    return ts.types["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=nsec)


def _header(ts, t: float, frame_id: str):
    return ts.types["std_msgs/msg/Header"](stamp=_stamp(ts, t), frame_id=frame_id)


def _pose_cov(ts, position, q_xyzw, cov6):
    T = ts.types
    pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](*map(float, position)),
                                       orientation=T["geometry_msgs/msg/Quaternion"](*map(float, q_xyzw)))
    return T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.ascontiguousarray(cov6, float).ravel())


def encode_pose(t: float, frame_id: str, position, q_xyzw, cov6, distro: str = "jazzy") -> bytes:
    """geometry_msgs/msg/PoseWithCovarianceStamped, CDR (little-endian, with its 4-byte header)."""
    ts = typestore(distro)
    msg = ts.types[POSE](header=_header(ts, t, frame_id), pose=_pose_cov(ts, position, q_xyzw, cov6))
    return bytes(ts.serialize_cdr(msg, POSE))


def encode_odometry(t: float, frame_id: str, child_frame_id: str, position, q_xyzw, cov6, twist6, twist_cov6,
                    distro: str = "jazzy") -> bytes:
    """nav_msgs/msg/Odometry, CDR: the pose in `frame_id`, the twist in `child_frame_id` (the body)."""
    ts = typestore(distro)
    T = ts.types
    v = T["geometry_msgs/msg/Vector3"]
    twist = T["geometry_msgs/msg/Twist"](linear=v(*map(float, twist6[:3])), angular=v(*map(float, twist6[3:])))
    msg = T[ODOMETRY](header=_header(ts, t, frame_id), child_frame_id=child_frame_id,
                      pose=_pose_cov(ts, position, q_xyzw, cov6),
                      twist=T["geometry_msgs/msg/TwistWithCovariance"](
                          twist=twist, covariance=np.ascontiguousarray(twist_cov6, float).ravel()))
    return bytes(ts.serialize_cdr(msg, ODOMETRY))


@dataclass(frozen=True)
class OdometrySample:
    """What an agent reads from a nav_msgs/msg/Odometry: the header's time (s), the pose, and the
    twist in the body frame (ROS: child_frame_id, x forward, y left, z up)."""

    t: float
    position: np.ndarray  # (3,), header.frame_id
    q: np.ndarray  # (4,) w x y z: body -> header.frame_id
    linear: np.ndarray  # (3,) m/s, body
    angular: np.ndarray  # (3,) rad/s, body


def decode_odometry(data: bytes, distro: str = "jazzy") -> OdometrySample:
    """A CDR nav_msgs/msg/Odometry (Ros2Error when it is not one, or not finite)."""
    try:
        m = typestore(distro).deserialize_cdr(bytes(data), ODOMETRY)
    except Exception as exc:  # rosbags raises several types on a short or garbled buffer
        raise Ros2Error(f"not a CDR nav_msgs/msg/Odometry: {exc.__class__.__name__}: {exc}") from None
    p, o, tw = m.pose.pose.position, m.pose.pose.orientation, m.twist.twist
    s = OdometrySample(m.header.stamp.sec + m.header.stamp.nanosec * 1e-9, np.array([p.x, p.y, p.z]),
                       np.array([o.w, o.x, o.y, o.z]), np.array([tw.linear.x, tw.linear.y, tw.linear.z]),
                       np.array([tw.angular.x, tw.angular.y, tw.angular.z]))
    if not all(np.all(np.isfinite(a)) for a in (s.position, s.q, s.linear, s.angular)) or not math.isfinite(s.t):
        raise Ros2Error("nav_msgs/msg/Odometry with non-finite numbers")
    n = float(np.linalg.norm(s.q))
    if not 0.5 < n < 1.5:
        raise Ros2Error(f"orientation quaternion of norm {n:.3g}")
    return OdometrySample(s.t, s.position, s.q / n, s.linear, s.angular)


# --------------------------------------------------------------------------- estimates as ROS messages


def _yaw_quat(yaw: float) -> np.ndarray:
    return np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])  # x y z w


def _xyzw(q_wxyz) -> np.ndarray:
    w, x, y, z = q_wxyz
    return np.array([x, y, z, w])


@dataclass(frozen=True)
class RosPose:
    """An estimate in ROS terms: position and orientation in the swarm's ENU frame with their
    6 x 6 covariance (x, y, z, rotation about x, y, z), and the body-frame twist with its own."""

    position: np.ndarray
    q_xyzw: np.ndarray
    cov: np.ndarray
    twist: np.ndarray
    twist_cov: np.ndarray


def ros_pose(model: str, mean: np.ndarray, cov: np.ndarray) -> RosPose | None:
    """An agent's estimate (its model's layout, swarmloc/models/motion.py) as a ROS pose; None for
    a model without a pose (a ground station). Coordinates the model does not estimate get
    UNKNOWN_VARIANCE and no correlation."""
    from scipy.spatial.transform import Rotation

    mean, cov = np.asarray(mean, float), np.asarray(cov, float)
    P = np.diag(np.full(6, UNKNOWN_VARIANCE))
    T = np.diag(np.full(6, UNKNOWN_VARIANCE))
    twist = np.zeros(6)
    pos = np.zeros(3)
    q = np.array([0.0, 0.0, 0.0, 1.0])
    if model in ("planar-speed-heading", "planar-pose"):
        pos[:2] = mean[:2]
        idx = [0, 1] if model == "planar-speed-heading" else [0, 1, 5]
        if model == "planar-pose":
            q = _yaw_quat(float(mean[2]))
        P[np.ix_(idx, idx)] = cov[: len(idx), : len(idx)]
    elif model == "uas-ins":
        pos = mean[0:3].copy()
        r = Rotation.from_rotvec(mean[6:9])  # body FLU -> ENU
        q = r.as_quat()
        P[np.ix_(range(3), range(3))] = cov[0:3, 0:3]
        P[np.ix_(range(3, 6), range(3, 6))] = cov[6:9, 6:9]
        P[np.ix_(range(3), range(3, 6))] = cov[0:3, 6:9]
        P[np.ix_(range(3, 6), range(3))] = cov[6:9, 0:3]
        C = r.as_matrix()
        twist[:3] = C.T @ mean[3:6]
        T[:3, :3] = C.T @ cov[3:6, 3:6] @ C
    elif model == "quadrotor":
        pos = mean[0:3].copy()
        qw = mean[3:7] / np.linalg.norm(mean[3:7])
        q = _xyzw(qw)
        P[:3, :3] = cov[0:3, 0:3]
        twist = mean[7:13].copy()
        T = cov[7:13, 7:13].copy()
    elif model == "ground-robot":
        pos = mean[0:3].copy()
        q = _yaw_quat(float(mean[3]))
        idx = [0, 1, 2, 5]
        P[np.ix_(idx, idx)] = cov[0:4, 0:4]
        twist[[0, 2, 5]] = mean[4:7]
        T[np.ix_([0, 2, 5], [0, 2, 5])] = cov[4:7, 4:7]
    else:
        return None
    return RosPose(pos, q, P, twist, T)


@dataclass(frozen=True)
class Topics:
    """The ROS 2 side of one swarm: its domain, namespace and distribution, and each agent's
    topic names: <namespace>/agent<id>/pose (PoseWithCovarianceStamped) and .../odom (Odometry)."""

    domain_id: int = 0
    namespace: str = "/swarmloc"
    distro: str = "jazzy"
    frame_id: str = "map"

    def __post_init__(self):
        check_domain(self.domain_id)
        check_namespace(self.namespace)
        if self.distro not in DISTROS:
            raise Ros2Error(f"ROS 2 distribution {self.distro!r}: one of {', '.join(DISTROS)}")

    def pose(self, aid: int) -> str:
        return qualified(self.namespace, f"agent{aid}/pose")

    def odom(self, aid: int) -> str:
        return qualified(self.namespace, f"agent{aid}/odom")

    def child_frame(self, aid: int) -> str:
        return f"agent{aid}/base_link"


class Ros2Publisher:
    """One ROS 2 node (`node` in the namespace) publishing agents' estimates on a Zenoh session.

    Declares the node's liveliness token, and per agent two publishers (pose and odom) with
    their tokens, so `ros2 node list`, `ros2 topic list` and `ros2 topic echo` on an rmw_zenoh
    node of the same Zenoh network see them. `session` is a zenoh.Session; `publisher_options`
    the options its publishers take."""

    def __init__(self, session, topics: Topics, node: str, agents: list[int], publisher_options: dict | None = None):
        if not NAME.fullmatch(node):
            raise Ros2Error(f"ROS 2 node name {node!r}: letters, digits and _ not starting with a digit")
        self.topics, self.node = topics, node
        self.session_id = str(session.info.zid())
        self.node_id = 0
        opts = publisher_options or {}
        lv = session.liveliness()
        self._tokens = [lv.declare_token(node_token(topics.domain_id, self.session_id, self.node_id,
                                                    topics.namespace, node))]
        self._pubs: dict[int, list] = {}
        self.seq: dict[tuple[int, str], int] = {}
        entity = 0
        for aid in agents:
            pubs = []
            for fqn, ros_type in ((topics.pose(aid), POSE), (topics.odom(aid), ODOMETRY)):
                entity += 1
                key = topic_key(topics.domain_id, fqn, ros_type, topics.distro)
                pubs.append((session.declare_publisher(key, **opts), gid_of(self.session_id, entity), ros_type))
                self._tokens.append(lv.declare_token(entity_token(
                    topics.domain_id, self.session_id, self.node_id, entity, "MP", topics.namespace, node, fqn,
                    ros_type, topics.distro)))
            self._pubs[aid] = pubs
        self.published = 0
        self.skipped = 0  # estimates of a model without a pose, or not finite

    def publish(self, aid: int, model: str, t: float, mean, cov, stamp_ns: int) -> bool:
        """Agent aid's estimate at modelled time t on its pose and odom topics."""
        pubs = self._pubs.get(aid)
        rp = ros_pose(model, mean, cov) if pubs else None
        if rp is None or not (np.all(np.isfinite(rp.cov)) and np.all(np.isfinite(rp.position))):
            self.skipped += 1
            return False
        tp = self.topics
        payloads = (encode_pose(t, tp.frame_id, rp.position, rp.q_xyzw, rp.cov, tp.distro),
                    encode_odometry(t, tp.frame_id, tp.child_frame(aid), rp.position, rp.q_xyzw, rp.cov, rp.twist,
                                    rp.twist_cov, tp.distro))
        for (pub, gid, ros_type), payload in zip(pubs, payloads):
            n = self.seq[(aid, ros_type)] = self.seq.get((aid, ros_type), 0) + 1
            pub.put(payload, attachment=encode_attachment(n, stamp_ns, gid))
        self.published += 1
        return True

    def close(self) -> None:
        for pubs in self._pubs.values():
            for pub, _, _ in pubs:
                pub.undeclare()
        for tok in self._tokens:
            tok.undeclare()


def odometry_key(topics: Topics, topic: str) -> str:
    """The key expression to subscribe to nav_msgs/msg/Odometry on `topic` (relative names are
    in the namespace): any type hash, so a Jazzy and a Humble publisher both match."""
    fqn = topic if topic.startswith("/") else qualified(topics.namespace, topic)
    return f"{topics.domain_id}/{fqn.strip('/')}/{dds_type_name(ODOMETRY)}/*"
