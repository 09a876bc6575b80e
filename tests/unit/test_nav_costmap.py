"""The costmap: scans mark and clear the obstacle layer; inflation by the footprint; unknown cells."""

from __future__ import annotations

import math

import numpy as np

from agent.navigation.config import NavConfig
from agent.navigation.costmap import Costmap, GridSpec

SPEC = GridSpec((0.0, 0.0), 0.05, (80, 120))  # 6 x 4 m


def _empty(config: NavConfig | None = None) -> Costmap:
    return Costmap(SPEC, np.zeros(SPEC.shape, bool), np.zeros(SPEC.shape, bool), config)


def _cell(x: float, y: float) -> tuple[int, int]:
    row, col = SPEC.to_cell(np.array([x, y]))[0]
    return int(row), int(col)


def test_a_scan_marks_its_returns_and_a_later_scan_clears_them() -> None:
    costmap = _empty()
    angles = np.array([0.0])
    assert costmap.update_scan((1.0, 2.0, 0.0), angles, np.array([2.0]), 0.02, 5.6)
    assert costmap.obstacles[_cell(3.0, 2.0)]
    assert math.isinf(costmap.cost_at(np.array([[3.0, 2.0]]))[0])
    # The obstacle walked away: the next beam goes through its cell to a wall farther on.
    assert costmap.update_scan((1.0, 2.0, 0.0), angles, np.array([3.5]), 0.02, 5.6)
    assert not costmap.obstacles[_cell(3.0, 2.0)]
    assert costmap.obstacles[_cell(4.5, 2.0)]
    assert math.isfinite(costmap.cost_at(np.array([[3.0, 2.0]]))[0])


def test_a_beam_without_return_clears_out_to_the_obstacle_range() -> None:
    costmap = _empty()
    costmap.update_scan((1.0, 2.0, 0.0), np.array([0.0]), np.array([2.0]), 0.02, 5.6)
    costmap.update_scan((1.0, 2.0, 0.0), np.array([0.0]), np.array([0.0]), 0.02, 5.6)  # no return
    assert not costmap.obstacles.any()


def test_an_unchanged_scan_does_not_bump_the_version() -> None:
    costmap = _empty()
    costmap.update_scan((1.0, 2.0, 0.0), np.array([0.0]), np.array([2.0]), 0.02, 5.6)
    version = costmap.version
    assert not costmap.update_scan((1.0, 2.0, 0.0), np.array([0.0]), np.array([2.0]), 0.02, 5.6)
    assert costmap.version == version


def test_inflation_forbids_the_footprint_and_the_cost_falls_off_with_clearance() -> None:
    config = NavConfig(radius_m=0.2, safety_margin_m=0.0, inflation_radius_m=0.8)
    occupied = np.zeros(SPEC.shape, bool)
    occupied[:, _cell(3.0, 0.0)[1]] = True  # a wall along x = 3
    costmap = Costmap(SPEC, occupied, np.zeros(SPEC.shape, bool), config)
    xs = np.array([3.1, 3.2, 3.35, 3.5, 3.7, 4.0])
    cost = costmap.cost_at(np.stack([xs, np.full_like(xs, 2.0)], axis=1))
    assert math.isinf(cost[0]) and math.isinf(cost[1])  # the footprint would touch the wall
    finite = cost[2:]
    assert np.all(np.isfinite(finite))
    assert np.all(np.diff(finite) <= 0.0) and finite[0] > finite[-1]
    assert cost[-1] == 0.0  # beyond the inflation radius


def test_unknown_cells_are_forbidden_unless_allowed() -> None:
    unknown = np.zeros(SPEC.shape, bool)
    unknown[:, 60:] = True
    costmap = Costmap(SPEC, np.zeros(SPEC.shape, bool), unknown, NavConfig())
    point = np.array([[4.5, 2.0]])
    assert math.isinf(costmap.cost_at(point)[0])
    assert math.isfinite(costmap.cost_at(point, allow_unknown=True)[0])
