"""The mission loop inside the agent: the explorer's targets become mission goals at the arbiter, the goal
statuses the agent sends come back to the explorer, it looks around first, waits without a pose, and a
controller taking over pauses it; go-to-place missions drive their legs and end with the mission's status;
bad missions are refused with a clear reason and leave the robot as it was."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest

from agent.config import AgentConfig
from agent.config_slam import SlamConfig
from agent.exploration import Command, ExploreConfig, ExploreState, FrontierExplorer
from agent.navigation.config import NavConfig
from agent.runtime.agent import Agent
from agent.runtime.arbiter import CommandArbiter, DriveSource
from agent.runtime.devices import Devices
from agent.runtime.mission_loop import LOOK_AROUND_TURNS, MISSION_GOAL_IDS, MissionLoop, NamedPlace
from agent.slam.mapio import save_topology, topology_path
from agent.slam.render import FREE_VALUE, OCCUPIED_VALUE, UNKNOWN_VALUE, OccupancyImage
from firmware_protocol.command_frame import (
    NO_SEQUENCE,
    ExploreAction,
    ExploreCommand,
    GoalReason,
    GoalState,
    GoalStatus,
    PlaceCommand,
    StopCommand,
    VelocityCommand,
)


def room_image() -> OccupancyImage:
    """A 6 x 4 m map: walls all round, the west half seen free, the east half unknown (a frontier)."""
    res = 0.05
    rows, cols = 80, 120
    pixels = np.full((rows, cols), UNKNOWN_VALUE, np.uint8)
    pixels[:, :60] = FREE_VALUE
    pixels[0, :] = pixels[-1, :] = OCCUPIED_VALUE
    pixels[:, 0] = pixels[:, -1] = OCCUPIED_VALUE
    return OccupancyImage(pixels, res, (0.0, 0.0, 0.0))


class Rig:
    def __init__(self, reject: GoalReason | None = None) -> None:
        self.pose: tuple[float, float, float] | None = (1.0, 2.0, 0.0)
        self.t_ns = 0
        self.sent: list[GoalStatus] = []
        self.arbiter = CommandArbiter(0.2, 1.0, check_goal=lambda goal: reject)
        self.explorer = FrontierExplorer(ExploreConfig(), NavConfig())
        places = {"desk": NamedPlace("desk", 2.0, 3.0, 0.0), "bin": NamedPlace("bin", 2.5, 1.0)}
        self.loop = MissionLoop(
            self.explorer,
            NavConfig(),
            self.arbiter,
            self.answer,
            lambda: self.pose,
            lambda: self.t_ns,
            places=places,
        )

    def answer(self, status: GoalStatus) -> None:
        self.sent.append(status)
        self.loop.on_status(status)

    def step(self, dt_s: float = 0.1) -> None:
        self.t_ns += int(dt_s * 1e9)
        self.loop.step()

    def mission(self) -> object:
        directive, _ = self.arbiter.directive(self.t_ns * 1e-9)
        return directive.goal if directive.source is DriveSource.MISSION else None

    def finish(self, state: GoalState, reason: GoalReason = GoalReason.NONE) -> None:
        goal = self.mission()
        assert goal is not None
        status = self.arbiter.goal_finished(goal.goal_id, state, reason)  # type: ignore[attr-defined]
        assert status is not None
        self.answer(status)


def test_it_looks_around_then_drives_to_the_explorers_target() -> None:
    rig = Rig()
    rig.loop.command(Command.START)
    rig.step()
    assert rig.mission() is None  # no map yet: nothing to drive on
    rig.loop.on_map(room_image())
    yaws = []
    for _ in range(LOOK_AROUND_TURNS):
        rig.step()
        goal = rig.mission()
        assert goal is not None and goal.allow_unknown  # type: ignore[attr-defined]
        assert (goal.x_m, goal.y_m) == (1.0, 2.0)  # type: ignore[attr-defined]
        yaws.append(goal.yaw_rad)  # type: ignore[attr-defined]
        rig.step()
        assert rig.mission() is goal  # held until it ends
        rig.finish(GoalState.REACHED)
    assert [round(math.degrees(y)) % 360 for y in yaws] == [120, 240, 0]
    rig.step()
    goal = rig.mission()
    assert goal is not None and not goal.allow_unknown  # type: ignore[attr-defined]
    assert goal.goal_id in MISSION_GOAL_IDS  # type: ignore[attr-defined]
    assert goal.x_m > 2.0  # type: ignore[attr-defined]  # towards the unknown east half
    assert rig.loop.status()["look_around_turns"] == LOOK_AROUND_TURNS
    assert rig.explorer.state is ExploreState.EXPLORING


def test_without_a_pose_nothing_is_sent_and_the_start_waits() -> None:
    rig = Rig()
    rig.pose = None
    rig.loop.on_map(room_image())
    rig.loop.command(Command.START)
    rig.step()
    rig.step()
    assert rig.mission() is None and rig.explorer.state is ExploreState.IDLE
    assert rig.loop.counts["passes_without_pose"] == 2
    rig.pose = (1.0, 2.0, 0.0)
    rig.step()
    assert rig.explorer.state is ExploreState.EXPLORING and rig.mission() is not None


def test_a_rejected_target_is_blacklisted_by_the_explorer() -> None:
    rig = Rig(reject=GoalReason.UNREACHABLE)
    rig.loop.on_map(room_image())
    rig.loop.command(Command.START)
    for _ in range(3):
        rig.step()
    # The look-around is refused too (not for a passing lack of pose): exploring starts with what is seen.
    assert rig.loop.counts["look_around_rejected_unreachable"] == 1
    assert rig.loop.counts["targets_rejected_unreachable"] >= 1
    assert rig.explorer.blacklist.entries and "unreachable" in rig.explorer.blacklist.entries[0].reason
    assert any(s.state is GoalState.REJECTED for s in rig.sent)


def test_a_controller_taking_over_pauses_the_exploration() -> None:
    rig = Rig()
    rig.loop.on_map(room_image())
    rig.loop.command(Command.START)
    rig.step()
    assert rig.mission() is not None
    statuses = rig.arbiter.command(VelocityCommand(1, 0.1, 0.0, 0.5), rig.t_ns * 1e-9)
    for status in statuses:
        rig.answer(status)
    rig.step()
    assert rig.explorer.state is ExploreState.PAUSED
    assert rig.loop.counts["look_around_cancelled"] == 1


def test_an_explore_mission_is_answered_and_ends_with_its_own_status() -> None:
    rig = Rig()
    rig.loop.on_map(room_image())
    answer = rig.loop.take(ExploreCommand(5, 77, ExploreAction.START))
    assert (answer.state, answer.command_sequence, answer.goal_id) == (GoalState.ACCEPTED, 5, 77)
    assert rig.loop.take(ExploreCommand(6, 78)).reason is GoalReason.BUSY  # one mission at a time
    rig.step()
    assert rig.explorer.state is ExploreState.EXPLORING
    pause = rig.loop.take(ExploreCommand(7, 77, ExploreAction.PAUSE))
    assert pause.state is GoalState.ACCEPTED
    rig.step()
    assert rig.explorer.state is ExploreState.PAUSED and rig.mission() is None
    rig.loop.take(ExploreCommand(8, 77, ExploreAction.CANCEL))
    rig.step()
    assert rig.loop.ended[77].state is GoalState.CANCELLED
    assert rig.loop.take(ExploreCommand(9, 77, ExploreAction.RESUME)).reason is GoalReason.UNKNOWN_GOAL


def test_a_place_mission_goes_there_and_back_and_ends_reached() -> None:
    rig = Rig()
    rig.loop.on_map(room_image())
    answer = rig.loop.take(PlaceCommand(3, 9, "desk", come_back=True))
    assert answer.state is GoalState.ACCEPTED and answer.goal_id == 9
    rig.step()
    goal = rig.mission()
    assert goal is not None and (goal.x_m, goal.y_m, goal.yaw_rad) == (2.0, 3.0, 0.0)  # type: ignore[attr-defined]
    rig.finish(GoalState.REACHED)
    rig.step()
    back = rig.mission()
    assert back is not None and (back.x_m, back.y_m) == (1.0, 2.0)  # type: ignore[attr-defined]
    rig.finish(GoalState.REACHED)
    rig.step()
    assert rig.loop.ended[9].state is GoalState.REACHED and rig.sent[-1].goal_id == 9
    assert rig.mission() is None


def test_a_failed_leg_fails_the_mission_with_its_reason() -> None:
    rig = Rig()
    rig.loop.on_map(room_image())
    rig.loop.take(PlaceCommand(3, 9, "bin"))
    rig.step()
    rig.finish(GoalState.FAILED, GoalReason.BLOCKED)
    rig.step()
    end = rig.loop.ended[9]
    assert (end.state, end.reason) == (GoalState.FAILED, GoalReason.BLOCKED)
    assert rig.mission() is None


def refused(rig: Rig, command: ExploreCommand | PlaceCommand) -> GoalReason:
    status = rig.loop.take(command)
    assert status.state is GoalState.REJECTED
    rig.step()
    assert rig.mission() is None  # nothing drives
    return status.reason


def test_bad_missions_get_a_clear_reason_and_the_robot_stays_stopped() -> None:
    rig = Rig()
    rig.loop.on_map(room_image())
    assert refused(rig, PlaceCommand(1, 1, "kitchen")) is GoalReason.UNKNOWN_PLACE
    rig.pose = None  # localization lost
    assert refused(rig, PlaceCommand(2, 2, "desk")) is GoalReason.NOT_LOCALIZED
    assert refused(rig, ExploreCommand(3, 3)) is GoalReason.NOT_LOCALIZED
    rig.pose = (1.0, 2.0, 0.0)
    boxed = room_image()
    boxed.pixels[20:60, 0:40] = OCCUPIED_VALUE  # a 2 x 2 m block over the robot: no free cell within reach
    rig.loop.on_map(boxed)
    assert refused(rig, PlaceCommand(4, 4, "desk")) is GoalReason.START_BLOCKED
    assert refused(rig, ExploreCommand(5, 5)) is GoalReason.START_BLOCKED
    walls_only = room_image()
    walls_only.pixels[1:-1, 1:-1] = UNKNOWN_VALUE  # no free cell anywhere
    rig.loop.on_map(walls_only)
    assert refused(rig, PlaceCommand(6, 6, "desk")) is GoalReason.NO_FREE_SPACE
    rig.arbiter.command(StopCommand(7), 0.0)
    assert refused(rig, PlaceCommand(8, 8, "desk")) is GoalReason.STOPPED
    assert all(s.goal_id not in MISSION_GOAL_IDS for s in rig.sent)  # no goal was ever handed over


def test_a_mission_without_a_mission_loop_is_refused_by_the_arbiter() -> None:
    arbiter = CommandArbiter(0.2, 1.0)
    (status,) = arbiter.command(PlaceCommand(4, 12, "desk"), 0.0)
    assert (status.state, status.reason, status.goal_id) == (GoalState.REJECTED, GoalReason.UNKNOWN_TYPE, 12)
    assert status.command_sequence != NO_SEQUENCE


def test_return_home_drives_to_the_start_and_ends_the_unfinished_mission() -> None:
    rig = Rig()
    rig.loop.on_map(room_image())
    rig.loop.take(ExploreCommand(1, 40))
    rig.step()  # started at (1, 2): the look-around's first turn is out
    rig.pose = (1.5, 2.5, 0.0)
    assert rig.loop.take(ExploreCommand(2, 40, ExploreAction.RETURN_HOME)).state is GoalState.ACCEPTED
    rig.step()
    home = rig.mission()
    assert home is not None and (home.x_m, home.y_m) == (1.0, 2.0)  # type: ignore[attr-defined]
    assert rig.explorer.state is ExploreState.RETURNING
    rig.finish(GoalState.REACHED)
    rig.step()
    assert rig.explorer.state is ExploreState.IDLE
    assert rig.loop.ended[40].state is GoalState.CANCELLED  # home, exploration not finished


def test_a_bad_mission_while_exploring_loses_nothing_and_a_lost_pose_only_pauses_a_route() -> None:
    rig = Rig()
    rig.loop.on_map(room_image())
    rig.loop.take(ExploreCommand(1, 50))
    for _ in range(LOOK_AROUND_TURNS + 2):
        rig.step()
        goal = rig.mission()
        if goal is not None and rig.loop._looking:  # type: ignore[attr-defined]
            rig.finish(GoalState.REACHED)
    before = rig.mission()
    assert before is not None and rig.explorer.state is ExploreState.EXPLORING
    assert refused_keeping(rig, PlaceCommand(2, 51, "kitchen")) is GoalReason.UNKNOWN_PLACE
    assert refused_keeping(rig, PlaceCommand(3, 52, "desk")) is GoalReason.BUSY
    assert rig.mission() == before and rig.explorer.state is ExploreState.EXPLORING  # exploring goes on
    rig.loop.take(ExploreCommand(4, 50, ExploreAction.CANCEL))
    rig.step()
    # A route whose pose is lost half-way: nothing new is sent, the mission stays open, and it carries on.
    rig.loop.take(PlaceCommand(5, 60, "desk", come_back=True))
    rig.step()
    rig.finish(GoalState.REACHED)
    rig.pose = None
    for _ in range(3):
        rig.step()
    assert 60 not in rig.loop.ended and rig.loop.counts["passes_without_pose"] == 3
    rig.pose = (2.0, 3.0, 0.0)
    rig.step()
    back = rig.mission()
    assert back is not None and (back.x_m, back.y_m) == (1.0, 2.0)  # type: ignore[attr-defined]
    rig.finish(GoalState.REACHED)
    rig.step()
    assert rig.loop.ended[60].state is GoalState.REACHED


def refused_keeping(rig: Rig, command: PlaceCommand) -> GoalReason:
    status = rig.loop.take(command)
    assert status.state is GoalState.REJECTED
    return status.reason


def test_the_topology_names_the_places_and_a_saved_one_gives_a_new_loop_its_places() -> None:
    rig = Rig()
    rig.loop.on_map(room_image())
    data = rig.loop.topology()
    assert data is not None
    names = {f["properties"].get("metadata", {}).get("name") for f in data["features"]}
    assert {"desk", "bin"} <= names
    fresh = MissionLoop(
        FrontierExplorer(ExploreConfig(), NavConfig()),
        NavConfig(),
        CommandArbiter(0.2, 1.0),
        lambda status: None,
        lambda: (1.0, 2.0, 0.0),
        lambda: 0,
    )
    assert fresh.take(PlaceCommand(1, 1, "desk")).reason is GoalReason.UNKNOWN_PLACE
    assert set(fresh.load_topology(data)) >= {"desk", "bin"}
    fresh.on_map(room_image())
    assert fresh.take(PlaceCommand(2, 2, "desk")).state is GoalState.ACCEPTED
    assert (fresh.places["desk"].x_m, fresh.places["desk"].y_m) == (2.0, 3.0)


def _agent_starting_on(map_path: Path) -> Agent:
    """An agent whose ``slam.map`` is ``map_path``, with a mission loop that knows one place already."""
    agent = Agent(AgentConfig(file="test", devices={}, slam=SlamConfig(map=map_path)), Devices())
    agent.missions = MissionLoop(
        FrontierExplorer(ExploreConfig(), NavConfig()),
        NavConfig(),
        CommandArbiter(0.2, 1.0),
        lambda status: None,
        lambda: (1.0, 2.0, 0.0),
        lambda: 0,
        places={"dock": NamedPlace("dock", 0.5, 0.5)},
    )
    return agent


def test_the_agent_reads_the_topology_beside_its_start_map_and_a_bad_file_loses_nothing(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    rig = Rig()
    rig.loop.on_map(room_image())
    data = rig.loop.topology()
    assert data is not None
    map_path = tmp_path / "office.yaml"
    path = save_topology(data, topology_path(map_path))
    agent = _agent_starting_on(map_path)
    agent._load_topology()
    assert agent.missions is not None
    assert set(agent.missions.places) == {"dock", "desk", "bin"}
    assert (agent.missions.places["desk"].x_m, agent.missions.places["desk"].y_m) == (2.0, 3.0)
    # No file beside the map: nothing to read, nothing said.
    agent = _agent_starting_on(tmp_path / "other.yaml")
    agent._load_topology()
    assert agent.missions is not None and set(agent.missions.places) == {"dock"}
    for broken, why in (
        ("{not json", "not JSON"),
        ('{"type": "FeatureCollection", "features": 3}', "features: must be a list"),
        ("[1, 2]", "not a JSON object"),
    ):
        path.write_text(broken, encoding="utf-8")
        agent = _agent_starting_on(map_path)
        caplog.clear()
        with caplog.at_level(logging.ERROR, logger="agent.runtime.agent"):
            agent._load_topology()
        assert agent.missions is not None and set(agent.missions.places) == {"dock"}  # kept, none added
        assert f"topological map {path} not loaded" in caplog.text and why in caplog.text, caplog.text
        assert path.read_text(encoding="utf-8") == broken  # the file left as it was, for the user to mend
