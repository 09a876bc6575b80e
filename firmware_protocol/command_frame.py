"""Command frames from the controller, goal-status frames back (``docs/wire-format.md``, "Commands").

They share the pose frame's link (``COBS(payload || CRC-16/CCITT-FALSE LE) || 00``, see
:mod:`firmware_protocol.framing`) and line. Every payload starts with a type byte and a version byte::

     0  u8   type      0x21 velocity, 0x22 goal, 0x23 cancel, 0x24 stop, 0x25 resume,
                       0x26 explore, 0x27 go to place (since v1.1), 0x28 follow (since v1.2)
                       (controller -> agent)
                       0xA1 goal status (agent -> controller)
     1  u8   version   major << 4 | minor: 0x10 (0x11, 0x12 for the types added in v1.1, v1.2)
     2  u16  sequence  the sender's counter, +1 per frame, wrapping; a goal status echoes the command's

The type byte never has 0x1 in its high nibble, which is the pose frame's version byte (0x1m), so a receiver
tells a pose from a goal status by the first byte. Fields are little-endian fixed point, as in the pose frame:
no NaN or infinity can cross the wire, and a controller without an FPU encodes with integer code.

Velocity (10 bytes): ``i16 v`` mm/s, ``i16 omega`` mrad/s (counter-clockwise), ``u16 timeout`` ms: the robot
stops unless another velocity command arrives within it (0 is refused). Goal (22 bytes): ``u16 goal_id``,
``u8 options`` (bit 0: the yaw is wanted, bit 1: the goal may be reached through unknown space), ``u8``
reserved, ``i32 x``, ``i32 y`` (0.1 mm, map frame), ``i16 yaw`` (2*pi/65536 rad), ``u16 tolerance_xy`` (mm,
0 = the agent's default), ``u16 tolerance_yaw`` (1e-4 rad, 0 = default). Cancel (6 bytes): ``u16 goal_id``
(0xFFFF: whatever goal is active). Stop and resume (4 bytes): the header only. Goal status (12 bytes):
``u16 command_sequence`` (the command it answers; 0xFFFF for a status the agent sends on its own), ``u16
goal_id`` (0xFFFF: none), ``u8 state`` (:class:`GoalState`), ``u8 reason`` (:class:`GoalReason`), ``u16
remaining`` (cm along the path, 0xFFFF unknown).

Explore (8 bytes, v1.1): ``u16 mission_id``, ``u8 action`` (:class:`ExploreAction`), ``u8`` reserved.
Go to place (24 bytes, v1.1): ``u16 mission_id``, ``u8 options`` (bit 0: then come back to where the
robot was when the command came), ``u8`` reserved, ``name`` 16 bytes of UTF-8, padded with 0x00 (1 to 16
bytes, no 0x00 inside). Both are answered, and end, with goal statuses whose ``goal_id`` is the
``mission_id``.

Follow (24 bytes, v1.2): ``u16 follow_id``, ``u8 action`` (:class:`FollowAction`: 0 start, 1 stop), ``u8
tag_length`` (0 to 16; 0: the agent's configured user tag), ``tag`` 16 bytes: the tag's EPC as the reader
reports it, most significant byte first, padded with 0x00 after ``tag_length`` bytes. Answered, and ended,
with goal statuses whose ``goal_id`` is the ``follow_id``; while following, ACTIVE statuses say how it goes
(the reasons FOLLOWING, SEARCHING, PERSON_LOST, TAG_ABSENT, NO_CAMERA_FRAMES, NOT_LOCALIZED).

Versioning as the pose frame's: a decoder rejects other majors, accepts any minor of its own and ignores
fields appended after the layout of the minor version that introduced the type; a payload of that minor
version has exactly its type's length. The types of v1.0 are still sent as 1.0 (their bytes unchanged);
explore and go-to-place are sent as 1.1, follow as 1.2, and a frame of theirs claiming an older minor is a
version error.
"""

from __future__ import annotations

import enum
import math
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

from firmware_protocol.errors import ProtocolError
from firmware_protocol.framing import FrameSplitter, LinkError, check_link_frame, encode_link_frame

__all__ = [
    "MAX_PAYLOAD_LENGTH",
    "NO_GOAL",
    "NO_SEQUENCE",
    "REMAINING_UNKNOWN",
    "VERSION",
    "CancelCommand",
    "Command",
    "CommandDecoder",
    "CommandFrameError",
    "CommandType",
    "ExploreAction",
    "ExploreCommand",
    "FollowAction",
    "FollowCommand",
    "GoalCommand",
    "GoalReason",
    "GoalState",
    "GoalStatus",
    "GoalStatusDecoder",
    "PlaceCommand",
    "ResumeCommand",
    "StopCommand",
    "VelocityCommand",
    "decode_command",
    "decode_goal_status",
    "encode_command",
    "encode_goal_status",
    "is_pose_payload",
]

VERSION_MAJOR = 1
VERSION_MINOR = 2  # the newest minor version this codec reads and writes
VERSION = VERSION_MAJOR << 4  # v1.0: the version byte of the types v1.0 defined (their bytes unchanged)
PLACE_NAME_LENGTH = 16  # bytes of a place's name in a go-to-place frame
TAG_LENGTH = 16  # bytes of a tag's EPC in a follow frame (96- and 128-bit EPCs fit)
MAX_PAYLOAD_LENGTH = 64  # the longest payload a later v1.x may send; bounds every decoder's buffer
NO_GOAL = 0xFFFF
NO_SEQUENCE = 0xFFFF
REMAINING_UNKNOWN = 0xFFFF

_PER_M = 10_000  # x, y: 0.1 mm
_YAW_LSB_RAD = math.pi / 32768
_SPEED_PER_MPS = 1000  # v: mm/s
_RATE_PER_RADPS = 1000  # omega: mrad/s
_TOL_XY_PER_M = 1000  # tolerance_xy: mm
_TOL_YAW_PER_RAD = 10_000  # tolerance_yaw: 1e-4 rad
_REMAINING_PER_M = 100  # remaining: cm

OPTION_YAW = 0x01
OPTION_ALLOW_UNKNOWN = 0x02
OPTION_COME_BACK = 0x01  # go to place: then back to where the robot was


class CommandType(enum.IntEnum):
    VELOCITY = 0x21
    GOAL = 0x22
    CANCEL = 0x23
    STOP = 0x24
    RESUME = 0x25
    EXPLORE = 0x26  # since v1.1
    GO_TO_PLACE = 0x27  # since v1.1
    FOLLOW = 0x28  # since v1.2
    GOAL_STATUS = 0xA1


# The minor version that introduced each type (0: v1.0).
_SINCE_MINOR = {CommandType.EXPLORE: 1, CommandType.GO_TO_PLACE: 1, CommandType.FOLLOW: 2}


class ExploreAction(enum.IntEnum):
    """What an explore command asks (the exploration's lifecycle, docs/exploration.md)."""

    START = 0
    PAUSE = 1
    RESUME = 2
    RETURN_HOME = 3
    CANCEL = 4


class FollowAction(enum.IntEnum):
    """What a follow command asks (docs/following.md, "Following on command")."""

    START = 0
    STOP = 1


class GoalState(enum.IntEnum):
    """What a goal status says; the first four also answer velocity, stop and resume commands."""

    ACCEPTED = 0  # taken: a goal is being planned, a velocity is being driven
    REJECTED = 1  # not taken: see the reason; the robot is stopped or keeps its previous command
    ACTIVE = 2  # the goal is being driven to (sent about once a second, with the remaining distance)
    REACHED = 3  # within its tolerances; the robot stopped
    FAILED = 4  # given up: see the reason; the robot stopped
    CANCELLED = 5  # by a cancel or stop command, a newer goal, or a controller velocity taking over


class GoalReason(enum.IntEnum):
    NONE = 0
    BAD_FRAME = 1  # COBS, length or CRC failed: the frame was unreadable (no command sequence known)
    UNKNOWN_TYPE = 2  # a type byte this agent does not know
    BAD_VERSION = 3  # a major version this agent does not read
    BAD_VALUE = 4  # a field out of range (e.g. a velocity timeout of 0; NaN through MAVLink)
    CLAMPED = 5  # a velocity beyond the configured limits, driven at the limits (state ACCEPTED)
    OUTSIDE_MAP = 6  # the goal is outside the map
    IN_OBSTACLE = 7  # the goal is inside a wall or too close to one for the robot's radius
    UNREACHABLE = 8  # no path to the goal on the map
    BLOCKED = 9  # the path stayed blocked through every recovery
    TIMEOUT = 10  # the goal was not reached within its time bound
    STOPPED = 11  # a stop command holds the robot: send resume first
    SUPERSEDED = 12  # a newer goal, a cancel, or a controller velocity (higher precedence) took over
    NOT_LOCALIZED = 13  # the agent has no pose to plan from
    UNKNOWN_GOAL = 14  # a cancel for a goal id that is not active
    DEAD_MAN = 15  # commands stopped arriving within their timeout: the robot stopped
    BUSY = 16  # a command of higher precedence is in force
    # Since v1.1 (missions):
    UNKNOWN_PLACE = 17  # a go-to-place names a place the agent does not know
    NO_FREE_SPACE = 18  # the map has no free space to drive in
    START_BLOCKED = 19  # the robot stands inside an obstacle on the map: no way out to plan from
    EXPLORED = 20  # (FAILED) exploration ended with reachable space it could not get to
    # Since v1.2 (following):
    FOLLOW_UNAVAILABLE = 21  # (REJECTED) following is not set up on this agent (no laser, no follow loop)
    NO_TAG_READER = 22  # (REJECTED) a follow names a tag, and the agent has no RFID reader to hear it
    FOLLOWING = 23  # (ACTIVE) the person is tracked: followed, or waited for at the distance
    SEARCHING = 24  # (ACTIVE) no track: turning toward the RFID bearing to find them
    PERSON_LOST = 25  # (ACTIVE) the person vanished or no track yet: stopped, waiting for them
    TAG_ABSENT = 26  # (ACTIVE) the RFID layer hears no tag (out of reach, or no answer yet): stopped
    NO_CAMERA_FRAMES = 27  # (ACTIVE) the forward camera the estimate uses gives no frames: stopped


@dataclass(frozen=True, slots=True)
class VelocityCommand:
    sequence: int
    v_mps: float
    omega_radps: float
    timeout_s: float


@dataclass(frozen=True, slots=True)
class GoalCommand:
    sequence: int
    goal_id: int
    x_m: float
    y_m: float
    yaw_rad: float | None = None  # None: any final heading
    tolerance_xy_m: float = 0.0  # 0: the agent's default
    tolerance_yaw_rad: float = 0.0  # 0: the agent's default
    allow_unknown: bool = False


@dataclass(frozen=True, slots=True)
class CancelCommand:
    sequence: int
    goal_id: int = NO_GOAL  # NO_GOAL: whatever goal is active


@dataclass(frozen=True, slots=True)
class StopCommand:
    sequence: int


@dataclass(frozen=True, slots=True)
class ResumeCommand:
    sequence: int


@dataclass(frozen=True, slots=True)
class ExploreCommand:
    sequence: int
    mission_id: int
    action: ExploreAction = ExploreAction.START


@dataclass(frozen=True, slots=True)
class PlaceCommand:
    """Go to a named place (docs/world.md ``[[places]]``), and with ``come_back`` back again."""

    sequence: int
    mission_id: int
    place: str
    come_back: bool = False


@dataclass(frozen=True, slots=True)
class FollowCommand:
    """Start following the person wearing ``tag`` (EPC hex as the reader reports it; None: the agent's
    configured user tag), or stop following."""

    sequence: int
    follow_id: int
    action: FollowAction = FollowAction.START
    tag: str | None = None


Command = (
    VelocityCommand
    | GoalCommand
    | CancelCommand
    | StopCommand
    | ResumeCommand
    | ExploreCommand
    | PlaceCommand
    | FollowCommand
)


@dataclass(frozen=True, slots=True)
class GoalStatus:
    sequence: int  # the agent's status counter
    command_sequence: int  # the command this answers, NO_SEQUENCE if none
    goal_id: int  # NO_GOAL if none
    state: GoalState
    reason: GoalReason = GoalReason.NONE
    remaining_m: float | None = None  # None: unknown


class CommandFrameError(ProtocolError):
    """A command or goal-status frame that cannot be encoded, or bytes that are not one.

    ``kind`` says which check failed: ``cobs``, ``length``, ``crc``, ``overflow`` (the link layer),
    ``type`` (unknown type byte), ``version`` (unknown major), ``value`` (a field that cannot be encoded).
    """

    def __init__(self, kind: str, reason: str, data: bytes = b"") -> None:
        super().__init__(reason, data)
        self.kind = kind


_HEADER = struct.Struct("<BBH")
_LAYOUTS: dict[CommandType, struct.Struct] = {
    CommandType.VELOCITY: struct.Struct("<BBHhhH"),
    CommandType.GOAL: struct.Struct("<BBHHBBiihHH"),
    CommandType.CANCEL: struct.Struct("<BBHH"),
    CommandType.STOP: _HEADER,
    CommandType.RESUME: _HEADER,
    CommandType.EXPLORE: struct.Struct("<BBHHBB"),
    CommandType.GO_TO_PLACE: struct.Struct(f"<BBHHBB{PLACE_NAME_LENGTH}s"),
    CommandType.FOLLOW: struct.Struct(f"<BBHHBB{TAG_LENGTH}s"),
    CommandType.GOAL_STATUS: struct.Struct("<BBHHHBBH"),
}
T = TypeVar("T")
_MIN_PAYLOAD = min(layout.size for layout in _LAYOUTS.values())


# -- fields ------------------------------------------------------------------------------------------


def _fixed(value: float, per_unit: int, lo: int, hi: int, what: str) -> int:
    scaled = value * per_unit
    if not math.isfinite(scaled):
        raise CommandFrameError("value", f"{what} must be finite, got {value}")
    q = round(scaled)
    if not lo <= q <= hi:
        raise CommandFrameError("value", f"{what} {value} is outside {lo / per_unit}..{hi / per_unit}")
    return q


def _u16(value: int, what: str) -> int:
    if not 0 <= value <= 0xFFFF:
        raise CommandFrameError("value", f"{what} {value} does not fit in 0..65535")
    return value


def _yaw_bam(yaw_rad: float) -> int:
    scaled = yaw_rad / _YAW_LSB_RAD
    if not math.isfinite(scaled):
        raise CommandFrameError("value", f"yaw must be finite, got {yaw_rad}")
    return (round(scaled) + 0x8000) % 0x10000 - 0x8000


# -- payloads ----------------------------------------------------------------------------------------


def _encode_payload(message: Command | GoalStatus) -> bytes:
    seq = _u16(message.sequence, "sequence")
    if isinstance(message, VelocityCommand):
        return _LAYOUTS[CommandType.VELOCITY].pack(
            CommandType.VELOCITY,
            VERSION,
            seq,
            _fixed(message.v_mps, _SPEED_PER_MPS, -32768, 32767, "v"),
            _fixed(message.omega_radps, _RATE_PER_RADPS, -32768, 32767, "omega"),
            _fixed(message.timeout_s, 1000, 0, 0xFFFF, "timeout"),
        )
    if isinstance(message, GoalCommand):
        options = (OPTION_YAW if message.yaw_rad is not None else 0) | (
            OPTION_ALLOW_UNKNOWN if message.allow_unknown else 0
        )
        return _LAYOUTS[CommandType.GOAL].pack(
            CommandType.GOAL,
            VERSION,
            seq,
            _u16(message.goal_id, "goal_id"),
            options,
            0,
            _fixed(message.x_m, _PER_M, -(1 << 31), (1 << 31) - 1, "x"),
            _fixed(message.y_m, _PER_M, -(1 << 31), (1 << 31) - 1, "y"),
            _yaw_bam(message.yaw_rad if message.yaw_rad is not None else 0.0),
            _fixed(message.tolerance_xy_m, _TOL_XY_PER_M, 0, 0xFFFF, "tolerance_xy"),
            _fixed(message.tolerance_yaw_rad, _TOL_YAW_PER_RAD, 0, 0xFFFF, "tolerance_yaw"),
        )
    if isinstance(message, CancelCommand):
        return _LAYOUTS[CommandType.CANCEL].pack(
            CommandType.CANCEL, VERSION, seq, _u16(message.goal_id, "goal_id")
        )
    if isinstance(message, StopCommand):
        return _HEADER.pack(CommandType.STOP, VERSION, seq)
    if isinstance(message, ResumeCommand):
        return _HEADER.pack(CommandType.RESUME, VERSION, seq)
    if isinstance(message, ExploreCommand):
        return _LAYOUTS[CommandType.EXPLORE].pack(
            CommandType.EXPLORE,
            VERSION_MAJOR << 4 | 1,
            seq,
            _u16(message.mission_id, "mission_id"),
            ExploreAction(message.action),
            0,
        )
    if isinstance(message, PlaceCommand):
        return _LAYOUTS[CommandType.GO_TO_PLACE].pack(
            CommandType.GO_TO_PLACE,
            VERSION_MAJOR << 4 | 1,
            seq,
            _u16(message.mission_id, "mission_id"),
            OPTION_COME_BACK if message.come_back else 0,
            0,
            _place_name(message.place),
        )
    if isinstance(message, FollowCommand):
        if message.action == FollowAction.STOP and message.tag is not None:
            raise CommandFrameError("value", "a follow stop names no tag")
        tag = _tag_bytes(message.tag)
        return _LAYOUTS[CommandType.FOLLOW].pack(
            CommandType.FOLLOW,
            VERSION_MAJOR << 4 | 2,
            seq,
            _u16(message.follow_id, "follow_id"),
            FollowAction(message.action),
            len(tag),
            tag,
        )
    remaining = REMAINING_UNKNOWN
    if message.remaining_m is not None:
        # Farther than 655 m reads as 655.34 m: the frame says "far", never "unknown".
        remaining = min(_fixed(message.remaining_m, _REMAINING_PER_M, 0, 1 << 40, "remaining"), 0xFFFE)
    return _LAYOUTS[CommandType.GOAL_STATUS].pack(
        CommandType.GOAL_STATUS,
        VERSION,
        seq,
        _u16(message.command_sequence, "command_sequence"),
        _u16(message.goal_id, "goal_id"),
        GoalState(message.state),
        GoalReason(message.reason),
        remaining,
    )


def _place_name(name: str) -> bytes:
    raw = name.encode("utf-8")
    if not 1 <= len(raw) <= PLACE_NAME_LENGTH or b"\x00" in raw:
        raise CommandFrameError(
            "value", f"a place name is 1 to {PLACE_NAME_LENGTH} bytes of UTF-8 without NUL, got {name!r}"
        )
    return raw


def _tag_bytes(tag: str | None) -> bytes:
    if tag is None:
        return b""
    try:
        raw = bytes.fromhex(tag)
    except ValueError:
        raw = b""
    if not 1 <= len(raw) <= TAG_LENGTH or len(tag) != 2 * len(raw):
        raise CommandFrameError(
            "value", f"a tag is 1 to {TAG_LENGTH} bytes as an even number of hex digits, got {tag!r}"
        )
    return raw


def _checked_type(payload: bytes) -> CommandType:
    """The payload's type after the versioning and length rules; :class:`CommandFrameError` if it fails."""
    try:
        kind = CommandType(payload[0])
    except ValueError:
        raise CommandFrameError("type", f"unknown frame type 0x{payload[0]:02X}", payload) from None
    major, minor = payload[1] >> 4, payload[1] & 0x0F
    if major != VERSION_MAJOR:
        raise CommandFrameError(
            "version", f"{kind.name.lower()} frame version {major}.{minor}: this decoder reads 1.x", payload
        )
    since = _SINCE_MINOR.get(kind, 0)
    if minor < since:
        raise CommandFrameError(
            "version",
            f"{kind.name.lower()} frames start at version 1.{since}, this one says 1.{minor}",
            payload,
        )
    size = _LAYOUTS[kind].size
    if (minor == since and len(payload) != size) or not size <= len(payload) <= MAX_PAYLOAD_LENGTH:
        raise CommandFrameError(
            "length", f"a v1.{minor} {kind.name.lower()} payload is {size} bytes, got {len(payload)}", payload
        )
    return kind


def _decode_command_payload(payload: bytes) -> Command:
    if payload[0] == CommandType.GOAL_STATUS:
        raise CommandFrameError("type", "a goal status is sent by the agent, not to it", payload)
    kind = _checked_type(payload)
    fields = _LAYOUTS[kind].unpack_from(payload)
    seq = fields[2]
    if kind is CommandType.VELOCITY:
        return VelocityCommand(seq, fields[3] / _SPEED_PER_MPS, fields[4] / _RATE_PER_RADPS, fields[5] / 1000)
    if kind is CommandType.GOAL:
        _, _, _, goal_id, options, _, x, y, yaw, tol_xy, tol_yaw = fields
        return GoalCommand(
            seq,
            goal_id,
            x / _PER_M,
            y / _PER_M,
            yaw * _YAW_LSB_RAD if options & OPTION_YAW else None,
            tol_xy / _TOL_XY_PER_M,
            tol_yaw / _TOL_YAW_PER_RAD,
            bool(options & OPTION_ALLOW_UNKNOWN),
        )
    if kind is CommandType.CANCEL:
        return CancelCommand(seq, fields[3])
    if kind is CommandType.STOP:
        return StopCommand(seq)
    if kind is CommandType.EXPLORE:
        try:
            action = ExploreAction(fields[4])
        except ValueError:
            raise CommandFrameError("value", f"unknown explore action {fields[4]}", payload) from None
        return ExploreCommand(seq, fields[3], action)
    if kind is CommandType.GO_TO_PLACE:
        raw = fields[6].rstrip(b"\x00")
        try:
            name = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise CommandFrameError("value", "the place name is not UTF-8", payload) from None
        if not name or b"\x00" in raw:
            raise CommandFrameError("value", "the place name is empty or has a NUL inside", payload)
        return PlaceCommand(seq, fields[3], name, bool(fields[4] & OPTION_COME_BACK))
    if kind is CommandType.FOLLOW:
        _, _, _, follow_id, action, tag_length, raw_tag = fields
        try:
            follow = FollowAction(action)
        except ValueError:
            raise CommandFrameError("value", f"unknown follow action {action}", payload) from None
        if tag_length > TAG_LENGTH or any(raw_tag[tag_length:]):
            raise CommandFrameError(
                "value", f"tag_length {tag_length}: beyond {TAG_LENGTH}, or non-zero bytes after it", payload
            )
        if follow is FollowAction.STOP and tag_length:
            raise CommandFrameError("value", "a follow stop names no tag", payload)
        return FollowCommand(seq, follow_id, follow, raw_tag[:tag_length].hex().upper() or None)
    return ResumeCommand(seq)


def _decode_status_payload(payload: bytes) -> GoalStatus:
    if payload[0] != CommandType.GOAL_STATUS:
        raise CommandFrameError("type", f"frame type 0x{payload[0]:02X} is not a goal status", payload)
    kind = _checked_type(payload)
    _, _, seq, cmd_seq, goal_id, state, reason, remaining = _LAYOUTS[kind].unpack_from(payload)
    try:
        goal_state = GoalState(state)
    except ValueError:
        raise CommandFrameError("value", f"unknown goal state {state}", payload) from None
    try:
        goal_reason = GoalReason(reason)
    except ValueError:
        # A later minor version may add reasons: keep the frame, the state is what a controller acts on.
        goal_reason = GoalReason.NONE
    return GoalStatus(
        seq,
        cmd_seq,
        goal_id,
        goal_state,
        goal_reason,
        None if remaining == REMAINING_UNKNOWN else remaining / _REMAINING_PER_M,
    )


# -- one frame ---------------------------------------------------------------------------------------


def encode_command(command: Command) -> bytes:
    """The wire bytes of one command: ``COBS(payload || CRC-LE) || 00``."""
    return encode_link_frame(_encode_payload(command))


def encode_goal_status(status: GoalStatus) -> bytes:
    """The wire bytes of one goal status."""
    return encode_link_frame(_encode_payload(status))


def _one_frame(wire: bytes | bytearray | memoryview) -> bytes:
    wire = bytes(wire)
    body = wire[:-1] if wire.endswith(b"\x00") else wire
    try:
        return check_link_frame(body, _MIN_PAYLOAD, MAX_PAYLOAD_LENGTH)
    except LinkError as exc:
        raise CommandFrameError(exc.kind, exc.reason, exc.data) from exc


def decode_command(wire: bytes | bytearray | memoryview) -> Command:
    """Decode one command frame as :func:`encode_command` writes it (the final 0x00 may be left off)."""
    return _decode_command_payload(_one_frame(wire))


def decode_goal_status(wire: bytes | bytearray | memoryview) -> GoalStatus:
    """Decode one goal-status frame as :func:`encode_goal_status` writes it."""
    return _decode_status_payload(_one_frame(wire))


# -- streams -----------------------------------------------------------------------------------------


class _StreamDecoder(Generic[T]):
    """Frames of one direction from a byte stream, every rejection counted by its kind.

    ``skip`` names payloads that are another reader's business on the same line (not errors): they are
    counted in ``skipped`` and dropped.
    """

    KINDS = ("cobs", "length", "crc", "overflow", "type", "version", "value")

    def __init__(self, decode: Callable[[bytes], T], skip: Callable[[bytes], bool] | None = None) -> None:
        self._decode = decode
        self._skip = skip
        self._splitter = FrameSplitter(_MIN_PAYLOAD, MAX_PAYLOAD_LENGTH)
        self.frames = 0
        self.skipped = 0
        self.errors = dict.fromkeys(self.KINDS, 0)
        self.discarded_bytes = 0
        self.rejected: list[CommandFrameError] = []  # since the last take_rejected(), bounded
        self.last_error: CommandFrameError | None = None

    @property
    def bad_frames(self) -> int:
        return sum(self.errors.values())

    def _sync_overflows(self) -> None:
        self.errors["overflow"] = self._splitter.overflows

    def counters(self) -> dict[str, int]:
        return {
            "frames": self.frames,
            "skipped": self.skipped,
            **{f"{k}_errors": v for k, v in self.errors.items()},
            "discarded_bytes": self.discarded_bytes,
        }

    def take_rejected(self) -> list[CommandFrameError]:
        """The rejections since the last call (the first 64), so that a caller can answer each one."""
        out, self.rejected = self.rejected, []
        return out

    def reset(self) -> None:
        """Forget a partial frame (e.g. after reopening the port); counters are kept."""
        self._splitter.reset()

    def feed(self, data: bytes | bytearray | memoryview) -> list[T]:
        """The frames completed so far; bytes after the last 0x00 wait for the next call."""
        out: list[T] = []
        for candidate in self._splitter.feed(data):
            payload = candidate.payload
            if payload is not None and self._skip is not None and self._skip(payload):
                self.skipped += 1
                continue
            try:
                if candidate.error is not None:
                    link = candidate.error
                    raise CommandFrameError(link.kind, link.reason, link.data) from link
                assert payload is not None
                message = self._decode(payload)
            except CommandFrameError as exc:
                if exc.kind != "overflow":  # counted by the splitter when it happened
                    self.errors[exc.kind] += 1
                self.discarded_bytes += candidate.raw_length + 1
                self.last_error = exc
                if len(self.rejected) < 64:
                    self.rejected.append(exc)
            else:
                self.frames += 1
                out.append(message)
        self._sync_overflows()
        return out


class CommandDecoder(_StreamDecoder[Command]):
    """The agent's side: commands from the controller's byte stream."""

    def __init__(self) -> None:
        super().__init__(_decode_command_payload)


def is_pose_payload(payload: bytes) -> bool:
    """A pose frame's payload: its first byte is the pose version, 0x1m."""
    return payload[0] >> 4 == 1


class GoalStatusDecoder(_StreamDecoder[GoalStatus]):
    """The controller's side: goal statuses from the agent's stream; its pose frames are ``skipped``."""

    def __init__(self) -> None:
        super().__init__(_decode_status_payload, skip=is_pose_payload)
