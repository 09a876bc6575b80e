"""What goes over Zenoh: key expressions and the JSON payloads under them (docs/fleet.md, "On the network").

Every payload is one UTF-8 JSON object of at most :data:`MAX_PAYLOAD` bytes with ``"v": 1`` (the schema
version) and the sender's robot name. Decoders are strict: a payload that is too large, not JSON, of another
schema version, missing a field, of the wrong type, not finite, or naming another robot than its key raises
:class:`FleetPayloadError` (a :class:`~firmware_protocol.errors.ProtocolError`); the bridge counts and drops
it. Nothing derived from pixels is in any payload: poses, flags, goals, and maps and topology built from the
laser (SLAM), not from the cameras. Maps and topology have their own, larger caps
(:data:`MAX_MAP_PAYLOAD`, :data:`MAX_TOPOLOGY_PAYLOAD`).
"""

from __future__ import annotations

import base64
import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from agent.fleet.local_protocol import (
    MAX_MAP_CELLS,
    MAX_PATH_POINTS,
    GoalMessage,
    GoalStateMessage,
    LocalProtocolError,
    MapMessage,
    PoseMessage,
    StatusMessage,
    TopologyMessage,
    check_cells,
    inflate_cells,
    valid_robot_name,
)
from agent.fleet.maps import Grid
from firmware_protocol.errors import ProtocolError

__all__ = [
    "MAP_FRAME",
    "MAX_MAP_PAYLOAD",
    "MAX_PAYLOAD",
    "MAX_TOPOLOGY_PAYLOAD",
    "SCHEMA",
    "FleetPayloadError",
    "RobotMap",
    "RobotStatus",
    "check_topology",
    "decode_goal",
    "decode_goal_state",
    "decode_map",
    "decode_pose",
    "decode_status",
    "decode_topology",
    "encode_goal",
    "encode_goal_state",
    "encode_map",
    "encode_pose",
    "encode_status",
    "encode_topology",
    "key",
    "robot_of",
]

SCHEMA = 1
MAX_PAYLOAD = 4096


class FleetPayloadError(ProtocolError):
    """A message from the network that is not a valid fleet payload."""


def key(prefix: str, robot: str, kind: str) -> str:
    """``<prefix>/<robot>/<kind>``, e.g. ``fleet/r1/pose``."""
    return f"{prefix}/{robot}/{kind}"


def robot_of(prefix: str, key_expr: str) -> str:
    """The robot chunk of ``<prefix>/<robot>/<kind>``; FleetPayloadError when the key is not one."""
    parts = key_expr.split("/")
    head = prefix.split("/")
    if len(parts) != len(head) + 2 or parts[: len(head)] != head or not valid_robot_name(parts[len(head)]):
        raise FleetPayloadError(f"not a fleet key: {key_expr[:120]!r}")
    return parts[len(head)]


def _dumps(obj: dict[str, Any]) -> bytes:
    return json.dumps(obj, allow_nan=False, separators=(",", ":")).encode()


def _opt(value: float) -> float | None:
    return value if math.isfinite(value) else None


def encode_pose(robot: str, pose: PoseMessage) -> bytes:
    return _dumps(
        {
            "v": SCHEMA,
            "robot": robot,
            "t_us": pose.t_us,
            "x_m": pose.x_m,
            "y_m": pose.y_m,
            "yaw_rad": pose.yaw_rad,
            "sigma_xy_m": _opt(pose.sigma_xy_m),
            "sigma_yaw_rad": _opt(pose.sigma_yaw_rad),
            "flags": pose.flags,
        }
    )


@dataclass(frozen=True)
class RobotStatus:
    """A robot's status as the fleet sees it: its agent's flags and its bridge's counters."""

    robot: str
    t_us: int
    pose_flags: int
    bits: int
    agent_connected: bool
    counters: dict[str, int]

    @property
    def state(self) -> str:
        if not self.agent_connected:
            return "agent-down"
        if not self.bits & StatusMessage.LOCALIZED:
            return "not-localized"
        return "ready" if self.bits & StatusMessage.READY else "starting"


def encode_status(robot: str, status: StatusMessage | None, counters: dict[str, int]) -> bytes:
    """The agent's last status (None: no agent connected) and the bridge's counters."""
    return _dumps(
        {
            "v": SCHEMA,
            "robot": robot,
            "t_us": status.t_us if status else 0,
            "pose_flags": status.pose_flags if status else 0,
            "bits": status.bits if status else 0,
            "agent": status is not None,
            "counters": dict(counters),
        }
    )


def encode_goal_state(robot: str, goal: GoalStateMessage) -> bytes:
    return _dumps(
        {
            "v": SCHEMA,
            "robot": robot,
            "t_us": goal.t_us,
            "goal_id": goal.goal_id,
            "state": goal.state,
            "reason": goal.reason,
            "remaining_m": _opt(goal.remaining_m),
        }
    )


def encode_goal(robot: str, goal: GoalMessage) -> bytes:
    return _dumps(
        {
            "v": SCHEMA,
            "robot": robot,
            "goal_id": goal.goal_id,
            "x_m": goal.x_m,
            "y_m": goal.y_m,
            "yaw_rad": _opt(goal.yaw_rad),
            "allow_unknown": goal.allow_unknown,
        }
    )


# -- decoding ------------------------------------------------------------------------------------------
def _load(payload: bytes, robot: str, limit: int = MAX_PAYLOAD) -> dict[str, Any]:
    if len(payload) > limit:
        raise FleetPayloadError(f"payload of {len(payload)} bytes, at most {limit}", payload[:64])
    try:
        obj = json.loads(payload.decode("utf-8"), parse_constant=_no_constant)
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise FleetPayloadError(f"not JSON: {exc}", payload[:64]) from exc
    if not isinstance(obj, dict):
        raise FleetPayloadError("not a JSON object", payload[:64])
    if obj.get("v") != SCHEMA:
        raise FleetPayloadError(f"schema version {obj.get('v')!r}, this side reads {SCHEMA}", payload[:64])
    if obj.get("robot") != robot:
        raise FleetPayloadError(f"names robot {obj.get('robot')!r} under the key of {robot!r}", payload[:64])
    return obj


def _no_constant(name: str) -> float:
    raise ValueError(f"{name} is not JSON")


def _int(obj: dict[str, Any], name: str, low: int, high: int) -> int:
    value = obj.get(name)
    if type(value) is not int or not low <= value <= high:
        raise FleetPayloadError(f"{name!r} must be an integer {low}..{high}, not {value!r}")
    return value


def _float(obj: dict[str, Any], name: str, *, optional: bool = False) -> float:
    value = obj.get(name)
    if value is None and optional:
        return math.nan
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise FleetPayloadError(f"{name!r} must be a finite number, not {value!r}")
    return float(value)


def decode_pose(payload: bytes, robot: str) -> PoseMessage:
    """A pose published under ``robot``'s key."""
    obj = _load(payload, robot)
    return PoseMessage(
        _int(obj, "t_us", 0, 2**64 - 1),
        _float(obj, "x_m"),
        _float(obj, "y_m"),
        _float(obj, "yaw_rad"),
        _float(obj, "sigma_xy_m", optional=True),
        _float(obj, "sigma_yaw_rad", optional=True),
        _int(obj, "flags", 0, 2**32 - 1),
    )


def decode_status(payload: bytes, robot: str) -> RobotStatus:
    obj = _load(payload, robot)
    counters = obj.get("counters")
    if not isinstance(counters, dict) or not all(
        isinstance(k, str) and type(v) is int for k, v in counters.items()
    ):
        raise FleetPayloadError("'counters' must be an object of integers")
    agent = obj.get("agent")
    if type(agent) is not bool:
        raise FleetPayloadError(f"'agent' must be true or false, not {agent!r}")
    return RobotStatus(
        robot,
        _int(obj, "t_us", 0, 2**64 - 1),
        _int(obj, "pose_flags", 0, 2**32 - 1),
        _int(obj, "bits", 0, 2**32 - 1),
        agent,
        counters,
    )


def decode_goal(payload: bytes, robot: str) -> GoalMessage:
    """A goal published under ``robot``'s goal key (it must name ``robot`` itself)."""
    obj = _load(payload, robot)
    allow = obj.get("allow_unknown", False)
    if type(allow) is not bool:
        raise FleetPayloadError(f"'allow_unknown' must be true or false, not {allow!r}")
    return GoalMessage(
        0,
        _int(obj, "goal_id", 0, 0xFFFF),
        _float(obj, "x_m"),
        _float(obj, "y_m"),
        _float(obj, "yaw_rad", optional=True),
        GoalMessage.ALLOW_UNKNOWN if allow else 0,
    )


def decode_goal_state(payload: bytes, robot: str) -> GoalStateMessage:
    """A goal status published under ``robot``'s ``goal_state`` key."""
    obj = _load(payload, robot)
    return GoalStateMessage(
        _int(obj, "t_us", 0, 2**64 - 1),
        _int(obj, "goal_id", 0, 0xFFFF),
        _int(obj, "state", 0, 255),
        _int(obj, "reason", 0, 255),
        _float(obj, "remaining_m", optional=True),
    )


# -- maps and topology (their own caps: a map is larger than a pose) ----------------------------------
MAX_MAP_PAYLOAD = 1 << 20  # bytes of one map payload (JSON with the base64 of the zlib cells)
MAX_TOPOLOGY_PAYLOAD = 256 * 1024
MAP_FRAME = "map"  # the shared frame of the surveyed ceiling LEDs
MAP_ENCODING = "zlib-int8"
_GEOMETRIES = {"Point": 1, "MultiLineString": 3, "Polygon": 3}


@dataclass(frozen=True)
class RobotMap:
    """A robot's map as the fleet hears it (``<prefix>/<robot>/map``): laser-derived occupancy, cells
    decoded and checked (``agent.fleet.maps.Grid``), and its recent path."""

    robot: str
    t_us: int
    grid: Grid
    path: tuple[tuple[float, float], ...]


def encode_map(robot: str, message: MapMessage) -> bytes:
    return _dumps(
        {
            "v": SCHEMA,
            "robot": robot,
            "t_us": message.t_us,
            "frame": MAP_FRAME,
            "resolution_m": float(message.resolution_m),
            "origin_x_m": message.origin_x_m,
            "origin_y_m": message.origin_y_m,
            "width": message.width,
            "height": message.height,
            "encoding": MAP_ENCODING,
            "cells": base64.b64encode(message.cells_zlib).decode("ascii"),
            "path": [[round(x, 3), round(y, 3)] for x, y in message.path],
        }
    )


def decode_map(payload: bytes, robot: str) -> RobotMap:
    """A map published under ``robot``'s key: at most :data:`MAX_MAP_PAYLOAD` bytes, the cells exactly
    ``width * height`` int8 of -1..100 after inflating (a zlib bomb stops at that size)."""
    obj = _load(payload, robot, MAX_MAP_PAYLOAD)
    if obj.get("frame") != MAP_FRAME or obj.get("encoding") != MAP_ENCODING:
        raise FleetPayloadError(f"map: frame {obj.get('frame')!r}, encoding {obj.get('encoding')!r}")
    res = _float(obj, "resolution_m")
    width, height = _int(obj, "width", 1, MAX_MAP_CELLS), _int(obj, "height", 1, MAX_MAP_CELLS)
    if res <= 0 or width * height > MAX_MAP_CELLS:
        raise FleetPayloadError(f"map: {width} x {height} cells of {res} m")
    text = obj.get("cells")
    if not isinstance(text, str):
        raise FleetPayloadError("map: 'cells' must be a base64 string")
    try:
        packed = base64.b64decode(text, validate=True)
        cells = inflate_cells(packed, width * height)
        check_cells(cells)
    except (ValueError, LocalProtocolError) as exc:
        raise FleetPayloadError(f"map: bad cells: {exc}") from exc
    path = obj.get("path")
    if not isinstance(path, list) or len(path) > MAX_PATH_POINTS:
        raise FleetPayloadError(f"map: 'path' must be a list of at most {MAX_PATH_POINTS} points")
    points = []
    for p in path:
        if not isinstance(p, list) or len(p) != 2:
            raise FleetPayloadError("map: a path point must be [x, y]")
        points.append((_float({"x": p[0]}, "x"), _float({"y": p[1]}, "y")))
    grid = Grid(
        np.frombuffer(cells, np.int8).reshape(height, width).copy(),
        res,
        _float(obj, "origin_x_m"),
        _float(obj, "origin_y_m"),
    )
    return RobotMap(robot, _int(obj, "t_us", 0, 2**64 - 1), grid, tuple(points))


def encode_topology(robot: str, message: TopologyMessage) -> bytes:
    """The agent's GeoJSON, checked (:func:`check_topology`) and wrapped; FleetPayloadError if it is not."""
    try:
        geojson = json.loads(message.geojson.decode("utf-8"), parse_constant=_no_constant)
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise FleetPayloadError(f"topology: not JSON: {exc}") from exc
    check_topology(geojson)
    return _dumps(
        {"v": SCHEMA, "robot": robot, "t_us": message.t_us, "frame": MAP_FRAME, "topology": geojson}
    )


def check_topology(geojson: Any) -> None:
    """A GeoJSON FeatureCollection of Point, MultiLineString and Polygon features with finite coordinates
    and a ``properties`` object (``docs/exploration.md``, "The topological map file")."""
    if not isinstance(geojson, dict) or geojson.get("type") != "FeatureCollection":
        raise FleetPayloadError("topology: not a GeoJSON FeatureCollection")
    features = geojson.get("features")
    if not isinstance(features, list):
        raise FleetPayloadError("topology: 'features' must be a list")
    for f in features:
        if not isinstance(f, dict) or f.get("type") != "Feature" or not isinstance(f.get("properties"), dict):
            raise FleetPayloadError("topology: a feature that is not a GeoJSON Feature with properties")
        geometry = f.get("geometry")
        if not isinstance(geometry, dict) or geometry.get("type") not in _GEOMETRIES:
            raise FleetPayloadError("topology: a geometry other than Point, MultiLineString, Polygon")
        _check_coordinates(geometry.get("coordinates"), _GEOMETRIES[geometry["type"]])


def _check_coordinates(value: Any, depth: int) -> None:
    if depth == 1:
        if (
            not isinstance(value, list)
            or len(value) != 2
            or not all(
                not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v) for v in value
            )
        ):
            raise FleetPayloadError("topology: a position that is not two finite numbers")
        return
    if not isinstance(value, list):
        raise FleetPayloadError("topology: coordinates nested wrongly")
    for v in value:
        _check_coordinates(v, depth - 1)


def decode_topology(payload: bytes, robot: str) -> dict[str, Any]:
    """A topology published under ``robot``'s key: the GeoJSON, checked."""
    obj = _load(payload, robot, MAX_TOPOLOGY_PAYLOAD)
    if obj.get("frame") != MAP_FRAME:
        raise FleetPayloadError(f"topology: frame {obj.get('frame')!r}")
    _int(obj, "t_us", 0, 2**64 - 1)
    geojson = obj.get("topology")
    check_topology(geojson)
    assert isinstance(geojson, dict)
    return geojson
