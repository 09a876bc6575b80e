"""The collision monitor: the last word on every velocity command, from the raw laser scan alone.

Independent of the map, the localization and the planner (a person who steps out of a doorway is in
the scan before any of them knows), it acts on every scan and on every command:

* each beam's return is put in the base frame (the laser's mount);
* only returns on the way count: those within the footprint's width (plus 3 cm for an arc's swing),
  ahead of it when the command goes forward, behind it when it goes back, measured from the footprint
  circle's front (back) edge; a turn in place sweeps nothing a circle does not already cover;
* a return within ``stop_margin_m`` of the footprint on the way stops the robot (zero velocity);
  within ``slow_margin_m`` the speed is scaled down linearly from full to ``slow_speed_fraction`` at
  the stop zone's edge;
* :meth:`CollisionMonitor.on_scan` returns the command to send *now* (the scan's verdict applied to the
  command in force), so a stop takes effect on the scan that first shows the obstacle, not at the next
  control step; :meth:`CollisionMonitor.filter` applies the latest scan's verdict to each new command.

Vectorized over the beams: tens of microseconds for a 682-beam URG scan (``benchmarks/nav_bench.py``).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from agent.navigation.config import NavConfig
from agent.navigation.controller import STOP, Command
from agent.navigation.costmap import FloatArray

# How far beside the footprint's width a return still counts as on the way (an arc swings the front out).
LATERAL_MARGIN_M = 0.03


class Zone(enum.StrEnum):
    CLEAR = "clear"
    SLOW = "slow"
    STOP = "stop"


@dataclass(frozen=True)
class Verdict:
    """What one scan says: the nearest return's distance to the footprint ahead and behind (metres,
    ``inf`` when none), and the speed scale each way (0 = stop)."""

    ahead_m: float
    behind_m: float
    scale_forward: float
    scale_backward: float
    t_s: float

    def zone(self, forward: bool) -> Zone:
        scale = self.scale_forward if forward else self.scale_backward
        return Zone.STOP if scale == 0.0 else Zone.SLOW if scale < 1.0 else Zone.CLEAR


CLEAR = Verdict(math.inf, math.inf, 1.0, 1.0, -math.inf)


class CollisionMonitor:
    def __init__(self, config: NavConfig, laser_mount: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
        self.config = config
        self.laser_mount = laser_mount
        self.verdict = CLEAR
        self.command = STOP  # the command in force (after this monitor)
        self.stops = 0  # commands this monitor zeroed

    def assess(
        self, t_s: float, angles_rad: FloatArray, ranges_m: FloatArray, min_range_m: float, max_range_m: float
    ) -> Verdict:
        """The verdict of one scan (laser-frame beam angles, ranges; out of [min, max] is no return)."""
        cfg = self.config
        mx, my, myaw = self.laser_mount
        ranges = np.asarray(ranges_m, dtype=np.float64)
        valid = (ranges >= min_range_m) & (ranges <= max_range_m)
        r = ranges[valid]
        theta = np.asarray(angles_rad, dtype=np.float64)[valid] + myaw
        px = mx + r * np.cos(theta)
        py = my + r * np.sin(theta)
        # The zones are what the footprint sweeps going straight on: returns within the footprint's width
        # (plus a little for the arc's swing), measured from the footprint's front (or back) edge.
        radius = cfg.radius_m
        lateral = np.abs(py)
        on_way = lateral <= radius + LATERAL_MARGIN_M
        edge = np.sqrt(np.maximum(radius * radius - np.minimum(lateral, radius) ** 2, 0.0))
        ahead = (px - edge)[on_way & (px > 0.0)]
        behind = (-px - edge)[on_way & (px < 0.0)]
        ahead_m = float(ahead.min()) if ahead.size else math.inf
        behind_m = float(behind.min()) if behind.size else math.inf
        verdict = Verdict(ahead_m, behind_m, self._scale(ahead_m), self._scale(behind_m), t_s)
        self.verdict = verdict
        return verdict

    def _scale(self, gap_m: float) -> float:
        cfg = self.config
        if gap_m <= cfg.stop_margin_m:
            return 0.0
        if gap_m >= cfg.slow_margin_m:
            return 1.0
        w = (gap_m - cfg.stop_margin_m) / (cfg.slow_margin_m - cfg.stop_margin_m)
        return cfg.slow_speed_fraction + w * (1.0 - cfg.slow_speed_fraction)

    def filter(self, want: Command) -> Command:
        """``want`` as the latest scan allows it."""
        v = want.v_mps
        if v > 0.0:
            scale = self.verdict.scale_forward
        elif v < 0.0:
            scale = self.verdict.scale_backward
        else:
            scale = 1.0
        if scale == 0.0:
            out = STOP if v != 0.0 else want
            if v != 0.0:
                self.stops += 1
        else:
            out = Command(v * scale, want.omega_radps * scale if scale < 1.0 else want.omega_radps)
        self.command = out
        return out

    def on_scan(
        self, t_s: float, angles_rad: FloatArray, ranges_m: FloatArray, min_range_m: float, max_range_m: float
    ) -> Command:
        """Assess a scan and return the command in force as it allows it: send this at once."""
        self.assess(t_s, angles_rad, ranges_m, min_range_m, max_range_m)
        return self.filter(self.command)

    def blocked(self, forward: bool = True) -> bool:
        return (self.verdict.scale_forward if forward else self.verdict.scale_backward) == 0.0
