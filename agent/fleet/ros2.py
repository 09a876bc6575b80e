"""ROS 2 messages as rmw_zenoh puts them on Zenoh: CDR payloads, key expressions, attachments and graph
tokens (docs/fleet.md, "ROS 2 over rmw_zenoh"). Sans-I/O: bytes and strings out, no session here.

What rmw_zenoh_cpp (the ROS 2 Zenoh middleware) puts on the wire for a topic, read from its source
(``docs/design.md``, ``README.md``, ``rmw_zenoh_cpp/src/detail/{liveliness_utils,attachment_helpers,
rmw_subscription_data,type_support_common}.cpp`` in ``ros2/rmw_zenoh``):

- **data key**: ``<domain_id>/<topic name without its outer slashes>/<DDS type name>/<RIHS01 type hash>``,
  e.g. ``0/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c74...``; the DDS type name is
  ``<package>::msg::dds_::<Message>_``;
- **payload**: the message in CDR as the ROS 2 type support writes it: a 4-byte encapsulation header
  (``00 01 00 00``: plain CDR, little endian) then XCDR1 with every primitive aligned to its size (at
  most 8) from the end of that header;
- **attachment** (a subscriber drops a sample without one): the zenoh-ext serialization of ``int64``
  sequence number, ``int64`` source timestamp (ns since the Unix epoch), and the 16-byte publisher GID as
  a sequence (LEB128 length ``0x10``, then the bytes): 33 bytes. This is the layout of rmw_zenoh_cpp
  0.2.4 and later (Jazzy, Kilted, Rolling); 0.2.3 and earlier prefixed each field with its name;
- **graph tokens**: liveliness tokens ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<NN|MP>/<enclave>/
  <namespace>/<node>[/<topic>/<type>/<hash>/<qos>]`` with every ``/`` inside a name written ``%``. A
  subscriber does not need them to receive data; ``ros2 topic list``, ``ros2 node list`` and
  ``ros2 topic echo`` without a type read the graph from them.

The type hashes below are the published RIHS01 values of ROS 2 Jazzy's interfaces (the tests check them
against ``rosbags``' own computation from the message definitions).
"""

from __future__ import annotations

import hashlib
import math
import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass

from agent.fleet.local_protocol import PoseMessage

__all__ = [
    "ENCAPSULATION_CDR_LE",
    "GID_SIZE",
    "OCCUPANCY_GRID",
    "POSE_WITH_COVARIANCE_STAMPED",
    "STRING",
    "TYPE_HASHES",
    "CdrWriter",
    "Ros2Topic",
    "attachment",
    "dds_type_name",
    "encode_occupancy_grid",
    "encode_pose",
    "encode_string",
    "node_token",
    "publisher_token",
    "topic_key",
    "valid_namespace",
]

POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
STRING = "std_msgs/msg/String"

#: RIHS01 type hashes (ROS 2 Jazzy): the last chunk of the data key; a subscriber only matches its own.
TYPE_HASHES = {
    POSE_WITH_COVARIANCE_STAMPED: "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e",
    OCCUPANCY_GRID: "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7",
    STRING: "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
}

ENCAPSULATION_CDR_LE = b"\x00\x01\x00\x00"
GID_SIZE = 16
ADMIN_SPACE = "@ros2_lv"
#: rmw_zenoh writes only the QoS fields that differ from its default profile (reliable, volatile, keep
#: last 42, no deadline, lifespan or liveliness lease; ``rmw_zenoh_cpp/src/detail/qos.cpp``), in the
#: order reliability:durability:history,depth:deadline s,ns:lifespan s,ns:liveliness,lease s,ns.
DEFAULT_QOS = "::,:,:,:,,"
#: Durability TRANSIENT_LOCAL (rmw's enum value 1), keep last 1: a latched map, as map servers publish.
LATCHED_QOS = ":1:,1:,:,:,,"

_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def valid_namespace(ns: str) -> bool:
    """A ROS 2 namespace: ``/`` or ``/a/b`` of tokens of letters, digits and ``_`` not led by a digit."""
    return ns == "/" or (ns.startswith("/") and all(_NAME.fullmatch(t) for t in ns[1:].split("/")))


def dds_type_name(ros_type: str) -> str:
    """``geometry_msgs/msg/PoseStamped`` -> ``geometry_msgs::msg::dds_::PoseStamped_``."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def topic_key(domain_id: int, topic: str, ros_type: str) -> str:
    """The data key expression of ``topic`` (a fully qualified name, ``/r1/pose``) in ``domain_id``."""
    return f"{domain_id}/{topic.strip('/')}/{dds_type_name(ros_type)}/{TYPE_HASHES[ros_type]}"


def _mangle(name: str) -> str:
    return name.replace("/", "%")


def node_token(domain_id: int, zid: str, node_id: int, namespace: str, node: str) -> str:
    """The liveliness key of a node (``NN``), enclave ``/``."""
    return f"{ADMIN_SPACE}/{domain_id}/{zid}/{node_id}/{node_id}/NN/%/{_mangle(namespace)}/{node}"


def publisher_token(
    domain_id: int,
    zid: str,
    node_id: int,
    entity_id: int,
    namespace: str,
    node: str,
    topic: str,
    ros_type: str,
    qos: str = DEFAULT_QOS,
) -> str:
    """The liveliness key of a publisher (``MP``) of ``topic`` with the QoS field ``qos``."""
    return (
        f"{ADMIN_SPACE}/{domain_id}/{zid}/{node_id}/{entity_id}/MP/%/{_mangle(namespace)}/{node}/"
        f"{_mangle(topic)}/{dds_type_name(ros_type)}/{TYPE_HASHES[ros_type]}/{qos}"
    )


def attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """The 33-byte attachment rmw_zenoh (0.2.4 and later) reads from every sample."""
    if len(gid) != GID_SIZE:
        raise ValueError(f"a GID is {GID_SIZE} bytes, not {len(gid)}")
    return struct.pack("<qqB", sequence_number, source_timestamp_ns, GID_SIZE) + gid


@dataclass
class Ros2Topic:
    """One published topic: its data key, its graph token and the publisher's GID (the first 16 bytes of
    the SHA-256 of the token: unique per session, as rmw_zenoh's hash of the token is) and sequence."""

    topic: str
    ros_type: str
    key: str
    token: str
    gid: bytes
    latched: bool = False
    sequence_number: int = 0

    @classmethod
    def make(
        cls,
        domain_id: int,
        zid: str,
        node_id: int,
        entity_id: int,
        namespace: str,
        node: str,
        name: str,
        ros_type: str,
        latched: bool = False,
    ) -> Ros2Topic:
        """``latched``: TRANSIENT_LOCAL, keep last 1 (:data:`LATCHED_QOS`); else the default profile."""
        topic = f"{namespace.rstrip('/')}/{name}"
        qos = LATCHED_QOS if latched else DEFAULT_QOS
        token = publisher_token(domain_id, zid, node_id, entity_id, namespace, node, topic, ros_type, qos)
        gid = hashlib.sha256(token.encode()).digest()[:GID_SIZE]
        return cls(topic, ros_type, topic_key(domain_id, topic, ros_type), token, gid, latched)

    def next_attachment(self, source_timestamp_ns: int) -> bytes:
        """The attachment of the next sample (sequence numbers from 1, as rmw_zenoh's)."""
        self.sequence_number += 1
        return attachment(self.sequence_number, source_timestamp_ns, self.gid)


class CdrWriter:
    """Plain CDR, little endian (XCDR1, the ROS 2 default): each primitive aligned to its size (at most
    8) counted from the end of the 4-byte encapsulation header."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def _align(self, n: int) -> None:
        self._buf.extend(b"\x00" * (-len(self._buf) % n))

    def _put(self, fmt: str, size: int, *values: float | int) -> None:
        self._align(size)
        self._buf.extend(struct.pack("<" + fmt, *values))

    def int32(self, v: int) -> None:
        self._put("i", 4, v)

    def uint32(self, v: int) -> None:
        self._put("I", 4, v)

    def float32(self, v: float) -> None:
        self._put("f", 4, v)

    def float64s(self, values: Sequence[float]) -> None:
        self._put(f"{len(values)}d", 8, *values)

    def string(self, text: str) -> None:
        """uint32 length counting the NUL, the UTF-8 bytes, the NUL."""
        data = text.encode("utf-8")
        if b"\x00" in data:
            raise ValueError("a CDR string cannot hold a NUL")
        self.uint32(len(data) + 1)
        self._buf.extend(data + b"\x00")

    def octets(self, data: bytes) -> None:
        """A sequence of 1-byte elements (``int8[]``, ``uint8[]``): uint32 count, the bytes."""
        self.uint32(len(data))
        self._buf.extend(data)

    def time(self, stamp_ns: int) -> None:
        """``builtin_interfaces/Time``: int32 sec, uint32 nanosec."""
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        self.int32(sec)
        self.uint32(nanosec)

    def header(self, stamp_ns: int, frame_id: str) -> None:
        """``std_msgs/Header``."""
        self.time(stamp_ns)
        self.string(frame_id)

    def pose(self, x: float, y: float, yaw: float) -> None:
        """``geometry_msgs/Pose`` of a planar pose: position (x, y, 0), orientation about z."""
        self.float64s((x, y, 0.0, 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)))

    def finish(self) -> bytes:
        return ENCAPSULATION_CDR_LE + bytes(self._buf)


def encode_pose(pose: PoseMessage, stamp_ns: int, frame_id: str = "map") -> bytes:
    """``geometry_msgs/msg/PoseWithCovarianceStamped``: the covariance (row-major over x, y, z, roll,
    pitch, yaw) carries ``sigma_xy_m**2`` for x and y and ``sigma_yaw_rad**2`` for yaw (NaN when the
    agent gives none); z, roll and pitch are held by the floor: 0."""
    w = CdrWriter()
    w.header(stamp_ns, frame_id)
    w.pose(pose.x_m, pose.y_m, pose.yaw_rad)
    cov = [0.0] * 36
    cov[0] = cov[7] = pose.sigma_xy_m**2
    cov[35] = pose.sigma_yaw_rad**2
    w.float64s(cov)
    return w.finish()


def encode_occupancy_grid(
    cells: bytes,
    width: int,
    height: int,
    resolution_m: float,
    origin_x_m: float,
    origin_y_m: float,
    stamp_ns: int,
    frame_id: str = "map",
) -> bytes:
    """``nav_msgs/msg/OccupancyGrid``: ``cells`` row-major int8 (-1 unknown, 0..100), row 0 the lowest y,
    origin the lower-left corner of cell (0, 0): the fleet map's own layout (``agent.fleet.maps.Grid``)."""
    if len(cells) != width * height:
        raise ValueError(f"{len(cells)} cells for a {width} x {height} grid")
    w = CdrWriter()
    w.header(stamp_ns, frame_id)
    w.time(stamp_ns)  # info.map_load_time
    w.float32(resolution_m)
    w.uint32(width)
    w.uint32(height)
    w.pose(origin_x_m, origin_y_m, 0.0)
    w.octets(cells)
    return w.finish()


def encode_string(text: str) -> bytes:
    """``std_msgs/msg/String``."""
    w = CdrWriter()
    w.string(text)
    return w.finish()
