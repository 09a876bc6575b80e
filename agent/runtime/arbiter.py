"""The command arbiter: which one command source drives the base now, and the goal status of each answer.

Sources, by precedence (``docs/navigation.md``)::

    controller velocity  >  controller goal | following  >  fleet goal | local mission goal (explore, ...)

* A **velocity** command is in force for its own timeout; it preempts any goal (the goal is CANCELLED,
  SUPERSEDED) and is clamped to the base's limits (ACCEPTED with CLAMPED). When it expires the base
  stops (the dead-man) and a lower source may drive again only after a new goal is given.
* A **goal** from the controller is checked first (``check_goal``: outside the map, inside an obstacle,
  unreachable...) and rejected with the reason, or ACCEPTED; it replaces the goal before it (CANCELLED,
  SUPERSEDED). While a controller velocity is in force a goal is REJECTED, BUSY.
* A **mission goal** drives only while the controller drives nothing; a controller goal cancels it.
* A **fleet goal** (``vlp-agent fleet goal``, through the bridge: :meth:`CommandArbiter.fleet_goal`)
  ranks with the missions, under the controller: REJECTED, BUSY while a controller velocity or goal is
  in force or a local mission drives (the robot's own operator started it); REJECTED, STOPPED while a
  stop holds; checked as a controller goal; it replaces an earlier fleet goal (CANCELLED, SUPERSEDED) and
  is itself cancelled (SUPERSEDED) by any controller velocity or goal, and (STOPPED) by a stop. A mission
  goal is REJECTED, BUSY while a fleet goal is in force. It never drives past the dead-man: the base
  moves through the same navigator and wheels' dead-man as every goal.
* **Following** (the controller's follow command, or ``vlp-agent run --follow`` at start-up) ranks with the
  controller's goal, and the newer of the two wins: a follow start is REJECTED, BUSY while a controller
  velocity is in force, REJECTED, STOPPED while a stop holds, REJECTED with ``check_follow``'s reason when
  the agent cannot follow (FOLLOW_UNAVAILABLE, NO_TAG_READER); else ACCEPTED, and it cancels (SUPERSEDED)
  any goal in force (controller, fleet, mission) and an earlier following. It ends (a status CANCELLED with
  the follow id) by a follow stop or a cancel naming it (or NO_GOAL) (reason NONE), a controller goal or
  velocity (SUPERSEDED), a stop (STOPPED). Mission and fleet goals are REJECTED, BUSY while it is on. The
  follow loop drives the base while it is on (``DriveSource.FOLLOW``); its ACTIVE statuses
  (:meth:`CommandArbiter.follow_status`) say how it goes.
* **Stop** holds the base at zero and cancels everything until **resume**; commands in between are
  REJECTED, STOPPED.

Every command gets exactly one answer; a frame that could not be read gets a REJECTED answer too. The
arbiter decides and keeps state only: it sends nothing and moves nothing (the command loop writes the
answers, the navigation loop asks :meth:`CommandArbiter.directive` what to do). Thread-safe.
"""

from __future__ import annotations

import enum
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass

from firmware_protocol.command_frame import (
    NO_GOAL,
    NO_SEQUENCE,
    CancelCommand,
    Command,
    CommandFrameError,
    ExploreCommand,
    FollowAction,
    FollowCommand,
    GoalCommand,
    GoalReason,
    GoalState,
    GoalStatus,
    PlaceCommand,
    ResumeCommand,
    StopCommand,
    VelocityCommand,
)

__all__ = ["STARTUP_FOLLOW_ID", "CommandArbiter", "Directive", "DriveSource"]

STARTUP_FOLLOW_ID = 0  # the follow id of the following ``vlp-agent run --follow`` starts


class DriveSource(enum.Enum):
    NONE = "none"  # nothing commands the base: zero
    STOPPED = "stopped"  # a stop command holds it: zero
    VELOCITY = "velocity"  # the controller's velocity
    GOAL = "goal"  # the controller's goal, through the navigator
    MISSION = "mission"  # a local mission's goal, through the navigator
    FLEET = "fleet"  # a goal from the fleet (the bridge), through the navigator
    FOLLOW = "follow"  # following a person: the follow loop's velocity


@dataclass(frozen=True, slots=True)
class Directive:
    """What drives the base now: a velocity (``v_mps``, ``omega_radps``) or a goal for the navigator."""

    source: DriveSource
    v_mps: float = 0.0
    omega_radps: float = 0.0
    goal: GoalCommand | None = None


_BAD_FRAME_REASONS = {
    "type": GoalReason.UNKNOWN_TYPE,
    "version": GoalReason.BAD_VERSION,
    "value": GoalReason.BAD_VALUE,
}


class CommandArbiter:
    """One command source at a time; answers every command with a :class:`GoalStatus`."""

    def __init__(
        self,
        max_speed_mps: float,
        max_turn_radps: float,
        check_goal: Callable[[GoalCommand], GoalReason | None] | None = None,
        check_follow: Callable[[FollowCommand], GoalReason | None] | None = None,
    ) -> None:
        self.max_speed_mps = max_speed_mps
        self.max_turn_radps = max_turn_radps
        self._check_goal = check_goal or (lambda goal: None)
        # Without a follow loop there is nothing to follow with: every follow start is refused.
        self.check_follow: Callable[[FollowCommand], GoalReason | None] = check_follow or (
            lambda follow: GoalReason.FOLLOW_UNAVAILABLE
        )
        self._lock = threading.Lock()
        self._sequence = 0
        self._stopped = False
        self._velocity: tuple[VelocityCommand, float, float, float] | None = None  # cmd, v, w, until_s
        self._goal: GoalCommand | None = None
        self._mission: GoalCommand | None = None
        self._fleet: GoalCommand | None = None
        self._follow: FollowCommand | None = None
        self.counts: dict[str, int] = {}

    # -- answers -------------------------------------------------------------------------------------

    def _status(
        self,
        command_sequence: int,
        goal_id: int,
        state: GoalState,
        reason: GoalReason = GoalReason.NONE,
        remaining_m: float | None = None,
    ) -> GoalStatus:
        self._sequence = (self._sequence + 1) & 0xFFFF
        key = (
            state.name.lower() if reason is GoalReason.NONE else f"{state.name.lower()}_{reason.name.lower()}"
        )
        self.counts[key] = self.counts.get(key, 0) + 1
        return GoalStatus(self._sequence, command_sequence, goal_id, state, reason, remaining_m)

    def bad_frame(self, error: CommandFrameError) -> GoalStatus:
        """The answer to a frame that could not be read: its sequence is not to be trusted."""
        with self._lock:
            reason = _BAD_FRAME_REASONS.get(error.kind, GoalReason.BAD_FRAME)
            return self._status(NO_SEQUENCE, NO_GOAL, GoalState.REJECTED, reason)

    # -- commands ------------------------------------------------------------------------------------

    def command(self, command: Command, now_s: float) -> list[GoalStatus]:
        """Take one command; the statuses to send back, the command's own answer first."""
        with self._lock:
            self._expire(now_s)
            if isinstance(command, StopCommand):
                return self._stop(command)
            if isinstance(command, ResumeCommand):
                self._stopped = False
                return [self._status(command.sequence, NO_GOAL, GoalState.ACCEPTED)]
            if isinstance(command, CancelCommand):
                return self._cancel(command)
            if isinstance(command, FollowCommand) and command.action == FollowAction.STOP:
                return self._end_following(command)
            if self._stopped:
                goal_id = NO_GOAL
                if isinstance(command, GoalCommand):
                    goal_id = command.goal_id
                elif isinstance(command, FollowCommand):
                    goal_id = command.follow_id
                return [self._status(command.sequence, goal_id, GoalState.REJECTED, GoalReason.STOPPED)]
            if isinstance(command, VelocityCommand):
                return self._take_velocity(command, now_s)
            if isinstance(command, (ExploreCommand, PlaceCommand)):
                # Missions are the mission loop's (the command loop routes them there); without one:
                return [
                    self._status(
                        command.sequence, command.mission_id, GoalState.REJECTED, GoalReason.UNKNOWN_TYPE
                    )
                ]
            if isinstance(command, FollowCommand):
                return self._take_following(command)
            return self._take_goal(command)

    def _stop(self, command: StopCommand) -> list[GoalStatus]:
        out = [self._status(command.sequence, NO_GOAL, GoalState.ACCEPTED)]
        self._stopped = True
        self._velocity = None
        out += self._drop_goals(GoalReason.STOPPED)
        return out

    def _take_following(self, command: FollowCommand) -> list[GoalStatus]:
        if self._velocity is not None:
            return [self._status(command.sequence, command.follow_id, GoalState.REJECTED, GoalReason.BUSY)]
        reason = self.check_follow(command)
        if reason is not None:
            return [self._status(command.sequence, command.follow_id, GoalState.REJECTED, reason)]
        out = [self._status(command.sequence, command.follow_id, GoalState.ACCEPTED)]
        out += self._drop_goals(GoalReason.SUPERSEDED)
        self._follow = command
        return out

    def _end_following(self, command: FollowCommand) -> list[GoalStatus]:
        active = self._follow
        if active is None or command.follow_id not in (NO_GOAL, active.follow_id):
            return [
                self._status(command.sequence, command.follow_id, GoalState.REJECTED, GoalReason.UNKNOWN_GOAL)
            ]
        self._follow = None
        return [self._status(command.sequence, active.follow_id, GoalState.CANCELLED)]

    def _cancel(self, command: CancelCommand) -> list[GoalStatus]:
        if self._follow is not None and command.goal_id in (NO_GOAL, self._follow.follow_id):
            follow, self._follow = self._follow, None
            return [self._status(command.sequence, follow.follow_id, GoalState.CANCELLED)]
        active = self._goal or self._fleet or self._mission
        if active is None or command.goal_id not in (NO_GOAL, active.goal_id):
            return [
                self._status(command.sequence, command.goal_id, GoalState.REJECTED, GoalReason.UNKNOWN_GOAL)
            ]
        if active is self._goal:
            self._goal = None
        elif active is self._fleet:
            self._fleet = None
        else:
            self._mission = None
        return [self._status(command.sequence, active.goal_id, GoalState.CANCELLED)]

    def _take_velocity(self, command: VelocityCommand, now_s: float) -> list[GoalStatus]:
        values = (command.v_mps, command.omega_radps, command.timeout_s)
        if not all(math.isfinite(x) for x in values) or command.timeout_s <= 0:
            return [self._status(command.sequence, NO_GOAL, GoalState.REJECTED, GoalReason.BAD_VALUE)]
        v = min(max(command.v_mps, -self.max_speed_mps), self.max_speed_mps)
        w = min(max(command.omega_radps, -self.max_turn_radps), self.max_turn_radps)
        reason = GoalReason.CLAMPED if (v, w) != (command.v_mps, command.omega_radps) else GoalReason.NONE
        out = [self._status(command.sequence, NO_GOAL, GoalState.ACCEPTED, reason)]
        out += self._drop_goals(GoalReason.SUPERSEDED)
        self._velocity = (command, v, w, now_s + command.timeout_s)
        return out

    def _take_goal(self, command: GoalCommand) -> list[GoalStatus]:
        if self._velocity is not None:
            return [self._status(command.sequence, command.goal_id, GoalState.REJECTED, GoalReason.BUSY)]
        fields = (command.x_m, command.y_m, command.tolerance_xy_m, command.tolerance_yaw_rad)
        if not all(math.isfinite(x) for x in fields) or (
            command.yaw_rad is not None and not math.isfinite(command.yaw_rad)
        ):
            return [self._status(command.sequence, command.goal_id, GoalState.REJECTED, GoalReason.BAD_VALUE)]
        reason = self._check_goal(command)
        if reason is not None:
            return [self._status(command.sequence, command.goal_id, GoalState.REJECTED, reason)]
        out = [self._status(command.sequence, command.goal_id, GoalState.ACCEPTED)]
        out += self._drop_goals(GoalReason.SUPERSEDED)
        self._goal = command
        return out

    def _drop_goals(self, reason: GoalReason) -> list[GoalStatus]:
        """End every goal and the following in force, each with a CANCELLED status of ``reason``."""
        out = []
        for goal in (self._goal, self._fleet, self._mission):
            if goal is not None:
                out.append(self._status(NO_SEQUENCE, goal.goal_id, GoalState.CANCELLED, reason))
        if self._follow is not None:
            out.append(self._status(NO_SEQUENCE, self._follow.follow_id, GoalState.CANCELLED, reason))
        self._goal = self._fleet = self._mission = None
        self._follow = None
        return out

    def _expire(self, now_s: float) -> GoalStatus | None:
        if self._velocity is not None and now_s > self._velocity[3]:
            self._velocity = None
            return self._status(NO_SEQUENCE, NO_GOAL, GoalState.CANCELLED, GoalReason.DEAD_MAN)
        return None

    # -- missions and the navigator ------------------------------------------------------------------

    def mission_goal(self, goal: GoalCommand) -> GoalStatus:
        """A local mission's goal: driven only while the controller drives nothing."""
        with self._lock:
            if self._stopped:
                return self._status(NO_SEQUENCE, goal.goal_id, GoalState.REJECTED, GoalReason.STOPPED)
            busy = (self._goal, self._velocity, self._fleet, self._follow)
            if any(x is not None for x in busy):
                return self._status(NO_SEQUENCE, goal.goal_id, GoalState.REJECTED, GoalReason.BUSY)
            reason = self._check_goal(goal)
            if reason is not None:
                return self._status(NO_SEQUENCE, goal.goal_id, GoalState.REJECTED, reason)
            self._mission = goal
            return self._status(NO_SEQUENCE, goal.goal_id, GoalState.ACCEPTED)

    def fleet_goal(self, goal: GoalCommand, now_s: float) -> list[GoalStatus]:
        """A goal from the fleet: its answer first, then the earlier fleet goal it replaced (if any).
        Under the controller and beside the missions (the module's doc): it cannot take the base from a
        stop, a controller velocity or goal, or a running mission."""
        with self._lock:
            self._expire(now_s)
            if self._stopped:
                return [self._status(NO_SEQUENCE, goal.goal_id, GoalState.REJECTED, GoalReason.STOPPED)]
            busy = (self._goal, self._velocity, self._mission, self._follow)
            if any(x is not None for x in busy):
                return [self._status(NO_SEQUENCE, goal.goal_id, GoalState.REJECTED, GoalReason.BUSY)]
            fields = (goal.x_m, goal.y_m, goal.tolerance_xy_m, goal.tolerance_yaw_rad)
            if not all(math.isfinite(x) for x in fields) or (
                goal.yaw_rad is not None and not math.isfinite(goal.yaw_rad)
            ):
                return [self._status(NO_SEQUENCE, goal.goal_id, GoalState.REJECTED, GoalReason.BAD_VALUE)]
            reason = self._check_goal(goal)
            if reason is not None:
                return [self._status(NO_SEQUENCE, goal.goal_id, GoalState.REJECTED, reason)]
            out = [self._status(NO_SEQUENCE, goal.goal_id, GoalState.ACCEPTED)]
            if self._fleet is not None:
                out.append(
                    self._status(NO_SEQUENCE, self._fleet.goal_id, GoalState.CANCELLED, GoalReason.SUPERSEDED)
                )
            self._fleet = goal
            return out

    @property
    def stopped(self) -> bool:
        """A stop command holds the base (until resume)."""
        with self._lock:
            return self._stopped

    @property
    def controller_in_force(self) -> bool:
        """A controller's velocity, goal or following drives the base (a mission would not)."""
        with self._lock:
            return self._goal is not None or self._velocity is not None or self._follow is not None

    @property
    def following(self) -> FollowCommand | None:
        """The follow command in force (None: not following)."""
        with self._lock:
            return self._follow

    def follow_status(
        self, follow_id: int, reason: GoalReason, distance_m: float | None = None
    ) -> GoalStatus | None:
        """An ACTIVE status about the following in force (``reason``: how it goes; ``distance_m``: to the
        person, as the status's remaining distance); None if ``follow_id`` is no longer it."""
        with self._lock:
            if self._follow is None or self._follow.follow_id != follow_id:
                return None
            return self._status(NO_SEQUENCE, follow_id, GoalState.ACTIVE, reason, distance_m)

    @property
    def fleet_in_force(self) -> bool:
        """A fleet goal drives the base (missions wait for it)."""
        with self._lock:
            return self._fleet is not None

    def mission_status(
        self, command_sequence: int, mission_id: int, state: GoalState, reason: GoalReason = GoalReason.NONE
    ) -> GoalStatus:
        """A status about a mission (its answer, its end), numbered with the arbiter's statuses."""
        with self._lock:
            return self._status(command_sequence, mission_id, state, reason)

    def cancel_mission(self, goal_id: int) -> GoalStatus | None:
        """The mission ends its own goal (CANCELLED); None if ``goal_id`` is not the mission goal in force."""
        with self._lock:
            if self._mission is None or self._mission.goal_id != goal_id:
                return None
            self._mission = None
            return self._status(NO_SEQUENCE, goal_id, GoalState.CANCELLED)

    def directive(self, now_s: float) -> tuple[Directive, GoalStatus | None]:
        """What drives the base now, and the dead-man's status if a velocity just expired."""
        with self._lock:
            expired = self._expire(now_s)
            if self._stopped:
                return Directive(DriveSource.STOPPED), expired
            if self._velocity is not None:
                _, v, w, _ = self._velocity
                return Directive(DriveSource.VELOCITY, v, w), expired
            if self._goal is not None:
                return Directive(DriveSource.GOAL, goal=self._goal), expired
            if self._fleet is not None:
                return Directive(DriveSource.FLEET, goal=self._fleet), expired
            if self._mission is not None:
                return Directive(DriveSource.MISSION, goal=self._mission), expired
            if self._follow is not None:
                return Directive(DriveSource.FOLLOW), expired
            return Directive(DriveSource.NONE), expired

    def goal_progress(self, goal_id: int, remaining_m: float | None) -> GoalStatus | None:
        """An ACTIVE status for the goal in force (None if ``goal_id`` is no longer it)."""
        with self._lock:
            if not any(
                g is not None and g.goal_id == goal_id for g in (self._goal, self._fleet, self._mission)
            ):
                return None
            return self._status(NO_SEQUENCE, goal_id, GoalState.ACTIVE, remaining_m=remaining_m)

    def goal_finished(
        self, goal_id: int, state: GoalState, reason: GoalReason = GoalReason.NONE
    ) -> GoalStatus | None:
        """The navigator ended the goal in force (REACHED, or FAILED with a reason); None if it is gone."""
        with self._lock:
            if self._goal is not None and self._goal.goal_id == goal_id:
                self._goal = None
            elif self._fleet is not None and self._fleet.goal_id == goal_id:
                self._fleet = None
            elif self._mission is not None and self._mission.goal_id == goal_id:
                self._mission = None
            else:
                return None
            return self._status(
                NO_SEQUENCE, goal_id, state, reason, 0.0 if state is GoalState.REACHED else None
            )
