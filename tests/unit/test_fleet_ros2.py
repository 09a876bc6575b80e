"""The ROS 2 encodings of the fleet bridge (``agent.fleet.ros2``) read back by independent decoders:
``rosbags`` (the pure-Python ROS 2 message codec and type store) for the CDR payloads and the RIHS01 type
hashes, zenoh's own ``zenoh.ext`` deserializer for the rmw_zenoh attachment; key expressions checked
against the literal forms rmw_zenoh documents."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.fleet import ros2
from agent.fleet.bridge_config import parse_bridge_config
from agent.fleet.local_protocol import PoseMessage
from drivers.errors import ConfigError

rosbags_typesys = pytest.importorskip("rosbags.typesys")


@pytest.fixture(scope="module")
def typestore():  # type: ignore[no-untyped-def]
    return rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_JAZZY)


@pytest.mark.parametrize("ros_type", sorted(ros2.TYPE_HASHES))
def test_type_hashes_are_what_rosbags_computes_from_the_definitions(typestore, ros_type: str) -> None:  # type: ignore[no-untyped-def]
    assert ros2.TYPE_HASHES[ros_type] == typestore.hash_rihs01(ros_type)


def test_data_keys_follow_rmw_zenoh() -> None:
    # The README's own example: ROS_DOMAIN_ID 0, /chatter, std_msgs/msg/String.
    assert ros2.topic_key(0, "/chatter", ros2.STRING) == (
        "0/chatter/std_msgs::msg::dds_::String_/"
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
    )
    topic = ros2.Ros2Topic.make(
        7, "abc123", 0, 1, "/r_1", "vlp_bridge", "pose", ros2.POSE_WITH_COVARIANCE_STAMPED
    )
    assert topic.topic == "/r_1/pose"
    assert topic.key.startswith(
        "7/r_1/pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/RIHS01_26432f98"
    )
    assert topic.token == (
        "@ros2_lv/7/abc123/0/1/MP/%/%r_1/vlp_bridge/%r_1%pose/"
        "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/"
        + ros2.TYPE_HASHES[ros2.POSE_WITH_COVARIANCE_STAMPED]
        + "/::,:,:,:,,"
    )
    assert (
        ros2.node_token(7, "abc123", 0, "/r_1", "vlp_bridge") == "@ros2_lv/7/abc123/0/0/NN/%/%r_1/vlp_bridge"
    )
    assert len(topic.gid) == ros2.GID_SIZE
    latched = ros2.Ros2Topic.make(7, "abc123", 0, 2, "/r_1", "vlp_bridge", "map", ros2.OCCUPANCY_GRID, True)
    assert latched.token.endswith(
        "/%r_1%map/nav_msgs::msg::dds_::OccupancyGrid_/"
        + ros2.TYPE_HASHES[ros2.OCCUPANCY_GRID]
        + "/:1:,1:,:,:,,"
    )
    assert latched.gid != topic.gid


def test_attachment_reads_back_with_zenohs_deserializer() -> None:
    zenoh = pytest.importorskip("zenoh")
    from zenoh.ext import Int64, z_deserialize

    topic = ros2.Ros2Topic.make(0, "z", 0, 1, "/r1", "n", "pose", ros2.POSE_WITH_COVARIANCE_STAMPED)
    topic.next_attachment(5)
    data = topic.next_attachment(1_700_000_000_123_456_789)
    assert len(data) == 33
    seq, stamp, gid = z_deserialize(tuple[Int64, Int64, bytes], zenoh.ZBytes(data))
    assert (seq, stamp, gid) == (2, 1_700_000_000_123_456_789, topic.gid)
    with pytest.raises(ValueError):
        ros2.attachment(1, 1, b"short")


def test_pose_decodes_with_rosbags(typestore) -> None:  # type: ignore[no-untyped-def]
    pose = PoseMessage(123, 3.25, -1.5, 2.5, 0.04, 0.02, 7)
    stamp_ns = 1_700_000_001_250_000_000
    data = ros2.encode_pose(pose, stamp_ns, "map")
    assert data[:4] == b"\x00\x01\x00\x00"
    msg = typestore.deserialize_cdr(data, ros2.POSE_WITH_COVARIANCE_STAMPED)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_700_000_001, 250_000_000)
    assert msg.header.frame_id == "map"
    p = msg.pose.pose
    assert (p.position.x, p.position.y, p.position.z) == (3.25, -1.5, 0.0)
    q = p.orientation
    assert math.isclose(2 * math.atan2(q.z, q.w), 2.5, abs_tol=1e-12) and q.x == q.y == 0.0
    cov = np.asarray(msg.pose.covariance).reshape(6, 6)
    assert cov[0, 0] == cov[1, 1] == pytest.approx(0.04**2)
    assert cov[5, 5] == pytest.approx(0.02**2)
    assert np.count_nonzero(cov) == 3
    # rosbags writes the same message to the same bytes (alignment and padding included).
    assert typestore.serialize_cdr(msg, ros2.POSE_WITH_COVARIANCE_STAMPED) == data


def test_occupancy_grid_decodes_with_rosbags(typestore) -> None:  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(3)
    cells = rng.choice(np.array([-1, 0, 100, 37], np.int8), size=(5, 7))
    data = ros2.encode_occupancy_grid(cells.tobytes(), 7, 5, 0.05, -2.0, 1.5, 42_000_000_007, "map")
    msg = typestore.deserialize_cdr(data, ros2.OCCUPANCY_GRID)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (42, 7)
    assert (msg.info.width, msg.info.height) == (7, 5)
    assert msg.info.resolution == pytest.approx(0.05)
    assert (msg.info.origin.position.x, msg.info.origin.position.y) == (-2.0, 1.5)
    assert msg.info.origin.orientation.w == 1.0
    assert np.array_equal(np.asarray(msg.data, np.int8).reshape(5, 7), cells)
    assert typestore.serialize_cdr(msg, ros2.OCCUPANCY_GRID) == data
    with pytest.raises(ValueError):
        ros2.encode_occupancy_grid(b"\x00" * 3, 2, 2, 0.05, 0.0, 0.0, 0)


def test_string_decodes_with_rosbags(typestore) -> None:  # type: ignore[no-untyped-def]
    text = '{"robot":"r1","état":1}'
    msg = typestore.deserialize_cdr(ros2.encode_string(text), ros2.STRING)
    assert msg.data == text
    with pytest.raises(ValueError):
        ros2.encode_string("a\x00b")


def _config(extra: str) -> dict:  # type: ignore[type-arg]
    import tomllib

    return tomllib.loads(
        '[bridge]\nrobot = "r-1"\nsocket = "/tmp/s"\n[zenoh]\nconnect = ["tcp/127.0.0.1:7447"]\n' + extra
    )


def test_ros2_is_off_by_default_and_configurable() -> None:
    assert parse_bridge_config(_config("")).ros2.enabled is False
    c = parse_bridge_config(
        _config('[ros2]\nenabled = true\ndomain_id = 5\nnode = "b"\ngraph_tokens = false\n')
    ).ros2
    assert (c.enabled, c.domain_id, c.namespace, c.node, c.graph_tokens) == (True, 5, "/r_1", "b", False)
    assert parse_bridge_config(_config('[ros2]\nnamespace = "/fleet/a"\n')).ros2.namespace == "/fleet/a"
    for bad, key in (
        ("domain_id = 300", "ros2.domain_id"),
        ('namespace = "/1a"', "ros2.namespace"),
        ('namespace = "fleet"', "ros2.namespace"),
        ('node = "a-b"', "ros2.node"),
        ("enable = true", "ros2.enable"),
    ):
        with pytest.raises(ConfigError) as err:
            parse_bridge_config(_config(f"[ros2]\n{bad}\n"))
        assert key in str(err.value), (bad, str(err.value))
