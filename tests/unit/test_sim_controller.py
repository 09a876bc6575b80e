"""The simulated controller process: it makes the pose stream's pty, decodes what is written to it, and
keeps its counts after it stops."""

from __future__ import annotations

import os
import select
import time
import tty
from pathlib import Path

import pytest

from drivers.sim.controller import ControllerCounts, SimulatedController
from firmware_protocol.command_frame import (
    NO_SEQUENCE,
    Command,
    CommandDecoder,
    GoalCommand,
    GoalReason,
    GoalState,
    GoalStatus,
    encode_goal_status,
)
from firmware_protocol.pose_frame import PoseFlags, PoseFrame, encode_pose


def _frame(k: int) -> bytes:
    return encode_pose(PoseFrame(k, 1_000_000 + k, 1.0, 2.0, 0.5, 0.01, 0.02, PoseFlags.VLP, 0))


def test_it_decodes_the_stream_written_to_its_pty() -> None:
    controller = SimulatedController()
    try:
        assert controller.url.startswith("/dev/pts/")
        fd = os.open(controller.url, os.O_WRONLY | os.O_NOCTTY)
        try:
            stream = _frame(1) + _frame(2)
            bad = bytearray(_frame(3))
            bad[5] ^= 0x40  # a flipped bit: the CRC rejects it
            os.write(fd, stream + bytes(bad) + _frame(4))
            deadline = time.monotonic() + 5.0
            while controller.frames < 3 and time.monotonic() < deadline:
                time.sleep(0.02)
            assert controller.counts() == ControllerCounts(3, 1, len(stream) + len(bad) + len(_frame(4)))
            os.write(fd, _frame(5))  # still in the pty when it stops: taken in
        finally:
            os.close(fd)
    finally:
        controller.stop()
    assert controller.frames == 4 and controller.bad == 1
    controller.stop()  # twice is fine; the counts stay
    assert controller.counts().frames == 4


def test_given_goals_it_sends_each_when_the_one_before_ends_and_records_the_stream(tmp_path: Path) -> None:
    record = tmp_path / "received.bin"
    controller = SimulatedController(goals=[(1.0, 2.0, None), (3.0, -1.0, 0.5)], record=str(record))
    try:
        fd = os.open(controller.url, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(fd)
        try:
            poses = b"".join(_frame(k) for k in range(25))
            os.write(fd, poses)
            commands = CommandDecoder()
            first = _read_commands(fd, commands, 1)
            assert isinstance(first[0], GoalCommand) and first[0].goal_id == 1
            assert (first[0].x_m, first[0].y_m, first[0].yaw_rad) == (1.0, 2.0, None)
            # Nothing more while goal 1 is in progress; its end brings goal 2.
            accepted = encode_goal_status(GoalStatus(1, first[0].sequence, 1, GoalState.ACCEPTED))
            reached = encode_goal_status(GoalStatus(2, NO_SEQUENCE, 1, GoalState.REACHED, remaining_m=0.0))
            os.write(fd, accepted)
            assert _read_commands(fd, commands, 1, wait_s=0.5) == []
            os.write(fd, _frame(30) + reached)
            second = _read_commands(fd, commands, 1)
            assert isinstance(second[0], GoalCommand) and second[0].goal_id == 2
            assert second[0].yaw_rad == pytest.approx(0.5, abs=1e-4)
        finally:
            os.close(fd)
    finally:
        controller.stop()
    counts = controller.counts()
    assert counts.goals_sent == 2
    assert counts.statuses == ((1, "ACCEPTED", "NONE"), (1, "REACHED", "NONE"))
    assert (counts.frames, counts.bad) == (26, 0)  # the statuses are not pose frames, and not bad ones either
    assert record.read_bytes() == poses + accepted + _frame(30) + reached


def _read_commands(fd: int, decoder: CommandDecoder, n: int, wait_s: float = 5.0) -> list[Command]:
    out: list[Command] = []
    deadline = time.monotonic() + wait_s  # only waits for the child; measures nothing
    while len(out) < n and time.monotonic() < deadline:
        if select.select([fd], [], [], 0.05)[0]:
            out += decoder.feed(os.read(fd, 4096))
    return out


def test_a_goal_rejected_not_localized_is_sent_again_and_the_last_end_makes_it_done() -> None:
    controller = SimulatedController(goals=[(1.0, 2.0, None)], allow_unknown=True)
    try:
        fd = os.open(controller.url, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(fd)
        try:
            os.write(fd, b"".join(_frame(k) for k in range(25)))
            commands = CommandDecoder()
            (first,) = _read_commands(fd, commands, 1)
            assert isinstance(first, GoalCommand) and first.allow_unknown
            rejected = GoalStatus(1, first.sequence, 1, GoalState.REJECTED, GoalReason.NOT_LOCALIZED)
            os.write(fd, encode_goal_status(rejected))
            (again,) = _read_commands(fd, commands, 1)  # about a second later: the same goal, a new sequence
            assert isinstance(again, GoalCommand) and (again.goal_id, again.x_m) == (1, 1.0)
            assert again.sequence != first.sequence
            assert not controller.counts().goals_done
            os.write(fd, encode_goal_status(GoalStatus(2, NO_SEQUENCE, 1, GoalState.REACHED)))
            deadline = time.monotonic() + 5.0  # only waits for the child; measures nothing
            while not controller.counts().goals_done and time.monotonic() < deadline:
                time.sleep(0.02)
            assert controller.counts().goals_done
        finally:
            os.close(fd)
    finally:
        controller.stop()
