"""Giving way to people walking: is the way just ahead about to be swept by a walker, and where is the
nearest place out of their way.

The costmap forbids a walker's predicted sweep (``agent.navigation.moving``). Two questions the navigator
asks of it at the control rate, between its periodic replans:

* :func:`way_ahead_blocked`: does the path's next stretch enter a forbidden cell? Then the robot stops
  where it is, outside the walker's way, and replans at once (a walker covers in one second what the
  robot drives in four);
* :func:`aside_target`: the robot stands in a walker's way and no free cell nearby leads to the goal
  (the sweep cuts it off): the nearest free cell within reach that a straight drive gets to without
  touching a wall or a scanned obstacle (walkers' sweeps may be crossed: that is what it leaves). The
  robot steps there and waits for the walker to pass.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from agent.navigation.controller import nearest_on_path, point_ahead
from agent.navigation.costmap import Costmap, FloatArray

SECTOR_RAD = math.radians(60)  # ahead of / behind the robot: within this of its heading / its back


def way_ahead_blocked(
    costmap: Costmap, path_m: FloatArray, xy: tuple[float, float], ahead_m: float, allow_unknown: bool
) -> bool:
    """Whether the path, from the point nearest ``xy`` to ``ahead_m`` further on, enters a forbidden cell
    (sampled every half cell). The robot's own cell does not count: it may be escaping."""
    if len(path_m) < 2:
        return False
    segment, fraction, _ = nearest_on_path(path_m, xy)
    step = 0.5 * costmap.spec.resolution_m
    distances = np.arange(step, ahead_m + step, step)
    points = np.array([point_ahead(path_m, segment, fraction, float(d)) for d in distances])
    here = costmap.spec.to_cell(np.array([xy]))[0]
    cells = costmap.spec.to_cell(points)
    points = points[np.any(cells != here, axis=1)]
    return bool(len(points)) and not bool(np.all(np.isfinite(costmap.cost_at(points, allow_unknown))))


def aside_target(
    costmap: Costmap,
    pose: tuple[float, float, float],
    reach_m: float,
    allow_unknown: bool,
    ahead_ok: bool = True,
    behind_ok: bool = True,
) -> FloatArray | None:
    """The nearest free cell's centre within ``reach_m`` of the robot reached in a straight line clear of
    the map's walls and the scanned obstacles (by the footprint), or None. Not ahead (within
    ``SECTOR_RAD`` of the heading) unless ``ahead_ok``, nor behind unless ``behind_ok``: the collision
    monitor's verdicts (driving towards what stops it would only leave the robot standing in the way)."""
    xy = (pose[0], pose[1])
    spec = costmap.spec
    res = spec.resolution_m
    inscribed = costmap.config.inscribed_m
    cell = spec.to_cell(np.array([xy]))[0]
    reach = math.ceil(reach_m / res)
    pad = reach + math.ceil(inscribed / res) + 2
    rows, cols = spec.shape
    r0, r1 = max(int(cell[0]) - pad, 0), min(int(cell[0]) + pad + 1, rows)
    c0, c1 = max(int(cell[1]) - pad, 0), min(int(cell[1]) + pad + 1, cols)
    if r0 >= r1 or c0 >= c1:
        return None
    solid = costmap.static_occupied[r0:r1, c0:c1] | costmap.obstacles[r0:r1, c0:c1]
    free = np.ascontiguousarray((~solid).astype(np.uint8))
    # Distance from walls and scanned obstacles only: the sweeps are what the robot is leaving.
    solid_m = np.asarray(cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE), np.float32) * res
    clear = solid_m - 0.5 * res >= inscribed
    cost = costmap.cost(allow_unknown)[r0:r1, c0:c1]
    rr, cc = np.mgrid[r0:r1, c0:c1]
    d2 = (rr - cell[0]) ** 2 + (cc - cell[1]) ** 2
    candidate = np.isfinite(cost) & (d2 <= reach * reach)
    bearing = (
        np.arctan2(spec.origin_m[1] + (rr + 0.5) * res - xy[1], spec.origin_m[0] + (cc + 0.5) * res - xy[0])
        - pose[2]
    )
    off_heading = np.abs(np.arctan2(np.sin(bearing), np.cos(bearing)))
    if not ahead_ok:
        candidate &= off_heading > SECTOR_RAD
    if not behind_ok:
        candidate &= off_heading < math.pi - SECTOR_RAD
    order = np.argsort(np.where(candidate, d2, np.iinfo(np.int64).max), axis=None)
    for flat in order[: int(np.count_nonzero(candidate))][:40]:
        r, c = divmod(int(flat), c1 - c0)
        n = max(math.ceil(math.sqrt(float(d2[r, c])) * 2), 1) + 1
        lr = np.rint(np.linspace(cell[0] - r0, r, n)).astype(np.intp)
        lc = np.rint(np.linspace(cell[1] - c0, c, n)).astype(np.intp)
        # The robot's own cell may be near the walker's returns: it is leaving it.
        away = (lr != cell[0] - r0) | (lc != cell[1] - c0)
        if np.all(clear[lr[away], lc[away]]):
            out: FloatArray = spec.to_world(np.array([[r + r0, c + c0]]))[0]
            return out
    return None


__all__ = ["aside_target", "way_ahead_blocked"]
