"""The grid's phase: the lattice the filter picks from its first scan so that walls run through cell
centres (agent.slam.lattice), and what the filter does with it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.slam.grid import GridGeometry, TileRect
from agent.slam.lattice import fit_grid_phase, phase_of
from agent.slam.rbpf import RbpfConfig, RbpfSlam
from agent.slam.scan import LaserGeometry
from drivers.sim.raycast import cast_rays

RES = 0.05
LASER = LaserGeometry(np.radians(np.linspace(-120.0, 120.0, 682)), 0.02, 5.6)


def walls(x_m: float, y_m: float, noise_m: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Endpoints on a wall across x at ``x_m`` and one across y at ``y_m`` (200 each, range noise across
    the wall), with their normals."""
    along = rng.uniform(-2.0, 2.0, 200)
    across_x = np.column_stack([x_m + rng.normal(0.0, noise_m, 200), along])
    across_y = np.column_stack([along, y_m + rng.normal(0.0, noise_m, 200)])
    normals = np.vstack([np.tile([-1.0, 0.0], (200, 1)), np.tile([0.0, 1.0], (200, 1))])
    return np.vstack([across_x, across_y]), normals


def centre_offset(wall_m: float, phase_m: float) -> float:
    """How far ``wall_m`` lies from the nearest cell centre of a lattice with that phase."""
    origin = GridGeometry(phase_m=(phase_m, 0.0)).origin_m[0]
    cells = (wall_m - origin) / RES - 0.5
    return abs(cells - round(cells)) * RES


@pytest.mark.parametrize("offset", [0.0, 0.0125, 0.025, 0.037, -0.011])
def test_the_phase_puts_cell_centres_on_the_walls(offset: float) -> None:
    rng = np.random.default_rng(1)
    points, normals = walls(2.0 + offset, -1.35 + offset, 0.004, rng)
    fit = fit_grid_phase(points, normals, RES)
    assert fit.votes == (200, 200)
    px, py = fit.phase_m
    assert px is not None and py is not None
    assert 0.0 <= px < RES and 0.0 <= py < RES
    assert centre_offset(2.0 + offset, px) < 0.002
    assert centre_offset(-1.35 + offset, py) < 0.002
    assert min(fit.resultant) > 0.8  # exp(-2 pi^2 sigma^2 / res^2) = 0.88 for 4 mm of noise


def test_walls_without_one_offset_or_along_no_axis_leave_the_phase_alone() -> None:
    rng = np.random.default_rng(2)
    # Two walls across x half a cell apart: their offsets cancel on the circle.
    a, na = walls(2.0, 0.0, 0.002, rng)
    b, nb = walls(-1.025, 0.0, 0.002, rng)
    fit = fit_grid_phase(np.vstack([a[:200], b[:200]]), np.vstack([na[:200], nb[:200]]), RES)
    assert fit.phase_m[0] is None and fit.resultant[0] < 0.1
    assert fit.phase_m[1] is None and fit.votes[1] == 0
    # An oblique wall: no endpoint's normal lies along an axis.
    t = np.linspace(0.0, 3.0, 300)
    oblique = np.column_stack([t * math.cos(0.5), t * math.sin(0.5)])
    normal = np.tile([-math.sin(0.5), math.cos(0.5)], (300, 1))
    assert fit_grid_phase(oblique, normal, RES).votes == (0, 0)
    # Too few endpoints: no vote counts.
    few = fit_grid_phase(a[:20], na[:20], RES)
    assert few.votes[0] == 20 and few.phase_m == (None, None)
    # Range noise as wide as a cell: the offsets spread over the circle.
    noisy, nn = walls(2.0, 0.0, 0.03, rng)
    assert fit_grid_phase(noisy, nn, RES).phase_m == (None, None)


def test_bad_input_is_refused() -> None:
    with pytest.raises(ValueError, match="shape"):
        fit_grid_phase(np.zeros((3, 2)), np.zeros((2, 2)), RES)
    with pytest.raises(ValueError, match="resolution"):
        fit_grid_phase(np.zeros((3, 2)), np.zeros((3, 2)), 0.0)
    with pytest.raises(ValueError, match="phase_m"):
        GridGeometry(phase_m=(0.05, 0.0))
    with pytest.raises(ValueError, match="phase_m"):
        GridGeometry(phase_m=(0.0, -0.001))
    assert phase_of(-1e-20, RES) == 0.0
    assert phase_of(0.123, RES) == pytest.approx(0.023)


def test_geometry_phase_moves_every_window_origin() -> None:
    moved = GridGeometry(phase_m=(0.02, 0.03))
    rect = TileRect.covering(moved, (-1.0, -1.0), (1.0, 1.0))
    x0, y0 = rect.origin_m(moved)
    bx, by = rect.origin_m(GridGeometry())
    assert (x0 - bx, y0 - by) == pytest.approx((0.02, 0.03))


# A 6 m x 5 m room whose walls lie on the 5 cm boundaries of the unmoved lattice, shifted by ``shift``.
ROOM = np.array(
    [(-3.0, -2.5, 3.0, -2.5), (3.0, -2.5, 3.0, 2.5), (3.0, 2.5, -3.0, 2.5), (-3.0, 2.5, -3.0, -2.5)]
)


def first_map(shift: float, phase_from_walls: bool) -> RbpfSlam:
    room = ROOM + shift
    start = (0.3 + shift, -0.2 + shift, 0.4)
    rng = np.random.default_rng(3)
    ranges = cast_rays(start[:2], LASER.angles_rad + start[2], room, None, 5.6)
    ranges = np.where(np.isfinite(ranges), ranges + rng.normal(0.0, 0.003, ranges.size), 0.0)
    config = RbpfConfig(
        particles=2, initial_pose=start, grid_phase_from_walls=phase_from_walls, loop_closure=None
    )
    slam = RbpfSlam(LASER, config)
    slam.process(0.0, ranges, np.zeros(3))
    return slam


def wall_rows(slam: RbpfSlam, y_wall: float) -> int:
    """How many rows of cells near the wall across y at ``y_wall`` hold obstacles (the map's columns in
    the room's middle third)."""
    window = slam.map_window()
    assert window is not None
    log_odds, (x0, y0) = window
    cols = slice(math.floor((-1.0 - x0) / RES), math.floor((1.0 - x0) / RES))
    row = math.floor((y_wall - y0) / RES)
    band = log_odds[row - 2 : row + 3, cols] > 0.0
    return int(np.count_nonzero(band.any(axis=1)))


@pytest.mark.parametrize("shift", [0.0, 0.0125, 0.031])
def test_the_filter_maps_each_wall_in_one_row_of_cells_wherever_the_room_lies(shift: float) -> None:
    slam = first_map(shift, phase_from_walls=True)
    px, py = slam.config.grid.phase_m
    # The room's walls run through cell centres of the lattice it chose.
    assert centre_offset(3.0 + shift, px) < 0.003
    origin_y = GridGeometry(phase_m=(0.0, py)).origin_m[1]
    cells = (2.5 + shift - origin_y) / RES - 0.5
    assert abs(cells - round(cells)) * RES < 0.003
    assert wall_rows(slam, 2.5 + shift) == 1
    assert wall_rows(slam, -2.5 + shift) == 1


def test_without_the_phase_a_wall_on_a_cell_boundary_is_mapped_in_two_rows() -> None:
    slam = first_map(0.0, phase_from_walls=False)
    assert slam.config.grid.phase_m == (0.0, 0.0)
    assert wall_rows(slam, 2.5) == 2


def test_a_continued_map_keeps_its_own_lattice() -> None:
    saved = first_map(0.0125, phase_from_walls=True)
    window = saved.map_window()
    assert window is not None
    log_odds, origin = window
    slam = RbpfSlam(LASER, RbpfConfig(particles=2, initial_pose=(0.3, -0.2, 0.4), loop_closure=None))
    slam.seed_map(log_odds, origin)
    assert slam.config.grid.phase_m == pytest.approx(saved.config.grid.phase_m, abs=1e-9)
    again = slam.map_window()
    assert again is not None
    assert again[1] == pytest.approx(origin)
    np.testing.assert_array_equal(np.sign(again[0]), np.sign(log_odds))
