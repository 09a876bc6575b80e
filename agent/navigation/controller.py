"""The local controller: regulated pure pursuit for a differential drive.

Why pure pursuit and not a DWA: the global path is already clearance-aware and smoothed on the live
costmap, and the collision monitor stops for whatever the costmap has not caught yet, so the local
controller's job is to track that path exactly, smoothly and predictably, which pure pursuit does with
no sampling (microseconds per step, deterministic, nothing to tune per environment). A DWA scores
hundreds of sampled arcs against the costmap every step and trades path fidelity for obstacle terms
the planner already paid. The "regulated" part (Macenski et al., 2023, Nav2's RPP) slows the robot on
tight curves and as it approaches the goal.

Per step, with the robot at pose (x, y, yaw) and the path as a polyline:

* the lookahead point is where the path, from the robot's nearest point on it, has run
  ``L = clamp(v t_L, L_min, L_max)`` farther;
* if it lies more than ``rotate_to_heading_rad`` off the heading the robot turns in place towards it;
* else the arc through it has curvature kappa = 2 y_r / L^2 (y_r its lateral offset in the robot's
  frame), v = v_max regulated by min(1, R_reg |kappa|^-1) on curves and by sqrt(2 a d) to stop at the
  path's end, omega = v kappa;
* within ``xy_tolerance_m`` of the end it turns in place to the goal's heading, with a deceleration
  profile omega = sqrt(2 alpha |e|) so it stops on the heading rather than oscillating across it;
* every command is limited to the robot's speeds, accelerations (against the previous command) and
  wheel speeds (|v| + |omega| track / 2 <= the wheels' top speed, scaled down keeping the curvature).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from agent.navigation.config import NavConfig
from agent.navigation.costmap import FloatArray


def wrap(angle_rad: float) -> float:
    return math.atan2(math.sin(angle_rad), math.cos(angle_rad))


@dataclass(frozen=True)
class Command:
    v_mps: float
    omega_radps: float


STOP = Command(0.0, 0.0)


def nearest_on_path(path_m: FloatArray, xy: tuple[float, float]) -> tuple[int, float, float]:
    """(segment index, fraction along it, distance) of the point of the polyline nearest ``xy``."""
    a = path_m[:-1]
    d = path_m[1:] - a
    p = np.asarray(xy, dtype=np.float64)
    len2 = np.maximum(np.sum(d * d, axis=1), 1e-12)
    t = np.clip(np.sum((p - a) * d, axis=1) / len2, 0.0, 1.0)
    q = a + t[:, None] * d
    dist = np.hypot(*(q - p).T)
    i = int(np.argmin(dist))
    return i, float(t[i]), float(dist[i])


def remaining_length(path_m: FloatArray, segment: int, fraction: float) -> float:
    seg = np.hypot(*np.diff(path_m, axis=0).T)
    return float(seg[segment] * (1.0 - fraction) + seg[segment + 1 :].sum())


def point_ahead(path_m: FloatArray, segment: int, fraction: float, distance_m: float) -> FloatArray:
    """The point ``distance_m`` along the path from (segment, fraction); the end if the path is shorter."""
    seg = np.hypot(*np.diff(path_m, axis=0).T)
    left = distance_m + seg[segment] * fraction
    for i in range(segment, len(seg)):
        if left <= seg[i] or i == len(seg) - 1:
            w = min(left / seg[i], 1.0) if seg[i] > 0 else 1.0
            out: FloatArray = path_m[i] + w * (path_m[i + 1] - path_m[i])
            return out
        left -= seg[i]
    last: FloatArray = path_m[-1].copy()
    return last


class PurePursuit:
    """Regulated pure pursuit (see the module docstring). Keeps the last command for the acceleration
    limits; :meth:`reset` when the robot was stopped by someone else."""

    def __init__(self, config: NavConfig) -> None:
        self.config = config
        self.last = STOP

    def reset(self, current: Command = STOP) -> None:
        self.last = current

    def limit(self, want: Command, dt_s: float) -> Command:
        """``want`` within the speed, acceleration and wheel limits, from the last command."""
        cfg = self.config
        v = min(max(want.v_mps, -cfg.max_reverse_mps), cfg.max_speed_mps)
        w = min(max(want.omega_radps, -cfg.max_turn_radps), cfg.max_turn_radps)
        dv = cfg.max_accel_mps2 * dt_s
        dw = cfg.max_turn_accel_radps2 * dt_s
        v = min(max(v, self.last.v_mps - dv), self.last.v_mps + dv)
        w = min(max(w, self.last.omega_radps - dw), self.last.omega_radps + dw)
        wheel = abs(v) + abs(w) * cfg.track_m / 2.0
        if wheel > cfg.max_wheel_speed_mps:
            scale = cfg.max_wheel_speed_mps / wheel
            v, w = v * scale, w * scale
        self.last = Command(v, w)
        return self.last

    def turn_to(self, heading_error_rad: float, dt_s: float) -> Command:
        """Turn in place, decelerating to stop on the heading."""
        cfg = self.config
        speed = min(
            cfg.max_turn_radps, math.sqrt(2.0 * cfg.max_turn_accel_radps2 * 0.5 * abs(heading_error_rad))
        )
        return self.limit(Command(0.0, math.copysign(speed, heading_error_rad)), dt_s)

    def follow(self, pose: tuple[float, float, float], path_m: FloatArray, dt_s: float) -> Command:
        """The command towards the path's end (the final heading is :meth:`turn_to`'s)."""
        cfg = self.config
        x, y, yaw = pose
        if len(path_m) < 2:
            return self.limit(STOP, dt_s)
        segment, fraction, _ = nearest_on_path(path_m, (x, y))
        to_go = remaining_length(path_m, segment, fraction)
        goal = path_m[-1]
        to_goal = math.hypot(float(goal[0]) - x, float(goal[1]) - y)
        speed = max(abs(self.last.v_mps), cfg.min_approach_speed_mps)
        lookahead = min(max(speed * cfg.lookahead_time_s, cfg.lookahead_min_m), cfg.lookahead_max_m)
        target = point_ahead(path_m, segment, fraction, lookahead)
        dx, dy = float(target[0]) - x, float(target[1]) - y
        c, s = math.cos(yaw), math.sin(yaw)
        x_r, y_r = c * dx + s * dy, -s * dx + c * dy
        distance = math.hypot(x_r, y_r)
        bearing = math.atan2(y_r, x_r)
        if distance > 1e-6 and abs(bearing) > cfg.rotate_to_heading_rad:
            return self.turn_to(bearing, dt_s)
        if distance < 1e-6:
            return self.limit(STOP, dt_s)
        curvature = 2.0 * y_r / (distance * distance)
        v = cfg.max_speed_mps
        if abs(curvature) > 1.0 / cfg.regulated_radius_m:
            v *= 1.0 / (cfg.regulated_radius_m * abs(curvature))
        # Stop at the end: v <= sqrt(2 a d), with the remaining path (and the straight line near the end).
        stop_v = math.sqrt(2.0 * cfg.max_accel_mps2 * 0.8 * max(min(to_go, to_goal + 0.02), 0.0))
        v = max(min(v, stop_v), cfg.min_approach_speed_mps)
        return self.limit(Command(v, v * curvature), dt_s)
