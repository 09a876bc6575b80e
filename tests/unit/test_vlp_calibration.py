"""Calibration: the rotation centre from a turn in place, the residual correction, the calibration file."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import numpy.typing as npt
import pytest

from agent.vlp.calibration import (
    ResidualCorrection,
    RotationCentre,
    VlpCalibration,
    fit_residual_correction,
    fit_rotation_centre,
    format_calibration,
    mount_tilt_from_shift,
    parse_calibration,
    validated_residual_correction,
)
from agent.vlp.geometry import level_rotation
from agent.vlp.model import CameraIntrinsics, CameraMount
from drivers.errors import ConfigError

INTRINSICS = CameraIntrinsics(800, 600, 488.0, 488.0, 397.0, 302.0, 32e-6)


def turning_tracks(centre: tuple[float, float], mount: CameraMount, heights: list[float]) -> list[np.ndarray]:  # type: ignore[type-arg]
    """Image tracks of LEDs while a base turns in place: a level camera whose principal point is ``centre``,
    its lens at ``mount`` on the base; each LED at (1 - 0.3 k, 0.4 k) m from the axis, ``heights`` above."""
    rng = np.random.default_rng(0)
    tracks = []
    for k, h in enumerate(heights):
        led = np.array([0.4 - 0.3 * k, 0.2 + 0.25 * k])
        pts = []
        for yaw in np.linspace(0.0, 2.0 * math.pi, 120, endpoint=False):
            c, s = math.cos(yaw + mount.yaw_rad), math.sin(yaw + mount.yaw_rad)
            cb, sb = math.cos(yaw), math.sin(yaw)
            lens = np.array([cb * mount.x_m - sb * mount.y_m, sb * mount.x_m + cb * mount.y_m])
            d = led - lens
            q = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]]) / h
            pts.append((centre[0] + 488.0 * q[0], centre[1] + 488.0 * q[1]))
        tracks.append(np.array(pts) + rng.normal(0.0, 0.05, (120, 2)))
    return tracks


@pytest.mark.parametrize("mount", [CameraMount(), CameraMount(0.04, -0.02, 0.2, yaw_rad=0.3)])
def test_rotation_centre_is_the_principal_point(mount: CameraMount) -> None:
    heights = [1.3, 1.3, 1.35]
    centre = fit_rotation_centre(turning_tracks((401.3, 298.4), mount, heights), heights, INTRINSICS, mount)
    assert isinstance(centre, RotationCentre)
    assert (centre.cx_px, centre.cy_px) == pytest.approx((401.3, 298.4), abs=0.02)
    assert len(centre.circles) == 3


def tilted_tracks(
    centre: tuple[float, float], roll_rad: float, pitch_rad: float, reach_m: list[float], h_m: float = 1.3
) -> list[np.ndarray]:  # type: ignore[type-arg]
    """Image tracks over a turn in place of a camera tilted by (roll, pitch) on its mount (R_level =
    Ry(pitch) Rx(roll), agent.vlp.geometry), its principal point ``centre``; LEDs ``reach_m`` from the
    axis."""
    rng = np.random.default_rng(4)
    r_level = level_rotation(CameraMount(roll_rad=roll_rad, pitch_rad=pitch_rad))
    tracks = []
    for k, reach in enumerate(reach_m):
        pts = []
        for yaw in np.linspace(0.0, 2.0 * math.pi, 120, endpoint=False):
            phase = yaw + 1.1 * k
            m = r_level.T @ np.array([reach * math.cos(phase) / h_m, reach * math.sin(phase) / h_m, 1.0])
            pts.append((centre[0] + 488.0 * m[0] / m[2], centre[1] + 488.0 * m[1] / m[2]))
        tracks.append(np.array(pts) + rng.normal(0.0, 0.05, (120, 2)))
    return tracks


def test_a_tilt_is_told_from_the_principal_point_by_circles_of_different_radii() -> None:
    """A camera tilted 1.5 degrees: LEDs at different distances from the turning axis give circles whose
    centres move with their radius (p + f tan(tilt) sec^2 alpha); the fit separates the principal point
    from the tilt, and the tilt comes back as the mount's roll and pitch. Circles of one radius cannot tell
    them apart: the rotation centre is then the tilt-shifted point, as before."""
    roll, pitch = math.radians(1.5), math.radians(-0.6)
    tracks = tilted_tracks((401.3, 298.4), roll, pitch, [0.3, 0.55, 0.8])
    centre = fit_rotation_centre(tracks, [1.3] * 3, INTRINSICS)
    assert isinstance(centre, RotationCentre) and centre.tilt_px is not None
    assert (centre.cx_px, centre.cy_px) == pytest.approx((401.3, 298.4), abs=0.3)
    got = mount_tilt_from_shift(centre.tilt_px, INTRINSICS)
    assert got == pytest.approx((roll, pitch), abs=math.radians(0.03))
    same = fit_rotation_centre(tilted_tracks((401.3, 298.4), roll, pitch, [0.55] * 3), [1.3] * 3, INTRINSICS)
    assert isinstance(same, RotationCentre) and same.tilt_px is None
    assert abs(same.cy_px - 298.4) > 10.0  # the tilt absorbed: f tan(1.5 deg) sec^2 alpha


def test_mount_tilt_from_shift_puts_the_vertical_there() -> None:
    for roll, pitch in ((0.02, -0.01), (-0.03, 0.025), (0.0, 0.0)):
        r_level = level_rotation(CameraMount(roll_rad=roll, pitch_rad=pitch))
        up = r_level.T @ np.array([0.0, 0.0, 1.0])
        shift = (488.0 * up[0] / up[2], 488.0 * up[1] / up[2])
        assert mount_tilt_from_shift(shift, INTRINSICS) == pytest.approx((roll, pitch), abs=1e-12)


def test_rotation_centre_needs_an_arc_and_says_so() -> None:
    """Too little of a circle, too few points or no track at all (a sparse ceiling): a reason, not an
    exception (``eval vlp`` used to end in a traceback on a sparse layout)."""
    tracks = [t[:8] for t in turning_tracks((400.0, 300.0), CameraMount(), [1.3])]
    refused = fit_rotation_centre(tracks, [1.3], INTRINSICS, min_points=4)
    assert isinstance(refused, str) and "1 sweeping at most 21 degrees" in refused, refused
    refused = fit_rotation_centre(tracks, [1.3], INTRINSICS)
    assert isinstance(refused, str) and "1 with fewer than 12 points" in refused, refused
    refused = fit_rotation_centre([], [], INTRINSICS)
    assert isinstance(refused, str) and "no LED of the map was tracked" in refused


def test_one_circle_gives_its_own_standard_error() -> None:
    """With one usable track the spread is that track's scatter over its own points, even when an unusable
    track comes first."""
    good = turning_tracks((400.0, 300.0), CameraMount(), [1.3])[0]
    centre = fit_rotation_centre([good[:3], good], [1.3, 1.3], INTRINSICS)
    assert isinstance(centre, RotationCentre)
    assert centre.sigma_px == pytest.approx(centre.circles[0][3] / math.sqrt(len(good)))


def test_residual_correction_recovers_an_affine_error_field() -> None:
    rng = np.random.default_rng(1)
    truth = rng.uniform(-0.5, 0.5, (60, 2))
    # Fixes off by 3 mm east, 1 mm north, plus 0.4 % scale and a 2 mrad rotation about the area's middle.
    fixes = truth + np.array([0.003, 0.001]) + truth @ np.array([[0.004, 0.002], [-0.002, 0.004]])
    fixes += rng.normal(0.0, 2e-4, fixes.shape)
    correction = fit_residual_correction(fixes, truth, degree=1)
    corrected = np.array([correction.apply(x, y) for x, y in fixes])
    assert np.sqrt(np.mean(np.sum((corrected - truth) ** 2, axis=1))) < 5e-4
    assert correction.rms_after_m < 0.2 * correction.rms_before_m


def grid_fixes(
    rng: np.random.Generator,
    points: npt.NDArray[np.float64],
    per_point: int,
    error: Callable[[float, float], tuple[float, float]],
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """``per_point`` fixes at each known point, off by ``error`` there plus 0.5 mm of noise."""
    truth = np.repeat(points, per_point, axis=0)
    fixes = truth + np.array([error(x, y) for x, y in truth]) + rng.normal(0.0, 5e-4, truth.shape)
    return fixes, truth


def test_a_validated_residual_correction_is_kept_when_it_helps_held_out_fixes() -> None:
    rng = np.random.default_rng(2)
    points = np.array([[x, y] for x in (-0.3, 0.0, 0.3) for y in (-0.3, 0.0, 0.3)])
    fixes, truth = grid_fixes(rng, points, 12, lambda x, y: (0.003 + 0.004 * x, 0.001 - 0.002 * y))
    correction = validated_residual_correction(fixes, truth)
    assert isinstance(correction, ResidualCorrection)
    assert correction.rms_after_m < 0.3 * correction.rms_before_m


def test_a_residual_correction_that_would_hurt_is_refused_with_a_reason() -> None:
    """Points clustered at one place (the issue's case: a slope from noise, 20x worse elsewhere), points
    along a line, and errors that are noise only (nothing to correct: held-out points do not improve)."""
    rng = np.random.default_rng(3)
    clustered = np.array([[0.0, 0.0], [0.02, 0.0], [0.0, 0.02], [0.02, 0.02]])
    fixes, truth = grid_fixes(rng, clustered, 12, lambda x, y: (0.002, 0.0))
    refused = validated_residual_correction(fixes, truth)
    assert isinstance(refused, str) and "spread" in refused
    line = np.array([[x, 0.0] for x in (-0.3, -0.1, 0.1, 0.3)])
    fixes, truth = grid_fixes(rng, line, 12, lambda x, y: (0.002, 0.0))
    refused = validated_residual_correction(fixes, truth)
    assert isinstance(refused, str) and "spread" in refused
    points = np.array([[x, y] for x in (-0.3, 0.0, 0.3) for y in (-0.3, 0.0, 0.3)])
    fixes, truth = grid_fixes(rng, points, 3, lambda x, y: (0.0, 0.0))
    refused = validated_residual_correction(fixes, truth)
    assert isinstance(refused, str) and "held-out" in refused, refused


def test_the_issues_clustered_points_are_refused() -> None:
    """Issue 19's case: known points within 1 cm of each other (three fixes at each of four marks, 1 mm
    noise, no error to correct). The plain fit reports a healthy fit (its rms falls) but its slope comes
    from noise: over a 1 x 1 m area it makes fixes more than 20x worse than uncorrected. The validated
    path refuses it and says why."""
    rng = np.random.default_rng(0)
    marks = np.array([[0.0, 0.0], [0.01, 0.0], [0.0, 0.01], [0.01, 0.01]])
    truth = np.repeat(marks, 3, axis=0)
    fixes = truth + rng.normal(0.0, 1e-3, truth.shape)
    plain = fit_residual_correction(fixes, truth)
    assert plain.rms_after_m < plain.rms_before_m
    area = np.array([[x, y] for x in np.linspace(-0.5, 0.5, 11) for y in np.linspace(-0.5, 0.5, 11)])
    area_fixes = area + rng.normal(0.0, 1e-3, area.shape)
    corrected = np.array([plain.apply(x, y) for x, y in area_fixes])
    rms_uncorrected = np.sqrt(np.mean(np.sum((area_fixes - area) ** 2, axis=1)))
    rms_corrected = np.sqrt(np.mean(np.sum((corrected - area) ** 2, axis=1)))
    assert rms_corrected > 20.0 * rms_uncorrected
    refused = validated_residual_correction(fixes, truth)
    assert isinstance(refused, str) and "not spread out" in refused, refused


def test_calibration_file_round_trip() -> None:
    residual = ResidualCorrection(
        (0.1, -0.2), 0.5, 1, (0.001, 0.002, -0.0005), (0.0, 0.0003, 0.0001), 108, 0.004, 0.001
    )
    cal = VlpCalibration((800, 600), (401.25, 298.5), 0.03, residual, (0.026, -0.004))
    text = format_calibration(cal, "a test\nof two lines")
    assert text.startswith("# vlp-agent VLP calibration")
    assert parse_calibration(text) == cal
    assert parse_calibration(format_calibration(VlpCalibration((800, 600)))) == VlpCalibration((800, 600))


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("[camera]\nimage_size_px = [800]\n", "camera.image_size_px"),
        (
            "[camera]\nimage_size_px = [800, 600]\nprincipal_point_px = [1.0, 'x']\n",
            "camera.principal_point_px[1]",
        ),
        ("[camera]\nimage_size_px = [800, 600]\nfocal = 3\n", "camera.focal"),
        ("[camera]\nimage_size_px = [800, 600]\nmount_tilt_rad = [0.5, 0.0]\n", "camera.mount_tilt_rad"),
        ("[camera]\nimage_size_px = [800, 600]\nmount_tilt_rad = [0.01]\n", "camera.mount_tilt_rad"),
        (
            "[camera]\nimage_size_px = [800, 600]\n[residual]\ndegree = 1\norigin_m = [0, 0]\nscale_m = 1.0\n"
            "x_coefficients = [1, 2]\ny_coefficients = [1, 2, 3]\n",
            "residual.x_coefficients",
        ),
        ("[cam]\n", "cam"),
        ("[camera\n", ""),
        # Issue 17: counts and sizes have bounds.
        ("[camera]\nimage_size_px = [8193, 600]\n", "camera.image_size_px"),
        ("[camera]\nimage_size_px = [800, 9223372036854775807]\n", "camera.image_size_px"),
        (
            "[camera]\nimage_size_px = [800, 600]\n[residual]\ndegree = 0\norigin_m = [0, 0]\nscale_m = 1.0\n"
            "x_coefficients = [1]\ny_coefficients = [1]\npoints = 1000001\n",
            "residual.points",
        ),
    ],
)
def test_calibration_file_mistakes_name_the_key(text: str, key: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_calibration(text, source="cal.toml")
    assert info.value.key == key


def test_calibration_for_another_image_size_is_refused() -> None:
    with pytest.raises(ValueError, match="1280x960"):
        VlpCalibration((1280, 960), (640.0, 480.0)).intrinsics(INTRINSICS)
    assert VlpCalibration((800, 600), (401.0, 299.0)).intrinsics(INTRINSICS).cx_px == 401.0


def test_the_image_side_limit_is_the_configs() -> None:
    from agent.config import MAX_IMAGE_SIDE_PX
    from agent.vlp import calibration

    assert calibration.MAX_IMAGE_SIDE_PX == MAX_IMAGE_SIDE_PX
    assert parse_calibration(f"[camera]\nimage_size_px = [{MAX_IMAGE_SIDE_PX}, 1]\n").image_size_px == (
        8192,
        1,
    )
