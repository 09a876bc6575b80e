"""The privacy audit of what goes over the fleet network: every key must be a documented fleet key and its
payload must decode strictly by that key's documented schema (``agent.fleet.payloads``). What the schemas
allow is poses, status flags and counters, goals and goal states, laser-built occupancy maps with the
robot's path, and topological graphs: no image, nothing computed from camera pixels except the pose the
LED observations give. So a payload that passes is free of images by construction; this module is what a
test (or ``vlp-agent sim --robots N``) runs over everything heard on ``**``.
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from agent.fleet import payloads
from firmware_protocol.errors import ProtocolError

__all__ = ["DECODERS", "Audit", "check"]

DECODERS: dict[str, Callable[[bytes, str], object]] = {
    "pose": payloads.decode_pose,
    "status": payloads.decode_status,
    "goal_state": payloads.decode_goal_state,
    "goal": payloads.decode_goal,
    "map": payloads.decode_map,
    "topology": payloads.decode_topology,
}


def check(prefix: str, key_expr: str, payload: bytes) -> str | None:
    """None when ``payload`` under ``key_expr`` is a documented fleet message; else what is wrong."""
    kind = key_expr.rsplit("/", 1)[-1]
    decoder = DECODERS.get(kind)
    if decoder is None:
        return f"undocumented key {key_expr[:120]!r}"
    try:
        robot = payloads.robot_of(prefix, key_expr)
        decoder(payload, robot)
    except ProtocolError as exc:
        return f"{key_expr[:120]}: {exc}"
    return None


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
