"""Calibration: the rotation centre from a turn in place, the residual correction, the calibration file."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import numpy.typing as npt
import pytest

from agent.vlp.calibration import (
    ResidualCorrection,
    VlpCalibration,
    fit_residual_correction,
    fit_rotation_centre,
    format_calibration,
    parse_calibration,
    validated_residual_correction,
)
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
    assert (centre.cx_px, centre.cy_px) == pytest.approx((401.3, 298.4), abs=0.02)
    assert len(centre.circles) == 3


def test_rotation_centre_needs_an_arc() -> None:
    tracks = [t[:8] for t in turning_tracks((400.0, 300.0), CameraMount(), [1.3])]
    with pytest.raises(ValueError, match="circle"):
        fit_rotation_centre(tracks, [1.3], INTRINSICS, min_points=4)


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


def test_calibration_file_round_trip() -> None:
    residual = ResidualCorrection(
        (0.1, -0.2), 0.5, 1, (0.001, 0.002, -0.0005), (0.0, 0.0003, 0.0001), 108, 0.004, 0.001
    )
    cal = VlpCalibration((800, 600), (401.25, 298.5), 0.03, residual)
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
