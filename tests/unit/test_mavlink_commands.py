"""MAVLink commands in and goal statuses out, written and read by pymavlink itself (an independent
client of the wire format): goals, body velocities, stop/resume, addressing, NaN fields, junk.
"""

from __future__ import annotations

import math
import os

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_protocol.command_frame import (
    CommandType,
    FollowAction,
    FollowCommand,
    GoalCommand,
    GoalReason,
    GoalState,
    GoalStatus,
    ResumeCommand,
    StopCommand,
    VelocityCommand,
)
from firmware_protocol.mavlink_commands import (
    MAV_CMD_DO_CHANGE_SPEED,
    MAV_CMD_DO_FOLLOW,
    MAV_CMD_DO_PAUSE_CONTINUE,
    MAV_CMD_NAV_WAYPOINT,
    MavlinkCommandDecoder,
    MavlinkStatusEncoder,
)

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mavlink

IGNORE_POSITION = 0b111
IGNORE_VELOCITY = 0b111 << 3
IGNORE_ACCEL = 0b111 << 6
IGNORE_YAW, IGNORE_YAW_RATE = 1 << 10, 1 << 11


def gcs() -> mavlink.MAVLink:
    return mavlink.MAVLink(None, srcSystem=255, srcComponent=190)


def position_target(
    frame: int,
    mask: int,
    x: float = 0.0,
    y: float = 0.0,
    yaw: float = 0.0,
    vx: float = 0.0,
    yaw_rate: float = 0.0,
    target: tuple[int, int] = (1, 197),
) -> bytes:
    msg = mavlink.MAVLink_set_position_target_local_ned_message(
        0, *target, frame, mask, x, y, 0.0, vx, 0.0, 0.0, 0.0, 0.0, 0.0, yaw, yaw_rate
    )
    return bytes(msg.pack(gcs()))


def command_long(command: int, param1: float, target: tuple[int, int] = (1, 197)) -> bytes:
    msg = mavlink.MAVLink_command_long_message(*target, command, 0, param1, 0, 0, 0, 0, 0, 0)
    return bytes(msg.pack(gcs()))


def test_a_local_ned_position_is_a_goal_in_the_z_up_map_frame() -> None:
    decoder = MavlinkCommandDecoder()
    mask = IGNORE_VELOCITY | IGNORE_ACCEL | IGNORE_YAW_RATE | 1 << 2
    out = decoder.feed(position_target(1, mask, x=3.0, y=-1.5, yaw=0.5))
    out += decoder.feed(position_target(1, mask | IGNORE_YAW, x=-2.0, y=4.0))
    assert len(out) == 2
    first, second = out
    assert isinstance(first, GoalCommand) and isinstance(second, GoalCommand)
    assert (first.x_m, first.y_m) == (3.0, 1.5)
    assert first.yaw_rad == pytest.approx(-0.5)
    assert (second.x_m, second.y_m, second.yaw_rad) == (-2.0, -4.0, None)
    assert (first.goal_id, second.goal_id) == (1, 2)


@pytest.mark.parametrize("frame", [8, 9])
def test_a_body_velocity_is_a_velocity_command_with_the_configured_timeout(frame: int) -> None:
    decoder = MavlinkCommandDecoder(velocity_timeout_s=0.3)
    mask = IGNORE_POSITION | IGNORE_ACCEL | IGNORE_YAW | 0b110 << 3
    (cmd,) = decoder.feed(position_target(frame, mask, vx=0.4, yaw_rate=0.25))
    assert isinstance(cmd, VelocityCommand)
    assert (cmd.v_mps, cmd.timeout_s) == (pytest.approx(0.4), 0.3)
    assert cmd.omega_radps == pytest.approx(-0.25)


def test_pause_and_continue_are_stop_and_resume() -> None:
    decoder = MavlinkCommandDecoder()
    out = decoder.feed(
        command_long(MAV_CMD_DO_PAUSE_CONTINUE, 0) + command_long(MAV_CMD_DO_PAUSE_CONTINUE, 1)
    )
    assert [type(c) for c in out] == [StopCommand, ResumeCommand]


def test_messages_for_others_are_ignored_and_broadcasts_taken() -> None:
    decoder = MavlinkCommandDecoder()
    assert decoder.feed(command_long(MAV_CMD_DO_PAUSE_CONTINUE, 0, target=(2, 197))) == []
    assert decoder.feed(command_long(MAV_CMD_DO_PAUSE_CONTINUE, 0, target=(1, 1))) == []
    assert len(decoder.feed(command_long(MAV_CMD_DO_PAUSE_CONTINUE, 0, target=(0, 0)))) == 1
    assert decoder.ignored == 2


def test_nan_fields_and_unsupported_commands_are_rejected_with_a_kind() -> None:
    decoder = MavlinkCommandDecoder()
    mask = IGNORE_VELOCITY | IGNORE_ACCEL | IGNORE_YAW | IGNORE_YAW_RATE
    data = (
        position_target(1, mask, x=math.nan, y=0.0)
        + command_long(400, 1)  # MAV_CMD_COMPONENT_ARM_DISARM: not ours
        + position_target(1, IGNORE_POSITION | IGNORE_ACCEL, vx=1.0)  # a velocity in a world frame
        + command_long(MAV_CMD_DO_PAUSE_CONTINUE, 2)
    )
    assert decoder.feed(data) == []
    assert [e.kind for e in decoder.take_rejected()] == ["value", "type", "type", "value"]
    assert decoder.rejections == 4


def test_junk_between_messages_is_counted_not_raised() -> None:
    decoder = MavlinkCommandDecoder()
    good = command_long(MAV_CMD_DO_PAUSE_CONTINUE, 0)
    out = decoder.feed(b"\x00\x11junk" + good + bytes(good[:-1]) + b"\x42" + good)
    assert [type(c) for c in out] == [StopCommand, StopCommand]
    assert decoder.bad_data > 0


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=300))
def test_any_bytes_decode_or_are_counted(data: bytes) -> None:
    decoder = MavlinkCommandDecoder()
    decoder.feed(data)
    decoder.feed(data[::-1])


@pytest.mark.parametrize(
    ("status", "answers", "command", "result", "progress"),
    [
        (GoalStatus(1, 5, 3, GoalState.ACCEPTED), CommandType.GOAL, MAV_CMD_NAV_WAYPOINT, 0, 255),
        (
            GoalStatus(2, 5, 3, GoalState.ACTIVE, remaining_m=2.0),
            CommandType.GOAL,
            MAV_CMD_NAV_WAYPOINT,
            5,
            255,
        ),
        (GoalStatus(3, 5, 3, GoalState.REACHED), CommandType.GOAL, MAV_CMD_NAV_WAYPOINT, 0, 100),
        (
            GoalStatus(4, 6, 4, GoalState.REJECTED, GoalReason.UNREACHABLE),
            CommandType.GOAL,
            MAV_CMD_NAV_WAYPOINT,
            2,
            255,
        ),
        (
            GoalStatus(5, 7, 0xFFFF, GoalState.ACCEPTED, GoalReason.CLAMPED),
            CommandType.VELOCITY,
            MAV_CMD_DO_CHANGE_SPEED,
            0,
            255,
        ),
        (GoalStatus(6, 8, 0xFFFF, GoalState.ACCEPTED), CommandType.STOP, MAV_CMD_DO_PAUSE_CONTINUE, 0, 255),
        (
            GoalStatus(7, 0xFFFF, 3, GoalState.ACTIVE, GoalReason.SEARCHING),
            CommandType.FOLLOW,
            MAV_CMD_DO_FOLLOW,
            5,
            255,
        ),
        (
            GoalStatus(8, 9, 3, GoalState.REJECTED, GoalReason.FOLLOW_UNAVAILABLE),
            CommandType.FOLLOW,
            MAV_CMD_DO_FOLLOW,
            2,
            255,
        ),
    ],
)
def test_statuses_go_out_as_command_acks_that_pymavlink_reads(
    status: GoalStatus, answers: CommandType, command: int, result: int, progress: int
) -> None:
    data = MavlinkStatusEncoder().encode(status, answers)
    rx = mavlink.MAVLink(None)
    (msg,) = rx.parse_buffer(data)
    assert msg.get_type() == "COMMAND_ACK"
    assert (msg.get_srcSystem(), msg.get_srcComponent()) == (1, 197)
    assert (msg.command, msg.result, msg.progress) == (command, result, progress)
    assert msg.result_param2 == status.goal_id << 8 | status.reason


def test_do_follow_starts_following_the_configured_tag_and_zero_stops_it() -> None:
    assert MAV_CMD_DO_FOLLOW == mavlink.MAV_CMD_DO_FOLLOW  # pymavlink's common dialect: 32
    decoder = MavlinkCommandDecoder()
    out = decoder.feed(command_long(MAV_CMD_DO_FOLLOW, 3) + command_long(MAV_CMD_DO_FOLLOW, 0))
    assert [(type(c), c.follow_id, c.action, c.tag) for c in out] == [  # type: ignore[union-attr]
        (FollowCommand, 3, FollowAction.START, None),
        (FollowCommand, 0xFFFF, FollowAction.STOP, None),
    ]


@pytest.mark.parametrize("param1", [1.5, -1.0, 256.0, math.nan, math.inf])
def test_do_follow_with_a_param1_that_is_no_system_id_is_rejected(param1: float) -> None:
    decoder = MavlinkCommandDecoder()
    assert decoder.feed(command_long(MAV_CMD_DO_FOLLOW, param1)) == []
    (error,) = decoder.take_rejected()
    assert error.kind == "value"
