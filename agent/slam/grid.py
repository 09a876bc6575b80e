"""Log-odds occupancy grids stored as copy-on-write tiles, and scan integration (ray casting) into them.

Storage. A *map* is a table of tile ids over a fixed square extent centred on the world origin; a tile is
``tile_cells`` x ``tile_cells`` int8 log-odds (see :class:`LogOddsModel`) in one shared pool. Tile 0 is
the pinned "unknown" tile (all zeros). Maps that descend from the same particle share tiles until one of
them writes: a write to a tile referenced more than once first copies it (copy on write). Resampling a
particle filter is then a table copy, and the memory in use is the number of distinct tiles, not
particles x map size. The seed's shared-map mode is the same store with a single table.

Indexing. Cell (row, col) of the whole extent covers x in [x0 + col res, x0 + (col+1) res) and y likewise
with rows, where (x0, y0) = ``GridGeometry.origin_m``; row 0 is the lowest y (so images of a window are
upside down with respect to a north-up picture; ``agent.slam.render`` flips them).

Ray casting. A scan is integrated with the inverse sensor model: the cell of each endpoint gets
``hit`` added, every other cell a beam passes through gets ``miss``, each cell at most once per scan
(l_t = l_{t-1} + l_inv, clamped to [l_min, l_max]). The swept cells are the scan's fan polygon
(laser origin, then the beams' free ends in angular order), rasterised with ``cv2.fillPoly``; this is the
same set a per-beam traversal marks, up to the cells that the thin wedge between neighbouring beams adds.
:func:`swept_cells_sampled` is the plain per-beam version (points every half cell along each beam) kept
as the reference and for measurements.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from agent.slam.malloc import release_pages
from agent.slam.pose import compose, transform_points

FloatArray = npt.NDArray[np.float64]
Float32Array = npt.NDArray[np.float32]
Int8Array = npt.NDArray[np.int8]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

log = logging.getLogger(__name__)

UNKNOWN_TILE = 0
# Tile slots the pool reserves up front (64 MB of address space at 32 x 32 cells; Intel's 30 maps peak
# near 26 000 tiles): a pool grown as it filled was reallocated, and where the allocator had put it on
# its heap the realloc copied it, briefly holding the old pool and the new one (Intel: +25 MB of peak
# at 21 MB of tiles). Beyond the reserve it grows by a quarter of its size (at least this many tiles).
_RESERVED_TILES = 65_536
_GROWTH_DIVISOR = 4
_MIN_GROWTH_TILES = 64
_SHIFT = 4  # cv2.fillPoly fixed-point fraction bits: vertices to 1/16 of a cell


@dataclass(frozen=True)
class LogOddsModel:
    """Inverse sensor model in log-odds, l = log(p / (1 - p)), stored as int8 multiples of ``step``.

    ``hit`` = log(0.7/0.3), ``miss`` = log(0.4/0.6); clamped to [``minimum``, ``maximum``] so that a
    cell can change its mind after a few scans. Cells with l > ``occupied`` are obstacles for matching.
    int8 at 0.05 per count holds [-6.4, 6.35]; the clamp keeps l_max + hit inside it, so the update
    l_t = clamp(l_{t-1} + l_inv) can be done in int8 without overflow (and tiles are 1 byte per cell).
    """

    hit: float = 0.85
    miss: float = -0.4
    minimum: float = -2.0
    maximum: float = 3.5
    occupied: float = 0.4
    step: float = 0.05

    def __post_init__(self) -> None:
        if not (self.miss < 0.0 < self.hit and self.minimum < 0.0 < self.maximum):
            raise ValueError("need miss < 0 < hit and minimum < 0 < maximum")
        if (
            self.counts(self.maximum) + self.counts(self.hit) > 127
            or self.counts(self.minimum) + self.counts(self.miss) < -128
        ):
            raise ValueError("log-odds limits plus one update must fit int8 at this step")

    def counts(self, value: float) -> int:
        return round(value / self.step)

    def lut(self) -> npt.NDArray[np.int8]:
        """Update per cell code: 0 untouched, 1 swept (miss), 2 endpoint (hit)."""
        return np.array([0, self.counts(self.miss), self.counts(self.hit)], dtype=np.int8)

    def to_log_odds(self, stored: npt.NDArray[np.int8]) -> Float32Array:
        values: Float32Array = stored.astype(np.float32) * np.float32(self.step)
        return values


@dataclass(frozen=True)
class GridGeometry:
    """Cell size and the fixed extent a map table covers (default 204.8 m x 204.8 m at 0.05 m), and
    ``phase_m``: how far (x, y) the whole lattice is moved from the one with a cell corner at the
    world origin, each in [0, resolution_m) (``agent.slam.lattice``: the filter moves its grid so that
    the walls of its first scan run through cell centres)."""

    resolution_m: float = 0.05
    tile_cells: int = 32
    tiles_per_side: int = 128
    phase_m: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        if not all(0.0 <= p < self.resolution_m for p in self.phase_m):
            raise ValueError(f"phase_m must lie in [0, {self.resolution_m}) per axis, got {self.phase_m}")

    @property
    def cells_per_side(self) -> int:
        return self.tile_cells * self.tiles_per_side

    @property
    def origin_m(self) -> tuple[float, float]:
        half = self.cells_per_side * self.resolution_m / 2.0
        return (-half + self.phase_m[0], -half + self.phase_m[1])

    @property
    def tile_m(self) -> float:
        return self.tile_cells * self.resolution_m


@dataclass(frozen=True)
class TileRect:
    """Tiles [ty0, ty1) x [tx0, tx1) of a map table."""

    ty0: int
    tx0: int
    ty1: int
    tx1: int

    @property
    def shape(self) -> tuple[int, int]:
        return (self.ty1 - self.ty0, self.tx1 - self.tx0)

    def origin_m(self, geometry: GridGeometry) -> tuple[float, float]:
        """World (x, y) of the lower-left corner of the rectangle's first cell."""
        x0, y0 = geometry.origin_m
        return (x0 + self.tx0 * geometry.tile_m, y0 + self.ty0 * geometry.tile_m)

    @classmethod
    def covering(
        cls, geometry: GridGeometry, xy_min: tuple[float, float], xy_max: tuple[float, float]
    ) -> TileRect:
        """The tiles that cover the world box [xy_min, xy_max], clipped to the map extent."""
        x0, y0 = geometry.origin_m
        n = geometry.tiles_per_side
        tx0 = min(max(math.floor((xy_min[0] - x0) / geometry.tile_m), 0), n - 1)
        ty0 = min(max(math.floor((xy_min[1] - y0) / geometry.tile_m), 0), n - 1)
        tx1 = min(max(math.floor((xy_max[0] - x0) / geometry.tile_m) + 1, tx0 + 1), n)
        ty1 = min(max(math.floor((xy_max[1] - y0) / geometry.tile_m) + 1, ty0 + 1), n)
        return cls(ty0, tx0, ty1, tx1)


class TiledMaps:
    """A set of log-odds maps (one per table row) sharing a copy-on-write tile pool."""

    def __init__(self, geometry: GridGeometry, maps: int, initial_tiles: int = _RESERVED_TILES) -> None:
        if maps < 1:
            raise ValueError("need at least one map")
        self.geometry = geometry
        t = geometry.tile_cells
        # Zero-filled by the kernel on first touch: slots that were never used take address space, not
        # memory (``np.zeros`` of this size is a fresh anonymous mapping).
        self.pool: Int8Array = np.zeros((max(initial_tiles, 2), t, t), dtype=np.int8)
        self.refcount: IntArray = np.zeros(self.pool.shape[0], dtype=np.int64)
        self.refcount[UNKNOWN_TILE] = 1 << 40  # pinned: never written, never freed
        self._next = 1  # slots from here on were never used
        self._free: list[int] = []  # slots used before and freed since (taken first)
        n = geometry.tiles_per_side
        self.tables: npt.NDArray[np.int32] = np.zeros((maps, n, n), dtype=np.int32)
        # Tiles [ty0, ty1) x [tx0, tx1) holding every table entry that is not UNKNOWN_TILE (None: none):
        # the reference counts are counted there only (a 30-map table of 128 x 128 tiles is ~0.5 M
        # entries; what the maps know is a small part of it).
        self._span: tuple[int, int, int, int] | None = None

    # -- bookkeeping -----------------------------------------------------------------------------------
    @property
    def maps(self) -> int:
        return int(self.tables.shape[0])

    def tiles_in_use(self) -> int:
        """Distinct stored tiles (the unknown tile excluded)."""
        return self._next - 1 - len(self._free)

    def memory_bytes(self) -> int:
        """Bytes held: the pool slots used so far (in use or free), tables and reference counts."""
        return int(self._next * self.pool[0].nbytes + self.tables.nbytes + self.refcount.nbytes)

    def used_bytes(self) -> int:
        """Bytes of the tiles actually referenced, plus tables: what the maps need."""
        return int(self.tiles_in_use() * self.pool[0].nbytes + self.tables.nbytes)

    def _allocate(self, count: int) -> IntArray:
        reused = min(count, len(self._free))
        taken = [self._free.pop() for _ in range(reused)]
        fresh = count - reused
        if self._next + fresh > self.pool.shape[0]:
            old = self.pool.shape[0]
            grown = max(old // _GROWTH_DIVISOR, _MIN_GROWTH_TILES, self._next + fresh - old)
            # Grown in place (realloc; for a pool this large the kernel remaps its pages), not by
            # concatenating into a new array: that briefly held the old pool and one twice its size.
            # Safe because the pool is never handed out as a view: ``gather`` copies out of it and
            # ``scatter`` writes into it.
            self.pool.resize((old + grown, *self.pool.shape[1:]), refcheck=False)
            self.refcount.resize(old + grown, refcheck=False)
        ids = np.array(taken + list(range(self._next, self._next + fresh)), dtype=np.int64)
        self._next += fresh
        return ids

    def _recount(self) -> None:
        if self._span is None:
            counts = np.zeros(self.pool.shape[0], dtype=np.int64)
        else:
            # Outside the span every entry is UNKNOWN_TILE, whose count is pinned below: the same counts
            # as over the whole table.
            ty0, tx0, ty1, tx1 = self._span
            used = self.tables[:, ty0:ty1, tx0:tx1]
            counts = np.bincount(used.ravel(), minlength=self.pool.shape[0]).astype(np.int64)
        counts[UNKNOWN_TILE] = 1 << 40
        freed = np.flatnonzero((counts == 0) & (self.refcount > 0))
        self._free.extend(int(i) for i in freed)
        self.refcount = counts

    def clear(self) -> None:
        """Every map back to unknown; every tile freed (slots are reused from the first one again). The
        pages of the slots used so far go back to the kernel (:func:`agent.slam.malloc.release_pages`):
        a loop closure's rebuild refills a fraction of them, and the rest would stay resident at the
        particles' high-water (Intel: up to ~30 MB of tiles before a rebuild, ~8 MB after)."""
        release_pages(self.pool[1 : self._next])
        self.tables[...] = UNKNOWN_TILE
        self._span = None
        self.refcount[1:] = 0
        self._free = []
        self._next = 1

    def select(self, rows: npt.ArrayLike) -> None:
        """Keep the maps ``rows`` (with repeats: resampling); tiles no longer referenced are freed."""
        self.tables = np.ascontiguousarray(self.tables[np.asarray(rows, dtype=np.int64)])
        self._recount()

    def share(self, sources: npt.ArrayLike, targets: npt.ArrayLike) -> None:
        """Make each map ``targets[k]`` identical to map ``sources[k]`` (sharing its tiles)."""
        target_rows = np.asarray(targets, dtype=np.int64)
        if target_rows.size == 0:
            return
        self.tables[target_rows] = self.tables[np.asarray(sources, dtype=np.int64)]
        self._recount()

    # -- windows ---------------------------------------------------------------------------------------
    def gather(self, rows: npt.ArrayLike, rect: TileRect) -> Int8Array:
        """Copies of the maps' stored log-odds over ``rect``: shape (len(rows), h*T, w*T)."""
        # (The rows' entries over the rectangle only, not whole table rows first.)
        ids = self.tables[np.asarray(rows, dtype=np.int64), rect.ty0 : rect.ty1, rect.tx0 : rect.tx1]
        u, h, w = ids.shape
        t = self.geometry.tile_cells
        # One gather of tile rows (T bytes each, as one opaque item) in the window's order: window row
        # (tile row i, cell row r) is, tile column by tile column, pool row ids[i, j] * T + r. (Gathering
        # whole tiles and transposing them into place was two copies.)
        tile_rows = self.pool.reshape(-1, t).view(np.dtype((np.void, t))).reshape(-1)
        index = ids.astype(np.int64)[:, :, None, :] * t + np.arange(t)[None, None, :, None]
        # np.take rather than tile_rows[index]: the same rows, ~2.5x faster (take copies items of a
        # fixed size in its own loop; indexing copies opaque items one by one).
        out: Int8Array = np.take(tile_rows, index.reshape(-1)).view(np.int8).reshape(u, h * t, w * t)
        return out

    def scatter(self, rows: npt.ArrayLike, rect: TileRect, windows: Int8Array, touched: BoolArray) -> None:
        """Write ``windows`` (U, h*T, w*T) back into maps ``rows`` (U,) over ``rect``, for the tiles
        marked in ``touched`` (U, h, w). Shared or unknown tiles are copied first (copy on write); maps
        must be distinct (two windows for one map would race)."""
        t = self.geometry.tile_cells
        row_ids = np.asarray(rows, dtype=np.int64)
        u, h, w = touched.shape
        k, ty, tx = np.nonzero(touched)
        if k.size == 0:
            return
        map_rows = row_ids[k]
        ids = self.tables[map_rows, ty + rect.ty0, tx + rect.tx0].astype(np.int64)
        shared = self.refcount[ids] > 1
        if np.any(shared):
            new_ids = self._allocate(int(np.count_nonzero(shared)))
            np.subtract.at(self.refcount, ids[shared], 1)
            self.refcount[new_ids] = 1
            ids[shared] = new_ids
            self.tables[map_rows[shared], ty[shared] + rect.ty0, tx[shared] + rect.tx0] = new_ids
            self._widen(rect)
        blocks = windows.reshape(u, h, t, w, t)
        self.pool[ids] = blocks[k, ty, :, tx, :]

    def _widen(self, rect: TileRect) -> None:
        """Grow the span of known table entries to hold ``rect``."""
        if self._span is None:
            self._span = (rect.ty0, rect.tx0, rect.ty1, rect.tx1)
            return
        ty0, tx0, ty1, tx1 = self._span
        self._span = (min(ty0, rect.ty0), min(tx0, rect.tx0), max(ty1, rect.ty1), max(tx1, rect.tx1))

    def extent(self, row: int) -> TileRect | None:
        """The smallest rectangle holding every known tile of map ``row`` (None for an empty map)."""
        ty, tx = np.nonzero(self.tables[row] != UNKNOWN_TILE)
        if ty.size == 0:
            return None
        return TileRect(int(ty.min()), int(tx.min()), int(ty.max()) + 1, int(tx.max()) + 1)


# -- scans ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ScanPoints:
    """One scan prepared for integration, in the robot base frame.

    ``origin_xy`` is the laser's position on the base; ``hit_xy`` (H, 2) the endpoints that hit
    something within the usable range, in beam order; ``fan_xy`` (F, 2) the free end of every beam that
    carries free space information (shortened by half a cell so the wall cell itself is not cleared), in
    beam order; ``polygon`` (V,) the fan polygon's vertices as indices into ``fan_xy``, -1 for the laser
    origin: the origin, the beams in angular order, and the origin again wherever a run of beams carries
    no information (no return), so the polygon goes back along the last beam and out along the next.
    """

    origin_xy: tuple[float, float]
    hit_xy: FloatArray
    fan_xy: FloatArray
    polygon: npt.NDArray[np.int32]


def prepare_scan(
    ranges_m: FloatArray,
    angles_rad: FloatArray,
    mount: tuple[float, float, float],
    min_range_m: float,
    no_return_m: float,
    max_usable_m: float,
    free_shrink_m: float,
    beam_offsets: FloatArray | None = None,
) -> ScanPoints:
    """Split a scan into endpoints and free-space fan, both in the base frame.

    A beam with min_range <= r < min(no_return, max_usable) is a hit at r; one with
    max_usable <= r < no_return (something far away) is free space up to max_usable, without a hit;
    anything else carries no information (GMapping's maxRange / maxUrange convention).

    ``beam_offsets`` (B, 3), if given, is where the base was when each beam was measured, relative to
    the base at the scan's timestamp (a scanning laser sweeps while the robot moves): each point is then
    placed at offset_k ⊕ mount ⊕ p_k, which removes the skew a turning robot puts into a scan.
    """
    r = np.asarray(ranges_m, dtype=np.float64)
    hit = (r >= min_range_m) & (r < min(no_return_m, max_usable_m))
    far = (r >= max_usable_m) & (r < no_return_m) & ~hit
    free = hit | far
    free_r = np.where(hit, np.maximum(r - free_shrink_m, 0.0), max_usable_m)[free]
    c, s = np.cos(angles_rad), np.sin(angles_rad)
    laser_hits = np.stack([r[hit] * c[hit], r[hit] * s[hit]], axis=1)
    laser_fan = np.stack([free_r * c[free], free_r * s[free]], axis=1)
    mount_arr = np.asarray(mount, dtype=np.float64)
    if beam_offsets is None:
        hit_xy = transform_points(mount_arr, laser_hits)
        fan_xy = transform_points(mount_arr, laser_fan)
    else:
        beam_lasers = compose(beam_offsets, mount_arr[None, :])  # (B, 3): the laser at each beam's time
        hit_xy = transform_points(beam_lasers[hit], laser_hits[:, None, :])[:, 0, :]
        fan_xy = transform_points(beam_lasers[free], laser_fan[:, None, :])[:, 0, :]
    # Polygon: -1 (origin), then each free beam; a gap (beams without information) inserts the origin.
    beam_of_fan = np.flatnonzero(free)
    gap_before = np.concatenate([[False], np.diff(beam_of_fan) > 1])
    fan_ids = np.arange(beam_of_fan.size, dtype=np.int64)
    order = np.argsort(np.concatenate([fan_ids * 2 + 1, np.flatnonzero(gap_before) * 2]), kind="stable")
    vertices = np.concatenate([fan_ids, np.full(int(gap_before.sum()), -1, dtype=np.int64)])[order]
    # int32: a loop closure keeps every node's scan for its rebuilds (Intel: ~0.7 MB less than int64).
    polygon = np.concatenate([[-1], vertices]).astype(np.int32)
    return ScanPoints((float(mount[0]), float(mount[1])), hit_xy, fan_xy, polygon)


def surface_normals(
    points_xy: FloatArray,
    subset: IntArray | None = None,
    window: int = 8,
    radius_m: float = 0.25,
    min_points: int = 5,
    max_thickness_m: float = 0.015,
    min_length_m: float = 0.04,
    radius_per_m: float = 0.0,
    origin_xy: tuple[float, float] = (0.0, 0.0),
) -> FloatArray:
    """Unit normals of the surface through a scan's endpoints (N, 2, in beam order), for the points
    ``subset`` (indices; default all): (len(subset), 2), (0, 0) where the neighbourhood is not a line.

    For point k the neighbours are the points k - ``window`` .. k + ``window`` within its radius,
    max(``radius_m``, ``radius_per_m`` × its range from ``origin_xy``, the laser): a scan's beams fan out,
    so a far wall's endpoints lie range × beam spacing apart or more (the SICK's 1° beams: 0.17 m at 10
    m, several times that at a grazing angle), and a fixed radius leaves every far endpoint alone; with
    at least ``min_points`` of them, their scatter matrix S = (1/n) sum (p - mean)(p - mean)ᵀ has
    eigenvalues l1 <= l2: the neighbourhood is a line when sqrt(l1) <= ``max_thickness_m`` (range noise)
    and sqrt(l2) >= ``min_length_m`` and l2 >= 9 l1; the normal is l1's eigenvector. Corners, wall ends,
    people and clutter get none.
    """
    n = points_xy.shape[0]
    centre = np.arange(n) if subset is None else np.asarray(subset, dtype=np.int64)
    normals = np.zeros((centre.size, 2))
    if n < min_points or centre.size == 0:
        return normals
    offsets = np.arange(-window, window + 1)
    idx = centre[:, None] + offsets[None, :]
    inside = (idx >= 0) & (idx < n)
    idx = np.clip(idx, 0, n - 1)
    nb = points_xy[idx]  # (M, K, 2)
    rel = nb - points_xy[centre][:, None, :]
    radius = np.full(centre.size, radius_m)
    if radius_per_m > 0.0:
        ranges = np.hypot(points_xy[centre, 0] - origin_xy[0], points_xy[centre, 1] - origin_xy[1])
        radius = np.maximum(radius, radius_per_m * ranges)
    use = inside & (rel[..., 0] ** 2 + rel[..., 1] ** 2 <= (radius * radius)[:, None])
    count = use.sum(axis=1)
    w = use / np.maximum(count, 1)[:, None]
    mean = np.einsum("nk,nki->ni", w, rel)
    dev = rel - mean[:, None, :]
    sxx = np.einsum("nk,nk->n", w, dev[..., 0] ** 2)
    syy = np.einsum("nk,nk->n", w, dev[..., 1] ** 2)
    sxy = np.einsum("nk,nk->n", w, dev[..., 0] * dev[..., 1])
    # Eigenvalues of [[sxx, sxy], [sxy, syy]]: m -+ sqrt(q), m = (sxx + syy)/2, q = ((sxx - syy)/2)^2 + sxy^2.
    half_trace = (sxx + syy) / 2.0
    root = np.sqrt(((sxx - syy) / 2.0) ** 2 + sxy**2)
    l1 = np.maximum(half_trace - root, 0.0)
    l2 = half_trace + root
    line = (count >= min_points) & (l1 <= max_thickness_m**2) & (l2 >= min_length_m**2) & (l2 >= 9.0 * l1)
    # The eigenvector of l2 is (sxy, l2 - sxx) (or (l2 - syy, sxy)); the normal is perpendicular to it.
    ax = np.where(np.abs(sxx - l2) > np.abs(syy - l2), sxy, l2 - syy)
    ay = np.where(np.abs(sxx - l2) > np.abs(syy - l2), l2 - sxx, sxy)
    norm = np.hypot(ax, ay)
    line &= norm > 0.0
    safe = np.where(norm > 0.0, norm, 1.0)
    normals[line, 0] = (-ay / safe)[line]
    normals[line, 1] = (ax / safe)[line]
    return normals


def integrate_scans(
    windows: Int8Array,
    window_origin_m: tuple[float, float],
    resolution_m: float,
    base_poses: FloatArray,
    scan: ScanPoints,
    model: LogOddsModel,
    tile_cells: int,
) -> BoolArray:
    """Integrate one scan into each window (U, H, W) in place (a stack: C-contiguous; one window may be
    a view), window u seeing it from ``base_poses[u]``.

    Per window the swept cells are the fan polygon rasterised by ``cv2.fillPoly`` (code 1), endpoint
    cells code 2 (drawn as their updates lut[code] themselves); then l_t = clamp(l_{t-1} + lut[code]) for
    all windows in one pass. Returns which tiles
    (U, H/T, W/T) were updated. Points outside a window are dropped (the caller sizes it to the scan).
    """
    u, h, w = windows.shape
    if u > 1 and not windows.flags.c_contiguous:
        # (One window may be a view into a larger array: its rows are updated where they lie.)
        raise ValueError("a stack of windows must be C-contiguous: it is updated in place")
    # Each cell's update l_inv(code) drawn straight (0 untouched, the miss where swept, the hit at an
    # endpoint) rather than codes 0 / 1 / 2 mapped through a lookup table afterwards: one pass fewer.
    # (Where the model rounds the miss or the hit to 0 counts, codes and the table as before: a code
    # still marks its tile touched.)
    lut = model.lut()
    direct = bool(lut[1] != 0 and lut[2] != 0)
    miss, hit = (int(lut[1]), int(lut[2])) if direct else (1, 2)
    codes = np.zeros((u, h, w), dtype=np.int8)
    x0, y0 = window_origin_m
    poses = np.asarray(base_poses, dtype=np.float64).reshape(u, 3)
    # Continuous cell coordinates c = (x - x0) / res; cv2 puts pixel centres on integers: subtract 1/2.
    shift = np.array([x0, y0]) + 0.5 * resolution_m
    local = np.vstack([scan.fan_xy, np.array([scan.origin_xy])])  # the origin is the last row
    vertices_px = (transform_points(poses, local[None, :, :]) - shift) / resolution_m
    if scan.fan_xy.shape[0]:
        fixed = np.ascontiguousarray(
            np.round(vertices_px * float(1 << _SHIFT)).astype(np.int32)[:, scan.polygon, :]
        )
        for k in range(u):
            cv2.fillPoly(codes[k], [fixed[k]], miss, cv2.LINE_8, _SHIFT)
    if scan.hit_xy.shape[0]:
        hits = transform_points(poses, scan.hit_xy[None, :, :])
        col = np.floor((hits[..., 0] - x0) / resolution_m).astype(np.int64)
        row = np.floor((hits[..., 1] - y0) / resolution_m).astype(np.int64)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        which = np.broadcast_to(np.arange(u)[:, None], col.shape)
        codes.reshape(-1)[((which * h + row) * w + col)[inside]] = hit
    # l_t = clamp(l_{t-1} + l_inv(code)) in stored counts, as 2-D cv2 operations over the whole stack
    # (add, min, max run at memory speed; numpy's int8 clip with scalars does not).
    flat_codes = codes.reshape(u * h, w)
    flat_windows = windows.reshape(u * h, w)
    if direct:
        cv2.add(flat_windows, flat_codes, dst=flat_windows)
    else:
        table = np.zeros(256, dtype=np.int8)
        table[:3] = lut
        cv2.add(flat_windows, cv2.LUT(flat_codes.view(np.uint8), table), dst=flat_windows)
    # (OpenCV's stubs do not list the scalar second operand these calls accept.)
    cv2.max(flat_windows, model.counts(model.minimum), dst=flat_windows)  # type: ignore[call-overload]
    cv2.min(flat_windows, model.counts(model.maximum), dst=flat_windows)  # type: ignore[call-overload]
    # A tile changed if any of its cells has a code: max over runs of T cells, then over T rows.
    # (numpy's max over the middle axis of (U, H/T, T, W/T) walks it with a strided inner loop, ~20x
    # slower than cv2.reduce over the runs laid out contiguously.)
    # (As bytes, the updates are nonzero exactly where a code was: max > 0.)
    runs = cv2.reduce(codes.view(np.uint8).reshape(-1, tile_cells), 1, cv2.REDUCE_MAX)
    columns = runs.reshape(u * (h // tile_cells), tile_cells, w // tile_cells).transpose(0, 2, 1)
    tiles = cv2.reduce(np.ascontiguousarray(columns).reshape(-1, tile_cells), 1, cv2.REDUCE_MAX)
    touched: BoolArray = tiles.reshape(u, h // tile_cells, w // tile_cells) > 0
    return touched


def swept_cells_sampled(
    window_shape: tuple[int, int],
    window_origin_m: tuple[float, float],
    resolution_m: float,
    base_pose: FloatArray,
    scan: ScanPoints,
) -> npt.NDArray[np.uint8]:
    """Reference ray casting: sample each beam every half cell from the laser to its free end (numpy, no
    polygon), mark those cells 1 and endpoint cells 2: the codes :func:`integrate_scans` rasterises."""
    h, w = window_shape
    codes = np.zeros((h, w), dtype=np.uint8)
    x0, y0 = window_origin_m
    pose = np.asarray(base_pose, dtype=np.float64)
    origin = compose(pose, np.array([scan.origin_xy[0], scan.origin_xy[1], 0.0]))[:2]
    ends = transform_points(pose, scan.fan_xy)
    length = np.hypot(ends[:, 0] - origin[0], ends[:, 1] - origin[1])
    step = resolution_m / 2.0
    samples = int(np.ceil(length.max() / step)) + 1 if length.size else 0
    if samples:
        frac = np.arange(samples, dtype=np.float64)[None, :] * step / np.maximum(length[:, None], 1e-9)
        keep = frac <= 1.0
        px = origin[0] + frac * (ends[:, 0:1] - origin[0])
        py = origin[1] + frac * (ends[:, 1:2] - origin[1])
        col = np.floor((px[keep] - x0) / resolution_m).astype(np.int64)
        row = np.floor((py[keep] - y0) / resolution_m).astype(np.int64)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        codes[row[inside], col[inside]] = 1
    if scan.hit_xy.shape[0]:
        hits = transform_points(pose, scan.hit_xy)
        col = np.floor((hits[:, 0] - x0) / resolution_m).astype(np.int64)
        row = np.floor((hits[:, 1] - y0) / resolution_m).astype(np.int64)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        codes[row[inside], col[inside]] = 2
    return codes
