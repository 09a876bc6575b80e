"""The privacy audit of what goes over the fleet network: every key must be a documented fleet key and its
payload must decode strictly by that key's documented schema (``agent.fleet.payloads``). What the schemas
allow is poses, status flags and counters, goals and goal states, laser-built occupancy maps with the
robot's path, and topological graphs: no image, nothing computed from camera pixels except the pose the
LED observations give, and no field beyond its schema's (``FIELDS``). So a payload that passes is free of
images by construction; this module is what a test (or ``vlp-agent sim --robots N``) runs over everything
heard on ``**``.

With the bridge's ``[ros2]`` side on, its ROS 2 topics (rmw_zenoh data keys ``<domain>/<ns>/<pose|map|
status>/<type>/<hash>``) are audited too, by ``agent.fleet.ros2_decode``: the key must be one of the three
topics with its own type and hash, the CDR payload exactly that type's layout with only what the JSON
schemas carry (a planar pose and its sigmas; an occupancy grid of ``width * height`` cells -1..100; a
``String`` that is the status JSON, then audited as the status payload is). A graph token key
(``@ros2_lv/...``), should one be heard as a sample, must be one the bridge declares, with no payload.
"""

from __future__ import annotations

import collections
import json
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from agent.fleet import payloads, ros2, ros2_decode
from agent.fleet.local_protocol import valid_robot_name
from firmware_protocol.errors import ProtocolError

__all__ = ["DECODERS", "FIELDS", "Audit", "check", "classify"]

DECODERS: dict[str, Callable[[bytes, str], object]] = {
    "pose": payloads.decode_pose,
    "status": payloads.decode_status,
    "goal_state": payloads.decode_goal_state,
    "goal": payloads.decode_goal,
    "map": payloads.decode_map,
    "topology": payloads.decode_topology,
}


# The fields each payload may carry (docs/fleet.md, "On the network"). The decoders read the fields they
# know and ignore others; the audit does not: an extra field could carry anything (a JPEG in base64).
_BASE = ("v", "robot")
FIELDS: dict[str, frozenset[str]] = {
    "pose": frozenset((*_BASE, "t_us", "x_m", "y_m", "yaw_rad", "sigma_xy_m", "sigma_yaw_rad", "flags")),
    "status": frozenset((*_BASE, "t_us", "pose_flags", "bits", "agent", "counters")),
    "goal_state": frozenset((*_BASE, "t_us", "goal_id", "state", "reason", "remaining_m")),
    "goal": frozenset((*_BASE, "goal_id", "x_m", "y_m", "yaw_rad", "allow_unknown")),
    "map": frozenset(
        (
            *_BASE,
            *("t_us", "frame", "resolution_m", "origin_x_m", "origin_y_m", "width", "height"),
            *("encoding", "cells", "path"),
        )
    ),
    "topology": frozenset((*_BASE, "t_us", "frame", "topology")),
}
_MAX_COUNTER_NAME = 64


def _extra(kind: str, payload: bytes) -> str | None:
    """What the decoded payload carries beyond its schema's fields, or None."""
    obj = json.loads(payload)  # it decoded as its schema: a JSON object
    extra = set(obj) - FIELDS[kind]
    if extra:
        return f"fields beyond the {kind} schema: {sorted(extra)[:5]}"
    if kind == "status":
        counters = obj["counters"]
        if not isinstance(counters, dict) or not all(
            isinstance(k, str)
            and len(k) <= _MAX_COUNTER_NAME
            and k.replace("_", "").isalnum()
            and type(v) is int
            for k, v in counters.items()
        ):
            return "counters must map short names to integers"
    return None


def _check_fleet(prefix: str, key_expr: str, payload: bytes) -> str | None:
    kind = key_expr.rsplit("/", 1)[-1]
    decoder = DECODERS.get(kind)
    if decoder is None:
        return f"undocumented key {key_expr[:120]!r}"
    try:
        robot = payloads.robot_of(prefix, key_expr)
        decoder(payload, robot)
    except ProtocolError as exc:
        return f"{key_expr[:120]}: {exc}"
    extra = _extra(kind, payload)
    return None if extra is None else f"{key_expr[:120]}: {extra}"


def _check_ros2_status(text: str) -> str | None:
    """The text of a ROS 2 ``String`` status: the status JSON, audited as the JSON key's payload."""
    try:
        obj = json.loads(text)
    except ValueError:
        return "status String: not JSON"
    robot = obj.get("robot") if isinstance(obj, dict) else None
    if not isinstance(robot, str) or not valid_robot_name(robot):
        return f"status String: no valid 'robot' ({str(robot)[:40]!r})"
    data = text.encode("utf-8")
    try:
        payloads.decode_status(data, robot)
    except ProtocolError as exc:
        return f"status String: {exc}"
    return _extra("status", data)


def _check_ros2(key_expr: str, payload: bytes) -> tuple[str, str | None]:
    try:
        if key_expr.startswith(ros2.ADMIN_SPACE + "/"):
            ros2_decode.parse_token_key(key_expr)
            if payload:
                return "ros2_token", f"{key_expr[:120]}: a graph token with a {len(payload)}-byte payload"
            return "ros2_token", None
        topic = ros2_decode.parse_topic_key(key_expr)
        problem: str | None = None
        if topic.kind == "pose":
            ros2_decode.decode_pose(payload)
        elif topic.kind == "map":
            ros2_decode.decode_occupancy_grid(payload)
        else:
            problem = _check_ros2_status(ros2_decode.decode_string(payload))
    except ProtocolError as exc:
        return "invalid", f"{key_expr[:120]}: {exc}"
    return f"ros2_{topic.kind}", None if problem is None else f"{key_expr[:120]}: {problem}"


def _is_ros2(prefix: str, key_expr: str) -> bool:
    """A key in the ROS 2 key space (a domain id first, or the graph tokens' ``@ros2_lv``) and not under
    the fleet's prefix."""
    first = key_expr.split("/", 1)[0]
    return not key_expr.startswith(prefix + "/") and (first.isdigit() or first == ros2.ADMIN_SPACE)


def classify(prefix: str, key_expr: str, payload: bytes) -> tuple[str, str | None]:
    """(kind, problem): the kind heard (``pose`` .. ``topology``, ``ros2_pose``, ``ros2_map``,
    ``ros2_status``, ``ros2_token``; ``invalid`` when the key is not recognised) and None when the
    payload passes, else what is wrong."""
    if _is_ros2(prefix, key_expr):
        return _check_ros2(key_expr, payload)
    problem = _check_fleet(prefix, key_expr, payload)
    return ("invalid" if problem else key_expr.rsplit("/", 1)[-1]), problem


def check(prefix: str, key_expr: str, payload: bytes) -> str | None:
    """None when ``payload`` under ``key_expr`` is a documented fleet message (its schema's fields and no
    other) or one of the bridge's ROS 2 messages (strictly its layout); else what is wrong."""
    return classify(prefix, key_expr, payload)[1]


@dataclass
class Audit:
    """Everything heard on a ``**`` subscriber: counts per kind, and every failure (the first 20 kept)."""

    prefix: str = "fleet"
    heard: collections.Counter[str] = field(default_factory=collections.Counter)
    failures: list[str] = field(default_factory=list)
    failed: int = 0
    largest: dict[str, int] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def __call__(self, sample: Any) -> None:
        key = str(sample.key_expr)
        data = bytes(sample.payload.to_bytes())
        kind, problem = classify(self.prefix, key, data)
        kind = kind if problem is None else "invalid"
        with self._lock:
            self.heard[kind] += 1
            if problem is None:
                self.largest[kind] = max(self.largest.get(kind, 0), len(data))
            else:
                self.failed += 1
                if len(self.failures) < 20:
                    self.failures.append(problem)

    def summary(self) -> dict[str, Any]:
        with self._lock:
            return {
                "messages": sum(self.heard.values()),
                "by_kind": dict(sorted(self.heard.items())),
                "largest_bytes": dict(sorted(self.largest.items())),
                "failed": self.failed,
                "failures": list(self.failures),
            }
