"""Calibration boards through the simulated camera (drivers/sim/targets.py): the same projection as the LED
renderer (checked point for point, with tilt, distortion and an off-centre principal point), corners where a
detector finds them, exact grey levels on edges, the sensor's noise, and the blank back of the sheet."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from drivers.sim.render import RollingShutterRenderer
from drivers.sim.targets import HAS_ARUCO, CharucoTarget, Chessboard, TargetLighting, TargetRenderer
from drivers.sim.world import CameraModel, Led, Mount, Pose2D

FloatArray = npt.NDArray[np.float64]

# No noise: geometry only.
QUIET = CameraModel(read_noise_dn=0.0, full_well_e=1e12)
# No resize: the output is the sensor, so corner detection is not limited by the nearest-neighbour sampling.
UNRESIZED = dataclasses.replace(
    QUIET,
    sensor_width_px=800,
    sensor_height_px=600,
    pixel_size_m=3.2e-6 * 2.56,
    output_width_px=800,
    output_height_px=600,
)


def pose_facing(
    board: Chessboard | CharucoTarget, rvec: tuple[float, float, float], centre: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """A pose putting the sheet's centre at ``centre`` (camera frame), turned by ``rvec``."""
    rot, _ = cv2.Rodrigues(np.array(rvec, dtype=np.float64))
    w, h = board.size_m
    return rot, np.asarray(centre, dtype=np.float64) - rot @ np.array([w / 2, h / 2, 0.0])


def rz(a: float) -> FloatArray:
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])


def ry(a: float) -> FloatArray:
    return np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])


def rx(a: float) -> FloatArray:
    return np.array([[1.0, 0.0, 0.0], [0.0, math.cos(a), -math.sin(a)], [0.0, math.sin(a), math.cos(a)]])


def matched(found: FloatArray, truth: FloatArray) -> FloatArray:
    """Per-corner error, with the detector's order reversed if it numbered the symmetric grid backwards."""
    forward = np.linalg.norm(found - truth, axis=1)
    backward = np.linalg.norm(found[::-1] - truth, axis=1)
    return forward if forward.mean() <= backward.mean() else backward


def test_projection_matches_the_led_renderer_with_tilt_distortion_and_principal_point() -> None:
    """A board corner placed where an LED's centre is lands on the LED renderer's pixel for it."""
    camera = dataclasses.replace(
        QUIET, cx_px=1031.0, cy_px=760.0, distortion=(-0.12, 0.03, 0.001, -0.0008, 0.0)
    )
    mount = Mount(0.03, -0.02, 0.2, math.radians(7.0), math.radians(1.5), math.radians(-2.0))
    base = Pose2D(0.4, -0.3, math.radians(35.0))
    led = Led("A", 0.9, 0.2, 1.5)
    leds = RollingShutterRenderer(camera, [led], mount)
    truth = leds.render(lambda t: base, 0.0).truth.leds[0]

    board = Chessboard()
    targets = TargetRenderer(camera, board)
    # The camera's pose in the world, by the renderer's convention: R = Rz(yaw) Ry(pitch) Rx(roll).
    yaw = base.yaw_rad + mount.yaw_rad
    r_wc = rz(yaw) @ ry(mount.pitch_rad) @ rx(mount.roll_rad)
    c, s = math.cos(base.yaw_rad), math.sin(base.yaw_rad)
    lens = np.array(
        [base.x_m + c * mount.x_m - s * mount.y_m, base.y_m + s * mount.x_m + c * mount.y_m, mount.z_m]
    )
    # A level board whose first corner is at the LED's centre.
    first = board.object_points()[0].astype(np.float64)
    r_wb = rz(0.3)
    origin = np.array([led.x_m, led.y_m, led.z_m]) - r_wb @ first
    rotation, translation = r_wc.T @ r_wb, r_wc.T @ (origin - lens)
    corner = targets.project(first[None, :], rotation, translation)[0]
    assert corner == pytest.approx(truth.centre_px, abs=1e-6)


def test_truth_intrinsics_are_the_led_renderers() -> None:
    camera = dataclasses.replace(QUIET, cx_px=1030.0)
    assert (
        TargetRenderer(camera, Chessboard()).output_intrinsics
        == RollingShutterRenderer(camera, ()).output_intrinsics
    )


@pytest.mark.parametrize("rvec", [(0.0, 0.0, 0.0), (0.5, -0.3, 0.2), (-0.4, 0.6, -1.0)])
def test_chessboard_corners_are_where_a_detector_finds_them(rvec: tuple[float, float, float]) -> None:
    board = Chessboard()
    renderer = TargetRenderer(UNRESIZED, board)
    rotation, translation = pose_facing(board, rvec, np.array([0.02, -0.01, 0.45]))
    view = renderer.render(rotation, translation)
    assert view.front_facing and view.corners_visible.all()
    found, corners = cv2.findChessboardCorners(view.image, board.pattern_size)
    assert found
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
    refined = cv2.cornerSubPix(view.image, corners, (7, 7), (-1, -1), criteria).reshape(-1, 2)
    error = matched(refined.astype(np.float64), view.corners_px)
    assert error.mean() < 0.15, error.mean()
    assert error.max() < 0.4


@pytest.mark.parametrize("blur", [0.0, 0.7])
def test_edge_grey_level_is_the_blurred_step(blur: float) -> None:
    """A straight edge's profile is the PSF's: black + (white - black) Phi(d / sigma), d the distance from the
    pixel centre to the edge, sigma^2 = blur^2 + 1/12 (the pixel's box), as the LED renderer has it."""
    camera = dataclasses.replace(UNRESIZED, blur_sigma_px=blur, black_level_dn=0.0)
    board = Chessboard()
    renderer = TargetRenderer(camera, board, TargetLighting(white_dn=200.0))
    sigma = math.sqrt(blur**2 + 1.0 / 12.0)
    f = camera.focal_length_px
    cx, cy = camera.principal_point_px
    z = 0.5
    corner = board.object_points()[0].astype(np.float64)
    for shift in (0.0, 0.37, 0.81):
        # Fronto-parallel, the first corner's column at 350 + shift: a vertical edge there, white to its left
        # on the rows below the corner.
        u_edge = 350.0 + shift
        tx = (u_edge - cx) / f * z - corner[0]
        ty = (300.3 - cy) / f * z - corner[1]
        view = renderer.render(np.eye(3), np.array([tx, ty, z]))
        row = 308
        u = np.arange(340, 361, dtype=np.float64)
        # cos^4 vignetting divided out (black level 0, no noise): what is left is reflectance x gain.
        vignette = 1.0 / (1.0 + ((u - cx) / f) ** 2 + ((row - cy) / f) ** 2) ** 2
        profile = view.image[row, 340:361].astype(np.float64) / vignette
        white, black = profile[:4].mean(), profile[-4:].mean()
        expected = black + (white - black) * 0.5 * np.vectorize(math.erfc)(
            (u - u_edge) / (math.sqrt(2.0) * sigma)
        )
        assert profile == pytest.approx(expected, abs=1.0)


def test_noise_is_shot_plus_read_noise() -> None:
    camera = dataclasses.replace(
        CameraModel(), sensor_width_px=800, sensor_height_px=600, output_width_px=800, output_height_px=600
    )
    board = Chessboard(square_m=0.2)
    renderer = TargetRenderer(camera, board, TargetLighting(white_dn=150.0), seed=3)
    # A huge square fills the middle of the picture (the sheet's centre is a corner: move half a square).
    rotation, translation = pose_facing(board, (0.0, 0.0, 0.0), np.array([0.1, 0.0, 0.4]))
    view = renderer.render(rotation, translation)
    region = view.image[280:320, 380:420].astype(np.float64)
    mean = region.mean()
    dn_per_e = (255.0 - camera.black_level_dn) / camera.full_well_e
    signal_e = (mean - camera.black_level_dn) / dn_per_e
    expected = math.sqrt(signal_e * dn_per_e**2 + camera.read_noise_dn**2 + 1.0 / 12.0)
    assert region.std() == pytest.approx(expected, rel=0.25)


def test_back_of_the_sheet_is_blank() -> None:
    board = Chessboard()
    renderer = TargetRenderer(UNRESIZED, board)
    rotation, translation = pose_facing(board, (0.0, math.pi, 0.0), np.array([0.0, 0.0, 0.45]))
    view = renderer.render(rotation, translation)
    assert not view.front_facing
    assert not view.corners_visible.any()
    found, _ = cv2.findChessboardCorners(view.image, board.pattern_size)
    assert not found
    # The sheet is still there, brighter than the room behind it.
    assert view.image[300, 400] > view.image[5, 5]


def test_corners_outside_the_picture_are_not_visible() -> None:
    board = Chessboard()
    renderer = TargetRenderer(QUIET, board)
    rotation, translation = pose_facing(board, (0.0, 0.0, 0.0), np.array([0.25, 0.0, 0.4]))
    view = renderer.render(rotation, translation)
    inside = (view.corners_px[:, 0] >= 0) & (view.corners_px[:, 0] <= 799)
    assert view.corners_visible.tolist() == inside.tolist()
    assert 0 < view.corners_visible.sum() < len(view.corners_visible)


def test_a_board_behind_the_camera_leaves_only_the_room() -> None:
    board = Chessboard()
    renderer = TargetRenderer(QUIET, board)
    rotation, translation = pose_facing(board, (0.0, 0.0, 0.0), np.array([0.0, 0.0, -0.5]))
    view = renderer.render(rotation, translation)
    assert view.image.shape == (600, 800) and view.image.dtype == np.uint8
    assert int(view.image.max()) - int(view.image.min()) < 60  # vignetting only
    assert not view.corners_visible.any()


@pytest.mark.skipif(not HAS_ARUCO, reason="this OpenCV has no cv2.aruco")
def test_charuco_board_is_found_with_the_right_ids() -> None:
    target = CharucoTarget()
    renderer = TargetRenderer(UNRESIZED, target)
    rotation, translation = pose_facing(target, (0.3, -0.2, 0.4), np.array([0.0, 0.0, 0.5]))
    view = renderer.render(rotation, translation)
    detector = cv2.aruco.CharucoDetector(target.board)
    corners, ids, _, _ = detector.detectBoard(view.image)
    assert ids is not None and len(ids) >= 0.8 * len(target.object_points())
    idx = ids.ravel()
    error = np.linalg.norm(corners.reshape(-1, 2) - view.corners_px[idx], axis=1)
    assert error.mean() < 0.2, error.mean()


@pytest.mark.skipif(not HAS_ARUCO, reason="this OpenCV has no cv2.aruco")
def test_charuco_marker_that_misses_the_raster_is_refused() -> None:
    with pytest.raises(ValueError, match="raster"):
        CharucoTarget(square_m=0.04, marker_m=0.031)


def test_views_repeat_with_the_seed() -> None:
    board = Chessboard()
    rotation, translation = pose_facing(board, (0.2, 0.1, 0.0), np.array([0.0, 0.0, 0.5]))
    a = TargetRenderer(CameraModel(), board, seed=5).render(rotation, translation).image
    b = TargetRenderer(CameraModel(), board, seed=5).render(rotation, translation).image
    c = TargetRenderer(CameraModel(), board, seed=6).render(rotation, translation).image
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
