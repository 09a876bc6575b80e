"""The other robots of the fleet as discs on the costmap grid (``Costmap.set_fleet``).

Every robot localizes in the same map frame (the surveyed ceiling LEDs), so another robot's pose from the
fleet (``agent.runtime.fleet_loop``) is where its footprint is on this robot's costmap. A disc of the
robot's radius centred there is lethal like a scan obstacle, and the costmap inflates it by this robot's own
footprint: the planner keeps the two footprints apart. Stale robots are not given here: the fleet loop drops
a robot whose pose is older than ``[fleet] peer_timeout_s``.

numpy in, numpy out: no I/O, no clock.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

from agent.navigation.costmap import BoolArray, GridSpec

__all__ = ["Disc", "disc_cells"]

Disc = tuple[float, float, float]  # x_m, y_m, radius_m in the map frame


def disc_cells(spec: GridSpec, discs: Iterable[Disc]) -> BoolArray:
    """The grid's cells covered by the discs: a cell whose centre lies within ``radius + res / 2`` of a
    disc's centre (so a disc smaller than a cell still marks the cell it stands in). Discs off the grid or
    with a coordinate that is not finite mark nothing."""
    rows, cols = spec.shape
    res = spec.resolution_m
    out = np.zeros(spec.shape, dtype=bool)
    x0, y0 = spec.origin_m
    for x, y, radius in discs:
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(radius)) or radius < 0:
            continue
        reach = radius + 0.5 * res
        c0 = max(math.floor((x - reach - x0) / res), 0)
        c1 = min(math.floor((x + reach - x0) / res), cols - 1)
        r0 = max(math.floor((y - reach - y0) / res), 0)
        r1 = min(math.floor((y + reach - y0) / res), rows - 1)
        if c0 > c1 or r0 > r1:
            continue
        cx = x0 + (np.arange(c0, c1 + 1) + 0.5) * res
        cy = y0 + (np.arange(r0, r1 + 1) + 0.5) * res
        inside = (cx[None, :] - x) ** 2 + (cy[:, None] - y) ** 2 <= reach * reach
        out[r0 : r1 + 1, c0 : c1 + 1] |= inside
    return out
