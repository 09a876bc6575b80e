"""The privacy audit of what goes over the fleet network: every key must be a documented fleet key and its
payload must decode strictly by that key's documented schema (``agent.fleet.payloads``). What the schemas
allow is poses, status flags and counters, goals and goal states, laser-built occupancy maps with the
robot's path, and topological graphs: no image, nothing computed from camera pixels except the pose the
LED observations give, and no field beyond its schema's (``FIELDS``). So a payload that passes is free of
images by construction; this module is what a test (or ``vlp-agent sim --robots N``) runs over everything
heard on ``**``.
"""

from __future__ import annotations

import collections
import json
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from agent.fleet import payloads
from firmware_protocol.errors import ProtocolError

__all__ = ["DECODERS", "FIELDS", "Audit", "check"]

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


def check(prefix: str, key_expr: str, payload: bytes) -> str | None:
    """None when ``payload`` under ``key_expr`` is a documented fleet message (its schema's fields and no
    other); else what is wrong."""
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
        problem = check(self.prefix, key, data)
        kind = key.rsplit("/", 1)[-1] if problem is None else "invalid"
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
