"""Scoring a simulated fleet run (``vlp-agent sim --robots N``): how close the robots came, from each one's
truth (``--truth`` CSVs, ``t_us`` on the machine's monotonic clock, which every simulator process shares).

numpy in, numpy out: no I/O, no clock.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["contacts", "separation"]

FloatArray = npt.NDArray[np.float64]


def separation(
    t_a: FloatArray, xy_a: FloatArray, t_b: FloatArray, xy_b: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Distances between two robots at robot a's truth times within the span both truths cover (b
    interpolated linearly): (times, distances); empty when the spans do not overlap or either has fewer
    than two samples."""
    t_a, t_b = np.asarray(t_a, np.float64), np.asarray(t_b, np.float64)
    xy_a, xy_b = np.asarray(xy_a, np.float64).reshape(-1, 2), np.asarray(xy_b, np.float64).reshape(-1, 2)
    if len(t_a) < 2 or len(t_b) < 2:
        return np.zeros(0), np.zeros(0)
    order = np.argsort(t_b, kind="stable")
    t_b, xy_b = t_b[order], xy_b[order]
    keep = (t_a >= t_b[0]) & (t_a <= t_b[-1])
    t = t_a[keep]
    bx = np.interp(t, t_b, xy_b[:, 0])
    by = np.interp(t, t_b, xy_b[:, 1])
    d = np.hypot(xy_a[keep, 0] - bx, xy_a[keep, 1] - by)
    return t, d


def contacts(distances: FloatArray, limit_m: float) -> int:
    """How many times the distance went below ``limit_m`` (the two footprints' radii: they touched), each
    stretch below it counted once."""
    below = np.asarray(distances) < limit_m
    if below.size == 0:
        return 0
    starts = below[1:] & ~below[:-1]
    return int(below[0]) + int(np.count_nonzero(starts))
