"""Giving way to walkers: a walker's sweep just ahead on the path stops the robot outside it at once
(not at the next periodic replan), a sweep that cuts the goal off is waited out without spending the
recoveries, and a robot standing in a sweep steps to the nearest place out of it, never through a wall."""

from __future__ import annotations

import math

import numpy as np

from agent.navigation.config import NavConfig
from agent.navigation.costmap import Costmap, GridSpec
from agent.navigation.give_way import aside_target, way_ahead_blocked
from agent.navigation.navigator import Goal, Navigator, NavStatus

SPEC = GridSpec((0.0, 0.0), 0.05, (40, 160))  # an 8 x 2 m corridor


def _costmap() -> Costmap:
    occupied = np.zeros(SPEC.shape, bool)
    occupied[[0, 39], :] = True
    return Costmap(SPEC, occupied, np.zeros(SPEC.shape, bool), NavConfig())


def _band(x0_m: float, x1_m: float, y0_m: float = 0.0, y1_m: float = 2.0) -> np.ndarray:
    """A walker's sweep: the cells of a rectangle."""
    cells = np.zeros(SPEC.shape, bool)
    cells[int(y0_m / 0.05) : int(y1_m / 0.05), int(x0_m / 0.05) : int(x1_m / 0.05)] = True
    return cells


def test_a_sweep_just_ahead_on_the_path_is_seen_and_one_further_on_is_not() -> None:
    costmap = _costmap()
    path = np.array([[1.0, 1.0], [7.0, 1.0]])
    costmap.set_predicted(_band(1.6, 2.0))  # 0.6 m ahead: inflated by the footprint, 0.475 m
    assert way_ahead_blocked(costmap, path, (1.0, 1.0), 0.5, False)
    costmap.set_predicted(_band(2.2, 2.6))
    assert not way_ahead_blocked(costmap, path, (1.0, 1.0), 0.5, False)


def test_the_place_aside_is_out_of_the_sweep_and_not_through_a_wall() -> None:
    costmap = _costmap()
    costmap.set_predicted(_band(0.0, 8.0, 0.9, 1.4))  # a walker's way along the corridor
    target = aside_target(costmap, (3.0, 1.1, 0.0), 1.0, False)
    assert target is not None
    assert math.isfinite(costmap.cost_at(target[None, :])[0])
    assert abs(target[0] - 3.0) < 0.1 and target[1] < 0.8  # straight to the nearer side
    # A wall across the corridor beside the robot: nothing beyond it is offered.
    occupied = costmap.static_occupied.copy()
    occupied[:, 70] = True
    walled = Costmap(SPEC, occupied, np.zeros(SPEC.shape, bool), NavConfig())
    walled.set_predicted(_band(2.0, 3.55))
    target = aside_target(walled, (3.2, 1.0, 0.0), 1.0, False)
    assert target is None or target[0] < 3.5


def test_a_sweep_cutting_the_way_stops_the_robot_at_once_and_is_waited_out_without_recoveries() -> None:
    config = NavConfig()
    navigator = Navigator(config, _costmap())
    navigator.set_goal(Goal(6.0, 1.0, 0.0), 0.0)
    pose = (1.0, 1.0, 0.0)
    t = 0.0
    for _ in range(10):  # under way
        t += 0.05
        out = navigator.step(t, pose)
    assert out.status is NavStatus.ACTIVE and out.command.v_mps > 0.0
    # A walker crosses the corridor 0.3 m ahead: their sweep closes it, from wall to wall.
    navigator.costmap.set_predicted(_band(1.3, 1.7))
    t += 0.05
    out = navigator.step(t, pose)
    assert out.command.v_mps == 0.0 and out.status is NavStatus.RECOVERING
    for _ in range(100):  # 5 s waiting for them to pass
        t += 0.05
        out = navigator.step(t, pose)
        assert out.command.v_mps == 0.0
    assert navigator.recovery.rounds == 0 and navigator.give_ways == 1
    navigator.costmap.set_predicted(_band(0.0, 0.0))  # they have passed
    for _ in range(20):
        t += 0.05
        out = navigator.step(t, pose)
    assert out.status is NavStatus.ACTIVE and out.command.v_mps > 0.0


def test_a_robot_standing_in_a_walkers_way_that_cuts_the_goal_off_steps_out_of_it() -> None:
    config = NavConfig()
    navigator = Navigator(config, _costmap())
    # The sweep covers the corridor from x = 2 to 4 but leaves a strip along the south wall, where the
    # robot can stand, that does not lead on to the goal.
    navigator.costmap.set_predicted(_band(2.0, 4.0, 0.45, 2.0) | _band(3.0, 4.0, 0.0, 2.0))
    navigator.set_goal(Goal(6.0, 1.0, 0.0), 0.0)
    pose = (2.5, 0.9, -math.pi / 2)  # facing the south wall
    out = navigator.step(0.05, pose)
    assert out.status is NavStatus.RECOVERING and navigator.give_ways == 1
    out = navigator.step(0.10, pose)
    assert out.command.v_mps > 0.0  # towards the strip, ahead of it
    assert navigator.recovery.rounds == 0


def test_no_place_aside_is_offered_in_the_direction_the_collision_monitor_blocks() -> None:
    costmap = _costmap()
    costmap.set_predicted(_band(2.5, 3.3, 0.0, 2.0))  # the robot at x = 3.2 in it, facing +x
    target = aside_target(costmap, (3.2, 1.0, 0.0), 1.0, False)
    assert target is not None and abs(math.atan2(target[1] - 1.0, target[0] - 3.2)) < math.radians(60)
    for behind_ok in (True, False):
        target = aside_target(costmap, (3.2, 1.0, 0.0), 1.0, False, ahead_ok=False, behind_ok=behind_ok)
        assert target is not None and math.isfinite(costmap.cost_at(target[None, :])[0])
        assert abs(math.atan2(target[1] - 1.0, target[0] - 3.2)) > math.radians(60)
