"""Likelihood-field scan matching on a synthetic room: known offsets are recovered."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import numpy.typing as npt
import pytest
from scipy import ndimage

from agent.slam.grid import (
    GridGeometry,
    LogOddsModel,
    ScanPoints,
    TileRect,
    integrate_scans,
    prepare_scan,
    surface_normals,
)
from agent.slam.matcher import (
    DistanceField,
    MatcherConfig,
    SearchConfig,
    _medial_at,
    _square_walls,
    correlative_search,
    degenerate_projection,
    match,
    scan_log_likelihood,
    truncated_energy,
)
from agent.slam.pose import between
from agent.slam.rbpf import voxel_filter, voxel_indices
from drivers.sim.raycast import cast_rays

RES = 0.05
MODEL = LogOddsModel()
ROOM = (
    np.array(
        [
            (-4.0, -3.0, 4.0, -3.0),
            (4.0, -3.0, 4.0, 3.0),
            (4.0, 3.0, -4.0, 3.0),
            (-4.0, 3.0, -4.0, -3.0),
            (1.0, 0.5, 2.0, 0.5),
            (2.0, 0.5, 2.0, 1.5),
            (2.0, 1.5, 1.0, 1.5),
            (1.0, 1.5, 1.0, 0.5),
            (-2.5, -1.0, -1.5, -2.0),
        ]
    )
    + 0.025
)  # walls through cell centres: the 5 cm grid then represents them without bias
ANGLES = np.radians(np.linspace(-120.0, 120.0, 682))
GEOMETRY = GridGeometry()


def scan_at(pose: tuple[float, float, float]) -> np.ndarray:
    ranges = cast_rays((pose[0], pose[1]), ANGLES + pose[2], ROOM, None, 5.6)
    return np.where(np.isfinite(ranges), ranges, 0.0)


def prepared(pose: tuple[float, float, float]):  # type: ignore[no-untyped-def]
    return prepare_scan(scan_at(pose), ANGLES, (0.0, 0.0, 0.0), 0.1, 5.6, 5.5, RES / 2)


def room_field(empty_too: bool = False) -> DistanceField:
    """A map of the room from three scans at known poses; optionally a second, empty window."""
    rect = TileRect.covering(GEOMETRY, (-5.0, -4.0), (5.0, 4.0))
    h, w = rect.shape[0] * GEOMETRY.tile_cells, rect.shape[1] * GEOMETRY.tile_cells
    windows = np.zeros((2 if empty_too else 1, h, w), dtype=np.int8)
    for pose in [(0.0, 0.0, 0.0), (-1.0, 1.0, 2.5), (2.5, -1.5, -2.0)]:
        integrate_scans(
            windows[:1],
            rect.origin_m(GEOMETRY),
            RES,
            np.array([pose]),
            prepared(pose),
            MODEL,
            GEOMETRY.tile_cells,
        )
    return DistanceField.from_obstacles(
        windows > MODEL.counts(MODEL.occupied), rect.origin_m(GEOMETRY), RES, 0.6
    )


def test_distance_field_is_euclidean_within_chamfer_error() -> None:
    obstacles = np.zeros((1, 60, 80), dtype=bool)
    obstacles[0, 20, 10:70] = True
    obstacles[0, 5:55, 40] = True
    field = DistanceField.from_obstacles(obstacles, (0.0, 0.0), RES, 10.0)
    exact = ndimage.distance_transform_edt(~obstacles[0]) * RES
    inner = field.distance_m[0, 1:-1, 1:-1]
    np.testing.assert_allclose(inner, exact, rtol=0.02, atol=1e-6)
    axis = inner[21:30, 25]  # straight below the horizontal wall, nearer to it than to anything: exact
    np.testing.assert_allclose(axis, exact[21:30, 25], rtol=1e-6)
    assert field.distance_m[0, 0, 0] == 10.0  # the border holds the cap


def test_sample_bilinear_and_gradient() -> None:
    obstacles = np.zeros((2, 40, 40), dtype=bool)
    obstacles[0, :, 20] = True  # a wall along y at x = 20.5 cells
    obstacles[1, 10, :] = True  # the second window: a wall along x
    field = DistanceField.from_obstacles(obstacles, (1.0, 2.0), RES, 0.6)
    x = 1.0 + 20.5 * RES + np.array([[0.1, -0.12, 0.0251]])
    y = np.full_like(x, 2.0 + 15.0 * RES)
    d, gx, gy = field.sample(np.array([0]), x, y)
    np.testing.assert_allclose(d, [[0.1, 0.12, 0.0251]], atol=0.003)
    np.testing.assert_allclose(gx, [[1.0, -1.0, 1.0]], atol=0.05)
    np.testing.assert_allclose(gy, 0.0, atol=1e-6)
    d, gx, gy = field.sample(np.array([1]), np.array([[1.5]]), np.array([[2.0 + 10.5 * RES + 0.2]]))
    assert d[0, 0] == pytest.approx(0.2, abs=0.005)
    assert gy[0, 0] == pytest.approx(1.0, abs=0.05)
    far, gx, gy = field.sample(np.array([0]), np.array([[100.0]]), np.array([[100.0]]))
    assert far[0, 0] == pytest.approx(0.6) and gx[0, 0] == 0.0 and gy[0, 0] == 0.0


def test_gauss_newton_recovers_known_offsets() -> None:
    field = room_field()
    truth = np.array([0.4, -0.3, 0.35])
    points = voxel_filter(prepared(tuple(truth)).hit_xy, 0.1, 200)
    offsets = np.array([[0.15, -0.10, math.radians(5.0)], [-0.2, 0.05, math.radians(-4.0)], [0.0, 0.0, 0.0]])
    start = truth[None, :] + offsets
    result = match(field, np.zeros(3, dtype=np.int64), points, start, MatcherConfig())
    assert result.ok.all()
    for pose in result.poses:
        error = between(truth, pose)
        assert math.hypot(error[0], error[1]) < 0.01
        assert abs(math.degrees(error[2])) < 0.3
    assert (result.inlier_fraction > 0.9).all()
    assert (result.rms_m < 0.03).all()
    # The information matrix is positive definite: the room constrains x, y and yaw.
    assert (np.linalg.eigvalsh(result.information) > 0).all()


def test_match_fails_on_an_empty_map() -> None:
    field = room_field(empty_too=True)
    truth = np.array([0.0, 0.0, 0.0])
    points = voxel_filter(prepared(tuple(truth)).hit_xy, 0.1, 200)
    result = match(field, np.array([0, 1]), points, np.tile(truth, (2, 1)), MatcherConfig())
    assert result.ok.tolist() == [True, False]


def test_match_is_trusted_on_a_few_fitting_endpoints_among_many_unexplained() -> None:
    """With eval slam's settings for radish logs, a scan that sees mostly past the map (a corner, a
    doorway) is still a match when enough of its endpoints fit the mapped walls: the share of the whole
    scan does not condemn it (on Intel that share sent hundreds of good matches to the motion model); too
    few fitting endpoints do."""
    field = room_field()
    truth = np.array([0.0, 0.0, 0.0])
    on_walls = voxel_filter(prepared(tuple(truth)).hit_xy, 0.1, 200)
    rng = np.random.default_rng(0)
    beyond = rng.uniform(30.0, 40.0, size=(150, 2))  # far outside the map
    start = (truth + np.array([0.03, -0.02, 0.01]))[None, :]
    few = np.vstack([on_walls[::8][:12], beyond])
    sparse = MatcherConfig(min_inliers=10, min_inlier_fraction=0.0)  # eval slam's for radish logs
    result = match(field, np.zeros(1, dtype=np.int64), few, start, sparse)
    assert result.inlier_fraction[0] < 0.1
    assert result.ok[0]
    too_few = np.vstack([on_walls[::8][:6], beyond])
    assert not match(field, np.zeros(1, dtype=np.int64), too_few, start, sparse).ok[0]
    # The filter's default also wants them to be a tenth of the scan.
    assert not match(field, np.zeros(1, dtype=np.int64), few, start, MatcherConfig()).ok[0]


def test_truncated_energy_ranks_the_true_pose_first_and_counts_the_prior() -> None:
    field = room_field()
    truth = np.array([0.4, -0.3, 0.35])
    points = voxel_filter(prepared(tuple(truth)).hit_xy, 0.1, 200)
    poses = truth[None, :] + np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, 0.0, math.radians(10.0)]])
    window = np.zeros(3, dtype=np.int64)
    energy = truncated_energy(field, window, points, poses, 0.12)
    assert energy[0] < 0.1 * energy[1] and energy[0] < 0.1 * energy[2]
    # Every endpoint counts at most the bound squared.
    assert (energy <= points.shape[0] * 0.12**2 + 1e-9).all()
    # The prior adds (x - x0)ᵀ Λ (x - x0): centred on the second pose, it charges the first for its move.
    prior = np.diag([100.0, 100.0, 100.0])
    centres = np.tile(poses[1], (3, 1))
    with_prior = truncated_energy(field, window, points, poses, 0.12, prior, centres)
    assert with_prior[1] == pytest.approx(energy[1])
    assert with_prior[0] == pytest.approx(energy[0] + 100.0 * 0.3**2)


def _mapped_corridor() -> tuple[ScanPoints, TileRect, npt.NDArray[np.bool_]]:
    """A corridor (two parallel walls 2 m apart, off the cell boundaries) scanned once from its centre: the
    scan, the map's tile rectangle and its obstacle cells (1, H, W)."""
    walls = np.array([(-20.0, -1.0, 20.0, -1.0), (-20.0, 1.0, 20.0, 1.0)]) + 0.025
    ranges = cast_rays((0.0, 0.0), ANGLES, walls, None, 5.6)
    scan = prepare_scan(
        np.where(np.isfinite(ranges), ranges, 0.0), ANGLES, (0.0, 0.0, 0.0), 0.1, 5.6, 5.5, RES / 2
    )
    rect = TileRect.covering(GEOMETRY, (-6.0, -3.0), (6.0, 3.0))
    h, w = rect.shape[0] * GEOMETRY.tile_cells, rect.shape[1] * GEOMETRY.tile_cells
    windows = np.zeros((1, h, w), dtype=np.int8)
    integrate_scans(windows, rect.origin_m(GEOMETRY), RES, np.zeros((1, 3)), scan, MODEL, GEOMETRY.tile_cells)
    return scan, rect, windows > MODEL.counts(MODEL.occupied)


def test_prior_holds_the_unconstrained_direction() -> None:
    """In a corridor (two parallel walls) the scan does not fix x; with a prior the match stays put."""
    scan, rect, obstacles = _mapped_corridor()
    field = DistanceField.from_obstacles(obstacles, rect.origin_m(GEOMETRY), RES, 0.6)
    points = voxel_filter(scan.hit_xy, 0.1, 200)
    start = np.array([[0.3, 0.08, 0.02]])
    free = match(field, np.zeros(1, dtype=np.int64), points, start, MatcherConfig())
    held = match(
        field, np.zeros(1, dtype=np.int64), points, start, MatcherConfig(), np.diag([20.0, 0.0, 0.0])
    )
    # Along the corridor only the ends of the mapped walls say anything: unheld, x wanders off the start.
    assert abs(free.poses[0, 0] - 0.3) > 2 * abs(held.poses[0, 0] - 0.3)
    assert abs(held.poses[0, 0] - 0.3) < 0.05
    for result in (free, held):  # across the corridor and in heading the walls decide
        assert abs(result.poses[0, 1]) < 0.01
        assert abs(result.poses[0, 2]) < math.radians(0.5)


def test_correlative_search_finds_a_large_heading_error() -> None:
    field = room_field()
    truth = np.array([-0.5, 0.6, -1.0])
    points = voxel_filter(prepared(tuple(truth)).hit_xy, 0.1, 200)
    start = truth + np.array([0.2, -0.15, math.radians(12.0)])
    found, cost = correlative_search(field, 0, points, start, SearchConfig())
    error = between(truth, found)
    assert math.hypot(error[0], error[1]) <= 0.1
    assert abs(math.degrees(error[2])) <= 1.5
    _, cost_at_start = correlative_search(
        field, 0, points, start, SearchConfig(xy_range_m=0.0, yaw_range_rad=0.0)
    )
    assert cost < cost_at_start


def test_log_likelihood_peaks_at_the_truth() -> None:
    field = room_field()
    truth = np.array([1.0, -1.0, 0.5])
    points = voxel_filter(prepared(tuple(truth)).hit_xy, 0.1, 200)
    shifts = np.linspace(-0.2, 0.2, 9)
    candidates = np.tile(truth, (1, 9, 1))
    candidates[0, :, 0] += shifts
    ll = scan_log_likelihood(field, np.zeros(1, dtype=np.int64), points, candidates, 0.05, 0.25)
    assert int(np.argmax(ll[0])) == 4
    assert np.all(np.diff(ll[0, :5]) > 0) and np.all(np.diff(ll[0, 4:]) < 0)


def test_stack_field_is_each_window_field() -> None:
    """The stack's windows are transformed one by one and scaled and coded together: nothing may leak
    between them (a wall at one window's edge is no wall in the next)."""
    rng = np.random.default_rng(3)
    obstacles = rng.random((3, 40, 50)) < 0.02
    obstacles[0, :, -1] = True  # a wall along y on the first window's last column
    obstacles[1, 0, :] = True  # a wall along x on the second window's first row
    obstacles[2, 10, 5:45] = obstacles[2, 11, 5:30] = True  # a wall two cells thick
    known = rng.random((3, 40, 50)) < 0.97
    known[:, :, 40:] = False
    known |= obstacles
    stack = DistanceField.from_obstacles(obstacles, (1.0, 2.0), RES, 0.55, known)
    assert (stack.medial > 0).any() and (stack.distance_m < 0).any()
    for k in range(3):
        alone = DistanceField.from_obstacles(obstacles[k : k + 1], (1.0, 2.0), RES, 0.55, known[k : k + 1])
        np.testing.assert_array_equal(stack.distance_m[k], alone.distance_m[0])
        np.testing.assert_array_equal(stack.medial[k], alone.medial[0])


def _whole_window_field(
    obstacles: np.ndarray, known: np.ndarray, cap_m: float, resolution_m: float
) -> np.ndarray:
    """The padded distance stack as ``from_windows`` built it before it cropped to the known box: the
    transform and the dilation over every window's whole canvas."""
    import cv2

    from agent.slam.matcher import UNKNOWN

    u, h, w = obstacles.shape
    out = np.empty((u, h + 2, w + 2), dtype=np.float32)
    for k in range(u):
        canvas = np.ones((h + 2, w + 2), dtype=np.uint8)
        canvas[1:-1, 1:-1] = ~obstacles[k]
        cv2.distanceTransform(canvas, cv2.DIST_L2, 5, dst=out[k])
        canvas[...] = 0
        canvas[1:-1, 1:-1] = known[k]
        near = cv2.dilate(canvas, np.ones((3, 3), np.uint8))
        np.copyto(out[k], np.float32(UNKNOWN / resolution_m), where=near == 0)
    out *= np.float32(resolution_m)
    np.minimum(out, np.float32(cap_m), out=out)
    out[:, 0, :] = out[:, -1, :] = cap_m
    out[:, :, 0] = out[:, :, -1] = cap_m
    return out


def test_field_cropped_to_the_known_box_is_the_whole_windows_bit_for_bit() -> None:
    """The transform runs on the box of the known cells and obstacles only: every cell as over the
    whole window (boxes touching each edge, a box in the middle, an empty window, a lone obstacle)."""
    rng = np.random.default_rng(7)
    u, h, w = 8, 70, 90
    obstacles = rng.random((u, h, w)) < 0.03
    known = rng.random((u, h, w)) < 0.9
    boxes = [(0, 40, 0, 50), (30, 70, 40, 90), (10, 60, 20, 70), (0, 70, 0, 90), (5, 6, 80, 90)]
    for k, (r0, r1, c0, c1) in enumerate(boxes):
        inside = np.zeros((h, w), dtype=bool)
        inside[r0:r1, c0:c1] = True
        known[k] &= inside
        obstacles[k] &= known[k]
    known[5] = obstacles[5] = False  # nothing mapped
    known[6] = False
    obstacles[6] = False
    obstacles[6, 35, 45] = known[6, 35, 45] = True  # one obstacle
    obstacles[7, 0:70:7, :] = True  # walls to the edges, some cells not marked known
    for cap in (0.55, 5.0):
        field = DistanceField.from_obstacles(obstacles, (1.0, 2.0), RES, cap, known)
        np.testing.assert_array_equal(field.distance_m, _whole_window_field(obstacles, known, cap, RES))


def test_field_from_log_odds_counts_is_from_windows_bit_for_bit() -> None:
    """``from_log_odds`` (the update's field, straight from the stored counts) gives ``from_windows``'s
    field of obstacles = counts > occupied and known = counts != 0, from views of larger arrays too
    (boxes touching each edge, an empty window, a lone obstacle, cells known but free)."""
    rng = np.random.default_rng(11)
    u, h, w = 7, 60, 80
    occupied = 8
    counts = rng.integers(-40, 40, size=(u, h + 4, w + 6)).astype(np.int8)
    counts[rng.random(counts.shape) < 0.5] = 0
    counts[0, :30] = 0  # known cells only in the upper half
    counts[1, :, 50:] = 0
    counts[2] = 0  # nothing mapped
    counts[3] = 0
    counts[3, 30, 40] = 20  # one obstacle
    counts[4] = np.where(counts[4] > occupied, 0, counts[4])  # known, no obstacle
    views = counts[:, 2 : 2 + h, 3 : 3 + w]  # (rows of the larger array: strided)
    for cap in (0.55, 5.0):
        from_counts = DistanceField.from_log_odds(
            u, (h, w), lambda k: views[k], occupied, (1.0, 2.0), RES, cap
        )
        masks = DistanceField.from_windows(
            u, (h, w), lambda k: (views[k] > occupied, views[k] != 0), (1.0, 2.0), RES, cap
        )
        np.testing.assert_array_equal(from_counts.distance_m, masks.distance_m)
    with pytest.raises(ValueError):
        DistanceField.from_log_odds(1, (h, w), lambda k: views[k], -1, (1.0, 2.0), RES, 0.55)


def test_medial_codes_at_lookup_match_the_whole_stack() -> None:
    """The codes a lookup computes for its cells are the whole stack's (walls one and two cells thick,
    along either axis, clutter, unknown cells)."""
    rng = np.random.default_rng(5)
    obstacles = np.zeros((2, 40, 50), dtype=bool)
    obstacles[0, 10, 5:40] = True
    obstacles[0, 20:22, 5:40] = True
    obstacles[1, 3:35, 12] = True
    obstacles[1, 3:35, 30:32] = True
    obstacles |= rng.random(obstacles.shape) < 0.02
    known = (rng.random(obstacles.shape) < 0.9) | obstacles
    field = DistanceField.from_obstacles(obstacles, (0.0, 0.0), 0.05, 0.55, known)
    _u, hp, wp = field.distance_m.shape
    rows, cols = np.meshgrid(np.arange(1, hp - 1), np.arange(1, wp - 1), indexing="ij")
    cells = (np.arange(2)[:, None, None] * hp + rows) * wp + cols
    whole = field.medial
    assert (whole > 0).sum() > 100
    np.testing.assert_array_equal(
        _medial_at(field.distance_m.reshape(-1), cells.reshape(-1), wp), whole.reshape(-1)[cells.reshape(-1)]
    )


def test_per_pose_convergence_gives_each_pose_its_answer_alone() -> None:
    """With ``per_pose_convergence`` a pose that converged leaves the batch: every pose of the batch
    then gets what matching it alone gives (a batch of one stops when its pose converges), pose,
    information and trust alike; the all-together batch differs only by the extra tiny steps."""
    field = room_field()
    truth = np.array([0.4, -0.3, 0.35])
    points = voxel_filter(prepared(tuple(truth)).hit_xy, 0.1, 200)
    normals = np.zeros_like(points)
    normals[::2, 0] = 1.0  # some endpoints with a normal, to run the point-to-line residual too
    offsets = np.array(
        [
            [0.15, -0.10, math.radians(5.0)],
            [-0.2, 0.05, math.radians(-4.0)],
            [0.0, 0.0, 0.0],
            [0.002, -0.001, 0.0005],
            [0.3, 0.25, math.radians(-8.0)],
        ]
    )
    start = truth[None, :] + offsets
    prior = np.diag([4.0, 4.0, 1.0])
    per_pose = MatcherConfig(per_pose_convergence=True)
    batch = match(field, np.zeros(5, dtype=np.int64), points, start, per_pose, prior, None, normals, 0.5)
    together = match(
        field, np.zeros(5, dtype=np.int64), points, start, MatcherConfig(), prior, None, normals, 0.5
    )
    for k in range(start.shape[0]):
        alone = match(
            field, np.zeros(1, dtype=np.int64), points, start[k : k + 1], per_pose, prior, None, normals, 0.5
        )
        np.testing.assert_allclose(batch.poses[k], alone.poses[0], rtol=0.0, atol=1e-9)
        np.testing.assert_allclose(batch.information[k], alone.information[0], rtol=1e-9, atol=1e-9)
        assert batch.ok[k] == alone.ok[0]
        assert batch.inlier_fraction[k] == pytest.approx(alone.inlier_fraction[0])
        # The flag off and alone are the same algorithm for a batch of one.
        off_alone = match(
            field,
            np.zeros(1, dtype=np.int64),
            points,
            start[k : k + 1],
            MatcherConfig(),
            prior,
            None,
            normals,
            0.5,
        )
        np.testing.assert_array_equal(off_alone.poses, alone.poses)
    # The poses reach the same optimum either way (within the convergence tolerance, a few of them).
    np.testing.assert_allclose(batch.poses, together.poses, atol=5e-3)
    assert not np.array_equal(batch.poses, together.poses)  # the extra steps do move the converged ones


def test_the_residual_gate_scores_new_wall_beyond_the_mapped_end_by_its_line() -> None:
    """A wall mapped up to x = 1 (free space known beyond it), seen up to x = 1.5: point to line, gated on
    the distance to the nearest obstacle, the endpoints past the mapped end are outliers and a pose slid
    back along the wall (every endpoint on mapped cells) scores better than the true one; gated on the
    residual (their offset across the wall's line) they count as fitting it."""
    h, w = 40, 80
    obstacles = np.zeros((1, h, w), dtype=bool)
    obstacles[0, 20, : int(1.0 / RES) + 40] = True  # y = 1.025, x from -2 to 1
    field = DistanceField.from_obstacles(obstacles, (-2.0, 0.0), RES, 0.6, np.ones_like(obstacles))
    xs = np.arange(0.0, 1.5, 0.05)  # within the field's reach (its cap less a cell) of the mapped end
    points = np.stack([xs, np.full_like(xs, 1.025)], axis=1)
    normals = np.tile([0.0, 1.0], (xs.size, 1))
    poses = np.array([[0.0, 0.0, 0.0], [-0.5, 0.0, 0.0]])  # the truth, slid back 0.5 m
    windows = np.zeros(2, dtype=np.int64)

    def energy(gate: bool) -> np.ndarray:
        return truncated_energy(field, windows, points, poses, 0.12, None, None, normals, 0.0, None, gate)

    by_distance, by_residual = energy(False), energy(True)
    assert by_distance[0] > by_distance[1] + 5 * 0.12**2  # the endpoints past x ~ 1.1: outliers
    # Gated on the residual they are inliers, each at its (bilinear field's) offset across the line, a few
    # centimetres: the truth's handicap against the slid pose shrinks to a third.
    assert by_residual[1] == pytest.approx(by_distance[1], abs=1e-9)  # on the mapped wall: the same
    assert by_residual[0] - by_residual[1] < (by_distance[0] - by_distance[1]) / 3


def test_degeneracy_aware_steps_leave_a_corridor_s_length_to_the_prior() -> None:
    """A corridor whose walls are mapped in patches (every other metre): the patches pull an endpoint
    between them along the wall (point to point), so with a weak prior the match slides along the
    corridor, and those pulls are information along it (sum J Jᵀ). The scan's surface normals all lie
    across the corridor: with ``min_translation_information`` the scan does not move the pose along it
    (the prior holds it at its centre), while across the corridor and in heading the walls still decide.
    In a room, where every direction is well observed, the option changes nothing."""
    scan, rect, obstacles = _mapped_corridor()
    x_cells = rect.origin_m(GEOMETRY)[0] + (np.arange(obstacles.shape[2]) + 0.5) * RES
    obstacles[0][:, (np.floor(x_cells) % 2) == 1] = False  # walls mapped on alternate metres only
    field = DistanceField.from_obstacles(obstacles, rect.origin_m(GEOMETRY), RES, 0.6)
    kept = voxel_indices(scan.hit_xy, 0.1, 200)
    points = scan.hit_xy[kept]
    normals = surface_normals(scan.hit_xy, kept)
    assert np.mean(np.abs(normals[:, 1]) > 0.99) > 0.5  # most endpoints: a normal across the corridor
    start = np.array([[0.3, 0.05, 0.02]])
    prior = np.diag([2.0, 2.0, 0.0])
    ix = np.zeros(1, dtype=np.int64)
    free = match(field, ix, points, start, MatcherConfig(), prior, normals_xy=normals)
    aware_config = MatcherConfig(min_translation_information=10.0)
    aware = match(field, ix, points, start, aware_config, prior, normals_xy=normals)
    assert free.information[0, 0, 0] > 10.0  # the patches' pulls: information along the corridor
    assert abs(free.poses[0, 0] - 0.3) > 0.02  # pulled along the corridor by the patches
    assert abs(aware.poses[0, 0] - 0.3) < 0.005  # held where the prior puts it
    for result in (free, aware):
        assert abs(result.poses[0, 1]) < 0.01
        assert abs(result.poses[0, 2]) < math.radians(0.5)
    room = room_field()
    scan_room = prepared((0.3, -0.2, 0.1))
    kept_room = voxel_indices(scan_room.hit_xy, 0.1, 200)
    normals_room = surface_normals(scan_room.hit_xy, kept_room)
    guess = np.array([[0.35, -0.15, 0.12]])
    args = (room, ix, scan_room.hit_xy[kept_room], guess)
    plain = match(*args, MatcherConfig(), normals_xy=normals_room, along_weight=0.0)
    same = match(*args, aware_config, normals_xy=normals_room, along_weight=0.0)
    assert np.array_equal(plain.poses, same.poses)
    assert np.allclose(same.poses[0], (0.3, -0.2, 0.1), atol=0.01)
    # With a ratio, a direction is weak only beside a well-observed one: a corridor (40 across, 1 along)
    # is, a scan with few surfaces anywhere (3 and 1) is not.
    info = np.array([[[40.0, 0.0], [0.0, 1.0]], [[3.0, 0.0], [0.0, 1.0]]])
    both = degenerate_projection(info, 2.0)
    corridor_only = degenerate_projection(info, 2.0, ratio=10.0)
    assert both is not None and corridor_only is not None
    assert np.allclose(both, [[[1.0, 0.0], [0.0, 0.0]], [[1.0, 0.0], [0.0, 0.0]]])
    assert np.allclose(corridor_only, [[[1.0, 0.0], [0.0, 0.0]], np.eye(2)])
    assert degenerate_projection(info[1:], 2.0, ratio=10.0) is None


def test_duplicate_rows_matched_once_as_the_whole_batch(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Rows that are the same problem bit for bit (a resampled particle's copies) are matched once; the
    answers are those of the whole batch matched row by row in one run (forced by disabling the check)."""
    from agent.slam import matcher as matcher_module

    field = room_field()
    points = voxel_filter(prepared((0.3, -0.2, 0.4)).hit_xy, 0.1, 200)
    rng = np.random.default_rng(3)
    distinct = np.array([0.3, -0.2, 0.4]) + rng.normal(0.0, [0.1, 0.1, 0.05], size=(4, 3))
    starts = distinct[[0, 1, 1, 2, 0, 3, 1]]
    prior = np.diag([5.0, 5.0, 1.0])
    windows = np.zeros(starts.shape[0], dtype=np.int64)
    calls: list[int] = []
    real_step = matcher_module._gauss_newton_step

    def counted(*args, **kwargs):  # type: ignore[no-untyped-def]
        calls.append(args[3].shape[0])
        return real_step(*args, **kwargs)

    monkeypatch.setattr(matcher_module, "_gauss_newton_step", counted)
    once, once_res = matcher_module.match_with_residuals(
        field, windows, points, starts, MatcherConfig(), prior, normals_xy=None
    )
    assert set(calls) == {4}  # four distinct rows stepped, not seven
    monkeypatch.setattr(matcher_module, "_distinct_rows", lambda *args: None)
    whole, whole_res = matcher_module.match_with_residuals(
        field, windows, points, starts, MatcherConfig(), prior, normals_xy=None
    )
    for a, b in ((once.poses, whole.poses), (once.information, whole.information), (once.ok, whole.ok)):
        assert np.array_equal(a, b)
    assert np.array_equal(once_res.r, whole_res.r) and np.array_equal(once_res.gate, whole_res.gate)


def test_a_boundary_wall_mapped_in_patches_is_measured_to_the_boundary() -> None:
    """``medial_window_cells`` 3: a wall on the boundary between rows 10 and 11, mapped as a grazing view maps
    it: single cells with gaps, alternating between the two rows. Its medial line is the boundary: a sample
    there is at 0, one 2 cm off at 2 cm, wherever it lies along the wall but on a saddle (bilinear distances,
    which the patches' four-cell neighbourhoods left, pull diagonally towards the nearest patch: 0-3.5 cm on
    the boundary). A corner and a wall's last cells keep the bilinear value."""
    obstacles = np.zeros((1, 30, 60), dtype=bool)
    obstacles[0, 10, 4:44:4] = True
    obstacles[0, 11, 6:44:4] = True
    obstacles[0, 11:25, 50] = True  # a wall along y ...
    obstacles[0, 11, 47:51] = True  # ... with a short one along x into its corner
    four = DistanceField.from_obstacles(obstacles, (0.0, 0.0), RES, 0.55)
    field = dataclasses.replace(four, medial_window_cells=3)
    boundary = 11 * RES
    # (Anywhere but the exact saddles midway between two patches, where the gradient that finds the
    # nearest obstacle cell is zero.)
    x = np.random.default_rng(0).uniform(10 * RES, 40 * RES, 61)
    for off in (0.0, 0.02, -0.02):
        d, ddx, ddy, known = field.sample_known(
            np.zeros(1, dtype=np.int64), x[None, :], np.full((1, 61), boundary + off)
        )
        assert known.all()
        np.testing.assert_allclose(d[0], abs(off), atol=1e-6)
        if off:
            np.testing.assert_allclose(ddy[0], math.copysign(1.0, off))
            np.testing.assert_allclose(ddx[0], 0.0)
    bilinear, *_ = field.sample_known(
        np.zeros(1, dtype=np.int64), x[None, :], np.full((1, 61), boundary), medial=False
    )
    assert bilinear.max() > 0.02
    by_neighbours, *_ = four.sample_known(
        np.zeros(1, dtype=np.int64), x[None, :], np.full((1, 61), boundary)
    )  # the four-neighbour test (the default) finds no wall here: the bilinear values
    np.testing.assert_array_equal(by_neighbours, bilinear)
    cells = np.arange(field.distance_m.size)
    _u, hp, wp = field.distance_m.shape
    wall, along_y, shift = _square_walls(field.distance_m.reshape(-1), cells, wp, hp, 3)
    whole = field.medial.reshape(-1)  # the lookups' test, coded
    np.testing.assert_array_equal(wall, whole > 0)
    np.testing.assert_array_equal(along_y & wall, (whole >= 1) & (whole <= 3))
    np.testing.assert_array_equal(shift[wall], ((whole[wall] - 1) % 3 - 1) * 0.5)
    codes = field.medial[0, 1:-1, 1:-1]
    assert codes[10, 8] == 1 + 3 + 2 and codes[11, 10] == 1 + 3 + 0  # along x, the line above / below
    assert codes[10, 4] == 0  # the wall's end: nothing on its left
    assert codes[11, 48] == 0 and codes[11, 50] == 0  # the corner's cells
    assert codes[20, 50] == 1 + 1  # along y, one cell thick: the line through the centre
