"""The navigation's settings: one frozen dataclass, read from the config file's ``[navigation]`` table by
``agent.config`` (the keys and how to tune them: ``docs/navigation.md``).

The defaults are for a TurtleBot3 burger (the simulated robot's default): 0.105 m footprint radius,
0.22 m/s top speed (its XL430 wheels top out at 6.6 rad/s x 0.033 m).
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class NavConfig:
    """Speed and acceleration limits, the footprint, the costmap's inflation, the collision monitor's
    zones, the recovery's bounds and the goal tolerances."""

    enabled: bool = True  # the agent drives goals when it has SLAM, a laser, wheels and a command line
    # the robot
    radius_m: float = 0.105  # footprint circle
    track_m: float = 0.160  # wheel separation: wheel speeds are v -+ omega track / 2
    max_wheel_speed_mps: float = 0.2178  # per wheel, at the rim (6.6 rad/s x 0.033 m)
    max_speed_mps: float = 0.20  # forward
    max_reverse_mps: float = 0.10  # backing up (recovery only)
    max_turn_radps: float = 1.5
    max_accel_mps2: float = 0.5
    max_turn_accel_radps2: float = 3.0
    # the costmap
    resolution_m: float = 0.05
    inflation_radius_m: float = 0.45  # beyond the footprint the cost falls to zero here
    cost_scaling: float = 6.0  # cost = exp(-cost_scaling (d - radius)) between the two
    safety_margin_m: float = 0.02  # cells closer than radius + this to an obstacle are forbidden
    obstacle_max_range_m: float = 4.0  # scans mark and clear the obstacle layer out to this range
    allow_unknown: bool = False  # plan through unknown cells (per goal: Goal.allow_unknown)
    # the global planner
    clearance_weight: float = 2.0  # edge cost = length (1 + weight cost): how far paths keep off walls
    replan_period_s: float = 1.0  # how often the remaining path is checked against the costmap
    # the local controller (regulated pure pursuit)
    lookahead_min_m: float = 0.25
    lookahead_max_m: float = 0.6
    lookahead_time_s: float = 1.5  # lookahead = speed x this, within the two bounds
    rotate_to_heading_rad: float = math.radians(50.0)  # turn in place first when the path is this far off
    regulated_radius_m: float = 0.6  # slow down on curves tighter than this radius
    min_approach_speed_mps: float = 0.03
    # the collision monitor
    stop_margin_m: float = 0.08  # an obstacle this close to the footprint, on the way, stops the robot
    slow_margin_m: float = 0.30  # ... this close slows it down, linearly to the stop zone
    slow_speed_fraction: float = 0.3  # the speed left at the stop zone's edge
    # recovery
    blocked_timeout_s: float = 5.0  # no progress for this long means blocked
    progress_m: float = 0.05  # progress: this much closer along the path
    wait_s: float = 2.0
    rotate_rad: float = math.pi / 2.0
    backup_m: float = 0.15
    max_recoveries: int = 4  # recovery rounds before the goal fails
    # goals
    xy_tolerance_m: float = 0.05
    yaw_tolerance_rad: float = math.radians(2.0)
    goal_timeout_s: float = 600.0

    @property
    def inscribed_m(self) -> float:
        """Cells nearer an obstacle than this are forbidden to the robot's centre."""
        return self.radius_m + self.safety_margin_m
