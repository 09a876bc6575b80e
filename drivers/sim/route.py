"""A pure-pursuit route follower: the simulated robot's autopilot when nothing else commands it."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass
class RouteFollower:
    """Drives a looped list of waypoints at ``speed_mps``; returns (v m/s, omega rad/s) commands."""

    waypoints: tuple[tuple[float, float], ...]
    speed_mps: float = 0.2
    lookahead_m: float = 0.3
    max_omega_radps: float = 2.0
    reach_m: float = 0.15
    index: int = 0

    def command(self, x_m: float, y_m: float, yaw_rad: float) -> tuple[float, float]:
        if not self.waypoints:
            return 0.0, 0.0
        tx, ty = self.waypoints[self.index]
        if math.hypot(tx - x_m, ty - y_m) < self.reach_m:
            self.index = (self.index + 1) % len(self.waypoints)
            tx, ty = self.waypoints[self.index]
        bearing = math.atan2(ty - y_m, tx - x_m)
        err = math.atan2(math.sin(bearing - yaw_rad), math.cos(bearing - yaw_rad))
        # Turn in place when facing away; pure pursuit curvature kappa = 2 sin(alpha) / L otherwise.
        if abs(err) > math.radians(60):
            return 0.0, math.copysign(self.max_omega_radps * 0.5, err)
        v = self.speed_mps * max(0.2, math.cos(err))
        omega = v * 2.0 * math.sin(err) / self.lookahead_m
        return v, max(-self.max_omega_radps, min(self.max_omega_radps, omega))
