"""Commands from an autopilot or ground station over MAVLink 2, and goal statuses back (the MAVLink
counterpart of :mod:`firmware_protocol.command_frame`; ``docs/wire-format.md``, "MAVLink commands").

In, through pymavlink's parser (``robust_parsing``: junk becomes bad-data records, never an exception):

* ``SET_POSITION_TARGET_LOCAL_NED`` (#84) in ``MAV_FRAME_LOCAL_NED`` with x and y used (``type_mask`` bits 0
  and 1 clear): a **goal** at ``(x, -y)`` in our map frame (z up), with the yaw ``-yaw`` when bit 10 is
  clear. Goal ids count the goals received (1, 2, ...; MAVLink has no id field).
* ``SET_POSITION_TARGET_LOCAL_NED`` in ``MAV_FRAME_BODY_NED`` or ``MAV_FRAME_BODY_OFFSET_NED`` with x and y
  ignored and vx used (bit 3 clear): a **velocity** ``v = vx``, ``omega = -yaw_rate`` (0 when bit 11 is
  set), held for ``velocity_timeout_s`` (MAVLink carries no timeout: stream it at 5 Hz or more).
* ``COMMAND_LONG`` ``MAV_CMD_DO_PAUSE_CONTINUE`` (193): param1 0 is **stop**, 1 is **resume**.
* ``COMMAND_LONG`` ``MAV_CMD_DO_FOLLOW`` (32): param1 is the "system ID of the FOLLOW_TARGET beacon"; here
  the beacon is the user's tag: 1 to 255 **starts following** the agent's configured user tag (MAVLink
  cannot carry an EPC) with that number as the follow id, 0 **stops following** (whatever following is on,
  as MAVLink's "0 disables follow-me"). Params 2 to 7 (altitude modes) are ignored: the robot drives on
  the floor.

Messages for another system or component are ignored (``target_system`` 0 is a broadcast). Anything
else addressed to us, or a field that is NaN or infinite, is a rejection (:class:`CommandFrameError` in
:meth:`MavlinkCommandDecoder.take_rejected`) that the agent answers.

Out: ``COMMAND_ACK`` (#77) for every status: ``command`` is ``MAV_CMD_NAV_WAYPOINT`` (16) for goals,
``MAV_CMD_DO_CHANGE_SPEED`` (178) for velocities, ``MAV_CMD_DO_PAUSE_CONTINUE`` (193) for stop and resume,
``MAV_CMD_DO_FOLLOW`` (32) for following (its answer and its ACTIVE statuses: following, searching, lost);
``result`` ACCEPTED (0; also REACHED, with progress 100), DENIED (2: REJECTED), FAILED (4), IN_PROGRESS
(5: ACTIVE), CANCELLED (6); ``result_param2`` is ``goal_id << 8 | reason``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from firmware_protocol.command_frame import (
    NO_GOAL,
    Command,
    CommandFrameError,
    CommandType,
    FollowAction,
    FollowCommand,
    GoalCommand,
    GoalState,
    GoalStatus,
    ResumeCommand,
    StopCommand,
    VelocityCommand,
)
from firmware_protocol.mavlink_out import DEFAULT_COMPID, DEFAULT_SYSID, mavlink_dialect

__all__ = [
    "MAV_CMD_DO_CHANGE_SPEED",
    "MAV_CMD_DO_FOLLOW",
    "MAV_CMD_DO_PAUSE_CONTINUE",
    "MAV_CMD_NAV_WAYPOINT",
    "MavlinkCommandDecoder",
    "MavlinkStatusEncoder",
]

MAV_CMD_NAV_WAYPOINT = 16
MAV_CMD_DO_FOLLOW = 32
MAV_CMD_DO_CHANGE_SPEED = 178
MAV_CMD_DO_PAUSE_CONTINUE = 193
MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_BODY_NED = 8
MAV_FRAME_BODY_OFFSET_NED = 9
_IGNORE_X, _IGNORE_Y, _IGNORE_VX = 1 << 0, 1 << 1, 1 << 3
_IGNORE_YAW, _IGNORE_YAW_RATE = 1 << 10, 1 << 11
_RESULT = {
    GoalState.ACCEPTED: 0,
    GoalState.REJECTED: 2,
    GoalState.ACTIVE: 5,
    GoalState.REACHED: 0,
    GoalState.FAILED: 4,
    GoalState.CANCELLED: 6,
}


def _finite(msg: Any, *names: str) -> None:
    for name in names:
        if not math.isfinite(getattr(msg, name)):
            raise CommandFrameError(
                "value", f"{msg.get_type()} {name} must be finite, got {getattr(msg, name)}"
            )


class MavlinkCommandDecoder:
    """Commands for (``sysid``, ``compid``) from a MAVLink 2 byte stream; counts what it drops."""

    def __init__(
        self, sysid: int = DEFAULT_SYSID, compid: int = DEFAULT_COMPID, velocity_timeout_s: float = 0.5
    ) -> None:
        self.sysid = sysid
        self.compid = compid
        self.velocity_timeout_s = velocity_timeout_s
        self._mav: Any = mavlink_dialect().MAVLink(None)
        self._mav.robust_parsing = True
        self._goals = 0
        self.frames = 0
        self.ignored = 0  # other messages, or for another system or component
        self.bad_data = 0  # bytes pymavlink could not frame (junk, CRC)
        self.rejected: list[CommandFrameError] = []  # since the last take_rejected(), the first 64
        self.rejections = 0
        self._handlers: dict[str, Callable[[Any], Command]] = {
            "SET_POSITION_TARGET_LOCAL_NED": self._position_target,
            "COMMAND_LONG": self._command_long,
        }

    def counters(self) -> dict[str, int]:
        return {
            "frames": self.frames,
            "ignored": self.ignored,
            "bad_data": self.bad_data,
            "rejections": self.rejections,
        }

    def take_rejected(self) -> list[CommandFrameError]:
        out, self.rejected = self.rejected, []
        return out

    def feed(self, data: bytes | bytearray | memoryview) -> list[Command]:
        out: list[Command] = []
        for msg in self._mav.parse_buffer(bytes(data)) or []:
            kind = msg.get_type()
            if kind == "BAD_DATA":
                self.bad_data += 1
                continue
            handler = self._handlers.get(kind)
            if handler is None or not self._for_us(msg):
                self.ignored += 1
                continue
            try:
                out.append(handler(msg))
            except CommandFrameError as exc:
                self.rejections += 1
                if len(self.rejected) < 64:
                    self.rejected.append(exc)
            else:
                self.frames += 1
        return out

    def _for_us(self, msg: Any) -> bool:
        return msg.target_system in (0, self.sysid) and msg.target_component in (0, self.compid)

    def _position_target(self, msg: Any) -> Command:
        seq = msg.get_seq()
        mask = msg.type_mask
        if msg.coordinate_frame == MAV_FRAME_LOCAL_NED and not mask & (_IGNORE_X | _IGNORE_Y):
            _finite(msg, "x", "y")
            yaw = None
            if not mask & _IGNORE_YAW:
                _finite(msg, "yaw")
                yaw = -msg.yaw
            self._goals = self._goals % (NO_GOAL - 1) + 1
            return GoalCommand(seq, self._goals, msg.x, -msg.y, yaw)
        if msg.coordinate_frame in (MAV_FRAME_BODY_NED, MAV_FRAME_BODY_OFFSET_NED) and not mask & _IGNORE_VX:
            _finite(msg, "vx")
            omega = 0.0
            if not mask & _IGNORE_YAW_RATE:
                _finite(msg, "yaw_rate")
                omega = -msg.yaw_rate
            return VelocityCommand(seq, msg.vx, omega, self.velocity_timeout_s)
        raise CommandFrameError(
            "type",
            f"SET_POSITION_TARGET_LOCAL_NED with frame {msg.coordinate_frame} and type_mask 0x{mask:04X} is "
            "neither a position goal (LOCAL_NED, x and y) nor a body velocity (BODY_NED, vx)",
        )

    def _command_long(self, msg: Any) -> Command:
        if msg.command == MAV_CMD_DO_FOLLOW:
            return self._follow(msg)
        if msg.command != MAV_CMD_DO_PAUSE_CONTINUE:
            raise CommandFrameError("type", f"COMMAND_LONG command {msg.command} is not supported")
        _finite(msg, "param1")
        if msg.param1 == 0:
            return StopCommand(msg.get_seq())
        if msg.param1 == 1:
            return ResumeCommand(msg.get_seq())
        raise CommandFrameError("value", f"MAV_CMD_DO_PAUSE_CONTINUE param1 must be 0 or 1, got {msg.param1}")

    def _follow(self, msg: Any) -> Command:
        _finite(msg, "param1")
        beacon = msg.param1
        if beacon != int(beacon) or not 0 <= beacon <= 255:
            raise CommandFrameError(
                "value", f"MAV_CMD_DO_FOLLOW param1 must be a system id 0..255 (0: stop), got {beacon}"
            )
        if beacon == 0:
            return FollowCommand(msg.get_seq(), NO_GOAL, FollowAction.STOP)
        return FollowCommand(msg.get_seq(), int(beacon), FollowAction.START)


class MavlinkStatusEncoder:
    """Goal statuses as ``COMMAND_ACK`` messages from (``sysid``, ``compid``)."""

    def __init__(self, sysid: int = DEFAULT_SYSID, compid: int = DEFAULT_COMPID) -> None:
        self._mav: Any = mavlink_dialect().MAVLink(None, srcSystem=sysid, srcComponent=compid)

    def encode(self, status: GoalStatus, answers: CommandType | None = CommandType.GOAL) -> bytes:
        """One ``COMMAND_ACK``; ``answers`` is the kind of command the status is about."""
        command = {
            CommandType.VELOCITY: MAV_CMD_DO_CHANGE_SPEED,
            CommandType.STOP: MAV_CMD_DO_PAUSE_CONTINUE,
            CommandType.RESUME: MAV_CMD_DO_PAUSE_CONTINUE,
            CommandType.FOLLOW: MAV_CMD_DO_FOLLOW,
        }.get(answers if answers is not None else CommandType.GOAL, MAV_CMD_NAV_WAYPOINT)
        progress = 100 if status.state is GoalState.REACHED else 255
        param2 = (status.goal_id & 0xFFFF) << 8 | int(status.reason)
        msg = mavlink_dialect().MAVLink_command_ack_message(
            command, _RESULT[status.state], progress, param2, 0, 0
        )
        self._mav.seq = status.sequence & 0xFF
        return bytes(msg.pack(self._mav))
