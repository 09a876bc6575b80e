"""The calibration steps' mathematics on synthetic data with known answers: wheel radius and track, the
laser's yaw and place from a corner, the camera's tilt, yaw and place from gravity and a board, the
nearest-neighbour resize correction, the servo plan, and view collection."""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from calibration.boards import BoardDetector, BoardSpec, Detection
from calibration.intrinsics import Coverage, NearestResize, View, ViewCollector, calibrate
from calibration.laser import (
    Corner,
    extract_lines,
    find_corner,
    fit_offset,
    laser_shift,
    rot,
    wall_turn,
    yaw_from_shift,
)
from calibration.mount import (
    fit_lens_offset,
    level_rotation,
    tilt_from_gravity,
    tilt_from_normal,
    yaw_from_board_shift,
)
from calibration.report import CalibrationError, Check
from calibration.servos import Found, plan_changes
from calibration.wheels import Run, fit_wheels
from drivers.servos.control_table import OperatingMode
from drivers.sim.render import nearest_indices

FloatArray = npt.NDArray[np.float64]


# -- wheels ------------------------------------------------------------------------------------------------
def test_wheels_recover_radius_and_track() -> None:
    r, b = 0.0335, 0.1625
    runs = [
        Run("straight", 1.0 / r, 1.0 / r, 1.0),
        Run("straight", 0.98 / r, 0.98 / r, 0.98),
        # A turn of 2 turns: wheels roll +-(b/2) * angle.
        Run("turn", -b / 2 * 4 * math.pi / r, b / 2 * 4 * math.pi / r, 4 * math.pi),
        Run("turn", -b / 2 * 4.1 * math.pi / r, b / 2 * 4.1 * math.pi / r, 4.1 * math.pi),
    ]
    fit = fit_wheels(runs)
    assert fit.wheel_radius_m == pytest.approx(r, rel=1e-12)
    assert fit.track_m == pytest.approx(b, rel=1e-12)
    assert fit.radius_spread_pct == pytest.approx(0.0, abs=1e-9)


def test_wheels_refuse_runs_too_short_to_measure() -> None:
    with pytest.raises(CalibrationError, match="drive further"):
        fit_wheels([Run("straight", 0.5, 0.5, 0.01), Run("turn", -10, 10, 6.3)])
    with pytest.raises(CalibrationError, match="straight run and one turn"):
        fit_wheels([Run("straight", 30, 30, 1.0)])


# -- laser ---------------------------------------------------------------------------------------------------
def corner_scan(
    pose_laser_world: tuple[float, float, float], corner: tuple[float, float], seed: int = 0
) -> FloatArray:
    """Points (laser frame, angle order) of two walls meeting at ``corner`` (one along -x, one along -y from
    it), seen from a laser at (x, y, yaw), with 5 mm of range noise."""
    rng = np.random.default_rng(seed)
    lx, ly, yaw = pose_laser_world
    cx, cy = corner
    angles = np.linspace(-2.0, 2.0, 700)
    pts = []
    for a in angles:
        d = np.array([math.cos(yaw + a), math.sin(yaw + a)])
        best = math.inf
        # Wall 1: x = cx, y <= cy; wall 2: y = cy, x <= cx.
        if abs(d[0]) > 1e-9:
            t = (cx - lx) / d[0]
            if t > 0 and ly + t * d[1] <= cy:
                best = min(best, t)
        if abs(d[1]) > 1e-9:
            t = (cy - ly) / d[1]
            if t > 0 and lx + t * d[0] <= cx:
                best = min(best, t)
        if best < 5.0:
            r = best + rng.normal(0.0, 0.005)
            pts.append((r * math.cos(a), r * math.sin(a)))
    return np.array(pts)


def laser_pose(
    base: tuple[float, float, float], mount: tuple[float, float, float]
) -> tuple[float, float, float]:
    bx, by, byaw = base
    mx, my, myaw = mount
    c, s = math.cos(byaw), math.sin(byaw)
    return bx + c * mx - s * my, by + s * mx + c * my, byaw + myaw


def test_corner_is_found_where_the_walls_meet() -> None:
    pts = corner_scan((0.0, 0.0, math.radians(45.0)), (1.0, 1.0))
    corner = find_corner(extract_lines(pts))
    assert corner is not None
    # In the laser frame the corner is straight ahead at sqrt(2) m.
    assert corner.point == pytest.approx([math.sqrt(2.0), 0.0], abs=0.01)
    angles = sorted(math.degrees(w.angle_rad) % 180 for w in corner.walls)
    assert angles == pytest.approx([45.0, 135.0], abs=0.5)


def test_laser_yaw_and_offset_from_a_drive_and_turns() -> None:
    mount = (0.04, -0.02, math.radians(2.5))
    world_corner = (1.0, 1.0)
    start = (0.0, 0.0, math.radians(45.0))

    def seen(base: tuple[float, float, float], seed: int) -> Corner:
        c = find_corner(extract_lines(corner_scan(laser_pose(base, mount), world_corner, seed)))
        assert c is not None
        return c

    home = seen(start, 1)
    d = 0.3
    ahead = seen((start[0] + d * math.cos(start[2]), start[1] + d * math.sin(start[2]), start[2]), 2)
    assert yaw_from_shift(laser_shift(home, ahead)) == pytest.approx(mount[2], abs=math.radians(0.3))
    corners, turns = [home], [0.0]
    for delta in (0.5, -0.5):
        c = seen((start[0], start[1], start[2] + delta), 3)
        corners.append(c)
        turns.append(wall_turn(home, c, delta))
    assert turns[1] == pytest.approx(0.5, abs=0.005)
    offset, rms = fit_offset(corners, turns, mount[2])
    assert offset == pytest.approx(mount[:2], abs=0.004)
    assert rms < 0.005


def test_wall_turn_uses_the_expected_turn_for_right_angled_walls() -> None:
    home = find_corner(extract_lines(corner_scan((0.0, 0.0, math.radians(45.0)), (1.0, 1.0))))
    turned = find_corner(extract_lines(corner_scan((0.0, 0.0, math.radians(45.0 - 60.0)), (1.0, 1.0))))
    assert home is not None and turned is not None
    assert wall_turn(home, turned, math.radians(-60.0)) == pytest.approx(
        math.radians(-60.0), abs=math.radians(0.5)
    )


def test_offset_fit_is_exact_on_exact_data() -> None:
    p, m, psi = np.array([1.3, 0.05]), np.array([0.012, -0.008]), math.radians(-1.7)
    turns = [0.0, 0.5, -0.5, 0.1]
    corners = [Corner(rot(-psi) @ (rot(-d) @ p - m), ()) for d in turns]  # type: ignore[arg-type]
    offset, rms = fit_offset(corners, turns, psi)
    assert offset == pytest.approx(m, abs=1e-12)
    assert rms < 1e-12


# -- mount ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(("roll", "pitch"), [(0.0, 0.0), (0.01, -0.02), (-0.2, 0.15)])
def test_tilt_from_gravity_inverts_the_renderers_rotation(roll: float, pitch: float) -> None:
    # R = Rz(yaw) Ry(pitch) Rx(roll); at rest the sensor reads R^T (0, 0, g).
    r = level_rotation(roll, pitch)
    accel = r.T @ np.array([0.0, 0.0, 9.80665])
    assert tilt_from_gravity(accel) == pytest.approx((roll, pitch), abs=1e-12)
    assert tilt_from_normal(accel * 3.0) == pytest.approx((roll, pitch), abs=1e-12)


def test_camera_yaw_from_the_board_moving_under_a_drive() -> None:
    yaw = math.radians(-2.5)
    # The base moves +d along its x; in the level camera frame (turned by yaw) the board moves -d R(-yaw) x.
    d = 0.2
    shift = -d * np.array([math.cos(yaw), -math.sin(yaw), 0.0])
    assert yaw_from_board_shift(shift) == pytest.approx(yaw, abs=1e-12)


def test_lens_offset_from_turned_views() -> None:
    q, c = np.array([0.05, -0.03, 0.6]), np.array([0.01, -0.007, 0.0])
    thetas = [0.0, math.pi + 0.01, 0.002]
    positions = []
    for theta in thetas:
        rz = np.array([[math.cos(-theta), -math.sin(-theta)], [math.sin(-theta), math.cos(-theta)]])
        positions.append(np.append(rz @ q[:2] - c[:2], 0.6))
    found, rms = fit_lens_offset(positions, thetas)
    assert found == pytest.approx(c[:2], abs=1e-12)
    assert rms < 1e-12


# -- intrinsics ----------------------------------------------------------------------------------------------
def test_nearest_resize_correction_follows_the_kept_samples() -> None:
    nn = NearestResize(2048, 1536, 800, 600)
    cols = nearest_indices(2048, 800).astype(float)
    a, b = np.polyfit(np.arange(800), cols, 1)
    # At a whole output pixel the position is that pixel's sensor column on the model line.
    pts = np.array([[k, 0.0] for k in (0, 1, 2, 100, 399, 798)], dtype=np.float32)
    out = nn.correct(pts)
    assert out[:, 0] == pytest.approx((cols[[0, 1, 2, 100, 399, 798]] - b) / a, abs=1e-4)
    # Between two pixels it interpolates their sensor columns.
    mid = nn.correct(np.array([[100.5, 0.0]], dtype=np.float32))[0, 0]
    assert mid == pytest.approx(((cols[100] + cols[101]) / 2 - b) / a, abs=1e-4)
    assert NearestResize(800, 600, 800, 600).correct(pts) == pytest.approx(pts, abs=1e-5)


def synthetic_views(k: FloatArray, dist: FloatArray, noise_px: float, n: int, seed: int = 0) -> list[View]:
    rng = np.random.default_rng(seed)
    spec = BoardSpec()
    obj = spec.target().object_points()
    views = []
    while len(views) < n:
        rvec = rng.normal(0.0, 0.4, 3)
        tvec = np.array([rng.uniform(-0.15, 0.05), rng.uniform(-0.12, 0.02), rng.uniform(0.35, 0.6)])
        img, _ = cv2.projectPoints(obj.astype(np.float64), rvec, tvec, k, dist)
        img = img.reshape(-1, 2) + rng.normal(0.0, noise_px, (len(obj), 2))
        if img.min() < 0 or img[:, 0].max() > 799 or img[:, 1].max() > 599:
            continue
        det = Detection(img.astype(np.float32), obj, np.arange(len(obj), dtype=np.int32))
        views.append(View(det, f"v{len(views)}", 30.0, 0.2))
    return views


def test_calibrate_recovers_a_known_camera() -> None:
    k = np.array([[490.0, 0.0, 405.0], [0.0, 489.0, 296.0], [0.0, 0.0, 1.0]])
    dist = np.array([-0.15, 0.04, 0.001, -0.0005, 0.0])
    fit = calibrate(synthetic_views(k, dist, 0.05, 25), 800, 600)
    assert fit.rms_px == pytest.approx(0.05 * math.sqrt(2), rel=0.2)
    assert fit.k == pytest.approx(k, abs=0.5)
    assert fit.d[:4] == pytest.approx(dist[:4], abs=0.01)


def test_calibrate_drops_an_outlier_view() -> None:
    k = np.array([[490.0, 0.0, 400.0], [0.0, 490.0, 300.0], [0.0, 0.0, 1.0]])
    views = synthetic_views(k, np.zeros(5), 0.05, 12)
    bad = views[4].detection
    shuffled = bad.image_points + np.random.default_rng(1).normal(0.0, 3.0, bad.image_points.shape).astype(
        np.float32
    )
    views[4] = View(Detection(shuffled, bad.object_points, bad.corner_ids), "bad", 30.0, 0.2)
    fit = calibrate(views, 800, 600)
    assert [label for label, _ in fit.dropped] == ["bad"]
    assert fit.rms_px < 0.1


def test_coverage_guides_towards_the_emptiest_cell() -> None:
    cov = Coverage(800, 600)
    obj = np.zeros((20, 3), dtype=np.float32)
    # Corners everywhere but the bottom right.
    for u, v in [
        (100, 100),
        (400, 100),
        (700, 100),
        (100, 300),
        (400, 300),
        (700, 300),
        (100, 500),
        (400, 500),
    ]:
        pts = np.tile(np.array([[u, v]], dtype=np.float32), (20, 1))
        cov.add(View(Detection(pts, obj, np.arange(20, dtype=np.int32)), "x", 10.0, 0.3))
    g = cov.guidance()
    assert g.cell == (2, 2)
    assert "bottom right" in g.text
    assert cov.covered == 8
    assert cov.missing() == ["bottom right"]
    assert g.tilt_more  # every view so far was nearly flat


def test_collector_takes_new_views_and_refuses_repeats() -> None:
    from drivers.sim.targets import TargetRenderer
    from drivers.sim.world import CameraModel

    detector = BoardDetector(BoardSpec())
    collector = ViewCollector(detector, 800, 600, 640.0)
    renderer = TargetRenderer(CameraModel(), detector.target, seed=2)
    w, h = detector.target.size_m

    def view(rvec: tuple[float, float, float], centre: tuple[float, float, float]) -> npt.NDArray[np.uint8]:
        rot, _ = cv2.Rodrigues(np.array(rvec))
        return renderer.render(rot, np.array(centre) - rot @ np.array([w / 2, h / 2, 0.0])).image

    first = view((0.3, 0.0, 0.0), (-0.05, 0.0, 0.45))
    taken, why = collector.consider(first, "a")
    assert taken is not None and why == "taken"
    assert collector.consider(first, "again") == (None, "too like view 1")
    moved, why = collector.consider(view((-0.4, 0.3, 0.2), (0.08, 0.05, 0.5)), "b")
    assert moved is not None, why
    assert collector.consider(np.full((600, 800), 40, dtype=np.uint8), "blank") == (None, "no board")
    assert "differs" in collector.consider(np.zeros((480, 640), dtype=np.uint8), "small")[1]
    assert len(collector.views) == 2 and collector.boards_seen == 3
    assert collector.rejected == {
        "too like view 1": 1,
        "no board": 1,
        next(k for k in collector.rejected if "differs" in k): 1,
    }
    # A live source takes a view only once the board has stood still for two frames.
    live = ViewCollector(detector, 800, 600, 640.0)
    assert live.consider(first, "f1", need_still=True) == (None, "moving")
    assert live.consider(first, "f2", need_still=True)[1] == "taken"


# -- servos --------------------------------------------------------------------------------------------------
def test_servo_plan_writes_mode_return_delay_id_and_baud_last() -> None:
    found = [
        Found(1, 57600, 1060, 46, int(OperatingMode.POSITION), 250),  # as from the box
        Found(3, 1_000_000, 1060, 46, 1, 0),
    ]
    plans = plan_changes(found, {1: "left", 3: "right"}, 1, 2, 1_000_000)
    left, right = plans
    assert [(i.name, v) for i, v in left.writes] == [
        ("Operating Mode", 1),
        ("Return Delay Time", 0),
        ("Baud Rate", 3),
    ]
    assert [(i.name, v) for i, v in right.writes] == [("ID", 2)]
    # A return delay that could not be read is written anyway.
    (unknown,) = plan_changes(
        [*found[:1], Found(2, 1_000_000, 1060, 46, 1)], {1: "left", 2: "right"}, 1, 2, 57600
    )[1:]
    assert [(i.name, v) for i, v in unknown.writes] == [("Return Delay Time", 0), ("Baud Rate", 1)]


def test_servo_plan_refuses_clashes_and_unknown_rates() -> None:
    found = [Found(1, 57600, 1060, 46, 1), Found(3, 57600, 1060, 46, 1), Found(2, 115200, 1060, 46, 1)]
    with pytest.raises(CalibrationError, match="already has id 2"):
        plan_changes(found, {1: "left", 3: "right"}, 1, 2, 1_000_000)
    with pytest.raises(CalibrationError, match="cannot run at"):
        plan_changes(found[:2], {1: "left", 3: "right"}, 1, 2, 250000)
    twins = [Found(1, 57600, 1060, 46, 1), Found(1, 1_000_000, 1060, 46, 1)]
    with pytest.raises(CalibrationError, match="share it"):
        plan_changes(twins, {1: "left", 5: "right"}, 1, 2, 1_000_000)


def test_check_verdicts() -> None:
    assert Check("rms", 0.2, 0.3, "px").ok
    assert not Check("rms", 0.4, 0.3, "px").ok
    assert Check("views", 12, 10, at_least=True).ok
    assert not Check("rms", math.nan, 0.3).ok
    assert "needs <= 0.3 px" in Check("rms", 0.4, 0.3, "px").describe()
