"""Set-ups the exploration tests share (``test_exploration_sp2atm``, ``test_exploration_closure``): a
10 x 4 m grid at 5 cm, a small robot, two rooms joined by a door, and an explorer started on them."""

from __future__ import annotations

import numpy as np

from agent.exploration import Command, ExploreConfig, GridMap, make_explorer
from agent.exploration.lifecycle import Explorer
from agent.navigation.config import NavConfig
from agent.navigation.costmap import GridSpec

RES = 0.05
SPEC = GridSpec((0.0, 0.0), RES, (80, 200))  # 10 x 4 m
NAV = NavConfig(radius_m=0.1, safety_margin_m=0.0)


def cells(x0: float, y0: float, x1: float, y1: float) -> tuple[slice, slice]:
    """The grid cells of the box x0-x1, y0-y1 (metres) as (rows, cols) slices."""
    return slice(round(y0 / RES), round(y1 / RES)), slice(round(x0 / RES), round(x1 / RES))


def two_rooms(door_m: float = 1.0, unknown_east: bool = False, known_to_x_m: float | None = None) -> GridMap:
    """Two 4 x 3.5 m rooms side by side (x 0.5-4.5 and 4.5-8.5, y 0.25-3.75), a door of ``door_m`` in the
    shared wall at y 2; known inside, unknown outside. ``unknown_east``: the east room's inside unknown;
    ``known_to_x_m``: only the part west of this x known (walls and all)."""
    occupied = np.zeros(SPEC.shape, bool)
    unknown = np.ones(SPEC.shape, bool)
    rows, cols = cells(0.5, 0.25, 8.55, 3.8)
    occupied[rows, cols] = True
    occupied[rows.start + 1 : rows.stop - 1, cols.start + 1 : cols.stop - 1] = False
    occupied[cells(4.5, 0.25, 4.55, 3.8)] = True
    occupied[cells(4.5, 2.0 - door_m / 2, 4.55, 2.0 + door_m / 2)] = False
    if known_to_x_m is None:
        unknown[rows, cols] = False
    else:
        unknown[cells(0.5, 0.25, known_to_x_m, 3.8)] = False
    if unknown_east:
        unknown[cells(4.55, 0.3, 8.5, 3.75)] = True
    return GridMap(SPEC, occupied, unknown)


def opened(grid: GridMap, x0: float, y0: float, x1: float, y1: float) -> GridMap:
    """``grid`` with the box x0-x1, y0-y1 known free (a gap in a wall)."""
    occupied, unknown = grid.occupied.copy(), grid.unknown.copy()
    rows, cols = cells(x0, y0, x1, y1)
    occupied[rows, cols] = False
    unknown[rows, cols] = False
    return GridMap(SPEC, occupied, unknown)


def started(config: ExploreConfig, pose: tuple[float, float, float]) -> Explorer:
    """An explorer of ``config``'s kind, sent START at ``pose`` at t 0."""
    explorer = make_explorer(config, NAV)
    assert explorer.command(Command.START, pose, 0.0)
    return explorer
