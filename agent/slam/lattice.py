"""Where a map's cells should sit: the grid's phase that puts the walls in view through cell centres.

An occupancy grid quantises a wall to the cells its endpoints fall in. A wall through cell centres is
hit in one row of cells and the matcher's distance to it has a sharp minimum on the wall; a wall on the
boundary between two rows is hit on both sides, comes out ragged (one row here, two there, one on the
other side further on) and a pose a little off settles half a cell off, since the row it mapped is the
one the next scan matches (docs/slam.md, "Scan matching", *Walls on cell boundaries*). Walls parallel to
the grid's axes are where this bites: an oblique wall crosses cells at every offset and the rows average
out. Buildings are mostly such walls when the map frame is the building's (the LED frame VLP works in is
usually surveyed along the walls), and a wall's offset from the lattice is the building's, not ours to
choose; the lattice's is. So the filter picks the grid's phase (the sub-cell offset of its origin,
``GridGeometry.phase_m``) from its first scan, before anything is mapped.

Pure numpy in, numpy out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class LatticeFit:
    """Per axis (x, y): the grid phase to use (metres, in [0, resolution)), or None where the walls
    gave none; the walls' mean resultant length (0: offsets spread over the cell, 1: all at one offset)
    and how many endpoints voted."""

    phase_m: tuple[float | None, float | None]
    resultant: tuple[float, float]
    votes: tuple[int, int]


def fit_grid_phase(
    points_xy: FloatArray,
    normals_xy: FloatArray,
    resolution_m: float,
    max_tilt_rad: float = math.radians(5.0),
    min_votes: int = 30,
    min_resultant: float = 0.5,
) -> LatticeFit:
    """The grid phase per axis that puts the walls through cell centres.

    ``points_xy`` (N, 2) are a scan's endpoints in the map frame, ``normals_xy`` (N, 2) their unit
    surface normals in the map frame ((0, 0) where there is none: ``grid.surface_normals``). An endpoint
    whose normal lies within ``max_tilt_rad`` of the x axis is on a wall across x and votes with its x
    (the same for y). Each axis's votes are offsets on a circle of one cell's circumference; their
    circular mean is the walls' offset w from the lattice (the origin at phase 0), and the phase p puts
    cell centres there: origin + (k + 1/2) resolution = w (mod resolution), p = w - resolution / 2 (mod
    resolution), the grid's origin being a whole number of cells from 0 at phase 0. An axis is left
    alone (None) with fewer than ``min_votes`` votes or a mean resultant length below ``min_resultant``
    (walls at several offsets, or range noise as wide as a cell: no phase serves them).
    """
    points = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    normals = np.asarray(normals_xy, dtype=np.float64).reshape(-1, 2)
    if points.shape != normals.shape:
        raise ValueError(f"points {points.shape} and normals {normals.shape} differ in shape")
    if resolution_m <= 0.0:
        raise ValueError(f"resolution_m must be positive, got {resolution_m}")
    cos_tilt = math.cos(max_tilt_rad)
    phases: list[float | None] = []
    resultants: list[float] = []
    votes: list[int] = []
    for axis in (0, 1):
        voting = np.abs(normals[:, axis]) >= cos_tilt
        angle = points[voting, axis] * (2.0 * math.pi / resolution_m)
        count = int(angle.size)
        votes.append(count)
        if count == 0:
            resultants.append(0.0)
            phases.append(None)
            continue
        c, s = float(np.cos(angle).mean()), float(np.sin(angle).mean())
        resultant = math.hypot(c, s)
        resultants.append(resultant)
        if count < min_votes or resultant < min_resultant:
            phases.append(None)
            continue
        wall = math.atan2(s, c) * resolution_m / (2.0 * math.pi)
        phases.append(phase_of(wall - resolution_m / 2.0, resolution_m))
    return LatticeFit((phases[0], phases[1]), (resultants[0], resultants[1]), (votes[0], votes[1]))


def phase_of(position_m: float, resolution_m: float) -> float:
    """``position_m`` modulo the cell size, in [0, resolution_m) (a float modulo can round up to the
    cell size itself: that is 0): the phase of a lattice with a cell corner at ``position_m``."""
    phase = position_m % resolution_m
    return 0.0 if phase >= resolution_m else phase
