"""ROS 2 in the processes: odometry from a ROS 2 topic as an agent's sensor source, the agent
configuration's `ros2` section, and netsim publishing every estimate on rmw_zenoh's keys (what
`ros2 topic echo` on the same Zenoh network receives)."""

import math
import time

import numpy as np
import pytest
import zenoh

from agents import config
from agents.companion.sources import FlightControllerTicks, Ros2Odometry
from swarmloc import wire
from swarmloc.wire import ros2


def _session():
    return zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("peer", ["tcp/127.0.0.1:0"])))


def test_odometry_from_a_ros2_topic_makes_ticks():
    """A ROS 2 node's nav_msgs/msg/Odometry (yawed 90 degrees, 0.5 m/s forward, turning at
    0.1 rad/s) on rmw_zenoh's key, Jazzy hash or Humble's placeholder alike, becomes one frame
    per tick: speed along the heading, heading, turn rate."""
    s = _session()
    try:
        topics = ros2.Topics(domain_id=3, namespace="/robot1")
        key = ros2.odometry_key(topics, "odom")
        assert key == "3/robot1/odom/nav_msgs::msg::dds_::Odometry_/*"
        link = Ros2Odometry(s, key, "jazzy")
        spec = config.Ros2Source(kind="ros2", topic="odom", tick=0.1)
        ticks = FlightControllerTicks(lambda: link, "planar-pose", spec, (np.zeros(3), np.eye(3)), 1)
        q = [0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)]
        for i, distro in enumerate(["jazzy"] * 15 + ["humble"] * 16):
            t = 100.0 + 0.05 * i
            pub_key = ros2.topic_key(3, "/robot1/odom", ros2.ODOMETRY, distro)
            s.put(pub_key, ros2.encode_odometry(t, "odom", "base_link", [0, 0, 0], q, np.eye(6), [0.5, 0, 0, 0, 0, 0.1],
                                                np.eye(6), distro))
        s.put(ros2.topic_key(3, "/robot1/odom", ros2.ODOMETRY), b"\x00\x01\x00\x00garbage")
        frames = []
        deadline = time.monotonic() + 5
        # Until every message has arrived, not only enough for the frames: the count is asserted below.
        while (len(frames) < 13 or link.received["ODOMETRY"] + link.dropped["bad-data"] < 32) \
                and time.monotonic() < deadline:
            frames += ticks.ready(time.monotonic())
            time.sleep(0.02)
        assert frames[0].k == 0 and frames[0].odometry.dt == 0.0 and math.isclose(frames[0].odometry.heading, math.pi / 2)
        moving = frames[1:]
        assert len(moving) >= 12 and [f.k for f in moving] == list(range(1, len(moving) + 1))
        for f in moving:
            assert math.isclose(f.odometry.speed, 0.5, abs_tol=1e-12)
            assert math.isclose(f.odometry.turn_rate, 0.1, abs_tol=1e-12)
            assert math.isclose(f.odometry.heading, math.pi / 2, abs_tol=1e-12)
            assert f.odometry.turn_rate_std == spec.turn_rate_std
        assert link.received["ODOMETRY"] == 31 and link.dropped["bad-data"] == 1
        link.close()
    finally:
        s.close()


def _config(tmp_path, **changes):
    data = {"version": 1, "id": 4, "model": "planar-pose", "estimator": {"name": "ekf"},
            "prior": {"position": [0.0, 0.0], "heading": 0.0}, "zenoh": {"mode": "peer", "listen": ["tcp/127.0.0.1:0"]},
            "ros2": {"domain_id": 5, "namespace": "/fleet"},
            "sensors": [{"kind": "ros2", "topic": "/robot4/odom"}], "outputs": {"record": "rec/agent4.mcap"}}
    data.update(changes)
    return config.parse_config(data, tmp_path)


def test_agent_configuration_ros2(tmp_path):
    cfg = _config(tmp_path)
    d = config.daemon_config(cfg)
    assert d.ros2 == ros2.Topics(5, "/fleet", "jazzy") and d.ros2_publish
    assert d.record == tmp_path / "rec/agent4.mcap" and d.record_meta["config"]["id"] == 4
    lines = "\n".join(config.summary(cfg, config.node_spec(cfg)))
    assert "ros2 /robot4/odom (nav_msgs/msg/Odometry, domain 5)" in lines
    assert "ros2 /fleet/agent4/pose, /fleet/agent4/odom (domain 5, jazzy)" in lines
    with pytest.raises(config.ConfigError, match="sensors.0.topic: a ros2 source needs the ros2 section"):
        _config(tmp_path, ros2=None)
    with pytest.raises(config.ConfigError, match="ros2.namespace"):
        _config(tmp_path, ros2={"namespace": "fleet"})
    with pytest.raises(config.ConfigError, match="not a ROS 2 topic"):
        _config(tmp_path, sensors=[{"kind": "ros2", "topic": "odom/"}])


@pytest.mark.slow
def test_netsim_publishes_every_estimate_on_ros2(cli, tmp_path):
    """`swarmloc run --ros2-domain 9`: a Zenoh session on netsim's router, subscribed as a ROS 2
    node would be, sees netsim's node and publisher tokens and receives each agent's pose, CDR
    with rmw_zenoh's attachment, equal to the estimate the run recorded."""
    from mcap_ros2._dynamic import generate_dynamic

    from swarmloc.experiment import scenario as S

    sc = S.load("wang2019").with_overrides(**{"clock.duration": 100.0, "clock.mode": "realtime", "clock.speed": 10.0})
    (tmp_path / "s.yaml").write_text(sc.to_yaml())
    run = cli.start_run("s.yaml", tmp_path / "run", "--ros2-domain", "9", "--ros2-namespace", "/swarm")
    cli.wait_tick(1, run)
    s = zenoh.open(zenoh.Config.from_json5(wire.zenoh_config("client", connect=[cli.endpoint])))
    got, tokens = [], []
    try:
        sub = s.declare_subscriber(ros2.topic_key(9, "/swarm/agent3/pose", ros2.POSE),
                                   lambda x: got.append((x.payload.to_bytes(), x.attachment.to_bytes())))
        lv = s.liveliness().declare_subscriber(
            "@ros2_lv/9/**", lambda x: tokens.append(str(x.key_expr)) if x.kind == zenoh.SampleKind.PUT else None,
            history=True)
        run.wait(120)
        del sub, lv
    finally:
        s.close()
    assert any(t.endswith("/NN/%/%swarm/swarmloc_netsim") for t in tokens)
    assert sorted(t.split("/")[9] for t in tokens if "/MP/" in t) == sorted(
        f"%swarm%agent{a}%{k}" for a in range(1, 5) for k in ("odom", "pose"))
    assert len(got) > 50
    text, _ = ros2.typestore().generate_msgdef(ros2.POSE, ros_version=2)
    decode = generate_dynamic(ros2.POSE, text)[ros2.POSE]
    est = np.load(tmp_path / "run/estimates/ukf-dcl.npz")
    col = list(est["ids"]).index(3)
    seqs = [ros2.decode_attachment(a)[0] for _, a in got]
    assert seqs == list(range(seqs[0], seqs[0] + len(got)))  # numbered per publisher, none lost
    payload, _ = got[-1]
    m = decode(payload)
    k = int(round((m.header.stamp.sec + m.header.stamp.nanosec * 1e-9) / sc.clock.dt))
    row = list(est["k"]).index(k)
    # The last pose published for a tick is the estimate the run recorded for it.
    assert [m.pose.pose.position.x, m.pose.pose.position.y] == est["mean"][row, col, :2].tolist()
    assert m.pose.covariance[0] == est["cov"][row, col, 0, 0] and m.header.frame_id == "map"
