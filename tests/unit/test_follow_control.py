"""Following on command (``agent.runtime.follow_control``): a follow frame turns the follow loop on through
the arbiter, the loop's state goes back as ACTIVE statuses of the follow id (on change, then once a period),
a follow stop turns it off with zero sent; refusals say why. The loop's steps are driven by hand on a
simulated clock (no threads, no sleeps)."""

from __future__ import annotations

from agent.following.follower import FollowCommand as Step
from agent.following.follower import FollowState
from agent.runtime.arbiter import CommandArbiter, DriveSource
from agent.runtime.follow_control import FollowControl, wire_reason
from agent.runtime.follow_loop import NO_CAMERA, NO_POSE, FollowSnapshot
from firmware_protocol.command_frame import (
    CommandType,
    FollowAction,
    FollowCommand,
    GoalReason,
    GoalState,
    GoalStatus,
    StopCommand,
)
from tests.unit.test_follow_loop import _loop, make_scan


def snap(state: FollowState, why: str = "", distance: float | None = None) -> FollowSnapshot:
    return FollowSnapshot(0.0, Step(0.0, 0.0, state, why, distance), None, (0.0, 0.0))


def test_the_loops_states_map_to_their_wire_reasons() -> None:
    cases = [
        (snap(FollowState.FOLLOWING, "keeping the distance", 1.1), GoalReason.FOLLOWING),
        (snap(FollowState.WAITING, "the person stands"), GoalReason.FOLLOWING),
        (snap(FollowState.LOST, "searching: turning toward the RFID bearing 40 deg"), GoalReason.SEARCHING),
        (snap(FollowState.LOST, "no person track for 0.3 s: stopped"), GoalReason.PERSON_LOST),
        (snap(FollowState.LOST, NO_POSE), GoalReason.NOT_LOCALIZED),
        (snap(FollowState.NO_TAG, "tag absent (p=0.9)"), GoalReason.TAG_ABSENT),
        (snap(FollowState.NO_CAMERA, NO_CAMERA), GoalReason.NO_CAMERA_FRAMES),
    ]
    assert [wire_reason(s) for s, _ in cases] == [r for _, r in cases]


class Wire:
    """What the agent sent its controller."""

    def __init__(self) -> None:
        self.sent: list[tuple[GoalStatus, CommandType | None]] = []

    def __call__(self, status: GoalStatus, about: CommandType | None) -> None:
        self.sent.append((status, about))

    def states(self) -> list[tuple[int, str, str]]:
        return [(s.goal_id, s.state.name, s.reason.name) for s, _ in self.sent]


def test_started_by_command_it_follows_reports_and_stops_on_command() -> None:
    now = [0.0]
    velocities: list[tuple[float, float]] = []
    loop = _loop(now, velocities)
    arbiter = CommandArbiter(1.0, 2.0)
    wire = Wire()
    control = FollowControl(arbiter, wire, loop, lambda: now[0], period_s=1.0, min_gap_s=0.25)
    # Off: the loop idles and looks at no scan.
    assert not loop.sync_active()
    loop.on_scan(make_scan(0.0, (3.5, 3.0), 0))
    assert loop.counts["scans"] == 0
    (answer,) = arbiter.command(FollowCommand(1, 9), now[0])
    assert (answer.goal_id, answer.state) == (9, GoalState.ACCEPTED)
    assert arbiter.directive(now[0])[0].source is DriveSource.FOLLOW
    assert loop.sync_active() and loop.counts["restarts"] == 1
    # The person walks away from 2.5 m ahead: the loop acquires them and follows.
    for k in range(1, 31):
        now[0] = k * 0.1
        loop.on_scan(make_scan(now[0], (3.5 + 0.7 * now[0], 3.0), k))
        control.on_step(loop.step())
    reports = wire.states()
    assert reports[-1] == (9, "ACTIVE", "FOLLOWING")
    assert all(about is CommandType.FOLLOW for _, about in wire.sent)
    # On change at most every 0.25 s, then once a second: 3 s of steady following is a few, not 30.
    assert 3 <= len(reports) <= 6
    assert wire.sent[-1][0].remaining_m is not None and wire.sent[-1][0].remaining_m > 1.0
    assert max(v for v, _ in velocities) > 0.3
    # Stopped by command: the loop turns off with zero sent, and reports nothing more.
    (ended,) = arbiter.command(FollowCommand(2, 9, FollowAction.STOP), now[0])
    assert (ended.goal_id, ended.state, ended.reason) == (9, GoalState.CANCELLED, GoalReason.NONE)
    assert not loop.sync_active() and velocities[-1] == (0.0, 0.0)
    before = len(wire.sent)
    control.on_step(loop.step())
    assert len(wire.sent) == before
    assert control.summary()["following"] is None and control.summary()["last_state"] == "FOLLOWING"


def test_a_second_following_restarts_the_loop_and_a_stop_command_ends_it() -> None:
    now = [0.0]
    loop = _loop(now, [])
    arbiter = CommandArbiter(1.0, 2.0)
    FollowControl(arbiter, Wire(), loop, lambda: now[0])
    arbiter.command(FollowCommand(1, 9), 0.0)
    assert loop.sync_active()
    arbiter.command(FollowCommand(2, 10), 0.0)  # another following while on
    assert loop.sync_active() and loop.counts["restarts"] == 2
    arbiter.command(StopCommand(3), 0.0)
    assert not loop.sync_active()


class Layer:
    """The RFID layer's retag, recorded."""

    def __init__(self) -> None:
        self.tags: list[str] = []

    def retag(self, tag_id: str) -> None:
        self.tags.append(tag_id)


def test_refusals_say_why_and_a_named_tag_points_the_rfid_layer_at_it() -> None:
    arbiter = CommandArbiter(1.0, 2.0)
    control = FollowControl(arbiter, Wire(), None, lambda: 0.0, unavailable="no laser")
    (answer,) = arbiter.command(FollowCommand(1, 9), 0.0)
    assert (answer.state, answer.reason) == (GoalState.REJECTED, GoalReason.FOLLOW_UNAVAILABLE)
    assert control.summary()["unavailable"] == "no laser"

    now = [0.0]
    loop = _loop(now, [])
    layer: Layer | None = None
    arbiter = CommandArbiter(1.0, 2.0)
    FollowControl(arbiter, Wire(), loop, lambda: 0.0, coarse=lambda: layer, configured_tag="E200")
    (answer,) = arbiter.command(FollowCommand(1, 9, tag="0415AB"), 0.0)
    assert (answer.state, answer.reason) == (GoalState.REJECTED, GoalReason.NO_TAG_READER)
    layer = Layer()
    arbiter.command(FollowCommand(2, 9, tag="0415AB"), 0.0)
    assert loop.sync_active() and layer.tags == ["0415AB"]
    assert loop.coarse() is layer
    arbiter.command(FollowCommand(3, 10), 0.0)  # the configured tag again
    loop.sync_active()
    assert layer.tags == ["0415AB", "E200"]
    assert loop.counts["restarts"] == 2
