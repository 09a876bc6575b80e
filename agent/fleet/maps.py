"""Robots' occupancy maps in the shared map frame: from the SLAM image to fleet cells, merged into one map,
and how well two robots' maps agree where both saw. Pure: numpy in, numpy out (docs/fleet.md, "Maps").

A grid here is ``nav_msgs/OccupancyGrid``-like: an (H, W) int8 array, row 0 the *lowest* y, -1 unknown,
0 free, 100 occupied, cell size ``resolution_m``, the lower-left corner of cell (0, 0) at ``origin``. Every
robot localizes against the same surveyed ceiling LEDs, so every robot's map is already in the one map
frame: merging is resampling onto one grid, no alignment search. What :func:`agreement` measures is how far
that holds: the fraction of cells both robots saw that they classify alike, and the shift between their
walls (the cross-correlation peak of the two occupied masks over the cells both saw, refined to a sub-cell
by a parabola through the peak and its neighbours).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = [
    "FREE",
    "OCCUPIED",
    "UNKNOWN",
    "Agreement",
    "Grid",
    "agreement",
    "grid_from_image",
    "merge",
    "resample",
]

UNKNOWN, FREE, OCCUPIED = -1, 0, 100
Int8Array = npt.NDArray[np.int8]


@dataclass(frozen=True)
class Grid:
    """Cells (row 0 = lowest y), cell size, the lower-left corner of cell (0, 0) in the map frame."""

    cells: Int8Array
    resolution_m: float
    origin_x_m: float
    origin_y_m: float

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """x_min, x_max, y_min, y_max (m)."""
        h, w = self.cells.shape
        r = self.resolution_m
        return (self.origin_x_m, self.origin_x_m + w * r, self.origin_y_m, self.origin_y_m + h * r)


def grid_from_image(
    pixels: npt.NDArray[np.uint8],
    resolution_m: float,
    origin: tuple[float, float],
    occupied_thresh: float = 0.65,
    free_thresh: float = 0.196,
) -> Grid:
    """A map_server image (row 0 the top, 0 black = occupied, 254 free, 205 unknown; ``agent.slam.render``)
    -> a grid: occupied where p = (255 - value) / 255 > occupied_thresh, free where p < free_thresh."""
    p = (255.0 - pixels.astype(np.float64)) / 255.0
    cells = np.full(pixels.shape, UNKNOWN, np.int8)
    cells[p < free_thresh] = FREE
    cells[p > occupied_thresh] = OCCUPIED
    return Grid(np.ascontiguousarray(cells[::-1]), float(resolution_m), float(origin[0]), float(origin[1]))


def resample(
    grid: Grid, resolution_m: float, origin: tuple[float, float], shape: tuple[int, int]
) -> Int8Array:
    """``grid`` on another grid (nearest cell centre); unknown outside it."""
    h, w = shape
    xs = origin[0] + (np.arange(w) + 0.5) * resolution_m
    ys = origin[1] + (np.arange(h) + 0.5) * resolution_m
    cols = np.floor((xs - grid.origin_x_m) / grid.resolution_m).astype(np.int64)
    rows = np.floor((ys - grid.origin_y_m) / grid.resolution_m).astype(np.int64)
    gh, gw = grid.cells.shape
    out = np.full(shape, UNKNOWN, np.int8)
    ci, ri = (cols >= 0) & (cols < gw), (rows >= 0) & (rows < gh)
    out[np.ix_(ri, ci)] = grid.cells[np.ix_(rows[ri], cols[ci])]
    return out


def common_frame(grids: list[Grid]) -> tuple[float, tuple[float, float], tuple[int, int]]:
    """The finest resolution and the extent covering every grid: (resolution, origin, (H, W))."""
    if not grids:
        raise ValueError("no maps")
    res = min(g.resolution_m for g in grids)
    x0 = min(g.bounds[0] for g in grids)
    x1 = max(g.bounds[1] for g in grids)
    y0 = min(g.bounds[2] for g in grids)
    y1 = max(g.bounds[3] for g in grids)
    shape = (max(1, math.ceil((y1 - y0) / res - 1e-9)), max(1, math.ceil((x1 - x0) / res - 1e-9)))
    return res, (x0, y0), shape


def merge(grids: list[Grid]) -> Grid:
    """One map of all: occupied where any robot saw occupied, free where any saw free and none occupied,
    unknown where nobody saw."""
    res, origin, shape = common_frame(grids)
    out = np.full(shape, UNKNOWN, np.int8)
    for g in grids:
        cells = resample(g, res, origin, shape)
        out[(cells == FREE) & (out == UNKNOWN)] = FREE
        out[cells == OCCUPIED] = OCCUPIED
    return Grid(out, res, origin[0], origin[1])


@dataclass(frozen=True)
class Agreement:
    """Two robots' maps where both saw: ``overlap_cells`` (known in both), ``agree`` (the fraction of those
    both call free or both occupied), ``shift_m`` (dx, dy: how far b's walls sit from a's, None with too
    few walls in the overlap) and its norm, ``walls`` (occupied cells of each in the overlap)."""

    overlap_cells: int
    agree: float | None
    shift_m: tuple[float, float] | None
    walls: tuple[int, int]

    @property
    def shift_norm_m(self) -> float | None:
        return None if self.shift_m is None else math.hypot(*self.shift_m)


MIN_WALL_CELLS = 20


def _parabola(lo: float, mid: float, hi: float) -> float:
    denom = lo - 2.0 * mid + hi
    return 0.0 if denom >= 0 else float(np.clip(0.5 * (lo - hi) / denom, -0.5, 0.5))


def agreement(a: Grid, b: Grid, max_shift_m: float = 0.3) -> Agreement:
    """How ``a`` and ``b`` agree where both saw (on the finer of their grids over both extents)."""
    res, origin, shape = common_frame([a, b])
    ca, cb = resample(a, res, origin, shape), resample(b, res, origin, shape)
    both = (ca != UNKNOWN) & (cb != UNKNOWN)
    n = int(both.sum())
    agree = float(((ca == cb) & both).sum() / n) if n else None
    # Walls near the overlap (dilated by the search radius, so a wall one side of the other is still in).
    k = max(1, round(max_shift_m / res))
    region = _dilate(both, k)
    wa = ((ca == OCCUPIED) & region).astype(np.float64)
    wb = ((cb == OCCUPIED) & region).astype(np.float64)
    walls = (int(wa.sum()), int(wb.sum()))
    if min(walls) < MIN_WALL_CELLS:
        return Agreement(n, agree, None, walls)
    # Blur by a cell so that walls a cell apart still correlate smoothly (the peak's parabola needs it).
    wa, wb = _blur(wa), _blur(wb)
    scores = np.zeros((2 * k + 1, 2 * k + 1))
    h, w = shape
    for dy in range(-k, k + 1):
        for dx in range(-k, k + 1):
            # b shifted by (dx, dy) cells against a
            ya, yb = slice(max(0, dy), min(h, h + dy)), slice(max(0, -dy), min(h, h - dy))
            xa, xb = slice(max(0, dx), min(w, w + dx)), slice(max(0, -dx), min(w, w - dx))
            scores[dy + k, dx + k] = float((wa[ya, xa] * wb[yb, xb]).sum())
    iy, ix = np.unravel_index(int(np.argmax(scores)), scores.shape)
    fy = _parabola(scores[iy - 1, ix], scores[iy, ix], scores[iy + 1, ix]) if 0 < iy < 2 * k else 0.0
    fx = _parabola(scores[iy, ix - 1], scores[iy, ix], scores[iy, ix + 1]) if 0 < ix < 2 * k else 0.0
    # The score at (dx, dy) pairs a's cell (y, x) with b's (y - dy, x - dx): at the peak b's walls sit
    # (-dx, -dy) cells from a's.
    shift = (-(float(ix) - k + fx) * res, -(float(iy) - k + fy) * res)
    return Agreement(n, agree, (round(float(shift[0]), 4) + 0.0, round(float(shift[1]), 4) + 0.0), walls)


def _dilate(mask: npt.NDArray[np.bool_], k: int) -> npt.NDArray[np.bool_]:
    out = mask.copy()
    for _ in range(k):
        grown = out.copy()
        grown[1:, :] |= out[:-1, :]
        grown[:-1, :] |= out[1:, :]
        grown[:, 1:] |= out[:, :-1]
        grown[:, :-1] |= out[:, 1:]
        out = grown
    return out


def _blur(x: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """A [1/4, 1/2, 1/4] kernel along both axes (zero outside)."""
    y = 0.5 * x
    y[1:, :] += 0.25 * x[:-1, :]
    y[:-1, :] += 0.25 * x[1:, :]
    out = 0.5 * y
    out[:, 1:] += 0.25 * y[:, :-1]
    out[:, :-1] += 0.25 * y[:, 1:]
    return out
