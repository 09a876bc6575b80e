"""The command arbiter: precedence, the dead-man, stop/resume, clamping, bad values, one answer each."""

from __future__ import annotations

import math

import pytest

from agent.runtime.arbiter import CommandArbiter, DriveSource
from firmware_protocol.command_frame import (
    NO_GOAL,
    NO_SEQUENCE,
    CancelCommand,
    CommandFrameError,
    FollowAction,
    FollowCommand,
    GoalCommand,
    GoalReason,
    GoalState,
    ResumeCommand,
    StopCommand,
    VelocityCommand,
)


def arbiter(check: dict[int, GoalReason] | None = None) -> CommandArbiter:
    reasons = check or {}
    return CommandArbiter(0.22, 2.0, check_goal=lambda g: reasons.get(g.goal_id))


def states(statuses: list) -> list[tuple[int, GoalState, GoalReason]]:
    return [(s.goal_id, s.state, s.reason) for s in statuses]


def test_a_velocity_drives_until_its_timeout_then_the_dead_man_stops_the_base() -> None:
    a = arbiter()
    (answer,) = a.command(VelocityCommand(1, 0.1, 0.2, 0.5), now_s=10.0)
    assert (answer.command_sequence, answer.state, answer.reason) == (1, GoalState.ACCEPTED, GoalReason.NONE)
    directive, expired = a.directive(10.4)
    assert (directive.source, directive.v_mps, directive.omega_radps, expired) == (
        DriveSource.VELOCITY,
        0.1,
        0.2,
        None,
    )
    directive, expired = a.directive(10.51)
    assert directive.source is DriveSource.NONE
    assert expired is not None and (expired.state, expired.reason) == (
        GoalState.CANCELLED,
        GoalReason.DEAD_MAN,
    )
    assert a.directive(11.0)[1] is None  # said once


def test_a_velocity_beyond_the_limits_is_clamped_and_says_so() -> None:
    a = arbiter()
    (answer,) = a.command(VelocityCommand(1, 5.0, -9.0, 0.5), now_s=0.0)
    assert (answer.state, answer.reason) == (GoalState.ACCEPTED, GoalReason.CLAMPED)
    directive, _ = a.directive(0.1)
    assert (directive.v_mps, directive.omega_radps) == (0.22, -2.0)


@pytest.mark.parametrize(
    "bad",
    [
        VelocityCommand(1, math.nan, 0.0, 0.5),
        VelocityCommand(1, 0.1, math.inf, 0.5),
        VelocityCommand(1, 0.1, 0.0, 0.0),
        GoalCommand(2, 7, math.nan, 1.0),
        GoalCommand(2, 7, 1.0, 1.0, yaw_rad=math.inf),
    ],
)
def test_non_finite_fields_and_a_zero_timeout_are_rejected_and_nothing_moves(bad: object) -> None:
    a = arbiter()
    (answer,) = a.command(bad, now_s=0.0)  # type: ignore[arg-type]
    assert (answer.state, answer.reason) == (GoalState.REJECTED, GoalReason.BAD_VALUE)
    assert a.directive(0.1)[0].source is DriveSource.NONE


def test_a_goal_is_checked_and_rejected_with_the_navigators_reason() -> None:
    a = arbiter({7: GoalReason.IN_OBSTACLE, 8: GoalReason.UNREACHABLE})
    assert states(a.command(GoalCommand(1, 7, 1.0, 1.0), 0.0)) == [
        (7, GoalState.REJECTED, GoalReason.IN_OBSTACLE)
    ]
    assert states(a.command(GoalCommand(2, 8, 1.0, 1.0), 0.0)) == [
        (8, GoalState.REJECTED, GoalReason.UNREACHABLE)
    ]
    assert a.directive(0.0)[0].source is DriveSource.NONE


def test_velocity_preempts_a_goal_and_a_goal_is_busy_while_a_velocity_is_in_force() -> None:
    a = arbiter()
    assert states(a.command(GoalCommand(1, 5, 1.0, 2.0), 0.0)) == [(5, GoalState.ACCEPTED, GoalReason.NONE)]
    assert a.directive(0.0)[0].source is DriveSource.GOAL
    out = a.command(VelocityCommand(2, 0.1, 0.0, 0.3), 1.0)
    assert states(out) == [
        (NO_GOAL, GoalState.ACCEPTED, GoalReason.NONE),
        (5, GoalState.CANCELLED, GoalReason.SUPERSEDED),
    ]
    assert states(a.command(GoalCommand(3, 6, 1.0, 2.0), 1.1)) == [(6, GoalState.REJECTED, GoalReason.BUSY)]
    # Once the velocity has expired, a goal is taken again.
    assert states(a.command(GoalCommand(4, 6, 1.0, 2.0), 2.0))[0] == (6, GoalState.ACCEPTED, GoalReason.NONE)


def test_a_controller_goal_supersedes_a_mission_goal_and_a_mission_waits_for_the_controller() -> None:
    a = arbiter()
    assert a.mission_goal(GoalCommand(NO_SEQUENCE, 100, 3.0, 3.0)).state is GoalState.ACCEPTED
    assert a.directive(0.0)[0].source is DriveSource.MISSION
    out = a.command(GoalCommand(1, 5, 1.0, 2.0), 0.0)
    assert states(out) == [
        (5, GoalState.ACCEPTED, GoalReason.NONE),
        (100, GoalState.CANCELLED, GoalReason.SUPERSEDED),
    ]
    assert a.mission_goal(GoalCommand(NO_SEQUENCE, 101, 3.0, 3.0)).reason is GoalReason.BUSY
    directive, _ = a.directive(0.0)
    assert directive.source is DriveSource.GOAL and directive.goal is not None and directive.goal.goal_id == 5


def test_stop_holds_everything_until_resume() -> None:
    a = arbiter()
    a.command(GoalCommand(1, 5, 1.0, 2.0), 0.0)
    out = a.command(StopCommand(2), 0.0)
    assert states(out) == [
        (NO_GOAL, GoalState.ACCEPTED, GoalReason.NONE),
        (5, GoalState.CANCELLED, GoalReason.STOPPED),
    ]
    assert a.directive(0.0)[0].source is DriveSource.STOPPED
    assert states(a.command(VelocityCommand(3, 0.1, 0.0, 0.5), 0.1)) == [
        (NO_GOAL, GoalState.REJECTED, GoalReason.STOPPED)
    ]
    assert a.mission_goal(GoalCommand(NO_SEQUENCE, 9, 0.0, 0.0)).reason is GoalReason.STOPPED
    a.command(ResumeCommand(4), 0.2)
    assert a.directive(0.2)[0].source is DriveSource.NONE  # resume restarts nothing by itself
    assert a.command(VelocityCommand(5, 0.1, 0.0, 0.5), 0.3)[0].state is GoalState.ACCEPTED


def test_cancel_names_the_active_goal_or_any() -> None:
    a = arbiter()
    a.command(GoalCommand(1, 5, 1.0, 2.0), 0.0)
    assert states(a.command(CancelCommand(2, 6), 0.0)) == [(6, GoalState.REJECTED, GoalReason.UNKNOWN_GOAL)]
    assert states(a.command(CancelCommand(3), 0.0)) == [(5, GoalState.CANCELLED, GoalReason.NONE)]
    assert a.directive(0.0)[0].source is DriveSource.NONE


def test_the_navigator_ends_goals_and_reports_progress_only_for_the_goal_in_force() -> None:
    a = arbiter()
    a.command(GoalCommand(1, 5, 1.0, 2.0), 0.0)
    progress = a.goal_progress(5, 2.5)
    assert progress is not None and (progress.state, progress.remaining_m) == (GoalState.ACTIVE, 2.5)
    assert a.goal_progress(6, 1.0) is None
    done = a.goal_finished(5, GoalState.REACHED)
    assert done is not None and (done.state, done.remaining_m) == (GoalState.REACHED, 0.0)
    assert a.goal_finished(5, GoalState.FAILED, GoalReason.BLOCKED) is None
    assert a.directive(0.0)[0].source is DriveSource.NONE


@pytest.mark.parametrize(
    ("kind", "reason"),
    [
        ("crc", GoalReason.BAD_FRAME),
        ("cobs", GoalReason.BAD_FRAME),
        ("type", GoalReason.UNKNOWN_TYPE),
        ("version", GoalReason.BAD_VERSION),
    ],
)
def test_unreadable_frames_are_answered_with_no_sequence(kind: str, reason: GoalReason) -> None:
    status = arbiter().bad_frame(CommandFrameError(kind, "x"))
    assert (status.command_sequence, status.state, status.reason) == (NO_SEQUENCE, GoalState.REJECTED, reason)


def test_status_sequence_numbers_increase_and_answers_are_counted() -> None:
    a = arbiter()
    seqs = [s.sequence for s in a.command(VelocityCommand(1, 9.0, 0.0, 0.5), 0.0)]
    seqs += [s.sequence for s in a.command(StopCommand(2), 0.0)]
    assert seqs == [1, 2]
    assert a.counts == {"accepted_clamped": 1, "accepted": 1}


# -- fleet goals (issue 24): under the controller's stop, velocity (and its dead-man) and goals -------------


def fleet(goal_id: int, x: float = 1.0) -> GoalCommand:
    return GoalCommand(NO_SEQUENCE, goal_id, x, 2.0)


def test_a_fleet_goal_drives_only_while_the_controller_drives_nothing() -> None:
    a = arbiter({0x8003: GoalReason.OUTSIDE_MAP})
    assert states(a.fleet_goal(fleet(0x8000), 1.0)) == [(0x8000, GoalState.ACCEPTED, GoalReason.NONE)]
    assert a.directive(1.0)[0].source is DriveSource.FLEET and a.fleet_in_force
    # A newer fleet goal replaces it; a checked one is rejected with the navigator's reason.
    assert states(a.fleet_goal(fleet(0x8001), 1.0)) == [
        (0x8001, GoalState.ACCEPTED, GoalReason.NONE),
        (0x8000, GoalState.CANCELLED, GoalReason.SUPERSEDED),
    ]
    assert states(a.fleet_goal(fleet(0x8003), 1.0)) == [(0x8003, GoalState.REJECTED, GoalReason.OUTSIDE_MAP)]
    # A mission waits for it; a controller goal supersedes it.
    assert a.mission_goal(GoalCommand(NO_SEQUENCE, 0xC000, 0.0, 0.0)).reason is GoalReason.BUSY
    assert states(a.command(GoalCommand(5, 7, 3.0, 3.0), 2.0)) == [
        (7, GoalState.ACCEPTED, GoalReason.NONE),
        (0x8001, GoalState.CANCELLED, GoalReason.SUPERSEDED),
    ]
    assert states(a.fleet_goal(fleet(0x8004), 2.0)) == [(0x8004, GoalState.REJECTED, GoalReason.BUSY)]
    assert a.directive(2.0)[0].goal == GoalCommand(5, 7, 3.0, 3.0)


def test_a_fleet_goal_never_overrides_the_stop_or_the_dead_man() -> None:
    a = arbiter()
    a.fleet_goal(fleet(0x8000), 1.0)
    # A controller velocity takes over; while it is in force (and up to its dead-man), fleet goals are busy.
    assert states(a.command(VelocityCommand(1, 0.1, 0.0, 0.5), 1.0))[1:] == [
        (0x8000, GoalState.CANCELLED, GoalReason.SUPERSEDED)
    ]
    assert a.fleet_goal(fleet(0x8001), 1.2)[0].reason is GoalReason.BUSY
    directive, expired = a.directive(1.6)  # the dead-man: the base stops, and the fleet goal stays refused
    assert (
        directive.source is DriveSource.NONE and expired is not None and expired.reason is GoalReason.DEAD_MAN
    )
    # After the dead-man a fleet goal may drive again (as a mission may)...
    assert a.fleet_goal(fleet(0x8002), 1.7)[0].state is GoalState.ACCEPTED
    # ...but a stop cancels it and holds until resume.
    assert states(a.command(StopCommand(2), 1.8))[1:] == [(0x8002, GoalState.CANCELLED, GoalReason.STOPPED)]
    assert a.fleet_goal(fleet(0x8003), 1.9)[0].reason is GoalReason.STOPPED
    assert a.directive(1.9)[0].source is DriveSource.STOPPED
    a.command(ResumeCommand(3), 2.0)
    assert a.fleet_goal(fleet(0x8004), 2.1)[0].state is GoalState.ACCEPTED
    # The controller's cancel reaches it; the navigator ends it like any goal.
    assert states(a.command(CancelCommand(4), 2.2)) == [(0x8004, GoalState.CANCELLED, GoalReason.NONE)]
    a.fleet_goal(fleet(0x8005), 2.3)
    assert a.goal_progress(0x8005, 1.5) is not None
    done = a.goal_finished(0x8005, GoalState.REACHED)
    assert (
        done is not None
        and done.state is GoalState.REACHED
        and a.directive(2.4)[0].source is DriveSource.NONE
    )


def test_a_fleet_goal_waits_for_a_running_mission_and_bad_values_are_refused() -> None:
    a = arbiter()
    assert a.mission_goal(GoalCommand(NO_SEQUENCE, 0xC000, 0.0, 0.0)).state is GoalState.ACCEPTED
    assert a.fleet_goal(fleet(0x8000), 1.0)[0].reason is GoalReason.BUSY
    b = arbiter()
    assert b.fleet_goal(fleet(0x8000, math.nan), 1.0)[0].reason is GoalReason.BAD_VALUE


# -- following (follow frames, v1.2) ------------------------------------------------------------------------
def follower_arbiter(refuse: GoalReason | None = None) -> CommandArbiter:
    a = arbiter()
    a.check_follow = lambda follow: refuse
    return a


def test_without_a_follow_check_every_follow_start_is_refused_unavailable() -> None:
    a = arbiter()
    assert states(a.command(FollowCommand(1, 5), 0.0)) == [
        (5, GoalState.REJECTED, GoalReason.FOLLOW_UNAVAILABLE)
    ]
    assert a.following is None and a.directive(0.1)[0].source is DriveSource.NONE


def test_a_follow_start_cancels_the_goal_and_the_follow_drives() -> None:
    a = follower_arbiter()
    a.command(GoalCommand(1, 7, 1.0, 1.0), 0.0)
    assert states(a.command(FollowCommand(2, 5), 0.0)) == [
        (5, GoalState.ACCEPTED, GoalReason.NONE),
        (7, GoalState.CANCELLED, GoalReason.SUPERSEDED),
    ]
    assert a.directive(0.1)[0].source is DriveSource.FOLLOW and a.controller_in_force
    progress = a.follow_status(5, GoalReason.FOLLOWING, 1.2)
    assert progress is not None and (progress.state, progress.reason, progress.remaining_m) == (
        GoalState.ACTIVE,
        GoalReason.FOLLOWING,
        1.2,
    )


@pytest.mark.parametrize(
    ("command", "reason"),
    [
        (GoalCommand(3, 8, 1.0, 1.0), GoalReason.SUPERSEDED),
        (VelocityCommand(3, 0.1, 0.0, 0.5), GoalReason.SUPERSEDED),
        (StopCommand(3), GoalReason.STOPPED),
    ],
)
def test_a_goal_a_velocity_or_a_stop_ends_following(command: object, reason: GoalReason) -> None:
    a = follower_arbiter()
    a.command(FollowCommand(1, 5), 0.0)
    out = states(a.command(command, 0.0))  # type: ignore[arg-type]
    assert out[0][1] is GoalState.ACCEPTED and out[1:] == [(5, GoalState.CANCELLED, reason)]
    assert a.following is None and a.follow_status(5, GoalReason.FOLLOWING) is None


@pytest.mark.parametrize(
    "command", [FollowCommand(2, 5, FollowAction.STOP), FollowCommand(2, NO_GOAL, 1), CancelCommand(2)]
)
def test_a_follow_stop_or_a_cancel_ends_following(command: object) -> None:
    a = follower_arbiter()
    a.command(FollowCommand(1, 5), 0.0)
    (answer,) = a.command(command, 0.0)  # type: ignore[arg-type]
    assert (answer.command_sequence, answer.goal_id, answer.state) == (2, 5, GoalState.CANCELLED)
    assert a.following is None and a.directive(0.1)[0].source is DriveSource.NONE
    # Nothing is following now: another stop names nothing.
    assert states(a.command(FollowCommand(3, 5, FollowAction.STOP), 0.0)) == [
        (5, GoalState.REJECTED, GoalReason.UNKNOWN_GOAL)
    ]


def test_a_follow_start_is_refused_under_a_stop_a_velocity_or_the_check() -> None:
    a = follower_arbiter()
    a.command(StopCommand(1), 0.0)
    assert states(a.command(FollowCommand(2, 5), 0.0)) == [(5, GoalState.REJECTED, GoalReason.STOPPED)]
    a.command(ResumeCommand(3), 0.0)
    a.command(VelocityCommand(4, 0.1, 0.0, 0.5), 0.0)
    assert states(a.command(FollowCommand(5, 6), 0.1)) == [(6, GoalState.REJECTED, GoalReason.BUSY)]
    b = follower_arbiter(GoalReason.NO_TAG_READER)
    assert states(b.command(FollowCommand(1, 7, tag="AB"), 0.0)) == [
        (7, GoalState.REJECTED, GoalReason.NO_TAG_READER)
    ]


def test_missions_and_fleet_goals_wait_while_following_and_a_new_follow_replaces_the_old() -> None:
    a = follower_arbiter()
    a.command(FollowCommand(1, 5), 0.0)
    assert a.mission_goal(GoalCommand(NO_SEQUENCE, 0xC000, 1.0, 1.0)).reason is GoalReason.BUSY
    (fleet,) = a.fleet_goal(GoalCommand(NO_SEQUENCE, 0x8000, 1.0, 1.0), 0.0)
    assert fleet.reason is GoalReason.BUSY
    assert states(a.command(FollowCommand(2, 6, tag="0415"), 0.0)) == [
        (6, GoalState.ACCEPTED, GoalReason.NONE),
        (5, GoalState.CANCELLED, GoalReason.SUPERSEDED),
    ]
    following = a.following
    assert following is not None and following.tag == "0415"
