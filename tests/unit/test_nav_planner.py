"""The global planner: shortest way round obstacles, clearance, unknown space, unreachable goals."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.navigation.config import NavConfig
from agent.navigation.costmap import Costmap, GridSpec
from agent.navigation.planner import GlobalPlanner, PlanStatus, path_is_free

SPEC = GridSpec((0.0, 0.0), 0.05, (80, 120))  # 6 x 4 m
CONFIG = NavConfig(radius_m=0.1, safety_margin_m=0.0)


def _wall_with_gap(gap_rows: slice | None) -> np.ndarray:
    """A wall along x = 3 m across the whole map, with a gap at ``gap_rows``."""
    occupied = np.zeros(SPEC.shape, bool)
    occupied[:, 60] = True
    if gap_rows is not None:
        occupied[gap_rows, 60] = False
    return occupied


def test_the_plan_goes_through_the_gap_and_is_nearly_as_short_as_the_taut_string() -> None:
    occupied = _wall_with_gap(slice(8, 20))  # gap at y = 0.4 .. 1.0
    costmap = Costmap(SPEC, occupied, np.zeros(SPEC.shape, bool), CONFIG)
    plan = GlobalPlanner(clearance_weight=0.0).plan(costmap, (1.0, 3.0), (5.0, 3.0))
    assert plan.ok
    # The taut string bends round the gap's upper post at (3.0, 1.0), kept off it by the radius.
    post = np.array([3.0, 1.0 - CONFIG.radius_m])
    taut = math.dist((1.0, 3.0), post) * 2
    assert taut <= plan.length_m <= taut * 1.03
    assert path_is_free(costmap, plan.path_m)
    # Any-angle: a handful of corners, not a staircase of cells.
    assert len(plan.path_m) <= 5 < plan.grid_cells


def test_the_clearance_term_keeps_the_path_off_a_wall_it_could_hug() -> None:
    occupied = np.zeros(SPEC.shape, bool)
    occupied[40, :] = True  # a wall along y = 2, start and goal just below it
    costmap = Costmap(SPEC, occupied, np.zeros(SPEC.shape, bool), NavConfig(radius_m=0.1))
    start, goal = (0.5, 1.8), (5.5, 1.8)
    hugging = GlobalPlanner(clearance_weight=0.0).plan(costmap, start, goal)
    keeping = GlobalPlanner(clearance_weight=5.0).plan(costmap, start, goal)
    assert hugging.ok and keeping.ok
    assert keeping.path_m[:, 1].min() < hugging.path_m[:, 1].min() - 0.1


def test_unknown_space_is_not_planned_through_unless_the_goal_allows_it() -> None:
    unknown = np.zeros(SPEC.shape, bool)
    unknown[:, 55:65] = True  # an unexplored band across the map
    costmap = Costmap(SPEC, np.zeros(SPEC.shape, bool), unknown, CONFIG)
    planner = GlobalPlanner()
    blocked = planner.plan(costmap, (1.0, 2.0), (5.0, 2.0))
    assert blocked.status is PlanStatus.UNREACHABLE
    allowed = planner.plan(costmap, (1.0, 2.0), (5.0, 2.0), allow_unknown=True)
    assert allowed.ok


@pytest.mark.parametrize(
    ("goal", "status"),
    [
        ((5.0, 2.0), PlanStatus.UNREACHABLE),
        ((3.0, 2.0), PlanStatus.GOAL_BLOCKED),
        ((9.0, 2.0), PlanStatus.GOAL_BLOCKED),
    ],
)
def test_goals_that_cannot_be_reached_are_reported_with_a_reason(
    goal: tuple[float, float], status: PlanStatus
) -> None:
    costmap = Costmap(SPEC, _wall_with_gap(None), np.zeros(SPEC.shape, bool), CONFIG)
    plan = GlobalPlanner().plan(costmap, (1.0, 2.0), goal)
    assert plan.status is status
    assert plan.reason


def test_the_search_tree_is_reused_while_the_costmap_stays_and_redone_when_it_changes() -> None:
    costmap = Costmap(SPEC, _wall_with_gap(slice(8, 20)), np.zeros(SPEC.shape, bool), CONFIG)
    planner = GlobalPlanner()
    first = planner.plan(costmap, (1.0, 3.0), (5.0, 3.0))
    moved = planner.plan(costmap, (1.5, 2.5), (5.0, 3.0))
    assert first.searched and not moved.searched
    # An obstacle appears in the gap: the next plan searches again and finds no way.
    costmap.update_scan((3.0, 0.1, math.pi / 2), np.array([0.0]), np.array([0.6]), 0.02, 5.6)
    costmap.obstacles[8:20, 60] = True
    costmap.version += 1
    again = planner.plan(costmap, (1.5, 2.5), (5.0, 3.0))
    assert again.searched and again.status is PlanStatus.UNREACHABLE


def test_a_start_inside_an_inflated_obstacle_escapes_to_the_nearest_free_cell() -> None:
    occupied = np.zeros(SPEC.shape, bool)
    occupied[40, 20] = True  # a post at (1.0, 2.0)
    costmap = Costmap(SPEC, occupied, np.zeros(SPEC.shape, bool), CONFIG)
    plan = GlobalPlanner().plan(costmap, (1.06, 2.0), (5.0, 2.0))
    assert plan.ok
    assert tuple(plan.path_m[0]) == (1.06, 2.0)
