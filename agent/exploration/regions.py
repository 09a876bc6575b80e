"""REGION nodes: the map's free space cut into rooms at doorways (SP2ATM's upper level, reference/eco.md
§1.1 step 4: "group places into regions at doorway-like gaps, width about 0.7-1.2 m").

A doorway is a narrow passage between free areas. On the grid: the distance from every free cell to the
nearest occupied cell (OpenCV's distance transform). The cells farther than half of ``door_width_m`` from
any wall are the *cores*: a passage narrower than ``door_width_m`` (a door, a gap between furniture) has no
core cells, so it cuts the cores apart, while a corridor wider than it keeps a core along its middle. Each
8-connected core with at least ``min_area_m2`` of area is a room; every other free cell joins the room whose
core is nearest (a door's cells go to one side or the other). A region's outline is the traced border of
its cells (world metres, simplified to within a cell).

Unknown cells are not walls here: a room seen only through its door has no core yet, and grows as it is
mapped. The result changes as the map grows; ``Htm.set_regions`` keeps ids and names across changes.

numpy in, numpy out: no I/O, no clock.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from agent.exploration.frontiers import GridMap
from agent.navigation.costmap import BoolArray, IntArray

Polygon = tuple[tuple[float, float], ...]


@dataclass(frozen=True)
class Region:
    """One room: ``label`` its value in the label image, ``polygon`` its outline (world metres),
    ``area_m2`` its free area, ``core_m2`` the area of its core (the part wider than a door)."""

    label: int
    polygon: Polygon
    area_m2: float
    core_m2: float


def find_regions(
    grid: GridMap, door_width_m: float = 1.2, min_area_m2: float = 1.0
) -> tuple[IntArray, list[Region]]:
    """The rooms of ``grid`` (see the module docstring): a label image (0: no region, k: ``Region`` k) and
    the regions, largest first."""
    if door_width_m <= 0.0 or min_area_m2 <= 0.0:
        raise ValueError("door_width_m and min_area_m2 must be positive")
    spec = grid.spec
    res = spec.resolution_m
    free = grid.free
    labels_out: IntArray = np.zeros(spec.shape, dtype=np.intp)
    if not free.any():
        return labels_out, []
    # Distance (cells) from each cell to the nearest occupied cell; with no wall at all, everything is core.
    clear = np.asarray(cv2.distanceTransform((~grid.occupied).astype(np.uint8), cv2.DIST_L2, 5))
    core = free & (clear * res > door_width_m / 2.0)
    count, comp, stats, _ = cv2.connectedComponentsWithStats(
        core.astype(np.uint8), connectivity=8, ltype=cv2.CV_32S
    )
    keep = [k for k in range(1, count) if stats[k, cv2.CC_STAT_AREA] * res * res >= min_area_m2]
    if not keep:
        return labels_out, []
    seeds = np.zeros(spec.shape, dtype=np.int32)
    for i, k in enumerate(keep, start=1):
        seeds[comp == k] = i
    # Every free cell to the nearest core (DIST_LABEL_PIXEL: the label of the nearest zero pixel).
    _, nearest = cv2.distanceTransformWithLabels(
        (seeds == 0).astype(np.uint8), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
    )
    seed_rows, seed_cols = np.nonzero(seeds)
    lookup = np.zeros(int(nearest.max()) + 1, dtype=np.int32)
    # The zero pixels of the mask are numbered in row-major order from 1.
    lookup[1 : len(seed_rows) + 1] = seeds[seed_rows, seed_cols]
    labels = lookup[nearest]
    labels[~free] = 0
    regions: list[Region] = []
    for i in range(1, len(keep) + 1):
        mask = labels == i
        polygon = outline(mask, grid)
        if len(polygon) < 3:
            continue
        core_m2 = float(np.count_nonzero(seeds == i)) * res * res
        regions.append(Region(i, polygon, float(np.count_nonzero(mask)) * res * res, core_m2))
    regions.sort(key=lambda r: -r.area_m2)
    relabel = np.zeros(len(keep) + 1, dtype=np.intp)
    out: list[Region] = []
    for new, r in enumerate(regions, start=1):
        relabel[r.label] = new
        out.append(Region(new, r.polygon, r.area_m2, r.core_m2))
    labels_out = relabel[labels]
    return labels_out, out


def outline(mask: BoolArray, grid: GridMap) -> Polygon:
    """The outer border of the largest 8-connected blob of ``mask`` as a world polygon (its border cells
    traced at half-cell steps: within half a cell of the cells' outer edges, simplified to a cell)."""
    # Upscale x2 so the traced pixel centres fall on cell corners after the shift below.
    big = cv2.resize(mask.astype(np.uint8), None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST)
    contours, _ = cv2.findContours(big, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return ()
    contour = max(contours, key=cv2.contourArea)
    contour = cv2.approxPolyDP(contour, 2.0, True).reshape(-1, 2).astype(np.float64)
    res = grid.spec.resolution_m
    x0, y0 = grid.spec.origin_m
    # Pixel (u, v) of the x2 image is the quarter of cell (v // 2, u // 2); its centre is at (u + 0.5) / 2.
    xs = x0 + (contour[:, 0] + 0.5) / 2.0 * res
    ys = y0 + (contour[:, 1] + 0.5) / 2.0 * res
    return tuple((round(float(x), 3), round(float(y), 3)) for x, y in zip(xs, ys, strict=True))
