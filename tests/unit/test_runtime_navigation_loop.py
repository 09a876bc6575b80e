"""The navigation loop between the runtime and agent.navigation: the SLAM image as the costmap's static
layer, goals checked with a reason, a scan that shows an obstacle in the way zeroing the wheels at once
(from that scan, not the next control step), a reached goal ended at the arbiter and reported."""

from __future__ import annotations

import math

import numpy as np

from agent.navigation.config import NavConfig
from agent.runtime.arbiter import CommandArbiter, DriveSource
from agent.runtime.motion import DriveCommand
from agent.runtime.navigation_loop import NavigationLoop, failure_reason, static_layers
from agent.slam.render import FREE_VALUE, OCCUPIED_VALUE, UNKNOWN_VALUE, OccupancyImage
from drivers.samples import Scan
from firmware_protocol.command_frame import GoalCommand, GoalReason, GoalState, GoalStatus

RES = 0.05


def room_image() -> OccupancyImage:
    """A 6 x 4 m room (walls on its border), origin (-1, -2); the strip along its north wall (y from 1.45
    to 1.95 m) not seen yet."""
    h, w = int(4 / RES), int(6 / RES)
    pixels = np.full((h, w), FREE_VALUE, np.uint8)
    pixels[1:11, 1:-1] = UNKNOWN_VALUE  # image row 0 is the top
    pixels[[0, -1], :] = OCCUPIED_VALUE
    pixels[:, [0, -1]] = OCCUPIED_VALUE
    return OccupancyImage(pixels, RES, (-1.0, -2.0, 0.0))


class Clock:
    def __init__(self) -> None:
        self.ns = 1_000_000_000

    def __call__(self) -> int:
        return self.ns


def make(
    pose: tuple[float, float, float] | None = (0.0, 0.0, 0.0),
) -> tuple[NavigationLoop, DriveCommand, list[GoalStatus], Clock]:
    clock = Clock()
    drive = DriveCommand(0.5, 0.5, 0.22, 2.0)
    answers: list[GoalStatus] = []
    arbiter = CommandArbiter(0.22, 2.0)
    loop = NavigationLoop(
        NavConfig(), (0.0, 0.0, 0.0), drive, arbiter, lambda s, a: answers.append(s), lambda: pose, clock
    )
    arbiter._check_goal = loop.check_goal  # the agent wires it so
    return loop, drive, answers, clock


def test_the_map_image_becomes_the_costmaps_grid_rows_along_y() -> None:
    spec, occupied, unknown = static_layers(room_image())
    assert spec.origin_m == (-1.0, -2.0) and spec.shape == (80, 120)
    assert unknown[-2, 1:-1].all() and not unknown[1].any()  # the north strip is in the last rows
    assert occupied[0].all() and occupied[-1].all()


def test_goals_are_checked_with_a_reason() -> None:
    loop, _, _, _ = make()
    assert loop.check_goal(GoalCommand(1, 1, 1.0, 0.0)) is GoalReason.NOT_LOCALIZED  # no map yet
    loop.on_map(room_image())
    assert loop.check_goal(GoalCommand(1, 1, 1.0, 0.0)) is None
    assert loop.check_goal(GoalCommand(1, 2, 30.0, 0.0)) is GoalReason.OUTSIDE_MAP
    assert loop.check_goal(GoalCommand(1, 3, -0.98, 0.0)) is GoalReason.IN_OBSTACLE  # at the west wall
    assert loop.check_goal(GoalCommand(1, 4, 1.0, 1.7)) is GoalReason.UNREACHABLE  # unknown space
    assert loop.check_goal(GoalCommand(1, 5, 1.0, 1.7, allow_unknown=True)) is None
    blind, _, _, _ = make(pose=None)
    blind.on_map(room_image())
    assert blind.check_goal(GoalCommand(1, 1, 1.0, 0.0)) is GoalReason.NOT_LOCALIZED


def scan_with_obstacle_ahead(distance_m: float, t_ns: int) -> Scan:
    angles = np.linspace(-math.pi, math.pi, 682, endpoint=False)
    ranges = np.full(angles.shape, 3000, np.int32)
    ranges[np.abs(angles) < 0.2] = int(distance_m * 1000)
    return Scan(ranges, float(angles[0]), float(angles[1] - angles[0]), 20, 5600, 0, t_ns)


def test_a_scan_showing_an_obstacle_in_the_way_zeroes_the_wheels_from_that_scan() -> None:
    loop, drive, _, clock = make()
    loop.on_map(room_image())
    arbiter = loop.arbiter
    arbiter.command(GoalCommand(1, 7, 2.0, 0.0), clock.ns * 1e-9)
    directive, _ = arbiter.directive(clock.ns * 1e-9)
    loop(directive, clock.ns * 1e-9)
    loop.on_scan(scan_with_obstacle_ahead(2.5, clock.ns))
    clock.ns += 60_000_000
    loop(directive, clock.ns * 1e-9)
    assert drive.current(clock.ns).v_mps > 0  # on its way
    # A person steps in 0.15 m ahead: the very next scan stops the base, no control step in between.
    clock.ns += 5_000_000
    loop.on_scan(scan_with_obstacle_ahead(0.15, clock.ns))
    command = drive.current(clock.ns)
    assert (command.v_mps, command.omega_radps) == (0.0, 0.0)
    assert loop.counts["collision_stops"] == 1
    # And a controller's velocity into it is held back by the same monitor.
    v, _ = loop.guard(0.2, 0.0, clock.ns * 1e-9)
    assert v == 0.0


def test_a_reached_goal_ends_at_the_arbiter_and_is_reported() -> None:
    loop, drive, answers, clock = make(pose=(0.0, 0.0, 0.0))
    loop.on_map(room_image())
    arbiter = loop.arbiter
    arbiter.command(GoalCommand(1, 9, 0.0, 0.0), clock.ns * 1e-9)  # where the robot already is
    directive, _ = arbiter.directive(clock.ns * 1e-9)
    for _ in range(5):
        clock.ns += 60_000_000
        loop(directive, clock.ns * 1e-9)
    assert [(s.goal_id, s.state) for s in answers][-1] == (9, GoalState.REACHED)
    assert arbiter.directive(clock.ns * 1e-9)[0].source is DriveSource.NONE
    assert drive.current(clock.ns).v_mps == 0.0


def test_failure_texts_map_to_reasons() -> None:
    assert failure_reason("timed out after 600 s") is GoalReason.TIMEOUT
    assert failure_reason("unreachable: no free way") is GoalReason.UNREACHABLE
    assert failure_reason("goal_blocked: in a wall") is GoalReason.IN_OBSTACLE
    assert failure_reason("still blocked after 4 recoveries") is GoalReason.BLOCKED


def test_a_fleet_goal_is_driven_and_the_other_robots_go_on_the_costmap_each_step() -> None:
    loop, drive, answers, clock = make()
    loop.on_map(room_image())
    others = [(1.0, 0.0, 0.105)]
    loop.others = lambda: list(others)  # FleetLoop.obstacles, as FleetLoop.for_agent wires it
    arbiter = loop.arbiter
    assert (
        arbiter.fleet_goal(GoalCommand(0xFFFF, 0x8000, 2.0, -1.0), clock.ns * 1e-9)[0].state
        is GoalState.ACCEPTED
    )
    directive, _ = arbiter.directive(clock.ns * 1e-9)
    assert directive.source is DriveSource.FLEET
    loop(directive, clock.ns * 1e-9)
    clock.ns += 60_000_000
    loop(directive, clock.ns * 1e-9)
    nav = loop.navigator
    assert nav is not None
    assert not np.isfinite(nav.costmap.cost_at(np.array([[1.0, 0.0]]))[0])  # the other robot's disc
    assert drive.current(clock.ns).v_mps >= 0.0
    others.clear()  # gone (stale): its disc leaves the costmap at the next step
    clock.ns += 60_000_000
    loop(directive, clock.ns * 1e-9)
    assert not nav.costmap.fleet.any() and np.isfinite(nav.costmap.cost_at(np.array([[1.0, 0.0]]))[0])
    assert all(s.goal_id == 0x8000 for s in answers)
