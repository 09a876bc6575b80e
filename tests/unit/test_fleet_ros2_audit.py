"""The privacy audit of the bridge's ROS 2 side (issue 24): the rmw_zenoh data keys and graph token keys are
recognised, the CDR payloads strictly decoded (``agent.fleet.ros2_decode``); anything else under a ROS 2 key
fails with a reason. ``rosbags`` (an independent ROS 2 CDR codec) cross-checks: everything the audit accepts,
including every accepted mutation of a valid payload, is the message rosbags decodes, with the same values."""

from __future__ import annotations

import json
import math
import struct

import numpy as np
import pytest

from agent.fleet import audit, payloads, ros2, ros2_decode
from agent.fleet.local_protocol import PoseMessage, StatusMessage

typesys = pytest.importorskip("rosbags.typesys")

POSE_KEY = ros2.topic_key(0, "/r1/pose", ros2.POSE_WITH_COVARIANCE_STAMPED)
MAP_KEY = ros2.topic_key(7, "/r1/map", ros2.OCCUPANCY_GRID)
STATUS_KEY = ros2.topic_key(0, "/fleet/r_2/status", ros2.STRING)
STAMP = 1_700_000_001_250_000_000


@pytest.fixture(scope="module")
def store():  # type: ignore[no-untyped-def]
    return typesys.get_typestore(typesys.Stores.ROS2_JAZZY)


def _pose(sigma_xy: float = 0.04, sigma_yaw: float = 0.02) -> bytes:
    return ros2.encode_pose(PoseMessage(123, 3.25, -1.5, 2.5, sigma_xy, sigma_yaw, 7), STAMP, "map")


def _cells() -> np.ndarray:
    rng = np.random.default_rng(5)
    return rng.choice(np.array([-1, 0, 100, 37], np.int8), size=(5, 7))


def _grid(cells: np.ndarray | None = None) -> bytes:
    c = _cells() if cells is None else cells
    return ros2.encode_occupancy_grid(c.tobytes(), c.shape[1], c.shape[0], 0.05, -2.0, 1.5, STAMP, "map")


def _status_text(robot: str = "r-2", **extra: object) -> str:
    text = payloads.encode_status(robot, StatusMessage(5, 3, 2), {"published_pose": 4}).decode()
    if extra:
        obj = json.loads(text)
        obj.update(extra)
        text = json.dumps(obj)
    return text


def test_the_bridges_three_topics_pass_and_decode_as_rosbags_decodes_them(store) -> None:  # type: ignore[no-untyped-def]
    data = _pose()
    assert audit.classify("fleet", POSE_KEY, data) == ("ros2_pose", None)
    p = ros2_decode.decode_pose(data)
    msg = store.deserialize_cdr(data, ros2.POSE_WITH_COVARIANCE_STAMPED)
    assert (p.x_m, p.y_m) == (msg.pose.pose.position.x, msg.pose.pose.position.y) == (3.25, -1.5)
    assert p.yaw_rad == pytest.approx(2.5, abs=1e-12)
    assert (p.sigma_xy_m, p.sigma_yaw_rad) == pytest.approx((0.04, 0.02))
    assert p.stamp_ns == msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == STAMP
    no_sigma = ros2_decode.decode_pose(_pose(math.nan, math.nan))  # the agent gave none: NaN variances
    assert math.isnan(no_sigma.sigma_xy_m) and math.isnan(no_sigma.sigma_yaw_rad)

    data = _grid()
    assert audit.classify("fleet", MAP_KEY, data) == ("ros2_map", None)
    g = ros2_decode.decode_occupancy_grid(data)
    msg = store.deserialize_cdr(data, ros2.OCCUPANCY_GRID)
    assert (g.width, g.height) == (msg.info.width, msg.info.height) == (7, 5)
    assert g.cells == _cells().tobytes() == np.asarray(msg.data, np.int8).tobytes()
    assert (g.origin_x_m, g.origin_y_m, g.resolution_m) == pytest.approx((-2.0, 1.5, 0.05))

    data = ros2.encode_string(_status_text())
    assert audit.classify("fleet", STATUS_KEY, data) == ("ros2_status", None)
    assert ros2_decode.decode_string(data) == store.deserialize_cdr(data, ros2.STRING).data


def test_what_rosbags_writes_for_a_planar_pose_passes(store) -> None:  # type: ignore[no-untyped-def]
    msg = store.deserialize_cdr(_pose(), ros2.POSE_WITH_COVARIANCE_STAMPED)
    assert audit.check("fleet", POSE_KEY, store.serialize_cdr(msg, ros2.POSE_WITH_COVARIANCE_STAMPED)) is None


def test_every_mutation_the_audit_accepts_is_the_message_rosbags_decodes(store) -> None:  # type: ignore[no-untyped-def]
    """Flip bytes of valid payloads and cut or extend them: a mutation either fails the audit or rosbags reads
    it as the same type with the values our decoder read (what passes is what it claims to be)."""
    rng = np.random.default_rng(11)
    cases = [(POSE_KEY, _pose(), ros2.POSE_WITH_COVARIANCE_STAMPED), (MAP_KEY, _grid(), ros2.OCCUPANCY_GRID)]
    cases.append((STATUS_KEY, ros2.encode_string(_status_text()), ros2.STRING))
    accepted = rejected = 0
    for key, good, ros_type in cases:
        for i in range(150):
            data = bytearray(good)
            if i % 3 == 0:
                data = data[: int(rng.integers(0, len(data)))]
            elif i % 3 == 1:
                data += bytes(rng.integers(0, 256, int(rng.integers(1, 9)), dtype=np.uint8))
            else:
                pos = int(rng.integers(0, len(data)))
                data[pos] = int(rng.integers(0, 256))
            problem = audit.check("fleet", key, bytes(data))
            if problem is not None:
                assert key[:40] in problem
                rejected += 1
                continue
            accepted += 1
            msg = store.deserialize_cdr(bytes(data), ros_type)
            assert store.serialize_cdr(msg, ros_type) == bytes(data)  # exactly the message, no extra byte
            if ros_type == ros2.OCCUPANCY_GRID:
                grid = ros2_decode.decode_occupancy_grid(bytes(data))
                assert grid.cells == np.asarray(msg.data, np.int8).tobytes()
                assert len(grid.cells) == msg.info.width * msg.info.height
            elif ros_type == ros2.POSE_WITH_COVARIANCE_STAMPED:
                pose = ros2_decode.decode_pose(bytes(data))
                assert (pose.x_m, pose.y_m) == (msg.pose.pose.position.x, msg.pose.pose.position.y)
    assert accepted > 20 and rejected > 200, (accepted, rejected)


def _cdr_pose(cov: list[float], position_z: float = 0.0, frame: str = "map") -> bytes:
    w = ros2.CdrWriter()
    w.header(STAMP, frame)
    w.float64s((1.0, 2.0, position_z, 0.0, 0.0, 0.0, 1.0))
    w.float64s(cov)
    return w.finish()


def _cov(**entries: float) -> list[float]:
    cov = [0.0] * 36
    for name, v in entries.items():
        cov[int(name[1:])] = v
    return cov


def _image(store) -> bytes:  # type: ignore[no-untyped-def]
    """A camera frame as ROS 2 would send it: sensor_msgs/msg/Image, 4 x 3 mono8."""
    image_cls = store.types["sensor_msgs/msg/Image"]
    header_cls, time_cls = store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]
    img = image_cls(header_cls(time_cls(1, 2), "map"), 3, 4, "mono8", 0, 4, np.arange(12, dtype=np.uint8))
    return bytes(store.serialize_cdr(img, "sensor_msgs/msg/Image"))


BAD_PAYLOADS = {
    "trailing byte": (POSE_KEY, lambda s: _pose() + b"\x00", "after the message"),
    "truncated": (POSE_KEY, lambda s: _pose()[:-8], "truncated"),
    "big endian": (POSE_KEY, lambda s: b"\x00\x00\x00\x00" + _pose()[4:], "little endian"),
    "other frame": (POSE_KEY, lambda s: _cdr_pose(_cov(c0=1.0, c7=1.0), frame="camera"), "frame_id"),
    "off-plane": (POSE_KEY, lambda s: _cdr_pose(_cov(c0=1.0, c7=1.0), position_z=0.5), "planar"),
    "covariance channel": (POSE_KEY, lambda s: _cdr_pose(_cov(c0=1.0, c7=1.0, c14=3.0)), "covariance"),
    "x and y variances differ": (POSE_KEY, lambda s: _cdr_pose(_cov(c0=1.0, c7=2.0)), "differ"),
    "negative variance": (POSE_KEY, lambda s: _cdr_pose(_cov(c0=-1.0, c7=-1.0)), "variance"),
    "an image on the pose topic": (POSE_KEY, _image, ""),
    "an image on the map topic": (MAP_KEY, _image, ""),
    "an image appended to the map": (MAP_KEY, lambda s: _grid() + bytes(64), "after the message"),
    "cell 101": (MAP_KEY, lambda s: _grid(np.full((2, 3), 101, np.int8)), "-1..100"),
    "cells short of width x height": (
        MAP_KEY,
        lambda s: _grid()[:-39] + struct.pack("<I", 34) + _grid()[-34:],
        "a sequence of 34 bytes",
    ),
    "not the status": (STATUS_KEY, lambda s: ros2.encode_string("hello"), "not JSON"),
    "status with a field more": (
        STATUS_KEY,
        lambda s: ros2.encode_string(_status_text(jpeg="/9j/4AAQSkZJRg==")),
        "beyond the status schema",
    ),
    "status without its robot": (STATUS_KEY, lambda s: ros2.encode_string('{"v": 1}'), "robot"),
    "a PNG as the string": (STATUS_KEY, lambda s: ros2.encode_string("\x89PNG\r\n\x1a\n"), "not JSON"),
    "string without its NUL": (STATUS_KEY, lambda s: ros2.encode_string("{}")[:-1] + b"}", "NUL"),
}


@pytest.mark.parametrize("case", sorted(BAD_PAYLOADS))
def test_anything_else_under_a_ros2_key_fails_with_a_reason(store, case: str) -> None:  # type: ignore[no-untyped-def]
    key, make, reason = BAD_PAYLOADS[case]
    kind, problem = audit.classify("fleet", key, make(store))
    assert kind == "invalid" or problem is not None
    assert problem is not None and reason in problem, problem


IMAGE_HASH = "RIHS01_" + "ab" * 32
BAD_KEYS = {
    "an image topic": "0/r1/camera/sensor_msgs::msg::dds_::Image_/" + IMAGE_HASH,
    "an image type on the pose topic": "0/r1/pose/sensor_msgs::msg::dds_::Image_/" + IMAGE_HASH,
    "a map type on the pose topic": ros2.topic_key(0, "/r1/pose", ros2.OCCUPANCY_GRID),
    "another type hash": POSE_KEY.rsplit("/", 1)[0] + "/" + IMAGE_HASH,
    "domain 233": "233" + POSE_KEY[1:],
    "no topic": "0/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/" + IMAGE_HASH,
    "a graph token of a subscriber": ros2.publisher_token(
        0, "ab12", 0, 1, "/r1", "n", "/r1/status", ros2.STRING
    ).replace("/MP/", "/MS/"),
    "a graph token of another topic": ros2.publisher_token(
        0, "ab12", 0, 1, "/r1", "n", "/r1/pose", ros2.POSE_WITH_COVARIANCE_STAMPED
    ).replace("%r1%pose", "%r1%image"),
    "a map token without its latched QoS": ros2.publisher_token(
        0, "ab12", 0, 2, "/r1", "n", "/r1/map", ros2.OCCUPANCY_GRID
    ),
}


@pytest.mark.parametrize("case", sorted(BAD_KEYS))
def test_keys_beyond_the_bridges_topics_fail(case: str) -> None:
    kind, problem = audit.classify("fleet", BAD_KEYS[case], _pose())
    assert kind == "invalid" and problem is not None, (kind, problem)


def test_graph_token_keys_pass_without_a_payload_only() -> None:
    topics = [
        ros2.Ros2Topic.make(5, "0f3a9c", 0, i + 1, "/r1", "vlp_bridge", name, t, name == "map")
        for i, (name, t) in enumerate(ros2_decode.KINDS.items())
    ]
    keys = [ros2.node_token(5, "0f3a9c", 0, "/r1", "vlp_bridge"), *(t.token for t in topics)]
    for key in keys:
        assert audit.classify("fleet", key, b"") == ("ros2_token", None)
        problem = audit.check("fleet", key, b"\xff\xd8\xff")  # a JPEG's first bytes
        assert problem is not None and "payload" in problem


def test_fleet_keys_are_audited_as_before() -> None:
    data = payloads.encode_pose("r1", PoseMessage(1, 0.0, 0.0, 0.0, 0.1, 0.1, 0))
    assert audit.classify("fleet", "fleet/r1/pose", data) == ("pose", None)
    # the ROS 2 pose under a fleet key, the fleet pose under a ROS 2 key: both fail
    assert audit.check("fleet", "fleet/r1/pose", _pose()) is not None
    assert audit.check("fleet", POSE_KEY, data) is not None
