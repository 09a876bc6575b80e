"""The command loop on a real pseudo-terminal: a controller writes command frames (or MAVLink) on the
pose output's line and reads goal statuses back between the pose frames; bad frames are answered too."""

from __future__ import annotations

import os
from collections.abc import Callable

import pytest

from agent.config import OutputConfig, OutputFormat
from agent.runtime.arbiter import CommandArbiter, DriveSource
from agent.runtime.command_loop import CommandLoop
from agent.runtime.output import PoseOutput
from firmware_protocol.command_frame import (
    NO_SEQUENCE,
    ExploreCommand,
    GoalCommand,
    GoalReason,
    GoalState,
    GoalStatus,
    GoalStatusDecoder,
    PlaceCommand,
    StopCommand,
    VelocityCommand,
    encode_command,
)
from firmware_protocol.framing import encode_link_frame
from firmware_protocol.pose_frame import PoseFlags, PoseFrameDecoder
from tests.unit.test_runtime_output import estimate, pty, read_all

__all__ = ["pty"]  # the fixture


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def setup(path: str, fmt: OutputFormat = OutputFormat.FRAME) -> tuple[PoseOutput, CommandLoop, Clock]:
    out = PoseOutput(OutputConfig(url=path, format=fmt), path)
    out.open()
    clock = Clock()
    arbiter = CommandArbiter(0.22, 2.0, check_goal=lambda g: GoalReason.UNREACHABLE if g.x_m > 50 else None)
    return out, CommandLoop(out, arbiter, fmt, clock_s=clock), clock


def pump(
    loop: CommandLoop, master: int, data: bytes, done: Callable[[bytes], bool], rounds: int = 100
) -> bytes:
    """The controller writes ``data``; the loop steps until what came back is ``done`` (at most ``rounds``
    steps of up to 50 ms: this waits for the pty and the answers, it measures nothing)."""
    os.write(master, data)
    reply = b""
    for _ in range(rounds):
        loop.step()
        reply += read_all(master)
        if done(reply):
            break
    return reply


def statuses(n: int) -> Callable[[bytes], bool]:
    return lambda reply: len(GoalStatusDecoder().feed(reply)) >= n


def test_commands_are_answered_between_pose_frames_and_drive_the_arbiter(pty: tuple[int, str]) -> None:
    master, path = pty
    out, loop, clock = setup(path)
    read_all(master)  # the leading 0x00
    out.publish(estimate(0), PoseFlags.VLP)
    reply = pump(loop, master, encode_command(VelocityCommand(7, 0.5, 0.0, 0.4)), statuses(1))
    out.publish(estimate(1), PoseFlags.VLP)
    reply += read_all(master)
    answers = GoalStatusDecoder().feed(reply)
    assert [(s.command_sequence, s.state, s.reason) for s in answers] == [
        (7, GoalState.ACCEPTED, GoalReason.CLAMPED)
    ]
    assert len(PoseFrameDecoder().feed(reply)) == 2  # poses and statuses share the line
    directive, _ = loop.arbiter.directive(clock.now)
    assert (directive.source, directive.v_mps) == (DriveSource.VELOCITY, 0.22)


def test_bad_crc_unknown_type_and_an_unreachable_goal_are_each_answered(pty: tuple[int, str]) -> None:
    master, path = pty
    _, loop, _ = setup(path)
    read_all(master)
    good = bytearray(encode_command(StopCommand(3)))
    good[2] ^= 0x01
    stream = (
        bytes(good)
        + encode_link_frame(bytes([0x2E, 0x10, 9, 0]))
        + encode_command(GoalCommand(4, 11, 99.0, 0.0))
    )
    reply = pump(loop, master, stream, statuses(3))
    answers = GoalStatusDecoder().feed(reply)
    assert [(s.command_sequence, s.goal_id, s.state, s.reason) for s in answers] == [
        (NO_SEQUENCE, 0xFFFF, GoalState.REJECTED, GoalReason.BAD_FRAME),
        (NO_SEQUENCE, 0xFFFF, GoalState.REJECTED, GoalReason.UNKNOWN_TYPE),
        (4, 11, GoalState.REJECTED, GoalReason.UNREACHABLE),
    ]
    assert loop.counts["rejected_crc"] == 1 and loop.counts["rejected_type"] == 1
    assert loop.arbiter.directive(0.0)[0].source is DriveSource.NONE


def test_mavlink_commands_are_answered_with_command_acks(pty: tuple[int, str]) -> None:
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink.dialects.v20 import common as mavlink

    master, path = pty
    _, loop, _ = setup(path, OutputFormat.MAVLINK)
    read_all(master)
    gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    msg = mavlink.MAVLink_command_long_message(1, 197, 193, 0, 0, 0, 0, 0, 0, 0, 0)
    reply = pump(loop, master, bytes(msg.pack(gcs)), lambda r: bool(mavlink.MAVLink(None).parse_buffer(r)))
    (ack,) = mavlink.MAVLink(None).parse_buffer(reply)
    assert (ack.get_type(), ack.command, ack.result) == ("COMMAND_ACK", 193, 0)
    assert loop.arbiter.directive(0.0)[0].source is DriveSource.STOPPED


@pytest.mark.parametrize("junk", [b"\x00" * 10, bytes(range(1, 256)) * 3, b""])
def test_junk_never_raises_and_never_moves_the_base(pty: tuple[int, str], junk: bytes) -> None:
    master, path = pty
    _, loop, _ = setup(path)
    pump(loop, master, junk + b"\x00", lambda reply: False, rounds=10)
    assert loop.arbiter.directive(0.0)[0].source is DriveSource.NONE


def test_mission_frames_go_to_the_mission_loop_or_are_refused_without_one(pty: tuple[int, str]) -> None:
    master, path = pty
    _, loop, _ = setup(path)
    read_all(master)
    # No mission loop: the arbiter answers UNKNOWN_TYPE with the mission id.
    reply = pump(loop, master, encode_command(PlaceCommand(5, 21, "S3")), statuses(1))
    (answer,) = GoalStatusDecoder().feed(reply)
    assert (answer.command_sequence, answer.goal_id, answer.reason) == (5, 21, GoalReason.UNKNOWN_TYPE)
    taken: list[object] = []

    def missions(command: ExploreCommand | PlaceCommand) -> GoalStatus:
        taken.append(command)
        return loop.arbiter.mission_status(command.sequence, command.mission_id, GoalState.ACCEPTED)

    loop.missions = missions
    heard: list[GoalStatus] = []
    loop.listeners.append(heard.append)
    stream = encode_command(ExploreCommand(6, 22)) + encode_command(PlaceCommand(7, 23, "N4", True))
    reply = pump(loop, master, stream, statuses(2))
    answers = GoalStatusDecoder().feed(reply)
    assert [(s.command_sequence, s.goal_id, s.state) for s in answers] == [
        (6, 22, GoalState.ACCEPTED),
        (7, 23, GoalState.ACCEPTED),
    ]
    assert taken == [ExploreCommand(6, 22), PlaceCommand(7, 23, "N4", True)]
    assert heard == answers and loop.counts["command_go_to_place"] == 2  # the refused one too


def test_follow_over_mavlink_and_the_goal_that_ends_it_are_acked_as_do_follow(pty: tuple[int, str]) -> None:
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink.dialects.v20 import common as mavlink

    master, path = pty
    _, loop, _ = setup(path, OutputFormat.MAVLINK)
    loop.arbiter.check_follow = lambda follow: None  # a follow loop is set up
    read_all(master)
    gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    start = mavlink.MAVLink_command_long_message(1, 197, mavlink.MAV_CMD_DO_FOLLOW, 0, 4, 0, 0, 0, 0, 0, 0)

    def acks(n: int) -> Callable[[bytes], bool]:
        return lambda r: len(mavlink.MAVLink(None).parse_buffer(r) or []) >= n

    (ack,) = mavlink.MAVLink(None).parse_buffer(pump(loop, master, bytes(start.pack(gcs)), acks(1)))
    assert (ack.command, ack.result, ack.result_param2) == (mavlink.MAV_CMD_DO_FOLLOW, 0, 4 << 8)
    assert loop.arbiter.directive(0.0)[0].source is DriveSource.FOLLOW
    goal = mavlink.MAVLink_set_position_target_local_ned_message(
        0, 1, 197, 1, 0b110111111000, 1.0, 1.0, 0, 0, 0, 0, 0, 0, 0, 0, 0
    )
    answers = mavlink.MAVLink(None).parse_buffer(pump(loop, master, bytes(goal.pack(gcs)), acks(2)))
    assert [(a.command, a.result, a.result_param2) for a in answers] == [
        (16, 0, 1 << 8),  # the goal, accepted
        (mavlink.MAV_CMD_DO_FOLLOW, 6, 4 << 8 | GoalReason.SUPERSEDED),  # following ended by it
    ]
