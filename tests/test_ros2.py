"""ROS 2 over Zenoh (swarmloc/wire/ros2.py) against rmw_zenoh's documented formats.

Golden values are rmw_zenoh's design document's own examples (docs/design.md of ros2/rmw_zenoh,
"Topic and Service name mapping to Zenoh key expressions", "Graph Cache" and "Publishers"), and
CDR bytes written out field by field from the CDR rules (little-endian encapsulation 00 01 00
00, each primitive aligned to its size from the end of that header, strings as a uint32 length
counting the NUL, the bytes and the NUL), never our own output. The Jazzy type hashes of the two
published types are docs/ros2.md's literals, the ones ROS 2's generator writes, recomputed by a
REP-2016 implementation of the test's own (REP2016). The round trips go through
mcap-ros2-support's CDR code, which shares nothing with rosbags'."""

import hashlib
import json
import math
import struct
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from swarmloc import wire
from swarmloc.wire import ros2

STRING = "std_msgs/msg/String"
# docs/design.md: "0/chatter/std_msgs::msg::dds_::String_/RIHS01_df66...".
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


def test_type_hash_is_the_documented_one():
    assert ros2.type_hash(STRING) == STRING_HASH
    assert ros2.type_hash(STRING, "humble") == "TypeHashNotSupported"
    for t in (ros2.POSE, ros2.ODOMETRY):
        h = ros2.type_hash(t)
        assert h.startswith("RIHS01_") and len(h) == 7 + 64 and h != STRING_HASH


# Jazzy's hashes of the two types swarmloc publishes, as docs/ros2.md lists them. The same
# literals are in code that ROS 2's own generator wrote (rosidl_generator_c's *__struct.h, e.g.
# nav_msgs/msg/detail/odometry__struct.h of micro-ROS/micro_ros_arduino:
# nav_msgs__msg__Odometry__TYPE_HASH = {1, {0x3c, 0xc9, 0x7d, ...}}), and REP2016 below computes
# them again from the types' .msg definitions without rosbags (whose hash swarmloc uses).
POSE_HASH = "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e"
ODOMETRY_HASH = "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0"


class REP2016:
    """REP-2016's type hash (RIHS01), written out from the REP and rosidl_generator_type_description:
    SHA-256 of the JSON of {"type_description", "referenced_type_descriptions"} (the referenced
    types sorted by name, default values left out), separators ", " and ": ", keys in this order."""

    NESTED, INT32, UINT32, DOUBLE, STRING = 1, 6, 7, 11, 17  # type_interfaces/msg/FieldType
    ARRAY = 48  # added to the element's type id for a fixed-size array (capacity: its size)
    # The fields of each type, from its .msg file in ros2/common_interfaces and rcl_interfaces (Jazzy).
    MSGS = {
        "builtin_interfaces/msg/Time": [("sec", INT32), ("nanosec", UINT32)],
        "std_msgs/msg/Header": [("stamp", "builtin_interfaces/msg/Time"), ("frame_id", STRING)],
        "std_msgs/msg/String": [("data", STRING)],
        "geometry_msgs/msg/Point": [("x", DOUBLE), ("y", DOUBLE), ("z", DOUBLE)],
        "geometry_msgs/msg/Vector3": [("x", DOUBLE), ("y", DOUBLE), ("z", DOUBLE)],
        "geometry_msgs/msg/Quaternion": [("x", DOUBLE), ("y", DOUBLE), ("z", DOUBLE), ("w", DOUBLE)],
        "geometry_msgs/msg/Pose": [("position", "geometry_msgs/msg/Point"),
                                   ("orientation", "geometry_msgs/msg/Quaternion")],
        "geometry_msgs/msg/PoseWithCovariance": [("pose", "geometry_msgs/msg/Pose"), ("covariance", (DOUBLE, 36))],
        "geometry_msgs/msg/PoseWithCovarianceStamped": [("header", "std_msgs/msg/Header"),
                                                        ("pose", "geometry_msgs/msg/PoseWithCovariance")],
        "geometry_msgs/msg/Twist": [("linear", "geometry_msgs/msg/Vector3"), ("angular", "geometry_msgs/msg/Vector3")],
        "geometry_msgs/msg/TwistWithCovariance": [("twist", "geometry_msgs/msg/Twist"),
                                                  ("covariance", (DOUBLE, 36))],
        "nav_msgs/msg/Odometry": [("header", "std_msgs/msg/Header"), ("child_frame_id", STRING),
                                  ("pose", "geometry_msgs/msg/PoseWithCovariance"),
                                  ("twist", "geometry_msgs/msg/TwistWithCovariance")],
    }

    @classmethod
    def field(cls, name, t) -> dict:
        type_id, capacity, nested = t, 0, ""
        if isinstance(t, str):
            type_id, nested = cls.NESTED, t
        elif isinstance(t, tuple):
            type_id, capacity = t[0] + cls.ARRAY, t[1]
        return {"name": name, "type": {"type_id": type_id, "capacity": capacity, "string_capacity": 0,
                                       "nested_type_name": nested}}

    @classmethod
    def description(cls, name: str) -> dict:
        return {"type_name": name, "fields": [cls.field(*f) for f in cls.MSGS[name]]}

    @classmethod
    def referenced(cls, name: str, seen: set) -> set:
        for _, t in cls.MSGS[name]:
            if isinstance(t, str) and t not in seen:
                seen.add(t)
                cls.referenced(t, seen)
        return seen

    @classmethod
    def hash(cls, name: str) -> str:
        d = {"type_description": cls.description(name),
             "referenced_type_descriptions": [cls.description(r) for r in sorted(cls.referenced(name, set()))]}
        return "RIHS01_" + hashlib.sha256(json.dumps(d, separators=(", ", ": ")).encode()).hexdigest()


def test_jazzy_type_hashes_of_the_published_types():
    # The independent implementation first gives the design document's own String hash...
    assert REP2016.hash(STRING) == STRING_HASH
    # ...then the documented hashes of the published types, which ours must be.
    assert REP2016.hash(ros2.POSE) == POSE_HASH and REP2016.hash(ros2.ODOMETRY) == ODOMETRY_HASH
    assert ros2.type_hash(ros2.POSE) == POSE_HASH and ros2.type_hash(ros2.ODOMETRY) == ODOMETRY_HASH
    assert ros2.topic_key(0, "/swarmloc/agent1/pose", ros2.POSE) == \
        f"0/swarmloc/agent1/pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/{POSE_HASH}"
    assert ros2.topic_key(0, "/swarmloc/agent1/odom", ros2.ODOMETRY) == \
        f"0/swarmloc/agent1/odom/nav_msgs::msg::dds_::Odometry_/{ODOMETRY_HASH}"
    doc = (Path(__file__).resolve().parents[1] / "docs" / "ros2.md").read_text()
    assert f"PoseWithCovarianceStamped_/{POSE_HASH}" in doc and f"Odometry_/{ODOMETRY_HASH}" in doc


def test_topic_keys_of_the_design_document():
    assert ros2.topic_key(0, "/chatter", STRING) == f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert ros2.topic_key(0, ros2.qualified("/robot1", "chatter"), STRING) == \
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert ros2.topic_key(3, "/chatter", STRING, "humble") == "3/chatter/std_msgs::msg::dds_::String_/TypeHashNotSupported"
    assert ros2.dds_type_name(ros2.ODOMETRY) == "nav_msgs::msg::dds_::Odometry_"


def test_liveliness_tokens_of_the_design_document():
    # The document's listener node, its subscription and the talker's publisher, byte for byte.
    assert ros2.node_token(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "/", "listener") == \
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    assert ros2.entity_token(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, 10, "MS", "/", "listener", "/chatter",
                             STRING) == (
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/"
        f"{STRING_HASH}/::,10:,:,:,,")
    assert ros2.entity_token(2, "8b20917502ee955ac4476e0266340d5c", 0, 10, "MP", "/", "talker", "/chatter", STRING,
                             qos="::,7:,:,:,,") == (
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
        f"{STRING_HASH}/::,7:,:,:,,")
    # A namespace is mangled like the topic: every / a %.
    tok = ros2.entity_token(0, "ab", 0, 1, "MP", "/swarmloc", "n", "/swarmloc/agent1/pose", ros2.POSE, "humble")
    assert tok.split("/")[7:10] == ["%swarmloc", "n", "%swarmloc%agent1%pose"] and "/TypeHashNotSupported/" in tok


def test_attachment_layout():
    gid = bytes(range(16))
    b = ros2.encode_attachment(258, 1_700_000_000_123_456_789, gid)
    # 8 bytes int64 LE sequence number, 8 bytes int64 LE ns timestamp, 1 byte GID length (16), the GID.
    assert b == (b"\x02\x01\x00\x00\x00\x00\x00\x00" + (1_700_000_000_123_456_789).to_bytes(8, "little") + b"\x10" + gid)
    assert len(b) == 33 and ros2.decode_attachment(b) == (258, 1_700_000_000_123_456_789, gid)
    for bad in (b[:-1], b[:16] + b"\x08" + gid):
        with pytest.raises(ros2.Ros2Error):
            ros2.decode_attachment(bad)


def _cdr_string(s: str, at: int) -> bytes:
    return struct.pack("<I", len(s) + 1) + s.encode() + b"\0"


def test_pose_cdr_bytes_by_the_rules():
    cov = np.arange(36.0) / 7
    got = ros2.encode_pose(12.25, "map", [1.5, -2.0, 0.0], [0.0, 0.0, 0.5, math.sqrt(0.75)], cov.reshape(6, 6))
    body = struct.pack("<iI", 12, 250_000_000) + _cdr_string("map", 8)  # 16 bytes: the doubles are aligned
    body += struct.pack("<7d", 1.5, -2.0, 0.0, 0.0, 0.0, 0.5, math.sqrt(0.75)) + struct.pack("<36d", *cov)
    assert got == b"\x00\x01\x00\x00" + body


def test_odometry_cdr_bytes_by_the_rules():
    got = ros2.encode_odometry(3.0, "map", "agent7/base_link", [1, 2, 3], [0, 0, 0, 1], np.eye(6) * 2,
                               [0.5, 0, 0, 0, 0, 0.1], np.eye(6) * 3)
    body = struct.pack("<iI", 3, 0) + _cdr_string("map", 8)  # ends at 16
    body += _cdr_string("agent7/base_link", 16)  # 4 + 17 = 21 bytes: ends at 37, padded to 40
    body += b"\0" * 3
    body += struct.pack("<7d", 1, 2, 3, 0, 0, 0, 1) + struct.pack("<36d", *(np.eye(6) * 2).ravel())
    body += struct.pack("<6d", 0.5, 0, 0, 0, 0, 0.1) + struct.pack("<36d", *(np.eye(6) * 3).ravel())
    assert got == b"\x00\x01\x00\x00" + body


def _mcap_ros2(ros_type: str):
    """mcap-ros2-support's CDR decoder and encoder of a type, from the type's .msg definition."""
    from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic

    text, _ = ros2.typestore().generate_msgdef(ros_type, ros_version=2)
    return generate_dynamic(ros_type, text)[ros_type], serialize_dynamic(ros_type, text)[ros_type]


def test_cdr_round_trip_through_an_independent_codec():
    decode, encode = _mcap_ros2(ros2.ODOMETRY)
    cov = np.arange(36.0).reshape(6, 6)
    data = ros2.encode_odometry(5.5, "map", "agent3/base_link", [4, 5, 6], [0, 0, 0.6, 0.8], cov,
                                [1.25, 0, 0, 0, 0, -0.5], cov.T)
    m = decode(data)
    assert (m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id, m.child_frame_id) == \
        (5, 500_000_000, "map", "agent3/base_link")
    assert [m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z] == [4, 5, 6]
    assert m.pose.pose.orientation.z == 0.6 and m.pose.pose.orientation.w == 0.8
    assert list(m.pose.covariance) == cov.ravel().tolist() and list(m.twist.covariance) == cov.T.ravel().tolist()
    assert m.twist.twist.linear.x == 1.25 and m.twist.twist.angular.z == -0.5
    # The other way: their encoder, our decoder (what an agent reads from a ROS 2 odometry topic).
    theirs = encode({"header": {"stamp": {"sec": 7, "nanosec": 250_000_000}, "frame_id": "odom"},
                     "child_frame_id": "base_link",
                     "pose": {"pose": {"position": {"x": 1.0, "y": 2.0, "z": 0.0},
                                       "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
                              "covariance": [0.0] * 36},
                     "twist": {"twist": {"linear": {"x": 0.3, "y": 0.0, "z": 0.0},
                                         "angular": {"x": 0.0, "y": 0.0, "z": 0.2}}, "covariance": [0.0] * 36}})
    s = ros2.decode_odometry(theirs)
    assert s.t == 7.25 and s.position.tolist() == [1, 2, 0] and s.q.tolist() == [1, 0, 0, 0]
    assert s.linear.tolist() == [0.3, 0, 0] and s.angular.tolist() == [0, 0, 0.2]
    with pytest.raises(ros2.Ros2Error):
        ros2.decode_odometry(theirs[:40])


def test_estimates_as_ros_poses():
    # planar-pose: heading -> yaw quaternion, (x, y, heading) -> rows and columns 0, 1, 5.
    P = np.array([[1.0, 0.1, 0.2], [0.1, 2.0, 0.3], [0.2, 0.3, 0.5]])
    rp = ros2.ros_pose("planar-pose", np.array([3.0, 4.0, math.pi / 2]), P)
    assert np.allclose(rp.q_xyzw, [0, 0, math.sqrt(0.5), math.sqrt(0.5)])
    assert rp.cov[np.ix_([0, 1, 5], [0, 1, 5])].tolist() == P.tolist() and rp.cov[2, 2] == ros2.UNKNOWN_VARIANCE
    assert rp.cov[0, 2] == 0
    # planar-speed-heading: no heading estimated, so the yaw is unknown too.
    rp = ros2.ros_pose("planar-speed-heading", np.array([1.0, 2.0]), np.eye(2))
    assert rp.cov[5, 5] == ros2.UNKNOWN_VARIANCE and rp.position.tolist() == [1, 2, 0]
    # uas-ins: yawed 90 degrees and flying north at 2 m/s is 2 m/s forward in the body frame.
    x = np.zeros(16)
    x[4], x[8] = 2.0, math.pi / 2
    rp = ros2.ros_pose("uas-ins", x, np.eye(15 + 1))
    assert np.allclose(rp.twist[:3], [2, 0, 0]) and np.allclose(rp.q_xyzw, [0, 0, math.sqrt(0.5), math.sqrt(0.5)])
    assert ros2.ros_pose("ground-station", np.zeros(0), np.zeros((0, 0))) is None


def test_bad_names_are_refused():
    for bad in ("swarm", "/a/", "/1a", "/a b"):
        with pytest.raises(ros2.Ros2Error):
            ros2.Topics(namespace=bad)
    with pytest.raises(ros2.Ros2Error):
        ros2.Topics(domain_id=300)
    with pytest.raises(ros2.Ros2Error):
        ros2.Topics(distro="iron")


def test_publisher_on_a_zenoh_session():
    """What a ROS 2 node would see: tokens under @ros2_lv/<domain>/, CDR with the attachment on the topic key."""
    s = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("peer", ["tcp/127.0.0.1:0"])))
    try:
        topics = ros2.Topics(domain_id=7, namespace="/swarmloc")
        got, tokens = [], []
        sub = s.declare_subscriber(ros2.topic_key(7, topics.pose(2), ros2.POSE),
                                   lambda x: got.append((x.payload.to_bytes(), x.attachment.to_bytes())))
        pub = ros2.Ros2Publisher(s, topics, "swarmloc_test", [2])
        lv = s.liveliness().declare_subscriber("@ros2_lv/7/**", lambda x: tokens.append(str(x.key_expr)), history=True)
        assert pub.publish(2, "planar-pose", 1.5, [1.0, 2.0, 0.0], np.eye(3), 1_700_000_000_000_000_000)
        deadline = time.monotonic() + 5
        while (not got or len(tokens) < 3) and time.monotonic() < deadline:
            time.sleep(0.02)
        zid = str(s.info.zid())
        assert f"@ros2_lv/7/{zid}/0/0/NN/%/%swarmloc/swarmloc_test" in tokens
        mp = [t for t in tokens if "/MP/" in t]
        assert sorted(t.split("/")[9] for t in mp) == ["%swarmloc%agent2%odom", "%swarmloc%agent2%pose"]
        payload, att = got[0]
        seq, stamp, gid = ros2.decode_attachment(att)
        assert (seq, stamp) == (1, 1_700_000_000_000_000_000) and gid == ros2.gid_of(zid, 1)
        m = _mcap_ros2(ros2.POSE)[0](payload)
        assert (m.pose.pose.position.x, m.pose.pose.position.y, m.header.stamp.sec) == (1.0, 2.0, 1)
        pub.close()
        del sub, lv
    finally:
        s.close()


def test_ros2_settings_are_plain_json():
    # What docs/ros2.md prints for the defaults.
    t = ros2.Topics()
    assert json.dumps([t.pose(1), t.odom(1), t.child_frame(1)]) == \
        '["/swarmloc/agent1/pose", "/swarmloc/agent1/odom", "agent1/base_link"]'
