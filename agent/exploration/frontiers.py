"""Frontier detection on an occupancy grid: free cells next to unknown ones, clustered, small clusters
dropped.

Grid convention as ``agent.navigation.costmap``: cell (row, col) covers x in [x0 + col res, ...), y in
[y0 + row res, ...) (rows along +y). A frontier cell is a *free* cell with an *unknown* 4-neighbour
(explore_lite marks the unknown cell instead; the free side is where the robot can stand and look from).
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


def frontier_mask(free: BoolArray, unknown: BoolArray) -> BoolArray:
    """Free cells with at least one unknown 4-neighbour (cells off the grid count as known)."""
    near = np.zeros_like(unknown)
    near[1:, :] |= unknown[:-1, :]
    near[:-1, :] |= unknown[1:, :]
    near[:, 1:] |= unknown[:, :-1]
    near[:, :-1] |= unknown[:, 1:]
    out: BoolArray = free & near
    return out


def detect_frontiers(grid: GridMap, min_size_m: float) -> list[Frontier]:
    """The frontier clusters of ``grid`` at least ``min_size_m`` long, longest first."""
    mask = frontier_mask(grid.free, grid.unknown)
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
