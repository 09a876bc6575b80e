"""A passage shut since the map saw it open: the evidence test behind pruning a blocked branch at its first
failure instead of retrying it (a door that closed during the run; reference/eco.md §1.3: "unreachable
goals retried forever").

The map is slow to show a door that closed: it was seen open many times, and a thin door seen at a slant
is crossed by as many beams as end on it. The navigator's obstacle layer (the last scans' hits) shows it
at once. When a target fails, :func:`wall_to_wall` looks at those hits:

1. *new* hits: cells the map has free (not occupied, nor within one cell of an occupied cell: a wall's
   hits land a cell either side of it), within ``near_m`` of the target or the robot;
2. grouped (8-connected, after a one-cell dilation that joins hits a cell or two apart);
3. a group is a closure when it bridges a gap wall to wall: the map's occupied cells within ``touch_m``
   of it span at least the robot's width plus ``margin`` and 80 % of the group's own extent, a door
   between its jambs. A person standing in a door or beside a wall touches at most one side, and is no
   closure.

The caller then checks that the closure cuts the way to the target (``FrontierExplorer.report_failed``);
only then the branch is pruned. Pure: numpy in, numpy out.
"""

from __future__ import annotations

import cv2
import numpy as np

from agent.exploration.frontiers import GridMap, dilate
from agent.navigation.costmap import BoolArray, FloatArray

TOUCH_M = 0.15  # a wall this close to a group of new hits touches it
SPAN_SHARE = 0.8  # the walls touched span at least this share of the group's extent
MARGIN_M = 0.1  # ... and at least the robot's width plus this (a gap the robot could have passed)


def wall_to_wall(
    grid: GridMap,
    hits_m: FloatArray,
    near_m: list[tuple[float, float]],
    radius_m: float,
    near_within_m: float = 1.5,
) -> BoolArray:
    """The cells of ``grid`` that the obstacle hits ``hits_m`` ((N, 2) metres) close off wall to wall,
    near one of the points ``near_m`` (see the module docstring); all False when none do."""
    spec = grid.spec
    out = np.zeros(spec.shape, dtype=bool)
    pts = np.asarray(hits_m, dtype=np.float64).reshape(-1, 2)
    if not len(pts) or not near_m:
        return out
    anchors = np.asarray(near_m, dtype=np.float64).reshape(-1, 2)
    close = np.min(np.hypot(pts[:, None, 0] - anchors[None, :, 0], pts[:, None, 1] - anchors[None, :, 1]), 1)
    pts = pts[close <= near_within_m]
    cells = spec.to_cell(pts)
    cells = cells[spec.inside(cells)]
    if not len(cells):
        return out
    hits = np.zeros(spec.shape, dtype=bool)
    hits[cells[:, 0], cells[:, 1]] = True
    walls = grid.occupied
    new = hits & ~dilate(walls, 1) & ~grid.unknown
    if not new.any():
        return out
    joined = dilate(new, 1)
    count, labels = cv2.connectedComponents(joined.astype(np.uint8), connectivity=8, ltype=cv2.CV_32S)
    res = spec.resolution_m
    touch = max(round(TOUCH_M / res), 1)
    for k in range(1, count):
        group = labels == k
        members = np.argwhere(group)
        extent = _span(members) * res
        contacts = np.argwhere(dilate(group, touch) & walls)
        if len(contacts) < 2:
            continue
        span = _span(contacts) * res
        if span >= max(2.0 * radius_m + MARGIN_M, SPAN_SHARE * extent):
            out |= group
    return out


def _span(cells: np.ndarray) -> float:
    """The largest distance between two of the (N, 2) cells, in cells (exact up to 400 cells, else
    along the principal axes' extreme points)."""
    pts = cells.astype(np.float64)
    if len(pts) > 400:
        centred = pts - pts.mean(axis=0)
        _, _, axes = np.linalg.svd(centred, full_matrices=False)
        proj = centred @ axes.T
        picks = np.concatenate([np.argmin(proj, axis=0), np.argmax(proj, axis=0)])
        pts = pts[picks]
    d = np.hypot(pts[:, None, 0] - pts[None, :, 0], pts[:, None, 1] - pts[None, :, 1])
    return float(d.max(initial=0.0))
