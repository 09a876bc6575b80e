"""SP2ATM's admissible space tree (AST), its first level: gaps in one laser scan and the branches to them
(reference/eco.md §1.1, steps 1-2; the thresholds are that page's proposals).

Per scan, in the laser's frame (x ahead, y left), ranges clipped to ``max_range_m``, a beam without a
return counted as reaching it:

* a beam at or beyond ``open_fraction`` x ``max_range_m`` is *open*, the others *closed*;
* gaps: (a) a run of consecutive open beams (an open boundary: its chord from the first to the last
  beam's end); (b) a range discontinuity ``|rho_i - rho_i+1| > 2 r`` between neighbouring beams (an
  occlusion edge or a doorway: the chord between the two ends);
* a gap is kept when its chord is at least ``2 r + margin_m`` wide (the robot fits through);
* its branch runs from the laser towards the chord's midpoint, pulled back by ``r``; it is kept only if it
  stays inside the scan's free polygon eroded by ``r`` (every point of it within the range seen along its
  bearing, less ``r``, and at least ``r`` from every return). The branch's tip is a *possible node*.

``grid_scan`` casts such a scan on an occupancy grid from a pose (a beam ends closed at an occupied cell,
open where unknown space begins or at the range limit): the SP2ATM explorer grows its AST from the map as
it is, the robot's memory of every scan, so the tree sees the same gaps from the same place whether the
last scan was blocked by a person or not. The possible-node filter against the grid (step 3) is the
explorer's (``sp2atm_explorer``). Not written: sub-branches from gaps seen through a gap (the tree's
depth); the grid's frontiers give the explorer what lies beyond.

numpy in, numpy out: no I/O, no clock.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from agent.exploration.frontiers import GridMap
from agent.navigation.costmap import BoolArray, FloatArray


class GapKind(enum.StrEnum):
    OPEN = "open"  # a run of beams reaching the range limit
    DISCONTINUITY = "discontinuity"  # a jump in range between neighbouring beams


@dataclass(frozen=True)
class Branch:
    kind: GapKind
    chord_m: tuple[tuple[float, float], tuple[float, float]]  # the gap's two ends (laser frame)
    width_m: float
    tip_m: tuple[float, float]  # the possible node (laser frame)
    length_m: float


def scan_branches(
    angles_rad: FloatArray,
    ranges_m: FloatArray,
    max_range_m: float,
    radius_m: float,
    margin_m: float = 0.1,
    open_fraction: float = 0.95,
    opened: BoolArray | None = None,
) -> list[Branch]:
    """The AST's branches for one scan (see the module docstring), in beam order. ``opened`` marks the
    open beams explicitly (a scan cast on a grid: a beam that ran into unknown space is open where the
    unknown begins); by default a beam is open at ``open_fraction`` of the range limit."""
    angles = np.asarray(angles_rad, dtype=np.float64)
    rho = np.asarray(ranges_m, dtype=np.float64)
    if angles.shape != rho.shape or angles.ndim != 1:
        raise ValueError(f"angles {angles.shape} and ranges {rho.shape} must be the same 1-D shape")
    rho = np.where((rho <= 0.0) | ~np.isfinite(rho), max_range_m, np.minimum(rho, max_range_m))
    ends = np.stack([rho * np.cos(angles), rho * np.sin(angles)], axis=1)
    if opened is None:
        opened = rho >= open_fraction * max_range_m
    elif opened.shape != rho.shape:
        raise ValueError(f"opened {opened.shape} must match the ranges {rho.shape}")
    returns = ends[~opened]
    chords: list[tuple[GapKind, int, int]] = []
    i, n = 0, len(rho)
    while i < n:  # (a) runs of open beams
        if opened[i]:
            j = i
            while j + 1 < n and opened[j + 1]:
                j += 1
            chords.append((GapKind.OPEN, i, j))
            i = j + 1
        else:
            i += 1
    jumps = np.flatnonzero(np.abs(np.diff(rho)) > 2.0 * radius_m)
    for k in jumps:  # (b) discontinuities (an open run's own edges are covered by (a))
        if not (opened[k] or opened[k + 1]):
            chords.append((GapKind.DISCONTINUITY, int(k), int(k + 1)))
    chords.sort(key=lambda c: c[1])
    out: list[Branch] = []
    for kind, a, b in chords:
        pa, pb = ends[a], ends[b]
        width = float(np.hypot(*(pb - pa)))
        if width < 2.0 * radius_m + margin_m:
            continue
        mid = (pa + pb) / 2.0
        reach = float(np.hypot(*mid)) - radius_m
        if reach <= 0.0:
            continue
        tip = mid * (reach / (reach + radius_m))
        if not _admissible(tip, angles, rho, returns, radius_m):
            continue
        out.append(
            Branch(
                kind,
                ((float(pa[0]), float(pa[1])), (float(pb[0]), float(pb[1]))),
                width,
                (float(tip[0]), float(tip[1])),
                reach,
            )
        )
    return out


def _admissible(
    tip: FloatArray, angles: FloatArray, rho: FloatArray, returns: FloatArray, radius_m: float
) -> bool:
    """Whether the segment laser -> ``tip`` stays in the free polygon eroded by ``radius_m``."""
    length = float(np.hypot(*tip))
    steps = max(math.ceil(length / (radius_m / 2.0)), 1)
    pts = np.linspace(0.0, 1.0, steps + 1)[1:, None] * tip[None, :]
    bearing = np.arctan2(pts[:, 1], pts[:, 0])
    beam = np.abs(angles[None, :] - bearing[:, None]).argmin(axis=1)
    off = np.abs(angles[beam] - bearing) > (np.max(np.abs(np.diff(angles))) if len(angles) > 1 else 0.0)
    if np.any(off):
        return False  # outside the field of view: not seen, not admissible
    if np.any(np.hypot(pts[:, 0], pts[:, 1]) > rho[beam] - radius_m):
        return False
    if len(returns):
        d = np.hypot(pts[:, None, 0] - returns[None, :, 0], pts[:, None, 1] - returns[None, :, 1])
        if np.any(d.min(axis=1) < radius_m):
            return False
    return True


def to_world(pose: tuple[float, float, float], xy_m: tuple[float, float]) -> tuple[float, float]:
    """A point in the laser's frame at ``pose`` (the laser's pose in the world) -> world x, y."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return pose[0] + c * xy_m[0] - s * xy_m[1], pose[1] + s * xy_m[0] + c * xy_m[1]


def grid_scan(
    grid: GridMap, pose: tuple[float, float, float], beams: int, max_range_m: float
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """A 360° scan of ``beams`` beams cast on ``grid`` from ``pose`` (angles relative to its heading, from
    behind, -pi, round to just short of pi): each beam's range and whether it is open (it ran into unknown
    space or off the grid, or reached ``max_range_m`` in free space) or closed (it hit an occupied
    cell)."""
    if beams < 3 or max_range_m <= 0.0:
        raise ValueError("a grid scan needs at least 3 beams and a positive range")
    spec = grid.spec
    res = spec.resolution_m
    angles: FloatArray = -math.pi + np.arange(beams, dtype=np.float64) * (2.0 * math.pi / beams)
    steps = np.arange(res / 2.0, max_range_m + res / 4.0, res / 2.0)
    theta = pose[2] + angles
    x = pose[0] + np.cos(theta)[:, None] * steps[None, :]
    y = pose[1] + np.sin(theta)[:, None] * steps[None, :]
    col = np.floor((x - spec.origin_m[0]) / res).astype(np.intp)
    row = np.floor((y - spec.origin_m[1]) / res).astype(np.intp)
    rows, cols = spec.shape
    inside = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
    rc, cc = np.clip(row, 0, rows - 1), np.clip(col, 0, cols - 1)
    hit = grid.occupied[rc, cc] & inside
    blind = grid.unknown[rc, cc] | ~inside
    stop = hit | blind
    first = np.where(stop.any(axis=1), stop.argmax(axis=1), len(steps))
    ranges = np.where(first < len(steps), steps[np.minimum(first, len(steps) - 1)], max_range_m)
    idx = np.arange(beams)
    closed = (first < len(steps)) & hit[idx, np.minimum(first, len(steps) - 1)]
    opened: BoolArray = ~closed
    out_ranges: FloatArray = np.asarray(ranges, dtype=np.float64)
    return angles, out_ranges, opened
