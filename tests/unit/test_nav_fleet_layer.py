"""The other robots' footprints on the costmap (agent.navigation.fleet_layer, Costmap.set_fleet): a disc of
their radius, inflated by this robot's footprint, that the planner routes around; gone when removed."""

from __future__ import annotations

import math

import numpy as np

from agent.navigation.config import NavConfig
from agent.navigation.costmap import Costmap, GridSpec
from agent.navigation.fleet_layer import disc_cells
from agent.navigation.planner import GlobalPlanner

SPEC = GridSpec((0.0, 0.0), 0.05, (40, 120))  # a corridor 6 m long, 2 m wide


def test_a_disc_marks_the_cells_within_its_radius_and_nothing_off_the_grid() -> None:
    cells = disc_cells(SPEC, [(3.0, 1.0, 0.2)])
    rows, cols = np.nonzero(cells)
    centres = SPEC.to_world(np.stack([rows, cols], axis=1))
    d = np.hypot(centres[:, 0] - 3.0, centres[:, 1] - 1.0)
    assert d.max() <= 0.2 + 0.025 + 1e-9
    area = cells.sum() * 0.05**2
    assert math.pi * 0.2**2 * 0.9 < area < math.pi * 0.225**2 * 1.1
    assert not disc_cells(SPEC, [(-5.0, 1.0, 0.2), (math.nan, 1.0, 0.2), (1.0, 1.0, math.inf)]).any()
    edge = disc_cells(SPEC, [(0.0, 0.0, 0.1)])  # clipped at the corner, not wrapped
    assert edge[:3, :3].any() and not edge[-3:, :].any() and not edge[:, -3:].any()
    tiny = disc_cells(SPEC, [(1.01, 1.01, 0.0)])
    assert tiny.sum() == 1 and tiny[20, 20]


def test_another_robot_in_the_corridor_is_avoided_and_forgotten_when_removed() -> None:
    config = NavConfig()
    costmap = Costmap(SPEC, np.zeros(SPEC.shape, bool), np.zeros(SPEC.shape, bool), config)
    start, goal = (0.5, 1.0), (5.5, 1.0)
    straight = GlobalPlanner().plan(costmap, start, goal)
    assert straight.ok
    assert np.abs(straight.path_m[:, 1] - 1.0).max() < 0.05
    before = costmap.version
    costmap.set_fleet(disc_cells(SPEC, [(3.0, 1.0, 0.105)]))
    assert costmap.version > before
    # The two footprints may not touch: the other robot's disc is lethal out to its radius plus ours.
    assert not np.isfinite(costmap.cost_at(np.array([[3.0, 1.0 + 0.105 + config.inscribed_m - 0.03]]))[0])
    around = GlobalPlanner().plan(costmap, start, goal)
    assert around.ok
    gap = np.hypot(around.path_m[:, 0] - 3.0, around.path_m[:, 1] - 1.0).min()
    assert gap >= 0.105 + config.inscribed_m - 0.05  # within a cell of the two radii
    costmap.set_fleet(disc_cells(SPEC, []))  # stale: dropped by the fleet loop, so gone here
    assert np.isfinite(costmap.cost_at(np.array([[3.0, 1.0]]))[0])
