"""The fleet view: who is out there. Subscribes to ``<prefix>/*/pose`` and ``<prefix>/*/status`` for a while
and keeps the newest of each per robot; malformed messages are counted, not shown. A robot heard earlier in
the window but silent for ``stale_s`` at its end is ``gone`` (it vanished: its bridge or its network)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from agent.fleet import payloads
from agent.fleet.bridge_config import ZenohConfig
from agent.fleet.local_protocol import PoseMessage
from firmware_protocol.errors import ProtocolError

__all__ = ["FleetView", "RobotSeen"]


@dataclass
class RobotSeen:
    robot: str
    pose: PoseMessage | None = None
    status: payloads.RobotStatus | None = None
    poses: int = 0
    last_seen_s: float = 0.0
    silent_s: float = 0.0  # at the end of the listening window
    gone: bool = False  # silent for the view's stale_s

    @property
    def state(self) -> str:
        if self.gone:
            return "gone"
        return self.status.state if self.status is not None else "unknown"

    def as_dict(self) -> dict[str, Any]:
        p, s = self.pose, self.status
        return {
            "robot": self.robot,
            "pose": None
            if p is None
            else {
                "x_m": p.x_m,
                "y_m": p.y_m,
                "yaw_rad": p.yaw_rad,
                "sigma_xy_m": p.sigma_xy_m,
                "flags": p.flags,
            },
            "state": self.state,
            "silent_s": round(self.silent_s, 3),
            "status": None
            if s is None
            else {
                "pose_flags": s.pose_flags,
                "bits": s.bits,
                "agent": s.agent_connected,
                "counters": s.counters,
            },
            "poses_heard": self.poses,
        }


@dataclass
class FleetView:
    zenoh: ZenohConfig
    key_prefix: str = "fleet"
    stale_s: float = 2.0
    robots: dict[str, RobotSeen] = field(default_factory=dict)
    rejected: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def _on(self, kind: str, sample: Any) -> None:
        try:
            robot = payloads.robot_of(self.key_prefix, str(sample.key_expr))
            data = bytes(sample.payload.to_bytes())
            decoded = (
                payloads.decode_pose(data, robot) if kind == "pose" else payloads.decode_status(data, robot)
            )
        except ProtocolError:
            with self._lock:
                self.rejected += 1
            return
        with self._lock:
            seen = self.robots.setdefault(robot, RobotSeen(robot))
            seen.last_seen_s = time.monotonic()
            if isinstance(decoded, PoseMessage):
                seen.pose, seen.poses = decoded, seen.poses + 1
            else:
                seen.status = decoded

    def _handler(self, kind: str) -> Callable[[Any], None]:
        return lambda sample: self._on(kind, sample)

    def listen(self, seconds: float, stop: threading.Event | None = None) -> list[RobotSeen]:
        """Listen ``seconds`` (or until ``stop``); the robots heard, by name."""
        import zenoh

        session: Any = zenoh.open(self.zenoh.zenoh_config())
        try:
            subs: list[Any] = [
                session.declare_subscriber(f"{self.key_prefix}/*/{kind}", self._handler(kind))
                for kind in ("pose", "status")
            ]
            (stop or threading.Event()).wait(seconds)
            for sub in subs:
                sub.undeclare()
        finally:
            session.close()
        return self.seen(time.monotonic())

    def seen(self, now_s: float) -> list[RobotSeen]:
        """The robots heard, by name, each marked gone when silent for ``stale_s`` at ``now_s``."""
        with self._lock:
            for seen in self.robots.values():
                seen.silent_s = now_s - seen.last_seen_s
                seen.gone = seen.silent_s > self.stale_s
            return [self.robots[name] for name in sorted(self.robots)]
