"""The simulated controller at the other end of the pose stream, in a process of its own.

On a robot the pose stream goes out on a serial line to another chip (the motor controller's firmware,
or a flight controller speaking MAVLink) that decodes it. Under ``vlp-agent sim`` the line is a
pseudo-terminal and this is that chip: it reads the pty's master side and decodes every frame, counting
good and bad ones, as the firmware would (``firmware_protocol.pose_frame.PoseFrameDecoder``, or pymavlink
for MAVLink output).

It runs in a child process (``python -m drivers.sim.controller FD``, started through
:mod:`drivers.child_process`), not a thread of the agent, for the reason the camera's renderer does: the
controller is another chip on the robot, and a reader thread in the agent's process would be woken by
every pose the agent writes, at the moment the hot path returns from its write and wants the interpreter
lock back. (On this development machine the write's wall-time p99 stayed 1.2-4 ms either way, against
0.1-0.2 ms of CPU: what it waits for there is the cores and the hypervisor, see docs/benchmarks.md.)
The child makes the pty pair itself (raw on both sides), tells the parent the slave's name to write to,
and answers requests for its counts over the socketpair; asked to stop, it takes in what is still in the
pty, sends its final counts and ends.

Given goals (``vlp-agent sim --goal``), it also commands the robot as a controller would
(``docs/wire-format.md``, "Commands and goal status"): it sends the first goal as a goal command frame
once the agent's pose stream is flowing, reads the goal statuses coming back between the pose frames
(:class:`~firmware_protocol.command_frame.GoalStatusDecoder`), and sends the next goal when the agent
reports the last one ended (REACHED, FAILED, REJECTED or CANCELLED), so a run drives the goals one after
another; a goal rejected NOT_LOCALIZED (no map or pose yet) is sent again a second later. ``record`` names
a file that gets every byte the agent sent, for an independent decoder (the reference C code) to read
afterwards. Goals are command frames only; with MAVLink output the controller
only decodes (the MAVLink commands are tested on their own).

Missions (``vlp-agent sim --explore``, ``--deliver``) go the same way, one after another: an item
``("explore",)`` is sent as an explore command frame (start), ``("place", NAME, COME_BACK)`` as a
go-to-place frame (command frames v1.1); the mission id is the item's place in the list, as a goal's
id is, and the mission's end is a status of that id.

Following (``vlp-agent sim --send-follow``) too: an item ``("follow", "start", TAG or None, DELAY_S)`` is a
follow start frame (v1.2; the follow id is the item's place in the list), ``("follow", "stop", None,
DELAY_S)`` a follow stop of the last follow started; each is sent ``DELAY_S`` after the item before it was
answered (from when the pose stream flows, for the first), and counts as done at its answer (the status
echoing its sequence). The following's ACTIVE statuses in between are decoded and kept as any status.
"""

from __future__ import annotations

import contextlib
import importlib
import multiprocessing.connection
import os
import select
import sys
import time
import tty
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from drivers.child_process import child_connection, start_child, stop_child
from drivers.errors import DeviceDisconnected

__all__ = ["ControllerCounts", "SimulatedController"]

_REPLY_TIMEOUT_S = 5.0


@dataclass(frozen=True)
class ControllerCounts:
    """What the controller has taken in: decoded frames, frames it rejected, bytes; with goals, the goal
    statuses it decoded (``(goal_id, state, reason)`` names, in order) and how many goals it sent."""

    frames: int = 0
    bad: int = 0
    bytes: int = 0
    statuses: tuple[tuple[int, str, str], ...] = ()
    goals_sent: int = 0
    goals_done: bool = False  # every goal sent and the last one ended for good


_ENDED = ("REACHED", "FAILED", "REJECTED", "CANCELLED")


class _Commander:
    """Sends the goals one after another as goal command frames, each when the one before has ended.

    A goal rejected NOT_LOCALIZED (the agent has no map or no pose yet, as right after start-up) is sent
    again every ``retry_s``, up to ``retries`` times, as a controller waiting for the robot would; any other
    end moves on to the next goal."""

    def __init__(
        self,
        goals: Sequence[tuple[Any, ...]],
        allow_unknown: bool,
        retry_s: float = 1.0,
        retries: int = 120,
    ) -> None:
        from firmware_protocol.command_frame import GoalStatusDecoder

        self.goals = list(goals)
        self.allow_unknown = allow_unknown
        self.retry_s = retry_s
        self.retries = retries
        self.sent = 0  # goals started (ids 1, 2, ...: the goal's place in the list)
        self.sequence = 0
        self.statuses: list[tuple[int, str, str]] = []
        self._decoder = GoalStatusDecoder()
        self._waiting = False  # a goal is out and has not ended yet
        self._retry_at: float | None = None
        self._tries = 0
        self._answered_at: float | None = None  # when the last follow item was answered (or poses flowed)
        self._follow_id = 0  # the last follow started

    @property
    def done(self) -> bool:
        """Every goal sent and the last one ended for good."""
        return self.sent == len(self.goals) and not self._waiting and self._retry_at is None

    def _following(self) -> bool:
        """The item out (or last sent) is a follow command."""
        return 0 < self.sent <= len(self.goals) and self.goals[self.sent - 1][:1] == ("follow",)

    def take(self, data: bytes) -> None:
        for status in self._decoder.feed(data):
            self.statuses.append((status.goal_id, status.state.name, status.reason.name))
            if self._following():
                if self._waiting and status.command_sequence == self.sequence:
                    self._waiting = False  # its answer: the next item may go (after its delay)
                    self._answered_at = time.monotonic()
                continue
            if self._waiting and status.goal_id == self.sent and status.state.name in _ENDED:
                self._waiting = False
                retry = status.state.name == "REJECTED" and status.reason.name == "NOT_LOCALIZED"
                if retry and self._tries < self.retries:
                    self._retry_at = time.monotonic() + self.retry_s

    def due(self, poses_seen: int) -> bytes:
        """The next frame to send, if one is due: a goal retried, or the next goal once the pose stream is
        flowing and nothing is in progress."""
        if self._waiting or poses_seen < 20:
            return b""
        if self._retry_at is not None:
            if time.monotonic() < self._retry_at:
                return b""
            self._retry_at = None
            self._tries += 1
        elif self.sent < len(self.goals):
            nxt = self.goals[self.sent]
            if nxt[:1] == ("follow",):
                if self._answered_at is None:
                    self._answered_at = time.monotonic()  # the pose stream flows from now
                if time.monotonic() < self._answered_at + float(nxt[3]):
                    return b""
            self.sent += 1
            self._tries = 0
        else:
            return b""
        from firmware_protocol.command_frame import GoalCommand, encode_command

        item = self.goals[self.sent - 1]
        self.sequence = (self.sequence + 1) & 0xFFFF
        self._waiting = True
        if item[:1] == ("follow",):
            from firmware_protocol.command_frame import FollowAction, FollowCommand

            if item[1] == "start":
                self._follow_id = self.sent
                return encode_command(FollowCommand(self.sequence, self.sent, FollowAction.START, item[2]))
            return encode_command(FollowCommand(self.sequence, self._follow_id, FollowAction.STOP))
        if item and isinstance(item[0], str):
            from firmware_protocol.command_frame import ExploreCommand, PlaceCommand

            if item[0] == "explore":
                return encode_command(ExploreCommand(self.sequence, self.sent))
            return encode_command(PlaceCommand(self.sequence, self.sent, str(item[1]), bool(item[2])))
        x, y, yaw = item
        goal = GoalCommand(self.sequence, self.sent, x, y, yaw, allow_unknown=self.allow_unknown)
        return encode_command(goal)


class _Decoder:
    """The controller's decoding: pose frames, or MAVLink through pymavlink."""

    def __init__(self, mavlink: bool) -> None:
        self.frames = self.bad = self.bytes = 0
        self._mav: Any = None
        self._pose: Any = None
        if mavlink:
            os.environ.setdefault("MAVLINK20", "1")
            common = importlib.import_module("pymavlink.dialects.v20.common")
            self._mav = common.MAVLink(None)
            self._mav.robust_parsing = True
        else:
            from firmware_protocol.pose_frame import PoseFrameDecoder

            self._pose = PoseFrameDecoder()

    def take(self, data: bytes) -> None:
        self.bytes += len(data)
        if self._pose is not None:
            self.frames += len(self._pose.feed(data))
            self.bad = self._pose.bad_frames
            return
        for msg in self._mav.parse_buffer(data) or []:
            if msg.get_type() == "BAD_DATA":
                self.bad += 1
            else:
                self.frames += 1

    def counts(self) -> tuple[int, int, int]:
        return (self.frames, self.bad, self.bytes)


def _counts(decoder: _Decoder, commander: _Commander | None) -> tuple[Any, ...]:
    # A plain tuple over the connection: the child's module is ``__main__``, whose classes the parent
    # cannot unpickle.
    if commander is None:
        return decoder.counts()
    frames, bad, nbytes = decoder.counts()
    # The pose decoder takes each good goal status for a pose frame of another version: not a bad frame.
    statuses = tuple(commander.statuses)
    return (frames, bad - len(statuses), nbytes, statuses, commander.sent, commander.done)


class _Receiver:
    """Everything the agent sends: to the pose decoder, to the goal commander, to the record file."""

    def __init__(self, decoder: _Decoder, commander: _Commander | None, record: str | None) -> None:
        self.decoder = decoder
        self.commander = commander
        self.record = open(record, "wb") if record else None  # noqa: SIM115 (closed in _serve)

    def take(self, data: bytes) -> None:
        self.decoder.take(data)
        if self.commander is not None:
            self.commander.take(data)
        if self.record is not None:
            self.record.write(data)


def _drain(fd: int, receiver: _Receiver) -> None:
    while select.select([fd], [], [], 0)[0]:
        try:
            data = os.read(fd, 4096)
        except OSError:
            return
        if not data:
            return
        receiver.take(data)


def _serve(conn: multiprocessing.connection.Connection) -> None:
    """The child: make the pty, report its name, then decode (and command) until asked to stop."""
    mavlink, goals, allow_unknown, record = conn.recv()
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    decoder = _Decoder(mavlink)
    commander = _Commander(goals, allow_unknown) if goals and not mavlink else None
    receiver = _Receiver(decoder, commander, record)
    conn.send(os.ttyname(slave))
    try:
        while True:
            ready, _, _ = select.select([master, conn.fileno()], [], [], 0.1)
            if master in ready:
                try:
                    data = os.read(master, 4096)
                except OSError:
                    data = b""
                receiver.take(data)
            if commander is not None:
                frame = commander.due(decoder.frames)
                if frame:
                    os.write(master, frame)
            if conn.fileno() in ready:
                try:
                    request = conn.recv()
                except (EOFError, OSError):
                    return
                if request is None:
                    _drain(master, receiver)
                    conn.send(_counts(decoder, commander))
                    return
                conn.send(_counts(decoder, commander))
    finally:
        if receiver.record is not None:
            receiver.record.close()
        os.close(master)
        os.close(slave)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m drivers.sim.controller FD``: serve the connection on file descriptor FD."""
    conn = child_connection("drivers.sim.controller", "SimulatedController", argv)
    if conn is None:
        return 2
    _serve(conn)
    return 0


class SimulatedController:
    """The controller child: ``url`` is the pty to write the pose stream to; :meth:`counts` what it decoded
    so far; :meth:`stop` takes in the rest and ends it (its last counts stay readable). ``goals``: (x, y,
    yaw or None) to send one after another as goal commands (``allow_unknown``: their option to cross unknown
    space), or missions (``("explore",)``, ``("place", name, come_back)``); ``record``: a file for every
    byte received."""

    def __init__(
        self,
        mavlink: bool = False,
        goals: Sequence[tuple[Any, ...]] = (),
        allow_unknown: bool = False,
        record: str | None = None,
    ) -> None:
        self._process, self._conn = start_child("drivers.sim.controller")
        self._final: ControllerCounts | None = None
        try:
            self._conn.send((mavlink, [tuple(g) for g in goals], allow_unknown, record))
            if not self._conn.poll(_REPLY_TIMEOUT_S):
                raise DeviceDisconnected("the simulated controller did not start", "output")
            self.url: str = self._conn.recv()
        except BaseException:
            stop_child(self._process, self._conn, "simulated controller")
            raise

    def counts(self) -> ControllerCounts:
        if self._final is not None:
            return self._final
        try:
            self._conn.send("counts")
            if self._conn.poll(_REPLY_TIMEOUT_S):
                return ControllerCounts(*self._conn.recv())
        except (EOFError, OSError):
            pass
        raise DeviceDisconnected("the simulated controller is gone", "output")

    @property
    def frames(self) -> int:
        return self.counts().frames

    @property
    def bad(self) -> int:
        return self.counts().bad

    def stop(self) -> None:
        """Take in what is still in the pty, keep the final counts, end the child. Safe to call twice."""
        if self._final is not None:
            return
        final = ControllerCounts()
        with contextlib.suppress(EOFError, OSError):
            self._conn.send(None)
            if self._conn.poll(_REPLY_TIMEOUT_S):
                final = ControllerCounts(*self._conn.recv())
        self._final = final
        stop_child(self._process, self._conn, "simulated controller")


if __name__ == "__main__":
    sys.exit(main())
