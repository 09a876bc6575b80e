"""The local protocol between the agent and its bridge over a Unix stream socket: a sans-I/O codec.

Every message is one frame (docs/fleet.md, "Local protocol")::

    magic "VF" (2) | version (u8) | type (u8) | payload length (u32, little-endian) | payload

A frame's payload is at most :data:`MAX_PAYLOAD` bytes (a map or topology snapshot: at most
:data:`MAX_SNAPSHOT_PAYLOAD`) and has the exact size its type fixes (a peer pose: the fixed part plus the
robot name's length; a map: its header, path and cells, which must inflate to the grid's size). Agent ->
bridge: :class:`PoseMessage`, :class:`StatusMessage`, :class:`GoalStateMessage`, :class:`MapMessage`,
:class:`TopologyMessage`; bridge -> agent: :class:`PeerPoseMessage`, :class:`GoalMessage`.

The stream is reliable and local, so there is no resync: the first malformed frame raises
:class:`LocalProtocolError` (a :class:`~firmware_protocol.errors.ProtocolError`) and the reader closes the
connection; the other side reconnects. :class:`FrameDecoder` buffers at most one frame.
"""

from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol

from firmware_protocol.errors import ProtocolError

__all__ = [
    "HEADER",
    "MAGIC",
    "MAX_MAP_CELLS",
    "MAX_NAME_BYTES",
    "MAX_PATH_POINTS",
    "MAX_PAYLOAD",
    "MAX_SNAPSHOT_PAYLOAD",
    "VERSION",
    "FrameDecoder",
    "FrameReader",
    "GoalMessage",
    "GoalStateMessage",
    "LocalProtocolError",
    "MapMessage",
    "Message",
    "PeerPoseMessage",
    "PoseMessage",
    "ReadResult",
    "StatusMessage",
    "TopologyMessage",
    "check_cells",
    "decode_frame",
    "encode",
    "inflate_cells",
    "max_payload",
    "receive",
    "valid_robot_name",
]

MAGIC = b"VF"
VERSION = 3  # 2: a goal carries its options (allow_unknown); 3: map and topology snapshots
HEADER = struct.Struct("<2sBBI")
MAX_PAYLOAD = 1024  # the largest small message (a peer pose with a 32-byte name) is 85 bytes
MAX_SNAPSHOT_PAYLOAD = 1 << 20  # a map or topology snapshot (types 0x04, 0x05): at most 1 MiB
MAX_MAP_CELLS = 4_000_000  # a snapshot's grid: at most 4 M cells (2000 x 2000, 100 x 100 m at 5 cm)
MAX_PATH_POINTS = 2000
MAX_NAME_BYTES = 32

_POSE = struct.Struct("<QdddffI")  # t_us, x_m, y_m, yaw_rad, sigma_xy_m, sigma_yaw_rad, pose flags
_STATUS = struct.Struct("<QII")  # t_us, pose flags, status bits
_GOAL_STATE = struct.Struct("<QHBBf")  # t_us, goal_id, state, reason, remaining_m (NaN: unknown)
_GOAL = struct.Struct("<QHdddB")  # t_us, goal_id, x_m, y_m, yaw_rad (NaN: any heading), options
# t_us, resolution_m, origin_x_m, origin_y_m, width, height, path points; then the path (f32 x, y each),
# then the zlib-compressed cells
_MAP = struct.Struct("<QdddIIH")
_PATH_POINT = struct.Struct("<ff")
_TOPOLOGY = struct.Struct("<Q")  # t_us; then the GeoJSON, UTF-8


class LocalProtocolError(ProtocolError):
    """Bytes on the agent's fleet socket that are not a frame of this protocol."""


def valid_robot_name(name: str) -> bool:
    """A robot name is 1..32 bytes of ASCII letters, digits, ``_`` and ``-`` (it is a Zenoh key chunk)."""
    return 0 < len(name) <= MAX_NAME_BYTES and all(c.isascii() and (c.isalnum() or c in "_-") for c in name)


@dataclass(frozen=True, slots=True)
class PoseMessage:
    """This robot's fused pose (agent -> bridge). ``t_us``: the agent's monotonic clock."""

    TYPE: ClassVar[int] = 0x01
    t_us: int
    x_m: float
    y_m: float
    yaw_rad: float
    sigma_xy_m: float
    sigma_yaw_rad: float
    flags: int  # firmware_protocol.pose_frame.PoseFlags

    def payload(self) -> bytes:
        return _POSE.pack(
            self.t_us, self.x_m, self.y_m, self.yaw_rad, self.sigma_xy_m, self.sigma_yaw_rad, self.flags
        )

    @classmethod
    def parse(cls, payload: bytes) -> PoseMessage:
        return cls(*_unpack(_POSE, payload, "pose"))


@dataclass(frozen=True, slots=True)
class StatusMessage:
    """The agent's status flags (agent -> bridge): the pose flags and :attr:`READY` | :attr:`LOCALIZED`
    (other bits reserved, sent as 0)."""

    TYPE: ClassVar[int] = 0x02
    READY: ClassVar[int] = 1  # every critical loop alive (what systemd's READY=1 says)
    LOCALIZED: ClassVar[int] = 2  # a position source is live
    t_us: int
    pose_flags: int
    bits: int

    def payload(self) -> bytes:
        return _STATUS.pack(self.t_us, self.pose_flags, self.bits)

    @classmethod
    def parse(cls, payload: bytes) -> StatusMessage:
        return cls(*_unpack(_STATUS, payload, "status"))


@dataclass(frozen=True, slots=True)
class GoalStateMessage:
    """A goal status of this robot (agent -> bridge): ``state`` and ``reason`` are
    ``firmware_protocol.command_frame.GoalState`` / ``GoalReason`` values."""

    TYPE: ClassVar[int] = 0x03
    t_us: int
    goal_id: int
    state: int
    reason: int
    remaining_m: float = math.nan

    def payload(self) -> bytes:
        return _GOAL_STATE.pack(self.t_us, self.goal_id, self.state, self.reason, self.remaining_m)

    @classmethod
    def parse(cls, payload: bytes) -> GoalStateMessage:
        return cls(*_unpack(_GOAL_STATE, payload, "goal state"))


@dataclass(frozen=True, slots=True)
class PeerPoseMessage:
    """Another robot's pose from the fleet (bridge -> agent): its name, then a :class:`PoseMessage`'s
    fields with ``t_us`` on the *sender's* clock (only for ordering and staleness per robot)."""

    TYPE: ClassVar[int] = 0x10
    robot: str
    pose: PoseMessage

    def payload(self) -> bytes:
        name = self.robot.encode("ascii")
        return bytes([len(name)]) + name + self.pose.payload()

    @classmethod
    def parse(cls, payload: bytes) -> PeerPoseMessage:
        if not payload:
            raise LocalProtocolError("peer pose: empty payload", payload)
        n = payload[0]
        if 1 + n + _POSE.size != len(payload):
            raise LocalProtocolError(
                f"peer pose: a {n}-byte name needs {1 + n + _POSE.size} bytes, got {len(payload)}", payload
            )
        try:
            robot = payload[1 : 1 + n].decode("ascii")
        except UnicodeDecodeError:
            robot = ""
        if not valid_robot_name(robot):
            raise LocalProtocolError("peer pose: not a robot name", payload[: 1 + n])
        return cls(robot, PoseMessage.parse(payload[1 + n :]))


@dataclass(frozen=True, slots=True)
class GoalMessage:
    """A goal for this robot from the fleet (bridge -> agent), in the shared map frame."""

    TYPE: ClassVar[int] = 0x11
    ALLOW_UNKNOWN: ClassVar[int] = 1  # options bit: the way may cross unknown space (a map being built)
    t_us: int
    goal_id: int
    x_m: float
    y_m: float
    yaw_rad: float = math.nan
    options: int = 0

    @property
    def allow_unknown(self) -> bool:
        return bool(self.options & self.ALLOW_UNKNOWN)

    def payload(self) -> bytes:
        return _GOAL.pack(self.t_us, self.goal_id, self.x_m, self.y_m, self.yaw_rad, self.options)

    @classmethod
    def parse(cls, payload: bytes) -> GoalMessage:
        goal = cls(*_unpack(_GOAL, payload, "goal"))
        if not (math.isfinite(goal.x_m) and math.isfinite(goal.y_m)) or math.isinf(goal.yaw_rad):
            raise LocalProtocolError("goal: a position that is not finite", payload)
        if goal.options & ~cls.ALLOW_UNKNOWN:
            raise LocalProtocolError(f"goal: unknown option bits 0x{goal.options:02x}", payload)
        return goal


def inflate_cells(data: bytes, n: int) -> bytes:
    """zlib ``data`` that must inflate to exactly ``n`` bytes (a bomb is stopped at ``n + 1``); raises
    LocalProtocolError otherwise."""
    inflater = zlib.decompressobj()
    try:
        cells = inflater.decompress(data, n + 1)
    except zlib.error as exc:
        raise LocalProtocolError(f"map: cells are not zlib data: {exc}") from exc
    if len(cells) != n or not inflater.eof or inflater.unused_data:
        raise LocalProtocolError(f"map: cells do not inflate to exactly {n} bytes")
    return cells


def check_cells(cells: bytes) -> None:
    """Every cell -1 (unknown) .. 100 (occupied), as int8."""
    values = set(cells)
    if any(v > 100 and v != 0xFF for v in values):
        raise LocalProtocolError("map: a cell outside -1..100")


@dataclass(frozen=True, slots=True)
class MapMessage:
    """This robot's occupancy map (agent -> bridge), laser-derived (SLAM): ``width`` x ``height`` int8 cells
    row-major from the lower-left corner (ROS ``nav_msgs/OccupancyGrid``: -1 unknown, 0 free, 100 occupied),
    zlib-compressed, cell size ``resolution_m``, the lower-left corner at (``origin_x_m``, ``origin_y_m``)
    in the shared map frame; ``path``: the robot's recent path, (x, y) pairs (f32) in the same frame."""

    TYPE: ClassVar[int] = 0x04
    t_us: int
    resolution_m: float
    origin_x_m: float
    origin_y_m: float
    width: int
    height: int
    cells_zlib: bytes
    path: tuple[tuple[float, float], ...] = ()

    def payload(self) -> bytes:
        head = _MAP.pack(
            self.t_us,
            self.resolution_m,
            self.origin_x_m,
            self.origin_y_m,
            self.width,
            self.height,
            len(self.path),
        )
        return head + b"".join(_PATH_POINT.pack(x, y) for x, y in self.path) + self.cells_zlib

    def cells(self) -> bytes:
        """The cells, inflated (int8 as bytes), checked."""
        cells = inflate_cells(self.cells_zlib, self.width * self.height)
        check_cells(cells)
        return cells

    @classmethod
    def parse(cls, payload: bytes) -> MapMessage:
        if len(payload) < _MAP.size:
            raise LocalProtocolError(f"map: payload of {len(payload)} bytes, at least {_MAP.size}", payload)
        t_us, res, ox, oy, width, height, n_path = _MAP.unpack_from(payload)
        if not (math.isfinite(res) and res > 0 and math.isfinite(ox) and math.isfinite(oy)):
            raise LocalProtocolError("map: a resolution or origin that is not finite and positive")
        if not (0 < width * height <= MAX_MAP_CELLS) or n_path > MAX_PATH_POINTS:
            raise LocalProtocolError(f"map: {width} x {height} cells, {n_path} path points: too many")
        end = _MAP.size + n_path * _PATH_POINT.size
        if len(payload) <= end:
            raise LocalProtocolError("map: truncated path or no cells", payload[:64])
        path = tuple(
            _PATH_POINT.unpack_from(payload, _MAP.size + i * _PATH_POINT.size) for i in range(n_path)
        )
        if not all(math.isfinite(v) for p in path for v in p):
            raise LocalProtocolError("map: a path point that is not finite")
        message = cls(t_us, res, ox, oy, width, height, payload[end:], path)
        message.cells()  # inflates and checks; the bridge forwards only what a receiver can read
        return message


@dataclass(frozen=True, slots=True)
class TopologyMessage:
    """This robot's topological map (agent -> bridge): ``agent.exploration.topology.to_geojson``'s GeoJSON
    as compact UTF-8 JSON (checked by the bridge's encoder, ``agent.fleet.payloads``)."""

    TYPE: ClassVar[int] = 0x05
    t_us: int
    geojson: bytes

    def payload(self) -> bytes:
        return _TOPOLOGY.pack(self.t_us) + self.geojson

    @classmethod
    def parse(cls, payload: bytes) -> TopologyMessage:
        if len(payload) <= _TOPOLOGY.size:
            raise LocalProtocolError("topology: no GeoJSON", payload)
        (t_us,) = _TOPOLOGY.unpack_from(payload)
        return cls(t_us, payload[_TOPOLOGY.size :])


Message = (
    PoseMessage
    | StatusMessage
    | GoalStateMessage
    | PeerPoseMessage
    | GoalMessage
    | MapMessage
    | TopologyMessage
)
_TYPES: dict[int, Any] = {
    cls.TYPE: cls
    for cls in (
        PoseMessage,
        StatusMessage,
        GoalStateMessage,
        PeerPoseMessage,
        GoalMessage,
        MapMessage,
        TopologyMessage,
    )
}
_SNAPSHOTS = frozenset({MapMessage.TYPE, TopologyMessage.TYPE})


def max_payload(kind: int) -> int:
    """The largest payload a frame of type ``kind`` may carry."""
    return MAX_SNAPSHOT_PAYLOAD if kind in _SNAPSHOTS else MAX_PAYLOAD


def _unpack(layout: struct.Struct, payload: bytes, what: str) -> tuple[Any, ...]:
    if len(payload) != layout.size:
        raise LocalProtocolError(f"{what}: payload of {len(payload)} bytes, expected {layout.size}", payload)
    return layout.unpack(payload)


def encode(message: Message) -> bytes:
    """One whole frame. Raises LocalProtocolError for a value the frame cannot carry (a bad robot name, an
    integer out of its field's range)."""
    if isinstance(message, PeerPoseMessage) and not valid_robot_name(message.robot):
        raise LocalProtocolError(f"cannot encode the robot name {message.robot!r}")
    try:
        payload = message.payload()
    except struct.error as exc:
        raise LocalProtocolError(f"cannot encode {type(message).__name__}: {exc}") from exc
    if len(payload) > max_payload(message.TYPE):
        raise LocalProtocolError(f"{type(message).__name__}: {len(payload)} bytes, over its cap")
    return HEADER.pack(MAGIC, VERSION, message.TYPE, len(payload)) + payload


def _check_header(header: bytes) -> tuple[int, int]:
    magic, version, kind, length = HEADER.unpack(header)
    if magic != MAGIC:
        raise LocalProtocolError("not a fleet frame (bad magic)", header)
    if version != VERSION:
        raise LocalProtocolError(f"protocol version {version}, this side speaks {VERSION}", header)
    if kind not in _TYPES:
        raise LocalProtocolError(f"unknown message type 0x{kind:02x}", header)
    if length > max_payload(kind):
        raise LocalProtocolError(f"payload of {length} bytes, at most {max_payload(kind)}", header)
    return kind, length


def decode_frame(frame: bytes) -> Message:
    """Exactly one whole frame -> its message; LocalProtocolError for anything else (truncated, trailing
    bytes, oversized, garbage)."""
    if len(frame) < HEADER.size:
        raise LocalProtocolError(f"truncated header ({len(frame)} of {HEADER.size} bytes)", frame)
    kind, length = _check_header(frame[: HEADER.size])
    if len(frame) != HEADER.size + length:
        what = "truncated" if len(frame) < HEADER.size + length else "trailing bytes after"
        raise LocalProtocolError(f"{what} a {length}-byte payload ({len(frame)} bytes given)", frame[:64])
    message: Message = _TYPES[kind].parse(frame[HEADER.size :])
    return message


class FrameDecoder:
    """Bytes from the stream in, whole messages out. Buffers at most one frame (header + its type's cap);
    the first bad frame raises LocalProtocolError and the decoder stays failed (close the connection)."""

    def __init__(self) -> None:
        self._buffer = bytearray()
        self._failed: LocalProtocolError | None = None

    @property
    def pending(self) -> int:
        """Bytes of an incomplete frame held (non-zero at the end of a stream: it was cut)."""
        return len(self._buffer)

    def feed(self, data: bytes) -> list[Message]:
        if self._failed is not None:
            raise self._failed
        self._buffer += data
        out: list[Message] = []
        try:
            while len(self._buffer) >= HEADER.size:
                _, length = _check_header(bytes(self._buffer[: HEADER.size]))
                end = HEADER.size + length
                if len(self._buffer) < end:
                    break
                out.append(decode_frame(bytes(self._buffer[:end])))
                del self._buffer[:end]
        except LocalProtocolError as exc:
            self._failed = exc
            self._buffer.clear()
            raise
        return out


@dataclass(frozen=True, slots=True)
class ReadResult:
    """What one read from the stream gave: the whole messages, and why the connection must now be closed
    (None: keep reading). ``malformed``: it closes for a bad frame (counted by the caller)."""

    messages: list[Message] = field(default_factory=list)
    close: str | None = None
    malformed: bool = False


class FrameReader:
    """One connection's reading side, sans I/O: hand it what ``recv`` returned (or the error it raised)
    and it says what came and whether the connection must close. Both ends (the agent's fleet loop, the
    bridge) read through it, so both treat the end of the stream, a failed receive and a bad frame alike:
    the connection closes, the other side reconnects."""

    def __init__(self) -> None:
        self._decoder = FrameDecoder()

    def received(self, data: bytes) -> ReadResult:
        """Bytes from the stream; ``b""`` is its end (the peer closed)."""
        if not data:
            cut = f" ({self._decoder.pending} bytes of a frame cut)" if self._decoder.pending else ""
            return ReadResult(close=f"the other side closed the connection{cut}")
        try:
            return ReadResult(self._decoder.feed(data))
        except LocalProtocolError as exc:
            return ReadResult(close=f"malformed frame: {exc}", malformed=True)

    @staticmethod
    def failed(exc: OSError) -> ReadResult:
        """``recv`` raised: a timeout or an interrupted call is nothing; anything else closes."""
        if isinstance(exc, TimeoutError | BlockingIOError | InterruptedError):
            return ReadResult()
        return ReadResult(close=f"receive failed: {exc}")


class _Receiver(Protocol):
    def recv(self, bufsize: int, /) -> bytes: ...


READ_SIZE = 65536


def receive(sock: _Receiver, reader: FrameReader) -> ReadResult:
    """One ``recv`` on a readable socket, through ``reader`` (the only I/O here: the caller selects)."""
    try:
        data = sock.recv(READ_SIZE)
    except OSError as exc:
        return reader.failed(exc)
    return reader.received(data)
