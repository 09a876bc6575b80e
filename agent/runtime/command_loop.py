"""The command loop: commands from the controller on the pose output's line, answered with goal statuses.

It reads what the controller sent on the pose output's port (``PoseOutput.read_available``), decodes it
with the codec of the configured output format (command frames, or MAVLink), gives each command to the
:class:`~agent.runtime.arbiter.CommandArbiter`, and writes every answer back between the pose frames
(``PoseOutput.send``). A frame it cannot read is answered too (REJECTED, with why) and counted. The
loop polls every ``poll_s``: at 115 200 baud a 26-byte goal takes 2.3 ms on the wire, so 10 ms adds at
most a few milliseconds to a command's way and costs ~100 wake-ups a second.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from typing import Protocol

from agent.config import OutputFormat
from agent.recording.messages import CommandSample, GoalSample
from agent.runtime.arbiter import CommandArbiter
from agent.runtime.health import Heartbeat
from firmware_protocol.command_frame import (
    Command,
    CommandDecoder,
    CommandFrameError,
    CommandType,
    ExploreCommand,
    FollowCommand,
    GoalCommand,
    GoalStatus,
    PlaceCommand,
    ResumeCommand,
    StopCommand,
    VelocityCommand,
    encode_goal_status,
)

__all__ = ["CommandLoop", "CommandPort"]

log = logging.getLogger(__name__)


class CommandPort(Protocol):
    def read_available(self) -> bytes: ...

    def send(self, data: bytes) -> bool: ...


class _Decoder(Protocol):
    def feed(self, data: bytes) -> list[Command]: ...

    def take_rejected(self) -> list[CommandFrameError]: ...


def _kind(command: Command) -> CommandType:
    if isinstance(command, ExploreCommand):
        return CommandType.EXPLORE
    if isinstance(command, PlaceCommand):
        return CommandType.GO_TO_PLACE
    if isinstance(command, FollowCommand):
        return CommandType.FOLLOW
    if isinstance(command, VelocityCommand):
        return CommandType.VELOCITY
    if isinstance(command, GoalCommand):
        return CommandType.GOAL
    if isinstance(command, StopCommand):
        return CommandType.STOP
    if isinstance(command, ResumeCommand):
        return CommandType.RESUME
    return CommandType.CANCEL


class CommandLoop:
    """Reads, decodes, arbitrates and answers; :meth:`step` is one pass, :meth:`run` the thread's body."""

    def __init__(
        self,
        port: CommandPort,
        arbiter: CommandArbiter,
        output_format: OutputFormat = OutputFormat.FRAME,
        *,
        mavlink_ids: tuple[int, int] = (1, 197),
        velocity_timeout_s: float = 0.5,
        poll_s: float = 0.01,
        clock_s: Callable[[], float] = time.monotonic,
    ) -> None:
        self.port = port
        self.arbiter = arbiter
        self.poll_s = poll_s
        self.clock_s = clock_s
        self.counts: collections.Counter[str] = collections.Counter()
        self.statuses: collections.deque[GoalStatus] = collections.deque(maxlen=256)  # for the summary
        # The flight recorder's entry (kind, time ns, sample); set by the agent when it records.
        self.record: Callable[[str, int, object], None] | None = None
        # Told of every status sent (the exploration loop learns its mission goals' outcomes so).
        self.listeners: list[Callable[[GoalStatus], None]] = []
        # The mission loop's entry for explore and go-to-place commands (its answer); None: none runs,
        # and the arbiter rejects them.
        self.missions: Callable[[ExploreCommand | PlaceCommand], GoalStatus] | None = None
        self._decoder: _Decoder
        self._encode: Callable[[GoalStatus, CommandType | None], bytes]
        if output_format is OutputFormat.MAVLINK:
            from firmware_protocol.mavlink_commands import MavlinkCommandDecoder, MavlinkStatusEncoder

            self._decoder = MavlinkCommandDecoder(*mavlink_ids, velocity_timeout_s=velocity_timeout_s)
            self._encode = MavlinkStatusEncoder(*mavlink_ids).encode
        else:
            self._decoder = CommandDecoder()
            self._encode = lambda status, answers: encode_goal_status(status)

    def answer(self, status: GoalStatus, answers: CommandType | None = CommandType.GOAL) -> None:
        """Send one status (also the navigator's ACTIVE / REACHED / FAILED reports, through the caller)."""
        self.statuses.append(status)
        for listener in self.listeners:
            listener(status)
        if self.record is not None:
            now_ns = int(self.clock_s() * 1e9)
            self.record("goal_status", now_ns, GoalSample(now_ns, status))
        self.counts[f"status_{status.state.name.lower()}"] += 1
        if not self.port.send(self._encode(status, answers)):
            self.counts["status_write_failures"] += 1

    def step(self) -> int:
        """Read and handle what arrived; the number of commands taken."""
        data = self.port.read_available()
        if not data:
            return 0
        commands = self._decoder.feed(data)
        for error in self._decoder.take_rejected():
            self.counts[f"rejected_{error.kind}"] += 1
            log.warning("command frame rejected: %s", error)
            self.answer(self.arbiter.bad_frame(error), None)
        for command in commands:
            if self.record is not None:
                now_ns = int(self.clock_s() * 1e9)
                self.record("command", now_ns, CommandSample(now_ns, command))
            self.counts[f"command_{_kind(command).name.lower()}"] += 1
            if isinstance(command, (ExploreCommand, PlaceCommand)) and self.missions is not None:
                self.answer(self.missions(command), _kind(command))
                continue
            following = self.arbiter.following
            for i, status in enumerate(self.arbiter.command(command, self.clock_s())):
                about = CommandType.GOAL
                if i == 0:
                    about = _kind(command)
                elif following is not None and status.goal_id == following.follow_id:
                    about = CommandType.FOLLOW  # the following this command ended
                self.answer(status, about)
        return len(commands)

    def run(self, beat: Heartbeat, stop: threading.Event, then: Callable[[], object] | None = None) -> None:
        """Poll until ``stop``; ``then``: called after each pass (the agent's driving step)."""
        while not stop.is_set():
            beat.beat()
            self.step()
            if then is not None:
                then()
            stop.wait(self.poll_s)
