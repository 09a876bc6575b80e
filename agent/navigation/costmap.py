"""The costmap: the SLAM occupancy grid (static layer) plus what the latest scans see (obstacle layer),
inflated by the robot's footprint with a clearance cost from a distance transform.

Grid convention: cell (row, col) covers x in [x0 + col res, x0 + (col + 1) res), y in
[y0 + row res, ...): rows run along +y, as the SLAM grid's log-odds (not the map image, whose row 0 is
the top).

Layers:

* **static**: occupied and unknown cells of the map (``agent.slam`` or a saved ``map_server`` map);
* **obstacles**: cells a scan's beam ended in (marking) minus cells a later beam passed through
  (clearing, ray tracing each beam up to one cell before its end, or out to ``obstacle_max_range_m``
  for beams with no return): a person who walked away is cleared as soon as the laser sees through the
  place they stood;
* **fleet**: the other robots' footprints (``agent.navigation.fleet_layer``, from their poses over the
  fleet), replaced whole each time, lethal like obstacles;
* **cost** (derived, lazily, when asked): d = the Euclidean distance transform to the nearest static or
  obstacle cell. Forbidden (``inf``) where d < ``radius + safety_margin`` (the footprint would touch) and
  on unknown cells (unless a goal allows them); elsewhere c = exp(-k (d - inscribed)) in (0, 1], zero
  beyond ``inflation_radius_m``. The planner pays ``length (1 + w c)``.

numpy in, numpy out: no I/O, no clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from agent.navigation.config import NavConfig

FloatArray = npt.NDArray[np.float64]
Float32Array = npt.NDArray[np.float32]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.intp]


@dataclass(frozen=True)
class GridSpec:
    """A grid's place in the world: ``origin_m`` the lower-left corner of cell (0, 0), ``shape`` (rows
    along y, columns along x)."""

    origin_m: tuple[float, float]
    resolution_m: float
    shape: tuple[int, int]

    def to_cell(self, xy: FloatArray) -> IntArray:
        """(N, 2) world points -> (N, 2) integer (row, col); may be outside the grid."""
        pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        col = np.floor((pts[:, 0] - self.origin_m[0]) / self.resolution_m)
        row = np.floor((pts[:, 1] - self.origin_m[1]) / self.resolution_m)
        out: IntArray = np.stack([row, col], axis=1).astype(np.intp)
        return out

    def to_world(self, cells: npt.ArrayLike) -> FloatArray:
        """(N, 2) (row, col) -> (N, 2) world x, y of the cells' centres."""
        rc = np.asarray(cells, dtype=np.float64).reshape(-1, 2)
        x = self.origin_m[0] + (rc[:, 1] + 0.5) * self.resolution_m
        y = self.origin_m[1] + (rc[:, 0] + 0.5) * self.resolution_m
        out: FloatArray = np.stack([x, y], axis=1)
        return out

    def inside(self, cells: IntArray) -> BoolArray:
        rows, cols = self.shape
        ok: BoolArray = (cells[:, 0] >= 0) & (cells[:, 0] < rows) & (cells[:, 1] >= 0) & (cells[:, 1] < cols)
        return ok


class Costmap:
    """Static map + scan obstacles -> a cost grid for the planner and the controller."""

    def __init__(
        self, spec: GridSpec, occupied: BoolArray, unknown: BoolArray, config: NavConfig | None = None
    ) -> None:
        if occupied.shape != spec.shape or unknown.shape != spec.shape:
            raise ValueError(f"layers {occupied.shape}, {unknown.shape} do not match the grid {spec.shape}")
        self.spec = spec
        self.config = config or NavConfig()
        self.static_occupied = occupied.astype(bool, copy=True)
        self.unknown = unknown.astype(bool, copy=True) & ~self.static_occupied
        self.obstacles = np.zeros(spec.shape, dtype=bool)
        self.predicted = np.zeros(spec.shape, dtype=bool)  # where moving obstacles are about to be
        self.fleet = np.zeros(spec.shape, dtype=bool)  # the other robots' footprints
        self.version = 0  # bumped whenever what the planner sees changes
        self._cost_version = -1
        self._cost: Float32Array = np.zeros(spec.shape, dtype=np.float32)
        self._cost_unknown: Float32Array = np.zeros(spec.shape, dtype=np.float32)
        self._distance_m: Float32Array = np.zeros(spec.shape, dtype=np.float32)
        self._static_distance: Float32Array = np.zeros(spec.shape, dtype=np.float32)
        self._static_version = -1

    # -- layers ------------------------------------------------------------------------------------
    def set_static(self, occupied: BoolArray, unknown: BoolArray) -> None:
        """A new map from SLAM (same grid)."""
        if occupied.shape != self.spec.shape or unknown.shape != self.spec.shape:
            raise ValueError("a new static map must keep the grid's shape")
        if np.array_equal(occupied, self.static_occupied) and np.array_equal(unknown, self.unknown):
            return
        self.static_occupied = occupied.astype(bool, copy=True)
        self.unknown = unknown.astype(bool, copy=True) & ~self.static_occupied
        self.version += 1

    def update_scan(
        self,
        laser_pose: tuple[float, float, float],
        angles_rad: FloatArray,
        ranges_m: FloatArray,
        min_range_m: float,
        max_range_m: float,
    ) -> bool:
        """Mark where the beams ended and clear what they passed through. ``laser_pose`` is the laser's
        (x, y, yaw) in the map frame, ``angles_rad`` the beams' directions in the laser's frame,
        ``ranges_m`` the readings (0 or out of [min, max]: no return). Returns whether the obstacle layer
        changed."""
        res = self.spec.resolution_m
        reach = self.config.obstacle_max_range_m
        lx, ly, lyaw = laser_pose
        ranges = np.asarray(ranges_m, dtype=np.float64)
        angles = np.asarray(angles_rad, dtype=np.float64)
        hit = (ranges >= min_range_m) & (ranges <= max_range_m)
        # Clearing: a beam without a return saw free space out to its usable range. Rays are sampled
        # every cell; every other beam is enough (a URG's beams are 2.5 cm apart at 4 m, half a cell).
        free_m = np.minimum(np.where(hit, ranges - res, min(reach, max_range_m)), reach)
        theta = lyaw + angles
        c, s = np.cos(theta), np.sin(theta)
        steps = np.arange(0.0, reach, res)
        sparse_beams = slice(None, None, 2)
        along = steps[None, :] <= free_m[sparse_beams, None]
        px = (lx + c[sparse_beams, None] * steps[None, :])[along]
        py = (ly + s[sparse_beams, None] * steps[None, :])[along]
        clear = self._flat_cells(px, py)
        near = hit & (ranges <= reach)
        mark = self._flat_cells(lx + c[near] * ranges[near], ly + s[near] * ranges[near])
        flat = self.obstacles.reshape(-1)
        was = int(np.count_nonzero(flat[clear])) if clear.size else 0
        fresh = int(np.count_nonzero(~flat[mark])) if mark.size else 0
        flat[clear] = False
        flat[mark] = True
        # Changed unless every cleared cell was free already and every marked one occupied already, or
        # the cleared cells that were marked are exactly re-marked (a person standing still).
        changed = fresh > 0 or (was > 0 and int(np.count_nonzero(flat[clear])) < was)
        if changed:
            self.version += 1
        return changed

    def _flat_cells(self, x: FloatArray, y: FloatArray) -> IntArray:
        """Flat indices of the grid cells holding the points (x, y); points off the grid are dropped."""
        rows, cols = self.spec.shape
        col = np.floor((x - self.spec.origin_m[0]) / self.spec.resolution_m).astype(np.intp)
        row = np.floor((y - self.spec.origin_m[1]) / self.spec.resolution_m).astype(np.intp)
        ok = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
        out: IntArray = row[ok] * cols + col[ok]
        return out

    def set_predicted(self, cells: BoolArray) -> None:
        """Cells moving obstacles will sweep over soon (``agent.navigation.moving``): forbidden like
        obstacles, replaced whole each time."""
        if not np.array_equal(cells, self.predicted):
            self.predicted = cells.astype(bool, copy=True)
            self.version += 1

    def set_fleet(self, cells: BoolArray) -> None:
        """The other robots' footprints (``agent.navigation.fleet_layer.disc_cells``): forbidden like
        obstacles, replaced whole each time."""
        if cells.shape != self.spec.shape:
            raise ValueError(f"a fleet layer of {cells.shape} does not match the grid {self.spec.shape}")
        if not np.array_equal(cells, self.fleet):
            self.fleet = cells.astype(bool, copy=True)
            self.version += 1

    def static_distance_m(self) -> Float32Array:
        """Distance from each cell to the nearest occupied cell of the map alone (no scans), metres."""
        if self._static_version != self._static_key():
            free = np.ascontiguousarray((~self.static_occupied).astype(np.uint8))
            cells = np.asarray(cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE), np.float32)
            self._static_distance = cells * np.float32(self.spec.resolution_m)
            self._static_version = self._static_key()
        return self._static_distance

    def _static_key(self) -> int:
        return id(self.static_occupied)

    def clear_obstacles(self) -> None:
        if self.obstacles.any():
            self.obstacles[:] = False
            self.version += 1

    # -- cost ---------------------------------------------------------------------------------------
    def _update_cost(self) -> None:
        if self._cost_version == self.version:
            return
        cfg = self.config
        lethal = self.static_occupied | self.obstacles | self.predicted | self.fleet
        if lethal.any():
            # The exact Euclidean distance to the nearest zero (the lethal cells); OpenCV's is ~6x faster
            # than scipy.ndimage.distance_transform_edt on the office map, and the same to 1e-5 cells.
            free = np.ascontiguousarray((~lethal).astype(np.uint8))
            cells = np.asarray(cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE), np.float32)
            distance = cells * np.float32(self.spec.resolution_m)
        else:
            distance = np.full(self.spec.shape, np.inf, dtype=np.float32)
        # A cell's centre may be half a cell nearer an obstacle's edge than to its centre.
        distance = np.maximum(distance - np.float32(0.5 * self.spec.resolution_m), np.float32(0.0))
        inscribed = np.float32(cfg.inscribed_m)
        cost = np.exp(np.float32(-cfg.cost_scaling) * np.maximum(distance - inscribed, np.float32(0.0)))
        cost[distance > cfg.inflation_radius_m] = 0.0
        cost[distance < inscribed] = np.inf
        self._distance_m = distance
        self._cost_unknown = cost
        known = cost.copy()
        known[self.unknown] = np.inf
        self._cost = known
        self._cost_version = self.version

    def cost(self, allow_unknown: bool | None = None) -> Float32Array:
        """The cost grid: ``inf`` forbidden, else in [0, 1]. Unknown cells are forbidden unless
        ``allow_unknown`` (default: the config's)."""
        self._update_cost()
        allow = self.config.allow_unknown if allow_unknown is None else allow_unknown
        return self._cost_unknown if allow else self._cost

    def distance_m(self) -> Float32Array:
        """Distance from each cell's centre to the nearest static or obstacle cell, metres."""
        self._update_cost()
        return self._distance_m

    def cost_at(self, xy: FloatArray, allow_unknown: bool | None = None) -> Float32Array:
        """Cost at world points; ``inf`` outside the grid."""
        cells = self.spec.to_cell(xy)
        inside = self.spec.inside(cells)
        out = np.full(cells.shape[0], np.inf, dtype=np.float32)
        grid = self.cost(allow_unknown)
        out[inside] = grid[cells[inside, 0], cells[inside, 1]]
        return out


def segment_cells(spec: GridSpec, a: FloatArray, b: FloatArray) -> IntArray:
    """Cells a straight segment a -> b passes through (sampled every quarter cell), in order."""
    length = math.hypot(float(b[0] - a[0]), float(b[1] - a[1]))
    n = max(math.ceil(length / (spec.resolution_m * 0.25)), 1)
    t = np.linspace(0.0, 1.0, n + 1)[:, None]
    pts = a[None, :] + t * (b - a)[None, :]
    return spec.to_cell(pts)
