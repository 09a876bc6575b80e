"""A flight recording -> a ROS 2 bag (rosbag2, MCAP storage) with standard message types, for ``ros2 bag
play``, RViz and every ROS tool.

The bag is a folder: ``<name>_0.mcap`` (profile ``ros2``, CDR messages, ``ros2msg`` schemas, written by
``mcap-ros2-support``) and the ``metadata.yaml`` rosbag2 reads first (format version 5, what Humble writes
and every later rosbag2 reads). What goes in:

======================  =============================================  ==============================
bag topic               type                                           from
======================  =============================================  ==============================
``/scan``               sensor_msgs/msg/LaserScan (frame ``laser``)    ``/laser/scan_raw``
``/odom``               nav_msgs/msg/Odometry (``odom`` -> base_link)  ``/fusion/input`` odometry
``/pose``               geometry_msgs/msg/PoseWithCovarianceStamped    ``/pose/fused`` (frame ``map``)
``/slam/pose``          geometry_msgs/msg/PoseWithCovarianceStamped    ``/slam/pose``
``/vlp/pose``           geometry_msgs/msg/PoseWithCovarianceStamped    ``/vlp/fix``
``/map``                nav_msgs/msg/OccupancyGrid (frame ``map``)     ``/map``
``/tf``                 tf2_msgs/msg/TFMessage (map -> base_link)      ``/tf`` (the fused pose)
``/tf_static``          tf2_msgs/msg/TFMessage (base_link -> laser)    ``/slam/setup``'s laser mount
``/imu``                sensor_msgs/msg/Imu (frame ``imu``)            ``/imu``
``/cmd_vel``            geometry_msgs/msg/TwistStamped (``base_link``)  ``/wheels/command`` (sent)
``/controller/cmd_vel`` geometry_msgs/msg/TwistStamped (``base_link``)  ``/commands/received`` velocity
``/goal_pose``          geometry_msgs/msg/PoseStamped (``map``)         ``/commands/received`` goal
``/diagnostics``        diagnostic_msgs/msg/DiagnosticArray            ``/health``
======================  =============================================  ==============================

``/map`` and ``/tf_static`` are offered transient-local (latched), as map servers and static transform
publishers offer them, so that RViz started after ``ros2 bag play`` still gets them.

Times are Unix time (the recording's monotonic times plus its ``unix_minus_monotonic_ns``), in the headers
and as the bag's receive times. A scan's error codes (below ``min_range_mm``) become NaN ("erroneous" in
REP 117), beyond ``max_range_mm`` +inf; ``time_increment`` and ``scan_time`` are 0 (not in the
recording). The IMU has no orientation estimate (``orientation_covariance[0] = -1``, REP 145) and its
other covariances are 0 ("unknown"); its frame ``imu`` has no transform in the bag (the recording holds
no IMU mount). ``/cmd_vel`` is the base velocity each wheel command sent was made from (after the
dead-man: zero when it stopped the robot; recordings made before those fields were recorded have none);
``/controller/cmd_vel`` and ``/goal_pose`` are the controller's velocity and goal commands as received (a
goal with any final heading has yaw 0); its stop, resume and cancel commands have no standard message
and are left out. A ``/health`` event is one DiagnosticStatus: ``name`` ``vlp-agent/<device>``,
``hardware_id`` the device, ``level`` OK (0) when it came up or recovered and ERROR (2) when it went bad,
``message`` the reason. Covariances are 6x6 over (x, y, z, roll, pitch, yaw) with the recorded 3x3 over
(x, y, yaw) in place and 0 for the three a planar robot does not measure (as AMCL publishes); a VLP fix
without a heading has yaw variance 1e6. The odometry's twist is the wheel interval's mean speed.
"""

from __future__ import annotations

import base64
import json
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.records import Schema
from mcap_ros2.writer import Writer

from agent.recording.reader import Recording
from agent.recording.ros2_types import (
    DIAGNOSTIC_ARRAY,
    IMU,
    LASER_SCAN,
    OCCUPANCY_GRID,
    ODOMETRY,
    POSE_STAMPED,
    POSE_WITH_COVARIANCE_STAMPED,
    TF_MESSAGE,
    TWIST_STAMPED,
    msgdef,
)
from agent.recording.slam_log import integrate_odometry

__all__ = ["ExportResult", "export_ros2"]

# A fix without a heading: its yaw variance (rad^2), "unknown" to a consumer that weighs by covariance.
_UNKNOWN_VARIANCE = 1e6
# The recorded 3x3 (x, y, yaw) -> its place in ROS's 6x6 (x, y, z, roll, pitch, yaw).
_AXES = (0, 1, 5)

Message = dict[str, Any]


@dataclass
class ExportResult:
    bag: Path
    files: list[Path]
    counts: dict[str, int] = field(default_factory=dict)  # bag topic -> messages written


def _stamp(t_ns: int) -> Message:
    t_ns = max(int(t_ns), 0)
    return {"sec": t_ns // 1_000_000_000, "nanosec": t_ns % 1_000_000_000}


def _header(t_ns: int, frame: str) -> Message:
    return {"stamp": _stamp(t_ns), "frame_id": frame}


def _pose(x: float, y: float, yaw: float) -> Message:
    return {
        "position": {"x": x, "y": y, "z": 0.0},
        "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(0.5 * yaw), "w": math.cos(0.5 * yaw)},
    }


def covariance6(values: list[float] | None, yaw_known: bool = True) -> list[float]:
    """A recorded row-major 3x3 over (x, y, yaw) (or 2x2 over x, y) as ROS's row-major 6x6."""
    out = [0.0] * 36
    values = values or []
    side = math.isqrt(len(values))
    for i in range(min(side, 3)):
        for j in range(min(side, 3)):
            out[6 * _AXES[i] + _AXES[j]] = float(values[side * i + j])
    if not yaw_known or side < 3:
        out[6 * 5 + 5] = _UNKNOWN_VARIANCE
    return out


def _scan(d: Message, offset: int) -> Message:
    lo, hi = int(d["min_range_mm"]), int(d["max_range_mm"])
    ranges = []
    for r in d["ranges_mm"]:
        if r < lo:
            ranges.append(math.nan)
        elif r > hi:
            ranges.append(math.inf)
        else:
            ranges.append(r * 1e-3)
    n = len(ranges)
    start, step = float(d["angle_min_rad"]), float(d["angle_increment_rad"])
    return {
        "header": _header(int(d["host_time_ns"]) + offset, "laser"),
        "angle_min": start,
        "angle_max": start + step * max(n - 1, 0),
        "angle_increment": step,
        "time_increment": 0.0,
        "scan_time": 0.0,
        "range_min": lo * 1e-3,
        "range_max": hi * 1e-3,
        "ranges": ranges,
        "intensities": [],
    }


def _pose_stamped(t_ns: int, frame: str, d: Message, x: str, y: str, yaw: str) -> Message:
    heading = d[yaw]
    return {
        "header": _header(t_ns, frame),
        "pose": {
            "pose": _pose(float(d[x]), float(d[y]), 0.0 if heading is None else float(heading)),
            "covariance": covariance6(d.get("covariance"), heading is not None),
        },
    }


def _grid(d: Message, offset: int) -> Message:
    stamp = d["timestamp"]
    t_ns = int(stamp["sec"]) * 1_000_000_000 + int(stamp["nsec"]) + offset
    cells = base64.b64decode(d["data"])
    width = int(d["column_count"])
    position, orientation = d["pose"]["position"], d["pose"]["orientation"]
    return {
        "header": _header(t_ns, "map"),
        "info": {
            "map_load_time": _stamp(t_ns),
            "resolution": float(d["cell_size"]["x"]),
            "width": width,
            "height": len(cells) // width if width else 0,
            "origin": {"position": dict(position), "orientation": dict(orientation)},
        },
        # Both lay rows out from the lowest y; the recording's INT8 bytes are the occupancy as it is.
        "data": [b - 256 if b > 127 else b for b in cells],
    }


def _quaternion(roll: float, pitch: float, yaw: float) -> Message:
    """Roll, pitch, yaw (fixed axes x, y, z) as a quaternion."""
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    return {
        "x": sr * cp * cy - cr * sp * sy,
        "y": cr * sp * cy + sr * cp * sy,
        "z": cr * cp * sy - sr * sp * cy,
        "w": cr * cp * cy + sr * sp * sy,
    }


def _transforms(d: Message, offset: int) -> Message:
    out = []
    for tf in d["transforms"]:
        stamp = tf["timestamp"]
        t_ns = int(stamp["sec"]) * 1_000_000_000 + int(stamp["nsec"]) + offset
        out.append(
            {
                "header": _header(t_ns, tf["parent_frame_id"]),
                "child_frame_id": tf["child_frame_id"],
                "transform": {"translation": dict(tf["translation"]), "rotation": dict(tf["rotation"])},
            }
        )
    return {"transforms": out}


def _laser_mount(t_ns: int, mount: Message) -> Message:
    def get(key: str) -> float:
        return float(mount.get(key, 0.0))

    rotation = _quaternion(get("roll_rad"), get("pitch_rad"), get("yaw_rad"))
    transform = {
        "translation": {"x": get("x_m"), "y": get("y_m"), "z": get("z_m")},
        "rotation": rotation,
    }
    stamped = {"header": _header(t_ns, "base_link"), "child_frame_id": "laser", "transform": transform}
    return {"transforms": [stamped]}


def _odometry(t_ns: int, pose: tuple[float, float, float], v: float, w: float) -> Message:
    return {
        "header": _header(t_ns, "odom"),
        "child_frame_id": "base_link",
        "pose": {"pose": _pose(*pose), "covariance": [0.0] * 36},
        "twist": {
            "twist": {"linear": {"x": v, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": w}},
            "covariance": [0.0] * 36,
        },
    }


def _vector(values: list[float]) -> Message:
    x, y, z = (float(v) for v in values[:3])
    return {"x": x, "y": y, "z": z}


def _imu(d: Message, offset: int) -> Message:
    unknown = [0.0] * 9
    return {
        "header": _header(int(d["host_time_ns"]) + offset, "imu"),
        "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 0.0},
        "orientation_covariance": [-1.0] + [0.0] * 8,  # REP 145: no orientation estimate
        "angular_velocity": _vector(d["gyro_radps"]),
        "angular_velocity_covariance": unknown,
        "linear_acceleration": _vector(d["accel_mps2"]),
        "linear_acceleration_covariance": unknown,
    }


def _twist(t_ns: int, v_mps: float, omega_radps: float) -> Message:
    return {
        "header": _header(t_ns, "base_link"),
        "twist": {
            "linear": {"x": float(v_mps), "y": 0.0, "z": 0.0},
            "angular": {"x": 0.0, "y": 0.0, "z": float(omega_radps)},
        },
    }


_OK, _ERROR = 0, 2  # diagnostic_msgs/DiagnosticStatus levels


def _diagnostics(t_ns: int, d: Message) -> Message:
    device = str(d["device"])
    ok = bool(d["ok"])
    return {
        "header": _header(t_ns, ""),
        "status": [
            {
                "level": _OK if ok else _ERROR,
                "name": f"vlp-agent/{device}",
                "message": str(d["reason"]) or ("up" if ok else "bad"),
                "hardware_id": device,
                "values": [{"key": "ok", "value": "true" if ok else "false"}],
            }
        ],
    }


def _command(t_ns: int, d: Message) -> tuple[str, str, Message] | None:
    """A received command with a standard message: velocity -> TwistStamped, goal -> PoseStamped."""
    fields = d.get("fields", {})
    if d["kind"] == "velocity":
        return "/controller/cmd_vel", TWIST_STAMPED, _twist(t_ns, fields["v_mps"], fields["omega_radps"])
    if d["kind"] == "goal":
        yaw = fields.get("yaw_rad")
        pose = _pose(float(fields["x_m"]), float(fields["y_m"]), 0.0 if yaw is None else float(yaw))
        return "/goal_pose", POSE_STAMPED, {"header": _header(t_ns, "map"), "pose": pose}
    return None


def _bag_messages(recordings: Iterable[Recording]) -> list[tuple[int, str, str, Message]]:
    """(time ns, bag topic, type, message) for every message that has a ROS counterpart, in time order."""
    out: list[tuple[int, str, str, Message]] = []
    for recording in recordings:
        offset = int(recording.metadata.get("vlp_agent", {}).get("unix_minus_monotonic_ns", "0"))
        odometry: list[Message] = []
        mount: Message | None = None
        for m in recording.messages:
            d, t = m.data, m.log_time_ns + offset
            if m.topic == "/laser/scan_raw":
                out.append((t, "/scan", LASER_SCAN, _scan(d, offset)))
            elif m.topic == "/pose/fused":
                stamped = _pose_stamped(int(d["t_ns"]) + offset, "map", d, "x_m", "y_m", "yaw_rad")
                out.append((t, "/pose", POSE_WITH_COVARIANCE_STAMPED, stamped))
            elif m.topic == "/slam/pose":
                stamped = _pose_stamped(int(d["t_ns"]) + offset, "map", d, "x_m", "y_m", "yaw_rad")
                out.append((t, "/slam/pose", POSE_WITH_COVARIANCE_STAMPED, stamped))
            elif m.topic == "/vlp/fix":
                stamped = _pose_stamped(int(d["t_ns"]) + offset, "map", d, "x_m", "y_m", "yaw_rad")
                out.append((t, "/vlp/pose", POSE_WITH_COVARIANCE_STAMPED, stamped))
            elif m.topic == "/map":
                out.append((t, "/map", OCCUPANCY_GRID, _grid(d, offset)))
            elif m.topic == "/tf":
                out.append((t, "/tf", TF_MESSAGE, _transforms(d, offset)))
            elif m.topic == "/slam/setup":
                mount = d["mount"]
            elif m.topic == "/imu":
                out.append((t, "/imu", IMU, _imu(d, offset)))
            elif m.topic == "/wheels/command" and "v_mps" in d:
                out.append((t, "/cmd_vel", TWIST_STAMPED, _twist(t, d["v_mps"], d["omega_radps"])))
            elif m.topic == "/commands/received":
                command = _command(t, d)
                if command is not None:
                    out.append((t, *command))
            elif m.topic == "/health":
                out.append((t, "/diagnostics", DIAGNOSTIC_ARRAY, _diagnostics(t, d)))
            elif m.topic == "/fusion/input" and d.get("k") == "odometry":
                odometry.append(d)
        for t_ns, pose, v, w in integrate_odometry(odometry):
            out.append((t_ns + offset, "/odom", ODOMETRY, _odometry(t_ns + offset, pose, v, w)))
        if mount is not None and out and not any(topic == "/tf_static" for _, topic, _, _ in out):
            first = min(t for t, _, _, _ in out)
            out.append((first, "/tf_static", TF_MESSAGE, _laser_mount(first, mount)))
    out.sort(key=lambda item: item[0])
    return out


# What a latched publisher offers (rosbag2's QoS fields; rmw's enum values: history 1 keep last,
# reliability 1 reliable, durability 1 transient local, liveliness 1 automatic; durations infinite).
_INFINITE = {"sec": 2147483647, "nsec": 4294967295}
_LATCHED_QOS = json.dumps(
    [
        {
            "history": 1,
            "depth": 1,
            "reliability": 1,
            "durability": 1,
            "deadline": _INFINITE,
            "lifespan": _INFINITE,
            "liveliness": 1,
            "liveliness_lease_duration": _INFINITE,
            "avoid_ros_namespace_conventions": False,
        }
    ]
)
_LATCHED = frozenset({"/map", "/tf_static"})


def _metadata(name: str, counts: dict[str, tuple[str, int]], start_ns: int, end_ns: int) -> str:
    """rosbag2's ``metadata.yaml`` (format version 5), as JSON (a YAML document too)."""
    total = sum(n for _, n in counts.values())
    duration = {"nanoseconds": max(end_ns - start_ns, 0)}
    starting = {"nanoseconds_since_epoch": start_ns}
    info = {
        "version": 5,
        "storage_identifier": "mcap",
        "relative_file_paths": [name],
        "duration": duration,
        "starting_time": starting,
        "message_count": total,
        "topics_with_message_count": [
            {
                "topic_metadata": {
                    "name": topic,
                    "type": msgtype,
                    "serialization_format": "cdr",
                    "offered_qos_profiles": _qos(topic),
                },
                "message_count": n,
            }
            for topic, (msgtype, n) in sorted(counts.items())
        ],
        "compression_format": "",
        "compression_mode": "",
        "files": [{"path": name, "starting_time": starting, "duration": duration, "message_count": total}],
    }
    return json.dumps({"rosbag2_bagfile_information": info}, indent=2) + "\n"


def _qos(topic: str) -> str:
    return _LATCHED_QOS if topic in _LATCHED else ""


def _register_channel(writer: Writer, topic: str, schema: Schema) -> None:
    """The topic's channel with its offered QoS in the channel's metadata, as rosbag2's MCAP storage writes
    it (readers match it with metadata.yaml's). mcap-ros2-support registers channels without metadata
    when it first writes a topic, so the channel is registered here first, in the two attributes its
    ``write_message`` looks in (the dependency's version is pinned below 0.7 for that reason)."""
    mcap_writer, channel_ids = getattr(writer, "_writer", None), getattr(writer, "_channel_ids", None)
    if mcap_writer is None or not isinstance(channel_ids, dict):
        raise RuntimeError("mcap-ros2-support changed: its Writer has no _writer/_channel_ids")
    channel_ids[topic] = mcap_writer.register_channel(
        topic=topic,
        message_encoding="cdr",
        schema_id=schema.id,
        metadata={"offered_qos_profiles": _qos(topic)},
    )


def export_ros2(recordings: list[Recording], out: Path) -> ExportResult:
    """Write what :func:`agent.recording.reader.read_recordings` read as the rosbag2 folder ``out`` (made;
    it must not exist or be empty: a bag is never written over)."""
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise FileExistsError(f"{out} exists and is not an empty folder: a bag is never written over")
    out.mkdir(parents=True, exist_ok=True)
    name = f"{out.name}_0.mcap"
    messages = _bag_messages(recordings)
    counts: dict[str, tuple[str, int]] = {}
    with open(out / name, "wb") as fp:
        writer = Writer(fp)
        schemas: dict[str, Schema] = {}
        for t_ns, topic, msgtype, message in messages:
            schema = schemas.get(msgtype)
            if schema is None:
                schema = schemas[msgtype] = writer.register_msgdef(msgtype, msgdef(msgtype))
            if topic not in counts:
                _register_channel(writer, topic, schema)
            writer.write_message(topic, schema, message, log_time=t_ns, publish_time=t_ns)
            kind, n = counts.get(topic, (msgtype, 0))
            counts[topic] = (kind, n + 1)
        writer.finish()  # type: ignore[no-untyped-call]
    start = messages[0][0] if messages else 0
    end = messages[-1][0] if messages else 0
    (out / "metadata.yaml").write_text(_metadata(name, counts, start, end), encoding="utf-8")
    return ExportResult(out, [out / name, out / "metadata.yaml"], {t: n for t, (_, n) in counts.items()})
