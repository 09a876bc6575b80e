"""``vlp-agent export --ros2``: a flight recording as a rosbag2 folder (MCAP storage), read back by an
independent reader: rosbags' rosbag2 Reader (the bag's metadata.yaml and MCAP file) and rosbags' own ROS 2
Humble type store for the CDR (not the definitions the bag carries), field by field against what was
recorded; a cut recording is exported up to where it stops and says where."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from agent.config import MountConfig, SlamConfig
from agent.recording.messages import (
    CommandSample,
    FusedSample,
    HealthSample,
    WheelCommandSample,
    occupancy_cells,
)
from agent.recording.reader import read_recording
from agent.recording.ros2_types import TYPES, msgdef
from agent.recording.slam_replay import slam_setup
from agent.runtime.types import AbsoluteFix
from agent.slam.render import OccupancyImage
from drivers.samples import ImuSample
from firmware_protocol.command_frame import GoalCommand, StopCommand, VelocityCommand
from tests.unit.test_recording import recorder, scan

UNIX_OFFSET_NS = 1_700_000_000_000_000_000  # fixed in the test (the recorder writes the real one)
T0_NS = 3_000_000_000


def _recorded(tmp_path: Path, seconds: float = 6.0) -> Path:
    """A recording of ``seconds``: scans at 10 Hz, wheel odometry at 50 Hz (the fusion's records, driving
    0.2 m/s on a 0.1 rad/s turn), IMU samples and wheel commands at 50 Hz, a fused pose at 20 Hz, a VLP fix
    without heading and a SLAM pose each second, a map every 2 s; a velocity command, a goal and a stop
    received; the laser up, then lost at 3 s; a chunk every 0.2 s of the fake clock."""
    from agent.fusion import Estimate

    rec, clock, _ = recorder(tmp_path / "rec", chunk_s=0.2)
    mount = MountConfig(x_m=0.1, z_m=0.2, yaw_rad=math.pi)
    rec.record("slam_setup", T0_NS, slam_setup(SlamConfig(), mount, "slam"))
    pixels = np.full((40, 60), 205, dtype=np.uint8)
    pixels[:10] = 254
    pixels[10:12] = 0
    for k in range(int(seconds * 50)):
        t = T0_NS + k * 20_000_000
        if k:
            record = {"k": "odometry", "t0": t - 20_000_000, "t1": t, "ds": 0.004, "dyaw": 0.002, "a": t + 1}
            rec.record("fusion_input", t, record)
        if k % 5 == 0:
            rec.record("scan", t, scan(k // 5, t))
        if k % 50 == 0:
            cov = np.array([[4e-6, 1e-6], [1e-6, 9e-6]])
            rec.record("vlp_fix", t, AbsoluteFix(t, 1.0 + k * 1e-3, 2.0, None, cov, detail={}))
            rec.record("slam_pose", t, AbsoluteFix(t, 1.5, 2.5, 0.25, np.diag([1e-4, 2e-4, 3e-4])))
        if k % 100 == 0:
            rec.record("map", t, (t, OccupancyImage(pixels, 0.05, (-1.0, -2.0, 0.0))))
        rec.record("imu", t, ImuSample((0.1, -0.2, 9.81), (0.01, 0.02, 0.1), 31.0, t))
        rec.record("wheel_command", t, WheelCommandSample(t, 5.0, 6.0, 0.2, 0.1))
        if k == 0:
            rec.record("command", t, CommandSample(t, VelocityCommand(1, 0.15, -0.3, 0.5)))
            rec.record("health", t, HealthSample(t, "laser", True, "up"))
        if k == 100:
            rec.record("command", t, CommandSample(t, GoalCommand(2, 7, 3.5, -1.25, None)))
            rec.record("command", t, CommandSample(t, StopCommand(3)))  # no standard message: left out
        if k == 150:
            rec.record("health", t, HealthSample(t, "laser", False, "no scan for 0.5 s"))
        if k % 10 == 0:
            estimate = Estimate(
                t, 1.0, 2.0, 0.5, 0.1, 0.0, np.diag([1e-4, 2e-4, 1e-5, 1e-3, 1e-3]), 0, 0.2, k
            )
            rec.record("pose", t, FusedSample(estimate, 3))
        clock.t_s += 0.02
        rec.pump()
    rec.close()
    [path] = rec.files
    _set_unix_offset(path)
    return path


def _set_unix_offset(path: Path) -> None:
    """The recorder writes the real Unix - monotonic offset; the test wants a known one (same length)."""
    data = path.read_bytes()
    recording = read_recording(path)
    real = recording.metadata["vlp_agent"]["unix_minus_monotonic_ns"].encode()
    fixed = str(UNIX_OFFSET_NS).encode()
    assert len(real) == len(fixed) and data.count(real) == 1
    path.write_bytes(data.replace(real, fixed))


def _read_bag(bag: Path) -> tuple[dict[str, list[tuple[int, Any]]], dict[str, str], dict[str, Any]]:
    """Every message of the bag, decoded by rosbags' Humble type store, by topic; each topic's type and
    the QoS profiles it was offered with."""
    typestore = get_typestore(Stores.ROS2_HUMBLE)
    out: dict[str, list[tuple[int, Any]]] = {}
    with Reader(bag) as reader:
        for connection, t_ns, raw in reader.messages():
            message = typestore.deserialize_cdr(raw, connection.msgtype)
            out.setdefault(connection.topic, []).append((t_ns, message))
        types = {c.topic: c.msgtype for c in reader.connections}
        qos = {c.topic: c.ext.offered_qos_profiles for c in reader.connections}  # type: ignore[union-attr]
    return out, types, qos


def test_the_message_definitions_are_the_standard_ones() -> None:
    typestore = get_typestore(Stores.ROS2_HUMBLE)
    for name in TYPES:
        standard, _ = typestore.generate_msgdef(name, ros_version=2)
        assert msgdef(name).strip() == standard.strip(), name


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def test_a_recording_exports_to_a_ros2_bag_that_an_independent_reader_decodes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from agent.cli import main

    path = _recorded(tmp_path)
    bag = tmp_path / "bag"
    assert main(["export", "--ros2", str(path), str(bag), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["complete"] and result["stopped"] is None
    assert result["topics"] == {
        "/scan": 60,
        "/odom": 300,
        "/pose": 30,
        "/tf": 30,
        "/tf_static": 1,
        "/slam/pose": 6,
        "/vlp/pose": 6,
        "/map": 3,
        "/imu": 300,
        "/cmd_vel": 300,
        "/controller/cmd_vel": 1,
        "/goal_pose": 1,
        "/diagnostics": 2,
    }
    assert sorted(p.name for p in bag.iterdir()) == ["bag_0.mcap", "metadata.yaml"]
    messages, types, qos = _read_bag(bag)
    assert types == {
        "/tf": "tf2_msgs/msg/TFMessage",
        "/tf_static": "tf2_msgs/msg/TFMessage",
        "/scan": "sensor_msgs/msg/LaserScan",
        "/odom": "nav_msgs/msg/Odometry",
        "/pose": "geometry_msgs/msg/PoseWithCovarianceStamped",
        "/slam/pose": "geometry_msgs/msg/PoseWithCovarianceStamped",
        "/vlp/pose": "geometry_msgs/msg/PoseWithCovarianceStamped",
        "/map": "nav_msgs/msg/OccupancyGrid",
        "/imu": "sensor_msgs/msg/Imu",
        "/cmd_vel": "geometry_msgs/msg/TwistStamped",
        "/controller/cmd_vel": "geometry_msgs/msg/TwistStamped",
        "/goal_pose": "geometry_msgs/msg/PoseStamped",
        "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
    }
    assert {topic: len(m) for topic, m in messages.items()} == result["topics"]

    # IMU: no orientation (REP 145), the gyro and the accelerometer as recorded, in frame imu.
    t_imu, imu = messages["/imu"][1]
    assert t_imu == _stamp_ns(imu.header) == T0_NS + 20_000_000 + UNIX_OFFSET_NS
    assert imu.header.frame_id == "imu" and imu.orientation_covariance[0] == -1.0
    gyro, accel = imu.angular_velocity, imu.linear_acceleration
    assert (gyro.x, gyro.y, gyro.z) == (0.01, 0.02, 0.1) and (accel.x, accel.y, accel.z) == (0.1, -0.2, 9.81)
    # Commands: the base velocity sent with each wheel command; the controller's velocity and goal.
    _, sent = messages["/cmd_vel"][0]
    assert sent.header.frame_id == "base_link" and (sent.twist.linear.x, sent.twist.angular.z) == (0.2, 0.1)
    _, received = messages["/controller/cmd_vel"][0]
    assert (received.twist.linear.x, received.twist.angular.z) == (0.15, -0.3)
    t_goal, goal = messages["/goal_pose"][0]
    assert t_goal == T0_NS + 100 * 20_000_000 + UNIX_OFFSET_NS and goal.header.frame_id == "map"
    assert (goal.pose.position.x, goal.pose.position.y, goal.pose.orientation.w) == (3.5, -1.25, 1.0)
    # Health: one status per event, OK then ERROR with the reason.
    statuses = [m.status[0] for _, m in messages["/diagnostics"]]
    assert [(st.level, st.name, st.hardware_id) for st in statuses] == [
        (0, "vlp-agent/laser", "laser"),
        (2, "vlp-agent/laser", "laser"),
    ]
    assert statuses[1].message == "no scan for 0.5 s"
    assert [(kv.key, kv.value) for kv in statuses[1].values] == [("ok", "false")]

    # Scans: metres, the error codes as NaN, the angles and limits of the recorded scan, Unix time.
    t_first, first = messages["/scan"][0]
    recorded = scan(0, T0_NS)
    assert t_first == _stamp_ns(first.header) == T0_NS + UNIX_OFFSET_NS and first.header.frame_id == "laser"
    ranges = np.asarray(first.ranges)
    valid = recorded.valid_mask()
    assert np.allclose(ranges[valid], recorded.ranges_mm[valid] * 1e-3, atol=1e-6)
    assert np.isnan(ranges[recorded.ranges_mm < recorded.min_range_mm]).all()
    assert np.isinf(ranges[recorded.ranges_mm > recorded.max_range_mm]).all()
    assert first.angle_min == pytest.approx(-2.09) and first.angle_increment == pytest.approx(0.00614)
    assert first.angle_max == pytest.approx(-2.09 + 681 * 0.00614, abs=1e-5)
    assert (first.range_min, first.range_max) == pytest.approx((0.02, 5.6))

    # The fused pose: yaw as a quaternion, the 3x3 covariance at (x, y, yaw) of the 6x6.
    _, pose = messages["/pose"][0]
    assert pose.header.frame_id == "map" and _stamp_ns(pose.header) == T0_NS + UNIX_OFFSET_NS
    p = pose.pose.pose
    assert (p.position.x, p.position.y) == (1.0, 2.0)
    assert 2.0 * math.atan2(p.orientation.z, p.orientation.w) == pytest.approx(0.5)
    cov = pose.pose.covariance.reshape(6, 6)
    assert (cov[0, 0], cov[1, 1], cov[5, 5]) == (1e-4, 2e-4, 1e-5) and cov[2, 2] == 0.0
    _, slam = messages["/slam/pose"][1]
    assert slam.pose.pose.position.x == 1.5 and slam.pose.covariance.reshape(6, 6)[5, 5] == 3e-4
    # A fix without heading: its 2x2 in place, the yaw variance "unknown".
    _, vlp = messages["/vlp/pose"][0]
    vcov = vlp.pose.covariance.reshape(6, 6)
    assert (vcov[0, 0], vcov[0, 1], vcov[1, 1]) == (4e-6, 1e-6, 9e-6) and vcov[5, 5] == 1e6

    # Odometry integrated from the wheel intervals: 300 of 0.004 m on a 0.002 rad turn each.
    _, last = messages["/odom"][-1]
    assert last.header.frame_id == "odom" and last.child_frame_id == "base_link"
    yaw = 2.0 * math.atan2(last.pose.pose.orientation.z, last.pose.pose.orientation.w)
    assert yaw == pytest.approx(299 * 0.002)
    radius = 0.004 / 0.002
    chord = 2.0 * radius * math.sin(299 * 0.002 / 2.0)
    assert math.hypot(last.pose.pose.position.x, last.pose.pose.position.y) == pytest.approx(chord, rel=1e-6)
    assert last.twist.twist.linear.x == pytest.approx(0.2) and last.twist.twist.angular.z == pytest.approx(
        0.1
    )

    # The map: the recorded occupancy, rows from the lowest y, its size, cell and origin.
    _, grid = messages["/map"][0]
    pixels = np.full((40, 60), 205, dtype=np.uint8)
    pixels[:10] = 254
    pixels[10:12] = 0
    assert (grid.info.width, grid.info.height) == (60, 40)
    assert grid.info.resolution == pytest.approx(0.05)
    assert (grid.info.origin.position.x, grid.info.origin.position.y) == (-1.0, -2.0)
    assert np.array_equal(np.asarray(grid.data, dtype=np.int8), occupancy_cells(pixels).ravel())

    # The transforms: the fused pose map -> base_link; the laser's mount base_link -> laser, latched.
    _, tf = messages["/tf"][0]
    [map_base] = tf.transforms
    assert (map_base.header.frame_id, map_base.child_frame_id) == ("map", "base_link")
    assert (map_base.transform.translation.x, map_base.transform.translation.y) == (1.0, 2.0)
    assert map_base.transform.rotation.z == pytest.approx(math.sin(0.25))
    t_static, static = messages["/tf_static"][0]
    [base_laser] = static.transforms
    assert (base_laser.header.frame_id, base_laser.child_frame_id) == ("base_link", "laser")
    assert t_static == T0_NS + UNIX_OFFSET_NS
    translation, rotation = base_laser.transform.translation, base_laser.transform.rotation
    assert (translation.x, translation.y, translation.z) == (0.1, 0.0, 0.2)
    assert (rotation.z, rotation.w) == pytest.approx((1.0, 0.0))
    for topic in ("/tf_static", "/map"):
        [profile] = qos[topic]
        latched = (profile.durability.name, profile.reliability.name, profile.depth)
        assert latched == ("TRANSIENT_LOCAL", "RELIABLE", 1)
    assert qos["/scan"] == []

    # A bag is never written over.
    assert main(["export", "--ros2", str(path), str(bag)]) == 1
    assert "never written over" in capsys.readouterr().err


def test_a_cut_recording_exports_what_is_readable_and_says_where_it_stopped(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from agent.cli import main

    data = _recorded(tmp_path).read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    assert main(["export", "--ros2", str(cut), str(tmp_path / "bag"), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    stopped = result["stopped"]
    assert not result["complete"] and stopped["file"] == str(cut) and stopped["error"]
    assert 0 < stopped["at_byte"] <= len(data) // 2
    assert 5 < result["topics"]["/scan"] < 60
    messages, _, _ = _read_bag(tmp_path / "bag")
    assert {topic: len(m) for topic, m in messages.items()} == result["topics"]
    last_scan_ns = messages["/scan"][-1][0] - UNIX_OFFSET_NS
    assert T0_NS < last_scan_ns < T0_NS + 6_000_000_000
