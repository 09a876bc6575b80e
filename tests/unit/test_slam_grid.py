"""Occupancy grid: scan preparation, ray casting by polygon fill against per-beam sampling, the log-odds
update, and the copy-on-write tile store."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from agent.slam.grid import (
    UNKNOWN_TILE,
    GridGeometry,
    LogOddsModel,
    TiledMaps,
    TileRect,
    integrate_scans,
    prepare_scan,
    surface_normals,
    swept_cells_sampled,
)
from agent.slam.logs import read_log
from drivers.sim.raycast import cast_rays

RES = 0.05
MODEL = LogOddsModel()
ROOM = np.array(
    [  # x1, y1, x2, y2: an 8 m x 6 m room with a 1 m box in it
        (-4.0, -3.0, 4.0, -3.0),
        (4.0, -3.0, 4.0, 3.0),
        (4.0, 3.0, -4.0, 3.0),
        (-4.0, 3.0, -4.0, -3.0),
        (1.0, 0.5, 2.0, 0.5),
        (2.0, 0.5, 2.0, 1.5),
        (2.0, 1.5, 1.0, 1.5),
        (1.0, 1.5, 1.0, 0.5),
    ]
) + np.array([0.021, 0.013, 0.021, 0.013])  # walls off the cell boundaries: no ties in the tests
ANGLES = np.radians(np.linspace(-120.0, 120.0, 682))


def room_scan(pose: tuple[float, float, float], max_range: float = 5.6) -> np.ndarray:
    ranges = cast_rays((pose[0], pose[1]), ANGLES + pose[2], ROOM, None, max_range)
    return np.where(np.isfinite(ranges), ranges, 0.0)


def window_for(geometry: GridGeometry, half_m: float = 5.0) -> tuple[TileRect, tuple[float, float]]:
    rect = TileRect.covering(geometry, (-half_m, -half_m), (half_m, half_m))
    return rect, rect.origin_m(geometry)


def cell(origin: tuple[float, float], x: float, y: float) -> tuple[int, int]:
    return math.floor((y - origin[1]) / RES), math.floor((x - origin[0]) / RES)


# -- scan preparation ------------------------------------------------------------------------------------


def test_prepare_scan_classifies_beams() -> None:
    angles = np.radians([-10.0, -5.0, 0.0, 5.0, 10.0, 15.0])
    # below min range, hit, no return (0), beyond usable but a return, saturation (no return), hit
    ranges = np.array([0.05, 2.0, 0.0, 7.0, 8.0, 3.0])
    scan = prepare_scan(ranges, angles, (0.0, 0.0, 0.0), 0.1, 8.0, 6.0, 0.025)
    np.testing.assert_allclose(np.hypot(*scan.hit_xy.T), [2.0, 3.0])
    # Free space: the two hits (shortened by half a cell) and the far beam, cut at the usable range.
    np.testing.assert_allclose(np.hypot(*scan.fan_xy.T), [1.975, 6.0, 2.975])
    # Polygon: origin, beam 1, origin (gap: beam 2 had no return), beam 3, origin (gap), beam 5.
    assert scan.polygon.tolist() == [-1, 0, -1, 1, -1, 2]


def test_prepare_scan_mount_and_deskew() -> None:
    angles = np.array([0.0, math.pi / 2])
    ranges = np.array([1.0, 1.0])
    mounted = prepare_scan(ranges, angles, (0.2, 0.1, math.pi / 2), 0.1, 5.0, 5.0, 0.0)
    # Laser turned left by 90 deg at (0.2, 0.1): its forward beam points along +y of the base.
    np.testing.assert_allclose(mounted.hit_xy, [[0.2, 1.1], [-0.8, 0.1]], atol=1e-12)
    # The base moved 0.1 m forward between the first beam and the scan's time: the first beam's point is
    # 0.1 m further back in the frame of the base at the scan's time.
    offsets = np.array([[-0.1, 0.0, 0.0], [0.0, 0.0, 0.0]])
    skewed = prepare_scan(ranges, angles, (0.0, 0.0, 0.0), 0.1, 5.0, 5.0, 0.0, offsets)
    np.testing.assert_allclose(skewed.hit_xy, [[0.9, 0.0], [0.0, 1.0]], atol=1e-12)


# -- ray casting ----------------------------------------------------------------------------------------


def test_single_scan_marks_wall_free_and_unknown() -> None:
    geometry = GridGeometry()
    maps = TiledMaps(geometry, 1)
    rect, origin = window_for(geometry)
    windows = maps.gather([0], rect)
    pose = np.array([[0.0, 0.0, 0.0]])
    scan = prepare_scan(room_scan((0.0, 0.0, 0.0)), ANGLES, (0.0, 0.0, 0.0), 0.1, 5.6, 5.5, RES / 2)
    integrate_scans(windows, origin, RES, pose, scan, MODEL, geometry.tile_cells)
    stored = windows[0]
    hit, miss = MODEL.counts(MODEL.hit), MODEL.counts(MODEL.miss)
    assert stored[cell(origin, 4.021, 0.0)] == hit  # the east wall straight ahead (4 m) is a hit
    for x in (0.5, 1.5, 2.5, 3.5):
        assert stored[cell(origin, x, -0.3)] == miss  # free in front of the wall
    assert stored[cell(origin, 4.3, 0.0)] == 0  # behind the wall: never seen
    assert stored[cell(origin, 1.5, 1.7)] == 0  # behind the box (in its shadow)
    assert stored[cell(origin, -3.0, 0.0)] == 0  # behind the laser (outside its 240 deg): unknown
    assert stored[cell(origin, 1.021, 0.9)] == hit  # the box's near face


def test_polygon_fill_matches_per_beam_sampling() -> None:
    geometry = GridGeometry()
    rect, origin = window_for(geometry)
    shape = rect.shape[0] * geometry.tile_cells, rect.shape[1] * geometry.tile_cells
    for pose in [(0.0, 0.0, 0.0), (-1.3, 0.7, 2.1), (2.5, -1.7, -0.8)]:
        scan = prepare_scan(room_scan(pose), ANGLES, (0.1, 0.0, 0.0), 0.1, 5.6, 5.5, RES / 2)
        windows = np.zeros((1, *shape), dtype=np.int8)
        integrate_scans(windows, origin, RES, np.array([pose]), scan, MODEL, geometry.tile_cells)
        reference = swept_cells_sampled(shape, origin, RES, np.array(pose), scan)
        filled = windows[0] == MODEL.counts(MODEL.miss)
        sampled = reference == 1
        union = np.count_nonzero(filled | sampled)
        agree = np.count_nonzero(filled & sampled) / union
        assert agree > 0.93, (pose, agree)
        # Endpoint cells are the same set either way.
        assert np.array_equal(windows[0] == MODEL.counts(MODEL.hit), reference == 2)


def test_polygon_fill_matches_sampling_on_a_real_scan(shared_data: Path) -> None:
    log = read_log(shared_data / "slam/breezyslam/exp1.dat", "breezyslam")
    geometry = GridGeometry()
    rect, origin = window_for(geometry, 6.0)
    shape = rect.shape[0] * geometry.tile_cells, rect.shape[1] * geometry.tile_cells
    record = log.records[400]  # 52 % of the beams have no return: many gaps in the fan
    g = log.geometry
    scan = prepare_scan(record.ranges_m, g.angles_rad, g.mount, 0.1, g.no_return_m, 5.5, RES / 2)
    pose = np.array([0.3, -0.2, 0.7])
    windows = np.zeros((1, *shape), dtype=np.int8)
    integrate_scans(windows, origin, RES, pose[None, :], scan, MODEL, geometry.tile_cells)
    reference = swept_cells_sampled(shape, origin, RES, pose, scan)
    filled = windows[0] == MODEL.counts(MODEL.miss)
    sampled = reference == 1
    assert np.count_nonzero(filled & sampled) / np.count_nonzero(filled | sampled) > 0.9


def test_log_odds_clamp_and_batch() -> None:
    """Two windows seeing the scan from different poses; repeated hits saturate at the clamp."""
    geometry = GridGeometry()
    rect, origin = window_for(geometry)
    shape = rect.shape[0] * geometry.tile_cells, rect.shape[1] * geometry.tile_cells
    windows = np.zeros((2, *shape), dtype=np.int8)
    poses = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, math.pi]])
    scan = prepare_scan(room_scan((0.0, 0.0, 0.0)), ANGLES, (0.0, 0.0, 0.0), 0.1, 5.6, 5.5, RES / 2)
    for _ in range(10):
        touched = integrate_scans(windows, origin, RES, poses, scan, MODEL, geometry.tile_cells)
    assert windows[0][cell(origin, 4.021, 0.0)] == MODEL.counts(MODEL.maximum)
    assert windows[0][cell(origin, 1.5, -0.3)] == MODEL.counts(MODEL.minimum)
    # The second window saw the same ranges turned round: the wall lands at x = -4.
    assert windows[1][cell(origin, -4.021, 0.0)] == MODEL.counts(MODEL.maximum)
    assert windows[1][cell(origin, 4.021, 0.0)] == 0
    assert touched.shape == (2, rect.shape[0], rect.shape[1])
    assert touched[0].any() and not touched[0].all()


def test_log_odds_model_must_fit_int8() -> None:
    with pytest.raises(ValueError, match="int8"):
        LogOddsModel(maximum=6.0, hit=1.0)


# -- copy-on-write tiles --------------------------------------------------------------------------------


def _consistent(maps: TiledMaps) -> None:
    counts = np.bincount(maps.tables.ravel(), minlength=maps.pool.shape[0])
    live = np.flatnonzero(counts[1:]) + 1
    np.testing.assert_array_equal(maps.refcount[live], counts[live])
    free = set(maps._free)
    assert not free & set(live.tolist())
    assert maps.tiles_in_use() == live.size


def test_copy_on_write_keeps_maps_apart() -> None:
    geometry = GridGeometry(tile_cells=8, tiles_per_side=16)
    maps = TiledMaps(geometry, 3, initial_tiles=4)
    rect = TileRect(2, 2, 4, 5)
    h, w = rect.shape[0] * 8, rect.shape[1] * 8
    window = np.full((1, h, w), 5, dtype=np.int8)
    touched = np.zeros((1, *rect.shape), dtype=bool)
    touched[0, 0, 0] = touched[0, 1, 2] = True
    maps.scatter([0], rect, window, touched)
    assert maps.tiles_in_use() == 2
    assert maps.gather([1], rect).max() == 0  # the other maps are still unknown there
    maps.select([0, 0, 0])  # resampling: three copies of map 0, sharing its two tiles
    assert maps.tiles_in_use() == 2
    _consistent(maps)
    window2 = maps.gather([1], rect)
    window2[0, :8, :8] = -3
    maps.scatter([1], rect, window2, touched)  # map 1 writes: its tiles are copied first
    assert maps.tiles_in_use() == 4
    assert maps.gather([0], rect)[0, 0, 0] == 5
    assert maps.gather([1], rect)[0, 0, 0] == -3
    assert maps.gather([2], rect)[0, 0, 0] == 5
    _consistent(maps)
    maps.select([1, 1, 2])  # map 0's copy of the first tile is now only held by map 2
    _consistent(maps)
    maps.select([0, 0, 0])  # only map 1's tiles survive; map 0's are freed
    assert maps.tiles_in_use() == 2
    _consistent(maps)
    assert maps.gather([2], rect)[0, 0, 0] == -3


def test_pool_grows_and_extent() -> None:
    geometry = GridGeometry(tile_cells=8, tiles_per_side=16)
    maps = TiledMaps(geometry, 2, initial_tiles=2)
    rect = TileRect(0, 0, 4, 4)
    window = np.ones((2, 32, 32), dtype=np.int8)
    maps.scatter([0, 1], rect, window, np.ones((2, 4, 4), dtype=bool))
    assert maps.tiles_in_use() == 32
    assert maps.pool.shape[0] >= 33
    _consistent(maps)
    assert maps.extent(0) == rect
    assert maps.tables[0, 5, 5] == UNKNOWN_TILE
    maps.share([0], [1])
    assert maps.tiles_in_use() == 16
    _consistent(maps)


def test_grazing_corridor_walls_stay_obstacles_with_the_radish_miss() -> None:
    """A 2.4 m corridor scanned every metre by a 1 deg laser along its axis (the radish logs), mapped at
    poses a little off: each wall cell is a hit for the scans beside it and swept by the beams of the
    others, which graze it. With the filter's default miss (-0.4) most of the wall goes free; with the
    radish logs' (`eval slam`: ``MISS_LOG_ODDS``) it stays an obstacle, which the scan match needs."""
    from agent.commands.eval_slam import log_odds_model

    half_width = 1.2 + 0.021
    walls = np.array([(-5.0, -half_width, 40.0, -half_width), (40.0, half_width, -5.0, half_width)])
    angles = np.radians(-90.0 + np.arange(180) * 1.0)
    origin = (-6.4, -3.2)
    shares = {}
    for name, model in (("default", LogOddsModel()), ("radish", log_odds_model("radish"))):
        window = np.zeros((1, 128, 640), dtype=np.int8)
        for k, x in enumerate(np.arange(0.0, 20.0, 1.0)):
            # Mapped at poses off by 2 cm / 0.2 deg either way, as a filter's are.
            sign = 1.0 if k % 2 else -1.0
            pose = np.array([x, 0.02 * sign, 0.0035 * sign])
            ranges = cast_rays((x, 0.0), angles, walls)
            ranges[~np.isfinite(ranges)] = 50.0  # the corridor's end is out of range: no return
            scan = prepare_scan(ranges, angles, (0.0, 0.0, 0.0), 0.1, 50.0, 15.0, RES / 2)
            integrate_scans(window, origin, RES, pose[None, :], scan, model, 32)
        occupied = window[0] > model.counts(model.occupied)
        columns = slice(int((3.0 - origin[0]) / RES), int((17.0 - origin[0]) / RES))
        rows = [int((y - origin[1]) / RES) for y in (-half_width, half_width)]
        shares[name] = float(np.mean([occupied[r, columns].mean() for r in rows]))
    # Measured: 0.21 of the wall cells with the default, 0.65 with the radish miss (0.57 / 1.0 at the
    # exact poses).
    assert shares["radish"] > 0.5
    assert shares["default"] < 0.35


def test_clear_hands_the_used_slots_back_and_the_maps_refill() -> None:
    """After ``clear`` (a loop closure's rebuild) the used slots' pages go back to the kernel; the unknown
    tile stays zero and maps written afterwards read back what was written."""
    geometry = GridGeometry(tile_cells=32, tiles_per_side=16)
    maps = TiledMaps(geometry, 2, initial_tiles=64)
    rect = TileRect(0, 0, 4, 4)
    maps.scatter([0, 1], rect, np.full((2, 128, 128), 7, dtype=np.int8), np.ones((2, 4, 4), dtype=bool))
    assert maps.tiles_in_use() == 32
    maps.clear()
    assert maps.tiles_in_use() == 0
    assert not maps.pool[UNKNOWN_TILE].any()
    assert maps.gather([0, 1], rect).max() == 0
    window = np.full((1, 128, 128), -2, dtype=np.int8)
    touched = np.zeros((1, 4, 4), dtype=bool)
    touched[0, 1, 2] = True
    maps.scatter([0], rect, window, touched)
    out = maps.gather([0, 1], rect)
    assert (out[0, 32:64, 64:96] == -2).all() and (out[0, :32].max() == 0) and out[1].max() == 0
    _consistent(maps)


def test_normals_of_far_walls_with_a_neighbourhood_that_grows_with_range() -> None:
    """A SICK's 1° beams on a wall 8 m ahead land ~0.14 m apart: within the fixed 0.25 m radius a point has
    three neighbours and no normal; with the radius grown to 0.1 × range (0.8 m) every point but the
    ends' gets the wall's normal. A corner near the laser stays without one either way."""
    angles = np.radians(np.arange(-20.0, 21.0, 1.0))
    far = np.stack([np.full_like(angles, 8.0), 8.0 * np.tan(angles)], axis=1)  # the wall x = 8
    fixed = surface_normals(far)
    grown = surface_normals(far, radius_per_m=0.1, origin_xy=(0.0, 0.0))
    assert not np.any(fixed)
    inner = grown[3:-3]
    assert np.allclose(np.abs(inner[:, 0]), 1.0) and np.allclose(inner[:, 1], 0.0)
    # A right-angled corner 1 m away, points 5 cm apart: not a line at any radius.
    leg = np.arange(0.0, 0.5, 0.05)
    one = np.full_like(leg, 1.0)
    corner = np.concatenate([np.stack([1.0 - leg[::-1], one], 1), np.stack([one, 1.0 - leg], 1)])
    at_corner = surface_normals(corner, np.array([leg.size - 1, leg.size]), radius_per_m=0.1)
    assert not np.any(at_corner)
    # The laser's position sets the range: seen from 7.5 m nearer, the same wall keeps the fixed radius.
    near = surface_normals(far, radius_per_m=0.1, origin_xy=(7.5, 0.0))
    assert not np.any(near[np.abs(far[:, 1]) < 0.5])
