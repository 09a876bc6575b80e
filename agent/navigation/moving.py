"""Moving obstacles (people walking) from the scans: where they will be in the next few seconds.

A walking person is a few times faster than the robot and does not step aside; marking where they
*are* is not enough (the robot would wait, or cross, in their way). So:

* a scan's returns that fall more than ``STATIC_GAP_M`` from anything on the map are *unmapped*;
* consecutive unmapped returns closer than ``CLUSTER_GAP_M`` form a cluster (a leg, a body); its
  centroid is tracked from scan to scan (nearest track within ``GATE_M``), its velocity low-pass
  filtered over the displacements;
* a track seen at least ``MIN_HITS`` times and faster than ``MOVING_MPS`` is moving; its *sweep* is the
  capsule from where it is to where it will be in ``horizon_s`` at that velocity, ``BODY_M`` wide each
  side. The costmap forbids the sweeps like obstacles (inflated by the footprint), so the planner routes
  behind a walker, the robot waits outside their way, and a robot standing in it escapes out of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from agent.navigation.costmap import BoolArray, Float32Array, FloatArray, GridSpec

STATIC_GAP_M = 0.15
CLUSTER_GAP_M = 0.2
GATE_M = 0.6
MIN_HITS = 3
MOVING_MPS = 0.25
BODY_M = 0.25
LOST_S = 0.5
VELOCITY_GAIN = 0.5


@dataclass
class Track:
    x_m: float
    y_m: float
    vx_mps: float = 0.0
    vy_mps: float = 0.0
    t_s: float = 0.0
    hits: int = 1

    @property
    def speed_mps(self) -> float:
        return math.hypot(self.vx_mps, self.vy_mps)


class MovingObstacles:
    def __init__(self, horizon_s: float = 3.0) -> None:
        self.horizon_s = horizon_s
        self.tracks: list[Track] = []

    def update(
        self, t_s: float, points_m: FloatArray, static_distance_m: Float32Array, spec: GridSpec
    ) -> None:
        """One scan's returns (``(N, 2)`` map frame, in beam order) against the static map's distance
        grid (metres to the nearest mapped obstacle)."""
        clusters = _clusters(points_m, static_distance_m, spec)
        self.tracks = [tr for tr in self.tracks if t_s - tr.t_s <= LOST_S]
        taken: set[int] = set()
        for cx, cy in clusters:
            best, best_d = None, GATE_M
            for i, tr in enumerate(self.tracks):
                d = math.hypot(cx - tr.x_m, cy - tr.y_m)
                if i not in taken and d < best_d:
                    best, best_d = i, d
            if best is None:
                self.tracks.append(Track(cx, cy, t_s=t_s))
                taken.add(len(self.tracks) - 1)
                continue
            tr = self.tracks[best]
            dt = t_s - tr.t_s
            if dt > 1e-3:
                g = VELOCITY_GAIN
                tr.vx_mps = (1 - g) * tr.vx_mps + g * (cx - tr.x_m) / dt
                tr.vy_mps = (1 - g) * tr.vy_mps + g * (cy - tr.y_m) / dt
            tr.x_m, tr.y_m, tr.t_s = cx, cy, t_s
            tr.hits += 1
            taken.add(best)

    def moving(self) -> list[Track]:
        return [tr for tr in self.tracks if tr.hits >= MIN_HITS and tr.speed_mps >= MOVING_MPS]

    def sweeps(self, spec: GridSpec) -> BoolArray:
        """Cells within ``BODY_M`` of a moving track's way over the next ``horizon_s``."""
        out = np.zeros(spec.shape, dtype=bool)
        res = spec.resolution_m
        for tr in self.moving():
            a = np.array([tr.x_m, tr.y_m])
            b = a + self.horizon_s * np.array([tr.vx_mps, tr.vy_mps])
            lo = np.minimum(a, b) - BODY_M
            hi = np.maximum(a, b) + BODY_M
            (r0, c0), (r1, c1) = spec.to_cell(np.stack([lo, hi]))
            r0, c0 = max(int(r0), 0), max(int(c0), 0)
            r1, c1 = min(int(r1) + 1, spec.shape[0]), min(int(c1) + 1, spec.shape[1])
            if r0 >= r1 or c0 >= c1:
                continue
            rr, cc = np.mgrid[r0:r1, c0:c1]
            px = spec.origin_m[0] + (cc + 0.5) * res
            py = spec.origin_m[1] + (rr + 0.5) * res
            d = b - a
            t = np.clip(((px - a[0]) * d[0] + (py - a[1]) * d[1]) / max(float(d @ d), 1e-12), 0.0, 1.0)
            near = np.hypot(px - (a[0] + t * d[0]), py - (a[1] + t * d[1])) <= BODY_M
            out[r0:r1, c0:c1] |= near
        return out


def _clusters(
    points_m: FloatArray, static_distance_m: Float32Array, spec: GridSpec
) -> list[tuple[float, float]]:
    if not len(points_m):
        return []
    cells = spec.to_cell(points_m)
    inside = spec.inside(cells)
    unmapped = np.zeros(len(points_m), dtype=bool)
    unmapped[inside] = static_distance_m[cells[inside, 0], cells[inside, 1]] > STATIC_GAP_M
    out: list[tuple[float, float]] = []
    idx = np.flatnonzero(unmapped)
    if not idx.size:
        return out
    pts = points_m[idx]
    # Break where consecutive unmapped returns are apart (or not neighbouring beams' returns).
    gaps = np.hypot(*np.diff(pts, axis=0).T) > CLUSTER_GAP_M
    breaks = np.flatnonzero(gaps | (np.diff(idx) > 2)) + 1
    for part in np.split(np.arange(len(pts)), breaks):
        if len(part) >= 3:
            chunk = pts[part]
            if float(np.hypot(*(chunk.max(axis=0) - chunk.min(axis=0)))) <= 1.0:
                out.append((float(chunk[:, 0].mean()), float(chunk[:, 1].mean())))
    return out
