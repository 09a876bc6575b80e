"""Frontier detection on an occupancy grid: free cells next to unknown ones, clustered, small clusters
dropped.

Grid convention as ``agent.navigation.costmap``: cell (row, col) covers x in [x0 + col res, ...), y in
[y0 + row res, ...) (rows along +y). A frontier cell is a *free* cell with an *unknown* 4-neighbour
(explore_lite marks the unknown cell instead; the free side is where the robot can stand and look from),
and none of whose 8 neighbours is occupied (see :func:`frontier_mask`).
Cells are clustered 8-connected (explore_lite's BFS; here OpenCV's connected components, C speed); a
cluster shorter than ``min_size_m`` (cells x resolution) is dropped as noise.

numpy in, numpy out: no I/O, no clock.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from agent.navigation.costmap import BoolArray, FloatArray, GridSpec, IntArray


@dataclass(frozen=True)
class GridMap:
    """What an explorer reads: the grid's place and its occupied and unknown cells (rows along +y); free is
    everything else."""

    spec: GridSpec
    occupied: BoolArray
    unknown: BoolArray

    def __post_init__(self) -> None:
        if self.occupied.shape != self.spec.shape or self.unknown.shape != self.spec.shape:
            raise ValueError(
                f"layers {self.occupied.shape}, {self.unknown.shape} do not match the grid {self.spec.shape}"
            )

    @property
    def free(self) -> BoolArray:
        out: BoolArray = ~self.occupied & ~self.unknown
        return out


@dataclass(frozen=True)
class Frontier:
    """One cluster of frontier cells: ``cells`` (N, 2) (row, col), their world centres ``points_m``,
    ``length_m`` (cells x resolution, explore_lite's size) and ``centroid_m``."""

    cells: IntArray
    points_m: FloatArray
    length_m: float
    centroid_m: tuple[float, float]


def frontier_mask(free: BoolArray, unknown: BoolArray, occupied: BoolArray | None = None) -> BoolArray:
    """Free cells with at least one unknown 4-neighbour (cells off the grid count as known) and, given
    ``occupied``, no occupied cell among their 8 neighbours.

    Why the second rule: a wall's surface rarely falls on a cell boundary, so range noise puts some hits in
    the cell just beyond it; that cell's misses can leave it free with never-seen cells behind it: a
    "frontier" along the far side of every wall, which no position of the robot can ever see past."""
    near = _shifted_any(unknown, diagonal=False)
    out: BoolArray = free & near
    if occupied is not None:
        out &= ~_shifted_any(occupied, diagonal=True) & ~occupied
    return out


def _shifted_any(mask: BoolArray, diagonal: bool) -> BoolArray:
    """Cells with a True 4-neighbour (8-neighbour with ``diagonal``)."""
    out = np.zeros_like(mask)
    out[1:, :] |= mask[:-1, :]
    out[:-1, :] |= mask[1:, :]
    out[:, 1:] |= mask[:, :-1]
    out[:, :-1] |= mask[:, 1:]
    if diagonal:
        out[1:, 1:] |= mask[:-1, :-1]
        out[1:, :-1] |= mask[:-1, 1:]
        out[:-1, 1:] |= mask[1:, :-1]
        out[:-1, :-1] |= mask[1:, 1:]
    return out


def detect_frontiers(grid: GridMap, min_size_m: float, min_unknown_m2: float = 0.0) -> list[Frontier]:
    """The frontier clusters of ``grid`` at least ``min_size_m`` long, longest first; unknown pockets (4-
    connected) smaller than ``min_unknown_m2`` do not make frontiers (the inside of a wall seen from both
    sides, a gap between two hits: nothing a robot could drive to see)."""
    unknown = grid.unknown
    if min_unknown_m2 > 0.0 and unknown.any():
        count, labels, stats, _ = cv2.connectedComponentsWithStats(
            unknown.astype(np.uint8), connectivity=4, ltype=cv2.CV_32S
        )
        small = stats[:, cv2.CC_STAT_AREA] * grid.spec.resolution_m**2 < min_unknown_m2
        small[0] = False  # label 0 is the known cells
        unknown = unknown & ~small[labels]
    mask = frontier_mask(grid.free, unknown, grid.occupied)
    if not mask.any():
        return []
    count, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8, ltype=cv2.CV_32S)
    res = grid.spec.resolution_m
    rows, cols = np.nonzero(mask)
    ids = labels[rows, cols]
    order = np.argsort(ids, kind="stable")
    rows, cols, ids = rows[order], cols[order], ids[order]
    starts = np.searchsorted(ids, np.arange(1, count))
    ends = np.append(starts[1:], len(ids))
    out: list[Frontier] = []
    for a, b in zip(starts, ends, strict=True):
        n = int(b - a)
        if n * res < min_size_m:
            continue
        cells: IntArray = np.stack([rows[a:b], cols[a:b]], axis=1).astype(np.intp)
        points = grid.spec.to_world(cells)
        centroid = points.mean(axis=0)
        out.append(Frontier(cells, points, n * res, (float(centroid[0]), float(centroid[1]))))
    out.sort(key=lambda f: -f.length_m)
    return out


def disk(spec: GridSpec, centre_m: tuple[float, float], radius_m: float) -> BoolArray:
    """Cells whose centres lie within ``radius_m`` of ``centre_m``."""
    rows, cols = spec.shape
    y = spec.origin_m[1] + (np.arange(rows) + 0.5) * spec.resolution_m
    x = spec.origin_m[0] + (np.arange(cols) + 0.5) * spec.resolution_m
    out: BoolArray = ((x[None, :] - centre_m[0]) ** 2 + (y[:, None] - centre_m[1]) ** 2) <= radius_m**2
    return out


def dilate(mask: BoolArray, radius_cells: int) -> BoolArray:
    """``mask`` grown by a disk of ``radius_cells``."""
    if radius_cells <= 0:
        return mask.copy()
    size = 2 * radius_cells + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    out: BoolArray = np.asarray(cv2.dilate(mask.astype(np.uint8), kernel)).astype(bool)
    return out
