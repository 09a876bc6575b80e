"""MAVLink pose output: pymavlink's own parser reads back what we emit, field by field; the frame CRC is
re-computed here without pymavlink (CRC-16/MCRF4XX plus CRC_EXTRA 158 / 91)."""

from __future__ import annotations

import math
import os
import struct
from dataclasses import replace
from typing import Any

import pytest
from hypothesis import given, settings

from firmware_protocol.crc import crc16_mcrf4xx
from firmware_protocol.mavlink_out import (
    CRC_EXTRA,
    DEFAULT_COMPID,
    DEFAULT_SYSID,
    MSG_ID,
    MavlinkEncodeError,
    MavlinkMessage,
    MavlinkPoseEncoder,
    pose_covariance,
)
from firmware_protocol.pose_frame import PoseFlags, PoseFrame
from tests.unit.test_pose_frame import pose_frames

mavlink = pytest.importorskip("pymavlink.dialects.v20.common", reason="pymavlink is not installed")

VPE = MavlinkMessage.VISION_POSITION_ESTIMATE
ODO = MavlinkMessage.ODOMETRY

POSE = PoseFrame(
    sequence=1234,
    t_us=12_345_678_901,
    x_m=3.1416,
    y_m=-2.5,
    yaw_rad=1.5,
    sigma_xy_m=0.0021,
    sigma_yaw_rad=0.0087,
    flags=PoseFlags.VLP | PoseFlags.SLAM,
    reset_counter=3,
)


def f32(value: float) -> float:
    result: float = struct.unpack("<f", struct.pack("<f", value))[0]
    return result


def parse(data: bytes) -> list[Any]:
    messages = mavlink.MAVLink(None).parse_buffer(data)
    assert messages is not None
    return list(messages)


def assert_frame_crc(frame: bytes, message: MavlinkMessage) -> None:
    """MAVLink 2 framing and CRC, checked without pymavlink."""
    assert frame[0] == 0xFD
    assert frame[1] == len(frame) - 12  # header 10 + CRC 2, unsigned
    assert frame[2] == 0 and frame[3] == 0  # incompat (not signed), compat flags
    assert int.from_bytes(frame[7:10], "little") == MSG_ID[message]
    expected = crc16_mcrf4xx(frame[1:-2] + bytes([CRC_EXTRA[message]]))
    assert int.from_bytes(frame[-2:], "little") == expected


def test_message_ids_and_crc_extras_are_pymavlinks() -> None:
    assert CRC_EXTRA == {VPE: 158, ODO: 91}
    assert MSG_ID == {VPE: 102, ODO: 331}
    assert mavlink.MAVLink_vision_position_estimate_message.crc_extra == 158
    assert mavlink.MAVLink_odometry_message.crc_extra == 91
    assert mavlink.MAVLINK_MSG_ID_VISION_POSITION_ESTIMATE == 102
    assert mavlink.MAVLINK_MSG_ID_ODOMETRY == 331
    assert crc16_mcrf4xx(b"123456789") == 0x6F91


def test_mavlink2_is_selected_before_pymavlink_loads() -> None:
    MavlinkPoseEncoder()
    assert os.environ.get("MAVLINK20") == "1"
    assert mavlink.WIRE_PROTOCOL_VERSION == "2.0"


def test_vision_position_estimate_reads_back() -> None:
    frame = MavlinkPoseEncoder(VPE).encode(POSE)
    assert_frame_crc(frame, VPE)
    assert len(frame) == 129
    [msg] = parse(frame)
    assert msg.get_type() == "VISION_POSITION_ESTIMATE"
    assert msg.get_srcSystem() == DEFAULT_SYSID and msg.get_srcComponent() == DEFAULT_COMPID
    assert msg.get_seq() == 1234 % 256
    assert msg.usec == 12_345_678_901
    assert (msg.x, msg.y, msg.z) == (f32(3.1416), f32(2.5), 0.0)  # y flipped into the z-down frame
    assert (msg.roll, msg.pitch, msg.yaw) == (0.0, 0.0, f32(-1.5))
    assert msg.reset_counter == 3
    cov = list(msg.covariance)
    assert cov[0] == cov[6] == f32(0.0021**2)
    assert cov[20] == f32(0.0087**2)
    assert [c for i, c in enumerate(cov) if i not in (0, 6, 20)] == [0.0] * 18


def test_odometry_reads_back() -> None:
    frame = MavlinkPoseEncoder(ODO, sysid=7, compid=191).encode(POSE, quality=80)
    assert_frame_crc(frame, ODO)
    [msg] = parse(frame)
    assert msg.get_type() == "ODOMETRY"
    assert (msg.get_srcSystem(), msg.get_srcComponent(), msg.get_seq()) == (7, 191, 1234 % 256)
    assert msg.time_usec == 12_345_678_901
    assert (msg.frame_id, msg.child_frame_id) == (mavlink.MAV_FRAME_LOCAL_FRD, mavlink.MAV_FRAME_BODY_FRD)
    assert (msg.x, msg.y, msg.z) == (f32(3.1416), f32(2.5), 0.0)
    assert list(msg.q) == [f32(math.cos(-0.75)), 0.0, 0.0, f32(math.sin(-0.75))]
    velocities = (msg.vx, msg.vy, msg.vz, msg.rollspeed, msg.pitchspeed, msg.yawspeed)
    assert all(math.isnan(v) for v in velocities)
    assert math.isnan(msg.velocity_covariance[0])
    assert msg.pose_covariance[0] == f32(0.0021**2) and msg.pose_covariance[20] == f32(0.0087**2)
    assert msg.reset_counter == 3
    assert msg.estimator_type == mavlink.MAV_ESTIMATOR_TYPE_VISION
    assert msg.quality == 80


def test_unknown_covariance() -> None:
    unknown_xy = PoseFrame(1, 2, 0.0, 0.0, 0.0, sigma_xy_m=math.inf, sigma_yaw_rad=0.1)
    cov = pose_covariance(unknown_xy)
    assert math.isnan(cov[0]) and cov[1:] == [0.0] * 20
    frame = MavlinkPoseEncoder(VPE).encode(unknown_xy)
    assert len(frame) == 48  # trailing zeros of the payload dropped, as MAVLink 2 does
    [msg] = parse(frame)
    assert math.isnan(msg.covariance[0])
    unknown_yaw = PoseFrame(1, 2, 0.0, 0.0, 0.0, sigma_xy_m=0.01, sigma_yaw_rad=math.inf)
    assert pose_covariance(unknown_yaw)[20] == pytest.approx(math.pi**2 / 3)


def test_yaw_is_wrapped_into_minus_pi_to_pi() -> None:
    [msg] = parse(MavlinkPoseEncoder(VPE).encode(PoseFrame(0, 0, 0.0, 0.0, 7.0)))
    assert msg.yaw == pytest.approx(math.remainder(-7.0, math.tau), abs=1e-6)


def test_a_stream_of_both_kinds_parses_in_order() -> None:
    vpe, odo = MavlinkPoseEncoder(VPE), MavlinkPoseEncoder(ODO, compid=198)
    poses = [
        PoseFrame(i, 1000 * i, 0.1 * i, -0.2 * i, 0.05 * i, 0.01, 0.02, reset_counter=i % 3)
        for i in range(300)
    ]
    data = b"".join((vpe if i % 2 else odo).encode(p) for i, p in enumerate(poses))
    messages = parse(data)
    assert [m.get_seq() for m in messages] == [i % 256 for i in range(300)]
    assert [m.get_type() for m in messages[:2]] == ["ODOMETRY", "VISION_POSITION_ESTIMATE"]
    assert [stamp(m) for m in messages] == [1000 * i for i in range(300)]


@pytest.mark.parametrize(
    ("kwargs", "pose_changes"),
    [
        ({"message": "attitude"}, {}),
        ({"sysid": 256}, {}),
        ({"compid": -1}, {}),
        ({}, {"x_m": math.nan}),
        ({}, {"yaw_rad": math.inf}),
        ({}, {"x_m": 1e39}),  # beyond float32
        ({}, {"t_us": -1}),
        ({}, {"reset_counter": 256}),
    ],
)
def test_what_does_not_fit_raises_mavlink_encode_error(
    kwargs: dict[str, Any], pose_changes: dict[str, Any]
) -> None:
    with pytest.raises(MavlinkEncodeError):
        MavlinkPoseEncoder(**kwargs).encode(replace(POSE, **pose_changes))


def test_quality_range() -> None:
    with pytest.raises(MavlinkEncodeError):
        MavlinkPoseEncoder(ODO).encode(POSE, quality=101)


def stamp(msg: Any) -> int:
    return int(msg.usec if msg.get_type() == "VISION_POSITION_ESTIMATE" else msg.time_usec)


@settings(max_examples=100, deadline=None)
@given(pose=pose_frames)
def test_any_encodable_pose_reads_back_from_both_messages(pose: PoseFrame) -> None:
    for kind in MavlinkMessage:
        frame = MavlinkPoseEncoder(kind).encode(pose)
        assert_frame_crc(frame, kind)
        [msg] = parse(frame)
        assert stamp(msg) == pose.t_us
        assert (msg.x, msg.y) == (f32(pose.x_m), f32(-pose.y_m))
        assert msg.reset_counter == pose.reset_counter
        assert msg.get_seq() == pose.sequence & 0xFF
