"""Strict reading of what the bridge's ROS 2 side (``agent.fleet.ros2_out``) puts on Zenoh: its data keys,
its graph-token keys and the CDR payloads of its three message types, for the privacy audit
(``agent.fleet.audit``). Sans-I/O: strings and bytes in, values out, :class:`Ros2PayloadError` for anything
else.

Strict means the exact layout ``agent.fleet.ros2`` writes and nothing more: plain CDR little endian
(``00 01 00 00``), every padding byte zero, no byte after the message, and values that carry only what the
fleet's JSON schemas carry. A ``PoseWithCovarianceStamped`` is a planar pose (z, roll, pitch 0; a unit
quaternion about z) with the covariance zero except the x and y variances (equal) and the yaw variance; an
``OccupancyGrid``'s data is exactly ``width * height`` cells of -1..100 in a planar frame; a ``String`` is
UTF-8 text (the audit then reads it as the status JSON). Every ``frame_id`` is ``map``.
"""

from __future__ import annotations

import math
import re
import struct
from dataclasses import dataclass

from agent.fleet import ros2
from agent.fleet.local_protocol import MAX_MAP_CELLS
from agent.fleet.payloads import MAP_FRAME
from firmware_protocol.errors import ProtocolError

__all__ = [
    "KINDS",
    "MAX_STRING_BYTES",
    "CdrReader",
    "Ros2Grid",
    "Ros2PayloadError",
    "Ros2Pose",
    "TopicKey",
    "decode_occupancy_grid",
    "decode_pose",
    "decode_string",
    "parse_token_key",
    "parse_topic_key",
]

#: The topics the bridge publishes: the last name of the topic -> its ROS 2 type.
KINDS = {"pose": ros2.POSE_WITH_COVARIANCE_STAMPED, "map": ros2.OCCUPANCY_GRID, "status": ros2.STRING}
_LATCHED = {"map"}
MAX_DOMAIN_ID = 232
MAX_STRING_BYTES = 4096  # a status JSON is at most payloads.MAX_PAYLOAD bytes
_DECIMAL = re.compile(r"0|[1-9][0-9]{0,9}")
_ZID = re.compile(r"[0-9a-f]{1,32}")
_TYPE_OF_DDS = {ros2.dds_type_name(t): t for t in KINDS.values()}


class Ros2PayloadError(ProtocolError):
    """A key or payload that is not exactly what the bridge's ROS 2 side publishes."""


@dataclass(frozen=True)
class TopicKey:
    """A parsed data key: ``kind`` is ``pose``, ``map`` or ``status``, ``namespace`` the topic's namespace."""

    domain_id: int
    topic: str
    namespace: str
    kind: str
    ros_type: str


def _domain(chunk: str, key: str) -> int:
    if not _DECIMAL.fullmatch(chunk) or int(chunk) > MAX_DOMAIN_ID:
        raise Ros2PayloadError(f"not a ROS 2 domain id 0..{MAX_DOMAIN_ID}: {key[:120]!r}")
    return int(chunk)


def _topic(name: str, key: str) -> tuple[str, str]:
    """``/ns/kind`` -> (namespace, kind) when ``kind`` is one the bridge publishes."""
    namespace, _, kind = name.rpartition("/")
    namespace = namespace or "/"
    if kind not in KINDS or not ros2.valid_namespace(namespace):
        raise Ros2PayloadError(f"not a topic the bridge publishes ({sorted(KINDS)}): {key[:120]!r}")
    return namespace, kind


def _type(dds: str, type_hash: str, kind: str, key: str) -> str:
    ros_type = _TYPE_OF_DDS.get(dds)
    if ros_type is None:
        raise Ros2PayloadError(f"unknown ROS 2 type {dds[:80]!r}: {key[:120]!r}")
    if ros_type != KINDS[kind]:
        raise Ros2PayloadError(f"{kind} topic of type {ros_type}, not {KINDS[kind]}: {key[:120]!r}")
    if type_hash != ros2.TYPE_HASHES[ros_type]:
        raise Ros2PayloadError(f"{ros_type} with type hash {type_hash[:80]!r}: {key[:120]!r}")
    return ros_type


def parse_topic_key(key: str) -> TopicKey:
    """``<domain>/<topic>/<dds type>/<RIHS01 hash>`` of one of the bridge's topics (:data:`KINDS`)."""
    parts = key.split("/")
    if len(parts) < 4:
        raise Ros2PayloadError(f"not a ROS 2 data key: {key[:120]!r}")
    domain = _domain(parts[0], key)
    topic = "/" + "/".join(parts[1:-2])
    namespace, kind = _topic(topic, key)
    ros_type = _type(parts[-2], parts[-1], kind, key)
    return TopicKey(domain, topic, namespace, kind, ros_type)


def parse_token_key(key: str) -> None:
    """A graph (liveliness) token key as ``ros2.node_token`` / ``ros2.publisher_token`` write them for the
    bridge's node and its three publishers; Ros2PayloadError otherwise."""
    parts = key.split("/")
    if parts[0] != ros2.ADMIN_SPACE or len(parts) not in (9, 13):
        raise Ros2PayloadError(f"not a ROS 2 graph token key: {key[:120]!r}")
    _domain(parts[1], key)
    ids_ok = all(_DECIMAL.fullmatch(p) for p in parts[3:5])
    if not _ZID.fullmatch(parts[2]) or not ids_ok or parts[6] != "%":
        raise Ros2PayloadError(f"graph token: bad zid, entity ids or enclave: {key[:120]!r}")
    namespace = parts[7].replace("%", "/")
    if not ros2.valid_namespace(namespace) or not ros2.valid_namespace("/" + parts[8]):
        raise Ros2PayloadError(f"graph token: bad namespace or node name: {key[:120]!r}")
    if len(parts) == 9:
        if parts[5] != "NN":
            raise Ros2PayloadError(f"graph token: a node token is NN: {key[:120]!r}")
        return
    if parts[5] != "MP":
        raise Ros2PayloadError(f"graph token: the bridge declares only publishers (MP): {key[:120]!r}")
    topic_ns, kind = _topic(parts[9].replace("%", "/"), key)
    if topic_ns != namespace:
        raise Ros2PayloadError(f"graph token: topic outside the node's namespace: {key[:120]!r}")
    _type(parts[10], parts[11], kind, key)
    qos = ros2.LATCHED_QOS if kind in _LATCHED else ros2.DEFAULT_QOS
    if parts[12] != qos:
        raise Ros2PayloadError(f"graph token: {kind} QoS {parts[12][:40]!r}, not {qos!r}: {key[:120]!r}")


class CdrReader:
    """Plain CDR little endian (XCDR1) read strictly: the ``00 01 00 00`` header, each primitive aligned to
    its size (at most 8) from the end of that header with zero padding, :meth:`end` when nothing may
    follow."""

    def __init__(self, data: bytes) -> None:
        if data[:4] != ros2.ENCAPSULATION_CDR_LE:
            raise Ros2PayloadError("not plain CDR little endian (00 01 00 00)", data[:16])
        self._data = memoryview(data)[4:]
        self._pos = 0
        self._raw = data

    def _need(self, n: int) -> memoryview:
        if self._pos + n > len(self._data):
            raise Ros2PayloadError(f"truncated: {n} bytes wanted at offset {self._pos + 4}", self._raw)
        out = self._data[self._pos : self._pos + n]
        self._pos += n
        return out

    def _align(self, n: int) -> None:
        pad = self._need(-self._pos % n)
        if any(pad):
            raise Ros2PayloadError(f"non-zero padding before offset {self._pos + 4}", self._raw)

    def _get(self, fmt: str, size: int, count: int = 1) -> tuple[float | int, ...]:
        self._align(size)
        return struct.unpack(f"<{count}{fmt}", self._need(size * count))

    def int32(self) -> int:
        return int(self._get("i", 4)[0])

    def uint32(self) -> int:
        return int(self._get("I", 4)[0])

    def float32(self) -> float:
        return float(self._get("f", 4)[0])

    def float64s(self, n: int) -> tuple[float, ...]:
        return tuple(float(v) for v in self._get("d", 8, n))

    def string(self, max_bytes: int) -> str:
        """uint32 length counting the NUL, UTF-8 without NUL, the NUL."""
        n = self.uint32()
        if not 1 <= n <= max_bytes + 1:
            raise Ros2PayloadError(f"string of {n} bytes (NUL included), at most {max_bytes + 1}", self._raw)
        raw = bytes(self._need(n))
        if raw[-1] != 0 or b"\x00" in raw[:-1]:
            raise Ros2PayloadError("a string must end in its one NUL", self._raw)
        try:
            return raw[:-1].decode("utf-8")
        except UnicodeDecodeError as exc:
            raise Ros2PayloadError(f"string not UTF-8: {exc}", self._raw) from exc

    def octets(self, n: int) -> bytes:
        """A sequence of exactly ``n`` 1-byte elements."""
        count = self.uint32()
        if count != n:
            raise Ros2PayloadError(f"a sequence of {count} bytes, {n} expected", self._raw)
        return bytes(self._need(n))

    def time_ns(self) -> int:
        """``builtin_interfaces/Time``: int32 sec, uint32 nanosec below 1e9."""
        sec, nanosec = self.int32(), self.uint32()
        if nanosec >= 1_000_000_000:
            raise Ros2PayloadError(f"nanosec {nanosec} out of range", self._raw)
        return sec * 1_000_000_000 + nanosec

    def header_ns(self) -> int:
        """``std_msgs/Header`` in frame ``map``: its stamp."""
        stamp = self.time_ns()
        frame = self.string(64)
        if frame != MAP_FRAME:
            raise Ros2PayloadError(f"frame_id {frame[:40]!r}, not {MAP_FRAME!r}", self._raw)
        return stamp

    def planar_pose(self) -> tuple[float, float, float]:
        """``geometry_msgs/Pose`` of a planar pose (finite x, y; z 0; unit quaternion about z): x, y, yaw."""
        x, y, z, qx, qy, qz, qw = self.float64s(7)
        if not (math.isfinite(x) and math.isfinite(y) and z == qx == qy == 0.0):
            raise Ros2PayloadError("a pose must be planar: finite x, y; z, qx, qy 0", self._raw)
        if not (math.isfinite(qz) and math.isfinite(qw)) or abs(math.hypot(qz, qw) - 1.0) > 1e-9:
            raise Ros2PayloadError("orientation not a unit quaternion about z", self._raw)
        return x, y, 2.0 * math.atan2(qz, qw)

    def end(self) -> None:
        if self._pos != len(self._data):
            raise Ros2PayloadError(f"{len(self._data) - self._pos} bytes after the message", self._raw)


@dataclass(frozen=True)
class Ros2Pose:
    stamp_ns: int
    x_m: float
    y_m: float
    yaw_rad: float
    sigma_xy_m: float  # NaN when the agent gave none
    sigma_yaw_rad: float


def _sigma(variance: float, raw: bytes) -> float:
    if math.isnan(variance):
        return math.nan
    if not (math.isfinite(variance) and variance >= 0.0):
        raise Ros2PayloadError(f"variance {variance!r}: not NaN, finite or non-negative", raw)
    return math.sqrt(variance)


def decode_pose(data: bytes) -> Ros2Pose:
    """``geometry_msgs/msg/PoseWithCovarianceStamped`` as ``ros2.encode_pose`` writes it."""
    r = CdrReader(data)
    stamp = r.header_ns()
    x, y, yaw = r.planar_pose()
    cov = r.float64s(36)
    r.end()
    if any(v != 0.0 for i, v in enumerate(cov) if i not in (0, 7, 35)):
        raise Ros2PayloadError("covariance beyond the x, y and yaw variances", data[:64])
    if not (cov[0] == cov[7] or (math.isnan(cov[0]) and math.isnan(cov[7]))):
        raise Ros2PayloadError("the x and y variances differ (one sigma_xy_m)", data[:64])
    return Ros2Pose(stamp, x, y, yaw, _sigma(cov[0], data), _sigma(cov[35], data))


@dataclass(frozen=True)
class Ros2Grid:
    stamp_ns: int
    map_load_ns: int
    resolution_m: float
    width: int
    height: int
    origin_x_m: float
    origin_y_m: float
    cells: bytes  # row-major int8, -1..100


def decode_occupancy_grid(data: bytes, max_cells: int = MAX_MAP_CELLS) -> Ros2Grid:
    """``nav_msgs/msg/OccupancyGrid`` as ``ros2.encode_occupancy_grid`` writes it: ``width * height``
    (1..``max_cells``) cells of -1..100 and nothing else; origin orientation identity."""
    r = CdrReader(data)
    stamp = r.header_ns()
    load = r.time_ns()
    res = r.float32()
    width, height = r.uint32(), r.uint32()
    if not (math.isfinite(res) and res > 0.0):
        raise Ros2PayloadError(f"resolution {res!r}", data[:64])
    if not (width >= 1 and height >= 1 and width * height <= max_cells):
        raise Ros2PayloadError(f"{width} x {height} cells, 1..{max_cells}", data[:64])
    ox, oy, yaw = r.planar_pose()
    if yaw != 0.0:
        raise Ros2PayloadError("the grid's origin orientation must be the identity", data[:64])
    cells = r.octets(width * height)
    r.end()
    if any(v > 100 and v != 0xFF for v in set(cells)):
        raise Ros2PayloadError("an occupancy cell outside -1..100", data[:64])
    return Ros2Grid(stamp, load, res, width, height, ox, oy, cells)


def decode_string(data: bytes, max_bytes: int = MAX_STRING_BYTES) -> str:
    """``std_msgs/msg/String``: UTF-8 text of at most ``max_bytes`` bytes."""
    r = CdrReader(data)
    text = r.string(max_bytes)
    r.end()
    return text
