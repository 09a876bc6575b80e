"""The driving step: what the command arbiter says drives the base, handed to the wheels' dead-man.

Run by the command loop's thread after each pass (``CommandLoop.run(..., then=...)``), so a controller's
velocity reaches :class:`~agent.runtime.motion.DriveCommand` within one poll of its frame:

* ``VELOCITY``: the controller's velocity (clamped by the arbiter) is set every pass while it is in force;
  DriveCommand's own dead-man still zeroes the wheels if this thread stops. When it ends, zero once.
* ``STOPPED``: zero, held (``DriveCommand.hold``) every pass until resume.
* ``NONE``: nothing: whoever else commands the base (``Agent.command_velocity``: the sim's route follower)
  keeps doing so.
* ``FOLLOW``: nothing here: the follow loop sends its velocity (``Agent.command_velocity``) while following
  is on; when it ends, zero at once (as below).
* ``GOAL`` / ``MISSION``: for the navigator (``navigator``), called with the directive each pass; without
  one nothing drives (and the agent answers goals NOT_LOCALIZED, see ``Agent``).

A controller velocity first passes ``guard`` (the navigation's collision monitor, when there is one): the
base slows down near an obstacle in its way and stops short of it whoever commands it. When a velocity or
a goal stops being in force, zero goes out at once, not after DriveCommand's own timeout.

The dead-man's CANCELLED status of an expired velocity goes back to the controller through ``answer``.
"""

from __future__ import annotations

import collections
from collections.abc import Callable

from agent.runtime.arbiter import CommandArbiter, Directive, DriveSource
from agent.runtime.motion import DriveCommand
from firmware_protocol.command_frame import CommandType, GoalStatus

__all__ = ["DirectiveDrive", "Guard", "Navigator"]

# The navigation loop's entry: the goal directive in force and the time (s, the arbiter's clock).
Navigator = Callable[[Directive, float], None]
# The collision monitor's say on a velocity: (v, omega, time s) -> the (v, omega) that may be driven.
Guard = Callable[[float, float, float], tuple[float, float]]


class DirectiveDrive:
    def __init__(
        self,
        arbiter: CommandArbiter,
        drive: DriveCommand,
        answer: Callable[[GoalStatus, CommandType | None], None],
        clock_ns: Callable[[], int],
        navigator: Callable[[], Navigator | None] = lambda: None,
        guard: Callable[[], Guard | None] = lambda: None,
    ) -> None:
        self.arbiter = arbiter
        self.drive = drive
        self.answer = answer
        self.clock_ns = clock_ns
        self.navigator = navigator
        self.guard = guard
        self.source = DriveSource.NONE
        self.counts: collections.Counter[str] = collections.Counter()

    @property
    def controller_drives(self) -> bool:
        """A controller velocity or stop is in force: other velocity commands give way."""
        return self.source in (DriveSource.VELOCITY, DriveSource.STOPPED)

    def step(self) -> Directive:
        now_ns = self.clock_ns()
        directive, expired = self.arbiter.directive(now_ns * 1e-9)
        if expired is not None:
            self.answer(expired, CommandType.VELOCITY)
        previous, self.source = self.source, directive.source
        if directive.source is DriveSource.VELOCITY:
            v, omega = directive.v_mps, directive.omega_radps
            guard = self.guard()
            if guard is not None:
                v, omega = guard(v, omega, now_ns * 1e-9)
                if (v, omega) != (directive.v_mps, directive.omega_radps):
                    self.counts["drive_velocity_guarded"] += 1
            self.drive.set(v, omega, now_ns)
            self.counts["drive_velocity"] += 1
        elif directive.source is DriveSource.STOPPED:
            self.drive.hold(now_ns)
            self.counts["drive_stopped"] += 1
        elif directive.source in (DriveSource.GOAL, DriveSource.MISSION, DriveSource.FLEET):
            navigator = self.navigator()
            if navigator is not None:
                navigator(directive, now_ns * 1e-9)
            else:
                self.counts["drive_goal_without_navigator"] += 1
        moving = (
            DriveSource.VELOCITY,
            DriveSource.GOAL,
            DriveSource.MISSION,
            DriveSource.FLEET,
            DriveSource.FOLLOW,
        )
        if previous in moving and directive.source is not previous:
            # The controller's velocity or the goal ended (dead-man, cancel, a new source, stop): the base
            # stops now, not after DriveCommand's own timeout.
            self.drive.set(0.0, 0.0, now_ns)
        return directive
