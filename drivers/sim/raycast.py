"""Laser geometry: rays against wall segments and circles (people), vectorised over all beams."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


def walls_array(walls: object) -> FloatArray:
    """(N, 4) array of x1, y1, x2, y2 from an iterable of ``Wall``."""
    rows = [(w.x1_m, w.y1_m, w.x2_m, w.y2_m) for w in walls]  # type: ignore[attr-defined]
    return np.asarray(rows, dtype=np.float64).reshape(-1, 4)


def cast_rays(
    origin_xy: tuple[float, float],
    angles_rad: FloatArray,
    segments: FloatArray,
    circles: FloatArray | None = None,
    max_range_m: float = np.inf,
) -> FloatArray:
    """Distance along each ray to the nearest hit, ``inf`` where nothing is hit within ``max_range_m``.

    Ray: p = o + t d, |d| = 1. Segment: q = a + s e, 0 <= s <= 1. With x the 2-D cross product,
    t = ((a - o) x e) / (d x e) and s = ((a - o) x d) / (d x e).
    ``circles`` is (K, 3): cx, cy, radius; hit at the smaller root of |o + t d - c|^2 = r^2.
    """
    ox, oy = origin_xy
    dx = np.cos(angles_rad)[:, None]
    dy = np.sin(angles_rad)[:, None]
    best = np.full(angles_rad.shape, np.inf)
    if segments.size:
        ax = segments[None, :, 0] - ox
        ay = segments[None, :, 1] - oy
        ex = segments[None, :, 2] - segments[None, :, 0]
        ey = segments[None, :, 3] - segments[None, :, 1]
        denom = dx * ey - dy * ex
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (ax * ey - ay * ex) / denom
            s = (ax * dy - ay * dx) / denom
        hit = (np.abs(denom) > 1e-12) & (t > 1e-9) & (s >= 0.0) & (s <= 1.0)
        t = np.where(hit, t, np.inf)
        best = np.minimum(best, t.min(axis=1))
    if circles is not None and circles.size:
        cx = circles[None, :, 0] - ox
        cy = circles[None, :, 1] - oy
        r = circles[None, :, 2]
        proj = cx * dx + cy * dy
        disc = proj**2 - (cx**2 + cy**2 - r**2)
        with np.errstate(invalid="ignore"):
            t = proj - np.sqrt(disc)
        t = np.where((disc >= 0) & (t > 1e-9), t, np.inf)
        best = np.minimum(best, t.min(axis=1))
    best[best > max_range_m] = np.inf
    return best


def distance_to_segments(xy: tuple[float, float], segments: FloatArray) -> float:
    """Distance from a point to the nearest of (N, 4) segments (``inf`` with none)."""
    if not segments.size:
        return float("inf")
    p = np.asarray(xy, dtype=np.float64)
    a, b = segments[:, :2], segments[:, 2:]
    d = b - a
    t = np.clip(np.sum((p - a) * d, axis=1) / np.maximum(np.sum(d * d, axis=1), 1e-12), 0.0, 1.0)
    return float(np.min(np.hypot(*(a + t[:, None] * d - p).T)))
