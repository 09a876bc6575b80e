"""The navigation loop: the goal in force driven through ``agent.navigation`` on the live SLAM map.

Three entries, from three threads, one lock:

* :meth:`NavigationLoop.on_map` (the SLAM loop, every ``map_period_s``): the SLAM occupancy grid becomes the
  costmap's static layer (a new costmap when the grid's geometry changes).
* :meth:`NavigationLoop.on_scan` (the laser loop, every scan): the costmap's obstacle layer and the
  collision monitor. When the monitor says stop while the base drives a goal or a controller velocity,
  zero goes to the wheels' dead-man at once, from the scan that shows the obstacle, not at the next step.
* :meth:`NavigationLoop.__call__` (the command loop's drive step, every poll while a goal is in force):
  a new goal is given to the navigator; every ``step_period_s`` it steps (plan, pure pursuit through the
  collision monitor, recovery) on the fused pose, and its velocity goes to the wheels. REACHED and FAILED
  end the goal at the arbiter and go back to the controller as goal statuses; while driving, an ACTIVE
  status with the remaining distance every ``progress_period_s``.

A goal is checked when it arrives (:meth:`check_goal`, the arbiter's ``check_goal``): no map or no pose
yet (NOT_LOCALIZED), outside the map (OUTSIDE_MAP), in or too near an obstacle (IN_OBSTACLE), in unknown
space without the goal's leave (UNREACHABLE), or no way there on the map (UNREACHABLE).
"""

from __future__ import annotations

import collections
import logging
import math
import threading
from collections.abc import Callable

import numpy as np

from agent.navigation.config import NavConfig
from agent.navigation.controller import STOP, Command, nearest_on_path, remaining_length
from agent.navigation.costmap import Costmap, FloatArray, GridSpec
from agent.navigation.fleet_layer import disc_cells
from agent.navigation.navigator import Goal, Navigator, NavStatus
from agent.navigation.planner import PlanStatus
from agent.runtime.arbiter import CommandArbiter, Directive
from agent.runtime.motion import DriveCommand
from agent.slam.render import OCCUPIED_VALUE, UNKNOWN_VALUE, OccupancyImage
from drivers.samples import Scan
from firmware_protocol.command_frame import CommandType, GoalCommand, GoalReason, GoalState, GoalStatus

__all__ = ["NavigationLoop", "failure_reason", "static_layers"]

log = logging.getLogger(__name__)

Pose = tuple[float, float, float]


def static_layers(image: OccupancyImage) -> tuple[GridSpec, np.ndarray, np.ndarray]:
    """A map_server image as the costmap's grid: rows along +y (the image's row 0 is the top)."""
    pixels = np.flipud(image.pixels)
    spec = GridSpec(
        (image.origin[0], image.origin[1]), image.resolution_m, (int(pixels.shape[0]), int(pixels.shape[1]))
    )
    return spec, pixels == OCCUPIED_VALUE, pixels == UNKNOWN_VALUE


def failure_reason(text: str) -> GoalReason:
    """The goal-status reason for the navigator's failure text."""
    if text.startswith("timed out"):
        return GoalReason.TIMEOUT
    if text.startswith((PlanStatus.GOAL_BLOCKED.value, PlanStatus.START_BLOCKED.value)):
        return GoalReason.IN_OBSTACLE
    if text.startswith(PlanStatus.UNREACHABLE.value):
        return GoalReason.UNREACHABLE
    return GoalReason.BLOCKED


class NavigationLoop:
    def __init__(
        self,
        config: NavConfig,
        laser_mount: Pose,
        drive: DriveCommand,
        arbiter: CommandArbiter,
        answer: Callable[[GoalStatus, CommandType | None], None],
        pose: Callable[[], Pose | None],
        clock_ns: Callable[[], int],
        *,
        step_period_s: float = 0.05,
        progress_period_s: float = 1.0,
    ) -> None:
        self.config = config
        self.laser_mount = laser_mount
        self.drive = drive
        self.arbiter = arbiter
        self.answer = answer
        self.pose = pose
        self.clock_ns = clock_ns
        self.step_period_s = step_period_s
        self.progress_period_s = progress_period_s
        self.navigator: Navigator | None = None
        self.counts: collections.Counter[str] = collections.Counter()
        self._lock = threading.Lock()
        self._goal: GoalCommand | None = None
        self._last_step_s = -math.inf
        self._last_progress_s = -math.inf
        self._driving_until_s = -math.inf  # a goal or a velocity drove the base up to then
        # The other robots as discs (x, y, radius) in the map frame (``FleetLoop.obstacles``); None: no
        # fleet. Put on the costmap's fleet layer before each step.
        self.others: Callable[[], list[tuple[float, float, float]]] | None = None

    # -- the map and the scans ----------------------------------------------------------------------

    def on_map(self, image: OccupancyImage) -> None:
        spec, occupied, unknown = static_layers(image)
        with self._lock:
            nav = self.navigator
            if nav is not None and nav.costmap.spec == spec:
                nav.costmap.set_static(occupied, unknown)
                return
            self.navigator = Navigator(
                self.config, Costmap(spec, occupied, unknown, self.config), self.laser_mount
            )
            self.counts["costmaps"] += 1
            if self._goal is not None:
                self._start(self._goal, self.clock_ns() * 1e-9)

    def obstacle_points(self) -> FloatArray | None:
        """The cells the scans mark occupied now (the costmap's obstacle layer), their centres in metres;
        None before the first map. The explorer's evidence that a passage was shut (a door closed)."""
        with self._lock:
            nav = self.navigator
            if nav is None:
                return None
            cells = np.argwhere(nav.costmap.obstacles)
            return nav.costmap.spec.to_world(cells)

    def on_scan(self, scan: Scan) -> None:
        pose = self.pose()
        with self._lock:
            nav = self.navigator
            if nav is None or pose is None:
                return
            ranges = scan.ranges_mm.astype(np.float64) / 1000.0
            command = nav.on_scan(
                scan.host_time_ns * 1e-9,
                pose,
                scan.angles_rad(),
                ranges,
                scan.min_range_mm / 1000.0,
                scan.max_range_mm / 1000.0,
            )
            self.counts["scans"] += 1
            now_ns = self.clock_ns()
            if command == STOP and now_ns * 1e-9 <= self._driving_until_s:
                self.drive.set(0.0, 0.0, now_ns)
                self.counts["collision_stops"] += 1

    # -- goals --------------------------------------------------------------------------------------

    def check_goal(self, goal: GoalCommand) -> GoalReason | None:
        pose = self.pose()
        with self._lock:
            nav = self.navigator
            if nav is None or pose is None:
                return GoalReason.NOT_LOCALIZED
            costmap = nav.costmap
            xy = np.array([[goal.x_m, goal.y_m]])
            if not costmap.spec.inside(costmap.spec.to_cell(xy))[0]:
                return GoalReason.OUTSIDE_MAP
            allow = goal.allow_unknown or self.config.allow_unknown
            if not math.isfinite(float(costmap.cost_at(xy, allow_unknown=True)[0])):
                return GoalReason.IN_OBSTACLE
            if not math.isfinite(float(costmap.cost_at(xy, allow_unknown=allow)[0])):
                return GoalReason.UNREACHABLE  # in unknown space, and the goal did not allow it
            plan = nav.planner.plan(costmap, pose[:2], (goal.x_m, goal.y_m), allow)
            if plan.status is PlanStatus.GOAL_BLOCKED:
                return GoalReason.IN_OBSTACLE
            if plan.status is PlanStatus.UNREACHABLE:
                return GoalReason.UNREACHABLE
            return None

    def _start(self, goal: GoalCommand, t_s: float) -> None:
        assert self.navigator is not None
        self.navigator.set_goal(Goal(goal.x_m, goal.y_m, goal.yaw_rad, goal.allow_unknown), t_s)
        self._last_progress_s = -math.inf

    def guard(self, v_mps: float, omega_radps: float, t_s: float) -> tuple[float, float]:
        """A controller's velocity through the collision monitor (``drive_loop.Guard``)."""
        with self._lock:
            self._driving_until_s = t_s + 2 * self.step_period_s
            nav = self.navigator
            if nav is None:
                return v_mps, omega_radps
            command = nav.monitor.filter(Command(v_mps, omega_radps))
            return command.v_mps, command.omega_radps

    def __call__(self, directive: Directive, t_s: float) -> None:
        goal = directive.goal
        if goal is None:
            return
        with self._lock:
            nav = self.navigator
            if goal is not self._goal:
                self._goal = goal
                self.counts["goals"] += 1
                if nav is not None:
                    self._start(goal, t_s)
            if nav is None or t_s - self._last_step_s < self.step_period_s:
                return
            self._last_step_s = t_s
            pose = self.pose()
            now_ns = self.clock_ns()
            if pose is None:
                self.drive.set(0.0, 0.0, now_ns)
                return
            if self.others is not None:
                nav.costmap.set_fleet(disc_cells(nav.costmap.spec, self.others()))
            out = nav.step(t_s, pose)
            self.drive.set(out.command.v_mps, out.command.omega_radps, now_ns)
            self._driving_until_s = t_s + 2 * self.step_period_s
            remaining = self._remaining_m(nav, pose)
        if out.status is NavStatus.REACHED:
            self._end(goal, GoalState.REACHED, GoalReason.NONE)
        elif out.status is NavStatus.FAILED:
            log.warning("goal %d failed: %s", goal.goal_id, out.reason)
            self._end(goal, GoalState.FAILED, failure_reason(out.reason))
        elif t_s - self._last_progress_s >= self.progress_period_s:
            self._last_progress_s = t_s
            status = self.arbiter.goal_progress(goal.goal_id, remaining)
            if status is not None:
                self.answer(status, CommandType.GOAL)

    def _end(self, goal: GoalCommand, state: GoalState, reason: GoalReason) -> None:
        self.counts[f"goals_{state.name.lower()}"] += 1
        with self._lock:
            self._goal = None
        status = self.arbiter.goal_finished(goal.goal_id, state, reason)
        if status is not None:
            self.answer(status, CommandType.GOAL)

    @staticmethod
    def _remaining_m(nav: Navigator, pose: Pose) -> float | None:
        plan = nav.plan
        if plan is None or len(plan.path_m) < 2:
            return None
        segment, fraction, _ = nearest_on_path(plan.path_m, pose[:2])
        return float(remaining_length(plan.path_m, segment, fraction))
