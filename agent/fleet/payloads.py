"""What goes over Zenoh: key expressions and the JSON payloads under them (docs/fleet.md, "On the network").

Every payload is one UTF-8 JSON object of at most :data:`MAX_PAYLOAD` bytes with ``"v": 1`` (the schema
version) and the sender's robot name. Decoders are strict: a payload that is too large, not JSON, of another
schema version, missing a field, of the wrong type, not finite, or naming another robot than its key raises
:class:`FleetPayloadError` (a :class:`~firmware_protocol.errors.ProtocolError`); the bridge counts and drops
it. Nothing derived from pixels is in any payload: poses, flags and goals only.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

from agent.fleet.local_protocol import (
    GoalMessage,
    GoalStateMessage,
    PoseMessage,
    StatusMessage,
    valid_robot_name,
)
from firmware_protocol.errors import ProtocolError

__all__ = [
    "MAX_PAYLOAD",
    "SCHEMA",
    "FleetPayloadError",
    "RobotStatus",
    "decode_goal",
    "decode_goal_state",
    "decode_pose",
    "decode_status",
    "encode_goal",
    "encode_goal_state",
    "encode_pose",
    "encode_status",
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
def _load(payload: bytes, robot: str) -> dict[str, Any]:
    if len(payload) > MAX_PAYLOAD:
        raise FleetPayloadError(f"payload of {len(payload)} bytes, at most {MAX_PAYLOAD}", payload[:64])
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
