"""The navigator: goal -> plan -> follow -> recover -> reached or failed (with a reason).

Pure and stepped: the caller passes time, the pose estimate and each scan; it gets velocity commands
back. Nothing here owns a thread, a clock or a device.

* :meth:`Navigator.on_scan` updates the costmap's obstacle layer and runs the collision monitor; the
  command it returns is to be sent at once (the monitor's stop, from the scan that shows the obstacle).
* :meth:`Navigator.step` (at the control rate) plans when there is no plan, when the map changed, and
  every ``replan_period_s`` when the costmap changed under the remaining path and blocks it; follows the
  path with the pure pursuit controller through the collision monitor; within ``xy_tolerance_m`` of
  the goal turns to its heading; reports REACHED within both tolerances.
* **Blocked** (no ``progress_m`` of way for ``blocked_timeout_s``, or no plan because of obstacles):
  a recovery round (wait, rotate, back up), then the obstacle layer is cleared and the goal replanned.
  After ``max_recoveries`` rounds the goal FAILS with why. A goal that cannot be reached on the map
  itself (in a wall, in unknown space, cut off) fails at once: it is reported, never retried forever.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from agent.navigation.collision import CollisionMonitor
from agent.navigation.config import NavConfig
from agent.navigation.controller import STOP, Command, PurePursuit, nearest_on_path, remaining_length, wrap
from agent.navigation.costmap import Costmap, FloatArray
from agent.navigation.give_way import aside_target, way_ahead_blocked
from agent.navigation.moving import MovingObstacles
from agent.navigation.planner import GlobalPlanner, Plan, PlanStatus, path_is_free
from agent.navigation.recovery import Recovery

# How far the planner looks for a free cell when the robot stands in a forbidden one (in a walker's way).
ESCAPE_M = 0.6
# Giving way to walkers (agent/navigation/give_way.py): how far ahead along the path a walker's sweep
# stops the robot at once; how far it steps aside out of a sweep that cuts the goal off; how often it
# tries the plan again while it waits; how long it waits before the blocked-goal recoveries take over.
WAY_AHEAD_M = 0.4
ASIDE_M = 1.0
GIVE_WAY_RETRY_S = 0.5
GIVE_WAY_MAX_S = 20.0
BACK_ASIDE_RAD = math.radians(60)  # a place aside this near straight behind is backed into


class NavStatus(enum.StrEnum):
    IDLE = "idle"
    ACTIVE = "active"
    RECOVERING = "recovering"
    REACHED = "reached"
    FAILED = "failed"


@dataclass(frozen=True)
class Goal:
    x_m: float
    y_m: float
    yaw_rad: float | None = None  # None: any heading
    allow_unknown: bool = False


@dataclass(frozen=True)
class NavOutput:
    command: Command
    status: NavStatus
    reason: str = ""


class Navigator:
    def __init__(
        self,
        config: NavConfig,
        costmap: Costmap,
        laser_mount: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> None:
        self.config = config
        self.costmap = costmap
        self.laser_mount = laser_mount
        self.planner = GlobalPlanner(config.clearance_weight, escape_m=ESCAPE_M)
        self.moving = MovingObstacles()
        self.controller = PurePursuit(config)
        self.monitor = CollisionMonitor(config, laser_mount)
        self.recovery = Recovery(config)
        self.goal: Goal | None = None
        self.status = NavStatus.IDLE
        self.reason = ""
        self.plan: Plan | None = None
        self.plans: list[Plan] = []  # every plan made for the current goal (for the statistics)
        self._t_goal = 0.0
        self._t_last = 0.0
        self._t_checked = -math.inf
        self._checked_version = -1
        self._best_to_go = math.inf
        self._t_progress = 0.0
        self._way_since_recovery = 0.0
        self._turning = False
        self._scans = 0
        self._await_scan = False
        self._giving_way_since: float | None = None  # waiting out a walker's way (no recovery counted)
        self._t_give_way_try = -math.inf
        self._aside: FloatArray | None = None
        self._t_aside = -math.inf
        self.give_ways = 0  # times it gave way to a walker (this goal)

    # -- inputs -------------------------------------------------------------------------------------
    def set_goal(self, goal: Goal, t_s: float) -> None:
        self.goal = goal
        self.status = NavStatus.ACTIVE
        self.reason = ""
        self.plan = None
        self.plans = []
        self.recovery.reset()
        self.planner.invalidate()
        self._t_goal = self._t_last = t_s
        self._t_checked = -math.inf
        self._best_to_go = math.inf
        self._t_progress = t_s
        self._turning = False
        self._giving_way_since = None
        self._aside = None
        self.give_ways = 0

    def cancel(self, reason: str = "cancelled") -> None:
        if self.status in (NavStatus.ACTIVE, NavStatus.RECOVERING):
            self.status, self.reason = NavStatus.FAILED, reason
        self.controller.reset()

    def on_scan(
        self,
        t_s: float,
        pose: tuple[float, float, float],
        angles_rad: FloatArray,
        ranges_m: FloatArray,
        min_range_m: float,
        max_range_m: float,
    ) -> Command:
        """A scan taken at ``pose`` (the base's estimated pose then): costmap and collision monitor. Send
        the returned command at once."""
        x, y, yaw = pose
        mx, my, myaw = self.laser_mount
        c, s = math.cos(yaw), math.sin(yaw)
        laser = (x + c * mx - s * my, y + s * mx + c * my, yaw + myaw)
        self.costmap.update_scan(laser, angles_rad, ranges_m, min_range_m, max_range_m)
        ranges = np.asarray(ranges_m, dtype=np.float64)
        hit = (ranges >= min_range_m) & (ranges <= max_range_m)
        theta = laser[2] + np.asarray(angles_rad, dtype=np.float64)[hit]
        points = np.stack(
            [laser[0] + ranges[hit] * np.cos(theta), laser[1] + ranges[hit] * np.sin(theta)], axis=1
        )
        self.moving.update(t_s, points, self.costmap.static_distance_m(), self.costmap.spec)
        self.costmap.set_predicted(self.moving.sweeps(self.costmap.spec))
        self._scans += 1
        self._await_scan = False
        command = self.monitor.on_scan(t_s, angles_rad, ranges_m, min_range_m, max_range_m)
        if command == STOP:
            self.controller.reset()
        return command

    # -- the control step ---------------------------------------------------------------------------
    def step(self, t_s: float, pose: tuple[float, float, float]) -> NavOutput:
        dt = max(t_s - self._t_last, 1e-3)
        self._t_last = t_s
        goal = self.goal
        if goal is None or self.status not in (NavStatus.ACTIVE, NavStatus.RECOVERING):
            self.controller.reset()
            return self._out(STOP)
        cfg = self.config
        if t_s - self._t_goal > cfg.goal_timeout_s:
            return self._fail(f"timed out after {cfg.goal_timeout_s:g} s")
        x, y, yaw = pose
        to_goal = math.hypot(goal.x_m - x, goal.y_m - y)
        # Final heading: latched once inside the tolerance, released if the robot drifts well out.
        if to_goal <= cfg.xy_tolerance_m or (self._turning and to_goal <= 2.0 * cfg.xy_tolerance_m):
            self._turning = True
            error = 0.0 if goal.yaw_rad is None else wrap(goal.yaw_rad - yaw)
            if abs(error) <= cfg.yaw_tolerance_rad:
                self.status = NavStatus.REACHED
                self.controller.reset()
                return self._out(STOP)
            return self._out(self.monitor.filter(self.controller.turn_to(error, dt)))
        self._turning = False
        # Standing where a walker is about to be: drop everything and get out of the way now.
        threatened = bool(self.costmap.predicted.any()) and not np.isfinite(
            self.costmap.cost_at(np.array([[x, y]]))[0]
        )
        if threatened and self._giving_way_since is None:
            self.recovery.abort()
            self.plan = None
            self._await_scan = False
            self._start_giving_way(t_s)
        if self.recovery.active:
            command = self.recovery.step(t_s, pose, not self.monitor.blocked(forward=False))
            if command is not None:
                self.controller.reset()
                return self._out(self.monitor.filter(command), NavStatus.RECOVERING)
            # The round is over: forget stale marks and replan from here, once a fresh scan has put back
            # what is really there (planning on the bare map would take the blocked way again).
            self.costmap.clear_obstacles()
            self.plan = None
            self._t_progress = t_s
            self._best_to_go = math.inf
            self._await_scan = self._scans > 0
        if self._await_scan:
            self.controller.reset()
            return self._out(STOP, NavStatus.RECOVERING)
        if self._giving_way_since is not None:
            waiting = self._give_way(t_s, pose, goal, dt)
            if waiting is not None:
                return waiting
        self.status = NavStatus.ACTIVE
        if not self._ensure_plan(t_s, pose, goal):
            return self._out(STOP, self.status)
        # A walker's way just ahead: stop outside it now and replan (behind them, or wait for them).
        if (
            self.plan is not None
            and self.costmap.predicted.any()
            and way_ahead_blocked(self.costmap, self.plan.path_m, (x, y), WAY_AHEAD_M, goal.allow_unknown)
        ):
            self.plan = None
            if not self._ensure_plan(t_s, pose, goal):
                self.controller.reset()
                return self._out(STOP, self.status)
        plan = self.plan
        assert plan is not None
        segment, fraction, _ = nearest_on_path(plan.path_m, (x, y))
        to_go = remaining_length(plan.path_m, segment, fraction)
        if to_go < self._best_to_go - cfg.progress_m:
            if math.isfinite(self._best_to_go):
                self._way_since_recovery += self._best_to_go - to_go
                self.recovery.progressed(self._way_since_recovery)
            self._best_to_go = to_go
            self._t_progress = t_s
        elif t_s - self._t_progress > cfg.blocked_timeout_s:
            why = "blocked ahead" if self.monitor.blocked() else "no progress"
            return self._recover(t_s, pose, why)
        command = self.controller.follow(pose, plan.path_m, dt)
        filtered = self.monitor.filter(command)
        if filtered != command:
            self.controller.reset(filtered)
        return self._out(filtered)

    # -- helpers -------------------------------------------------------------------------------------
    def _ensure_plan(self, t_s: float, pose: tuple[float, float, float], goal: Goal) -> bool:
        cfg = self.config
        need = self.plan is None
        if not need and t_s - self._t_checked >= cfg.replan_period_s:
            self._t_checked = t_s
            if self.costmap.version != self._checked_version:
                self._checked_version = self.costmap.version
                assert self.plan is not None
                segment, _, _ = nearest_on_path(self.plan.path_m, pose[:2])
                rest = np.vstack([np.array(pose[:2])[None, :], self.plan.path_m[segment + 1 :]])
                need = not path_is_free(self.costmap, rest, goal.allow_unknown)
        if not need:
            return True
        plan = self.planner.plan(self.costmap, pose[:2], (goal.x_m, goal.y_m), goal.allow_unknown)
        self.plans.append(plan)
        self._t_checked = t_s
        self._checked_version = self.costmap.version
        if plan.ok:
            # Progress is measured along the new path, from now (a detour is longer than the old way).
            self._best_to_go = math.inf
            self._t_progress = t_s
            self.plan = plan
            return True
        self.plan = None
        # Would it plan on the map alone? If not, no waiting helps: fail now with the planner's reason.
        static = Costmap(self.costmap.spec, self.costmap.static_occupied, self.costmap.unknown, cfg)
        alone = GlobalPlanner(cfg.clearance_weight).plan(
            static, pose[:2], (goal.x_m, goal.y_m), goal.allow_unknown
        )
        if not alone.ok:
            self._fail(f"{plan.status.value}: {alone.reason}")
            return False
        if self.costmap.predicted.any() and self._open_but_for_walkers(pose, goal):
            # Only a walker's way cuts the goal off: it passes; step out of it and wait, no recovery.
            self._start_giving_way(t_s)
            return False
        self._recover(t_s, pose, f"{plan.status.value} by obstacles ({plan.reason})")
        return False

    def _start_giving_way(self, t_s: float) -> None:
        self._giving_way_since = t_s
        self._t_give_way_try = t_s
        self._aside = None
        self.give_ways += 1
        self.status = NavStatus.RECOVERING
        self.controller.reset()

    def _open_but_for_walkers(self, pose: tuple[float, float, float], goal: Goal) -> bool:
        """Whether the goal plans on the map and the scanned obstacles without the walkers' sweeps."""
        cfg = self.config
        bare = Costmap(self.costmap.spec, self.costmap.static_occupied, self.costmap.unknown, cfg)
        bare.obstacles = self.costmap.obstacles.copy()
        plan = GlobalPlanner(cfg.clearance_weight, escape_m=ESCAPE_M).plan(
            bare, pose[:2], (goal.x_m, goal.y_m), goal.allow_unknown
        )
        return plan.ok

    def _give_way(
        self, t_s: float, pose: tuple[float, float, float], goal: Goal, dt: float
    ) -> NavOutput | None:
        """While a walker's way cuts the goal off: out of it, then wait; None once a plan is made."""
        assert self._giving_way_since is not None
        x, y, _ = pose
        here = np.array([[x, y]])
        in_sweep = not np.isfinite(self.costmap.cost_at(here, goal.allow_unknown)[0])
        if in_sweep and (self._aside is None or t_s - self._t_aside >= GIVE_WAY_RETRY_S):
            self._aside = aside_target(
                self.costmap,
                pose,
                ASIDE_M,
                goal.allow_unknown,
                ahead_ok=not self.monitor.blocked(),
                behind_ok=not self.monitor.blocked(forward=False),
            )
            self._t_aside = t_s
        # Standing in a walker's way, plan only when there is no way out of it (the planner's escape
        # would take the nearest cell towards the goal, maybe towards the walker).
        if (not in_sweep or self._aside is None) and t_s - self._t_give_way_try >= GIVE_WAY_RETRY_S:
            self._t_give_way_try = t_s
            plan = self.planner.plan(self.costmap, (x, y), (goal.x_m, goal.y_m), goal.allow_unknown)
            self.plans.append(plan)
            if plan.ok:
                self.plan = plan
                self._giving_way_since = None
                self._aside = None
                self._best_to_go = math.inf
                self._t_progress = t_s
                self._t_checked = t_s
                self._checked_version = self.costmap.version
                return None
        if t_s - self._giving_way_since > GIVE_WAY_MAX_S:
            self._giving_way_since = None
            self._aside = None
            return self._recover(t_s, pose, f"a walker's way cut the goal off for {GIVE_WAY_MAX_S:g} s")
        if not in_sweep:
            self._aside = None
            self.controller.reset()
            return self._out(STOP, NavStatus.RECOVERING)
        # Standing in their way: step to the nearest place out of it.
        if self._aside is None:
            self.controller.reset()
            return self._out(STOP, NavStatus.RECOVERING)
        ax, ay = float(self._aside[0]) - x, float(self._aside[1]) - y
        behind = wrap(math.atan2(ay, ax) - pose[2] - math.pi)
        if abs(behind) < BACK_ASIDE_RAD:
            # Behind the robot: back straight out (a turn first would leave it in the way for seconds).
            cfg = self.config
            backing = Command(-cfg.max_reverse_mps, max(-cfg.max_turn_radps, min(cfg.max_turn_radps, behind)))
            command = self.controller.limit(backing, dt)
        else:
            command = self.controller.follow(pose, np.vstack([here, self._aside[None, :]]), dt)
        filtered = self.monitor.filter(command)
        if filtered != command:
            self.controller.reset(filtered)
        return self._out(filtered, NavStatus.RECOVERING)

    def _recover(self, t_s: float, pose: tuple[float, float, float], why: str) -> NavOutput:
        if self.recovery.exhausted():
            return self._fail(self.recovery.reason(why))
        self.recovery.begin(t_s, pose, why)
        self._way_since_recovery = 0.0
        self.status = NavStatus.RECOVERING
        self.controller.reset()
        return self._out(STOP, NavStatus.RECOVERING)

    def _fail(self, reason: str) -> NavOutput:
        self.status = NavStatus.FAILED
        self.reason = reason
        self.controller.reset()
        return self._out(STOP)

    def _out(self, command: Command, status: NavStatus | None = None) -> NavOutput:
        if status is not None:
            self.status = status
        return NavOutput(command, self.status, self.reason)


__all__ = ["Goal", "NavOutput", "NavStatus", "Navigator", "PlanStatus"]
