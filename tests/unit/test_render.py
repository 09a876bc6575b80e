"""The rolling-shutter renderer against the physics it claims: OpenCV's nearest-neighbour selection, the
camera convention of reference/vlp.md §1.5 (checked with the reference 2-LED solver), stripe period and duty
cycle, stripe phase, saturation and blooming, motion during readout, distortion, noise."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from drivers.sim.render import (
    LedCover,
    RenderedFrame,
    RollingShutterRenderer,
    nearest_indices,
    pwm_exposure_fraction,
)
from drivers.sim.world import CameraModel, Led, Mount, Pose2D

MOUNT = Mount(0.0, 0.0, 0.2)
# A camera without noise, for geometry: no read noise, and a full well so deep that shot noise is < 1e-3 DN.
QUIET = CameraModel(read_noise_dn=0.0, full_well_e=1e12, black_level_dn=10.0)
# Exposure much longer than the PWM period makes every row see the same mean: a flat, stripe-free disk whose
# centroid is its centre (for measuring positions on the image).
FLAT = dataclasses.replace(QUIET, exposure_s=2e-3, led_peak_dn=200.0)


def still(x: float, y: float, yaw: float) -> Callable[[float], Pose2D]:
    """A robot standing at (x, y, yaw) whatever the time."""
    return lambda t: Pose2D(x, y, yaw)


def blob_centroid(
    image: npt.NDArray[np.uint8], near: tuple[float, float], black: float, half: int = 40
) -> tuple[float, float]:
    """Intensity-weighted centroid (above black level) of the blob around ``near``, output px."""
    u0, v0 = round(near[0]), round(near[1])
    r0, c0 = max(v0 - half, 0), max(u0 - half, 0)
    patch = image[r0 : v0 + half, c0 : u0 + half].astype(np.float64) - black
    patch[patch < 5.0] = 0.0
    rows, cols = np.indices(patch.shape)
    total = patch.sum()
    assert total > 0, "no LED blob found"
    return float((cols * patch).sum() / total + c0), float((rows * patch).sum() / total + r0)


# -- nearest-neighbour selection -----------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("src", "dst"),
    [
        ((2048, 1536), (800, 600)),
        ((2048, 1536), (1280, 960)),
        ((1000, 700), (333, 211)),
        ((640, 480), (800, 600)),
        ((2048, 1536), (2048, 1536)),
    ],
)
def test_nearest_indices_match_cv2_resize(src: tuple[int, int], dst: tuple[int, int]) -> None:
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (src[1], src[0]), dtype=np.uint8)
    resized = cv2.resize(image, dst, interpolation=cv2.INTER_NEAREST)
    rows, cols = nearest_indices(src[1], dst[1]), nearest_indices(src[0], dst[0])
    np.testing.assert_array_equal(resized, image[np.ix_(rows, cols)])


def test_renderer_keeps_exactly_the_rows_and_columns_cv2_keeps() -> None:
    renderer = RollingShutterRenderer(QUIET, [], MOUNT)
    sensor = np.arange(QUIET.sensor_height_px * QUIET.sensor_width_px, dtype=np.float32).reshape(
        QUIET.sensor_height_px, QUIET.sensor_width_px
    )
    resized = cv2.resize(
        sensor, (QUIET.output_width_px, QUIET.output_height_px), interpolation=cv2.INTER_NEAREST
    )
    np.testing.assert_array_equal(resized, sensor[np.ix_(renderer.selected_rows, renderer.selected_cols)])


# -- the PWM box filter --------------------------------------------------------------------------------------
def test_pwm_exposure_fraction_matches_numeric_integration() -> None:
    rng = np.random.default_rng(5)
    starts = rng.uniform(0.0, 0.01, 50)
    for freq, duty, exposure, phase in [
        (2000.0, 0.3, 20e-6, 0.1),
        (4500.0, 0.6, 300e-6, 0.77),
        (1000.0, 0.5, 1.3e-3, 0.0),
    ]:
        fast = pwm_exposure_fraction(starts, exposure, freq, duty, phase)
        fine = np.linspace(0.0, exposure, 20001)
        wave = (np.mod(freq * (starts[:, None] + fine[None, :]) + phase, 1.0) < duty).astype(np.float64)
        numeric = wave.mean(axis=1)
        np.testing.assert_allclose(fast, numeric, atol=2e-3)


def test_pwm_exposure_over_whole_periods_is_the_duty_cycle() -> None:
    starts = np.linspace(0.0, 1e-3, 37)
    np.testing.assert_allclose(pwm_exposure_fraction(starts, 3 / 2500.0, 2500.0, 0.35, 0.4), 0.35, atol=1e-9)


# -- geometry: reference/vlp.md §1.5 -------------------------------------------------------------------------
def test_led_straight_above_lands_at_the_principal_point() -> None:
    camera = dataclasses.replace(FLAT, cx_px=1000.3, cy_px=790.8)  # off the sensor centre on purpose
    led = Led("A", 1.2, -0.7, 1.5, frequency_hz=5000.0, duty=0.5)
    renderer = RollingShutterRenderer(camera, [led], MOUNT)
    frame = renderer.render(still(1.2, -0.7, 0.4), 10.0)
    intr = renderer.output_intrinsics
    (truth,) = frame.truth.leds
    assert truth.centre_px == pytest.approx((intr.cx_px, intr.cy_px), abs=1e-9)
    measured = blob_centroid(frame.image, truth.centre_px, camera.black_level_dn)
    assert measured == pytest.approx(truth.centre_px, abs=0.3)


def two_led_solver(
    p1: tuple[float, float],
    p2: tuple[float, float],
    uv1: tuple[float, float],
    uv2: tuple[float, float],
    fx: float,
    fy: float,
    cx: float,
    cy: float,
) -> tuple[float, float, float]:
    """reference/vlp.md §1.5, the steps of positioningCalculation.cpp::VLPbyLED, in normalised image units
    (u - cx) / fx so unequal fx, fy are handled. Returns the lens position and the camera yaw."""
    (x1, y1), (x2, y2) = p1, p2
    (u1, v1), (u2, v2) = ((uv1[0] - cx) / fx, (uv1[1] - cy) / fy), ((uv2[0] - cx) / fx, (uv2[1] - cy) / fy)
    if (x1, y1) > (x2, y2):  # step 1: order so that X1 < X2 (or Y1 < Y2)
        (x1, y1, u1, v1), (x2, y2, u2, v2) = (x2, y2, u2, v2), (x1, y1, u1, v1)
    alpha = math.pi / 2 if x1 == x2 else math.atan((y2 - y1) / (x2 - x1))
    beta = math.pi / 2 if u1 == u2 else math.atan((v2 - v1) / (u2 - u1))
    theta = alpha - beta if u2 <= u1 else math.pi + alpha - beta  # step 3
    height = math.hypot(x1 - x2, y1 - y2) / math.hypot(u1 - u2, v1 - v2)  # step 4: H = f D12 / d12
    xr, yr = (u1 + u2) / 2 * height, (v1 + v2) / 2 * height  # step 5
    c, s = math.cos(theta), math.sin(theta)  # step 6
    x = c * xr - s * yr + (x1 + x2) / 2
    y = s * xr + c * yr + (y1 + y2) / 2
    return x, y, theta - math.pi


@pytest.mark.parametrize("pose", [(0.0, 0.0, 0.0), (0.13, -0.21, 0.7), (-0.3, 0.25, -2.4), (0.05, 0.4, 3.1)])
def test_reference_two_led_solver_recovers_the_pose_from_the_true_centres(
    pose: tuple[float, float, float],
) -> None:
    leds = [Led("A", -0.30, 0.25, 1.5, frequency_hz=2000.0), Led("B", 0.35, -0.20, 1.5, frequency_hz=3000.0)]
    mount = Mount(0.05, -0.02, 0.2, yaw_rad=0.3)
    renderer = RollingShutterRenderer(QUIET, leds, mount)
    frame = renderer.render(still(*pose), 100.0)
    by_id = {t.id: t for t in frame.truth.leds}
    assert set(by_id) == {"A", "B"}
    intr = renderer.output_intrinsics
    x, y, yaw = two_led_solver(
        (leds[0].x_m, leds[0].y_m),
        (leds[1].x_m, leds[1].y_m),
        by_id["A"].centre_px,
        by_id["B"].centre_px,
        intr.fx_px,
        intr.fy_px,
        intr.cx_px,
        intr.cy_px,
    )
    cam = frame.truth.camera_pose
    assert math.hypot(x - cam.x_m, y - cam.y_m) < 1e-3
    assert abs(math.remainder(yaw - cam.yaw_rad, 2 * math.pi)) < 1e-6
    # The lens is where the mount puts it, and the camera's yaw is the robot's plus the mount's.
    c, s = math.cos(pose[2]), math.sin(pose[2])
    assert cam.x_m == pytest.approx(pose[0] + c * 0.05 + s * 0.02)
    assert cam.y_m == pytest.approx(pose[1] + s * 0.05 - c * 0.02)


def test_the_rendered_image_itself_gives_the_pose_to_a_millimetre() -> None:
    leds = [Led("A", -0.30, 0.25, 1.5, frequency_hz=4000.0), Led("B", 0.35, -0.20, 1.5, frequency_hz=5000.0)]
    renderer = RollingShutterRenderer(FLAT, leds, MOUNT, seed=2)
    frame = renderer.render(still(0.04, -0.07, 1.1), 20.0)
    by_id = {t.id: t for t in frame.truth.leds}
    measured = {k: blob_centroid(frame.image, t.centre_px, FLAT.black_level_dn) for k, t in by_id.items()}
    intr = renderer.output_intrinsics
    x, y, yaw = two_led_solver(
        (leds[0].x_m, leds[0].y_m),
        (leds[1].x_m, leds[1].y_m),
        measured["A"],
        measured["B"],
        intr.fx_px,
        intr.fy_px,
        intr.cx_px,
        intr.cy_px,
    )
    cam = frame.truth.camera_pose
    # 1 px at 800x600 is ~2.7 mm on the LED plane 1.3 m above the lens; centroids of flat disks are within
    # ~0.2 px of the true centres, so the fix is within a millimetre.
    assert math.hypot(x - cam.x_m, y - cam.y_m) < 1e-3
    assert abs(math.remainder(yaw - cam.yaw_rad, 2 * math.pi)) < math.radians(0.5)


def test_moving_the_robot_plus_x_moves_the_led_as_the_model_predicts() -> None:
    led = Led("A", 0.1, 0.05, 1.5, frequency_hz=5000.0)
    renderer = RollingShutterRenderer(QUIET, [led], MOUNT)
    fx, fy = renderer.output_intrinsics.fx_px, renderer.output_intrinsics.fy_px
    for yaw in (0.0, math.pi / 2, 2.0):
        before = renderer.render(still(0.0, 0.0, yaw), 1.0).truth.leds[0].centre_px
        after = renderer.render(still(0.01, 0.0, yaw), 1.0).truth.leds[0].centre_px
        # d = LED - camera shrinks by (0.01, 0): du = -f (0.01 cos yaw) / H, dv = -f (0.01 (-sin yaw)) / H.
        height = 1.5 - 0.2
        assert after[0] - before[0] == pytest.approx(-fx * 0.01 * math.cos(yaw) / height, abs=1e-6)
        assert after[1] - before[1] == pytest.approx(fy * 0.01 * math.sin(yaw) / height, abs=1e-6)


def test_distorted_projection_matches_opencv_and_the_image() -> None:
    camera = dataclasses.replace(FLAT, distortion=(-0.12, 0.03, 0.001, -0.0015, 0.0))
    led = Led("A", 0.55, 0.38, 1.5, frequency_hz=5000.0)
    renderer = RollingShutterRenderer(camera, [led], MOUNT)
    frame = renderer.render(still(0.0, 0.0, 0.0), 5.0)
    (truth,) = frame.truth.leds
    k = np.array(
        [
            [camera.focal_length_px, 0, camera.principal_point_px[0]],
            [0, camera.focal_length_px, camera.principal_point_px[1]],
            [0, 0, 1.0],
        ]
    )
    # Yaw 0, no tilt: the camera frame is the world frame shifted up to the lens.
    point = np.array([[led.x_m, led.y_m, led.z_m - MOUNT.z_m]])
    projected, _ = cv2.projectPoints(point, np.zeros(3), np.zeros(3), k, np.array(camera.distortion))
    u_s, v_s = projected.reshape(2)
    assert truth.centre_px == pytest.approx(renderer.sensor_to_output(float(u_s), float(v_s)), abs=1e-6)
    assert blob_centroid(frame.image, truth.centre_px, camera.black_level_dn) == pytest.approx(
        truth.centre_px, abs=0.4
    )


def test_camera_tilt_moves_the_image_by_f_tan_tilt() -> None:
    led = Led("A", 0.0, 0.0, 1.5, frequency_hz=5000.0)
    level = RollingShutterRenderer(QUIET, [led], MOUNT).render(still(0, 0, 0), 1.0).truth.leds[0].centre_px
    tilt = math.radians(0.5)
    tilted = RollingShutterRenderer(QUIET, [led], MOUNT, tilt_rad=(0.0, tilt))
    moved = tilted.render(still(0, 0, 0), 1.0).truth.leds[0].centre_px
    # Pitch (about the camera y axis) turns the optical axis towards +x: a zenith point appears at
    # u = cx - f tan(pitch), v unchanged.
    assert moved[0] - level[0] == pytest.approx(-tilted.output_intrinsics.fx_px * math.tan(tilt), rel=1e-6)
    assert moved[1] == pytest.approx(level[1], abs=1e-9)


# -- stripes -------------------------------------------------------------------------------------------------
def centre_column_profile(frame: RenderedFrame) -> tuple[npt.NDArray[np.float64], int]:
    (truth,) = frame.truth.leds
    u, v = (round(c) for c in truth.centre_px)
    span = int(truth.radius_px * 0.8)
    column = frame.image[v - span : v + span, u - 1 : u + 2].astype(np.float64).mean(axis=1)
    return column, v - span


def rising_edges(profile: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """Sub-row positions where the profile crosses half its range upwards."""
    level = (profile.max() + profile.min()) / 2
    above = profile > level
    idx = np.flatnonzero(~above[:-1] & above[1:])
    frac = (level - profile[idx]) / (profile[idx + 1] - profile[idx])
    edges: npt.NDArray[np.float64] = idx + frac
    return edges


BIG = Led("A", 0.0, 0.0, 1.5, diameter_m=0.6, frequency_hz=2000.0, duty=0.5)


@pytest.mark.parametrize("freq", [1500.0, 2000.0, 3700.0])
def test_stripe_period_in_rows_is_one_over_f_t_row_over_k(freq: float) -> None:
    camera = dataclasses.replace(QUIET, radial_falloff=0.0)
    renderer = RollingShutterRenderer(camera, [dataclasses.replace(BIG, frequency_hz=freq)], MOUNT)
    profile, _ = centre_column_profile(renderer.render(still(0, 0, 0), 3.0))
    edges = rising_edges(profile)
    assert len(edges) >= 8
    period = np.polyfit(np.arange(len(edges)), edges, 1)[0]
    k = camera.sensor_height_px / camera.output_height_px
    assert period == pytest.approx(1.0 / (freq * camera.t_row_s) / k, rel=0.01)


@pytest.mark.parametrize("duty", [0.3, 0.5, 0.7])
def test_duty_cycle_appears_in_the_stripe_profile(duty: float) -> None:
    camera = dataclasses.replace(QUIET, radial_falloff=0.0)
    renderer = RollingShutterRenderer(
        camera, [dataclasses.replace(BIG, frequency_hz=1200.0, duty=duty)], MOUNT
    )
    profile, _ = centre_column_profile(renderer.render(still(0, 0, 0), 3.0))
    bright = profile > (profile.max() + profile.min()) / 2
    assert bright.mean() == pytest.approx(duty, abs=0.04)


def test_frames_differ_in_stripe_phase_as_their_start_times_say() -> None:
    renderer = RollingShutterRenderer(dataclasses.replace(QUIET, radial_falloff=0.0), [BIG], MOUNT)
    profile_a, _ = centre_column_profile(renderer.render(still(0, 0, 0), 3.0))
    dt = 0.37 / BIG.frequency_hz  # a start 0.37 cycle later
    profile_b, _ = centre_column_profile(renderer.render(still(0, 0, 0), 3.0 + 1 / 20 + dt))
    assert not np.array_equal(profile_a, profile_b)
    period = 1.0 / (BIG.frequency_hz * QUIET.t_row_s) / (QUIET.sensor_height_px / QUIET.output_height_px)
    # A later start shows the same wave phase in earlier rows: the edges move up by (f dt) periods (mod 1).
    phase_a = np.mod(rising_edges(profile_a) / period, 1.0)
    phase_b = np.mod(rising_edges(profile_b) / period, 1.0)
    mean_a = np.angle(np.exp(2j * np.pi * phase_a).mean()) / (2 * np.pi)
    mean_b = np.angle(np.exp(2j * np.pi * phase_b).mean()) / (2 * np.pi)
    shift = math.remainder(mean_a - mean_b - (BIG.frequency_hz * (1 / 20 + dt)), 1.0)
    assert abs(shift) < 0.05


# -- sensor --------------------------------------------------------------------------------------------------
def test_saturation_clips_at_255_and_blooms_into_neighbouring_rows() -> None:
    # Output = sensor size here, so neighbouring output rows are neighbouring sensor rows (blooming spills
    # charge into the very next sensor row, which the 2.56x downsampling usually skips).
    hot = dataclasses.replace(
        QUIET,
        sensor_width_px=640,
        sensor_height_px=480,
        output_width_px=640,
        output_height_px=480,
        led_peak_dn=2000.0,
        full_well_e=20000.0,
        radial_falloff=0.0,
    )
    led = Led("A", 0.0, 0.0, 1.5, diameter_m=0.2, frequency_hz=1000.0, duty=0.5)
    frame_c = RollingShutterRenderer(dataclasses.replace(hot, bloom_fraction=0.0), [led], MOUNT).render(
        still(0, 0, 0), 2.0
    )
    frame_b = RollingShutterRenderer(dataclasses.replace(hot, bloom_fraction=0.1), [led], MOUNT).render(
        still(0, 0, 0), 2.0
    )
    assert frame_c.image.max() == 255
    profile_c, _ = centre_column_profile(frame_c)
    profile_b, _ = centre_column_profile(frame_b)
    saturated = profile_c >= 254.5
    assert saturated.mean() > 0.3  # bright stripes are flat at the top, not noise-topped
    dark = profile_c < 128
    next_to_bright = dark & (np.roll(saturated, 1) | np.roll(saturated, -1))
    away = dark & ~next_to_bright & ~np.roll(next_to_bright, 1) & ~np.roll(next_to_bright, -1)
    assert next_to_bright.sum() >= 4 and away.sum() >= 10
    # Dark rows right next to saturated ones collect spilled charge only with blooming on; rows farther
    # into the dark stripe do not.
    assert (profile_b[next_to_bright] - profile_c[next_to_bright]).mean() > 20
    np.testing.assert_array_equal(profile_b[away], profile_c[away])


def test_background_has_black_level_and_read_noise() -> None:
    camera = CameraModel(black_level_dn=16.0, read_noise_dn=2.0)
    frame = RollingShutterRenderer(camera, [], MOUNT, seed=4).render(still(0, 0, 0), 1.0)
    assert frame.image.mean() == pytest.approx(16.0, abs=0.1)
    assert frame.image.std() == pytest.approx(math.sqrt(2.0**2 + 1 / 12), rel=0.1)


def test_shot_noise_grows_with_signal() -> None:
    camera = dataclasses.replace(
        CameraModel(read_noise_dn=0.0, full_well_e=2000.0, led_peak_dn=150.0),
        exposure_s=2e-3,
        radial_falloff=0.0,
        blur_sigma_px=0.5,
    )
    led = Led("A", 0.0, 0.0, 1.5, diameter_m=0.3, frequency_hz=5000.0, duty=0.5)
    frame = RollingShutterRenderer(camera, [led], MOUNT, seed=9).render(still(0, 0, 0), 1.0)
    (truth,) = frame.truth.leds
    u, v = (round(c) for c in truth.centre_px)
    patch = frame.image[v - 10 : v + 10, u - 10 : u + 10].astype(np.float64)
    dn_per_e = (255.0 - camera.black_level_dn) / camera.full_well_e
    signal_dn = patch.mean() - camera.black_level_dn
    # Poisson: var(DN) = dn_per_e * mean(DN) (plus 1/12 from rounding).
    assert patch.var() == pytest.approx(dn_per_e * signal_dn + 1 / 12, rel=0.25)


# -- motion during readout -----------------------------------------------------------------------------------
def test_motion_during_readout_shifts_each_led_by_its_own_row_time() -> None:
    speed = 1.0  # m/s along +y, camera yaw 0: the image moves towards -v as time goes on
    leds = [
        Led("top", 0.0, -0.55, 1.5, frequency_hz=5000.0),
        Led("bottom", 0.0, 0.55, 1.5, frequency_hz=4000.0),
    ]
    renderer = RollingShutterRenderer(FLAT, leds, MOUNT)
    t0 = 50.0
    t_mid = renderer.row_time_s(t0, (FLAT.sensor_height_px - 1) / 2)
    frame = renderer.render(lambda t: Pose2D(0.0, speed * (t - t_mid), 0.0), t0)
    height = 1.5 - 0.2
    fy = renderer.output_intrinsics.fy_px
    by_id = {t.id: t for t in frame.truth.leds}
    for name in ("top", "bottom"):
        truth = by_id[name]
        dt = truth.row_time_s - frame.truth.t_mid_s
        expected_dv = -fy * speed * dt / height
        assert truth.centre_px[1] - truth.centre_mid_px[1] == pytest.approx(expected_dv, rel=0.02)
        assert abs(expected_dv) > 4.0
        # The image shows the row-time position, not the mid-readout one.
        measured = blob_centroid(frame.image, truth.centre_px, FLAT.black_level_dn)
        assert measured == pytest.approx(truth.centre_px, abs=0.5)
    assert by_id["top"].row_time_s < frame.truth.t_mid_s < by_id["bottom"].row_time_s


def test_leds_out_of_view_are_not_reported_and_frames_are_repeatable() -> None:
    leds = [Led("near", 0.1, 0.1, 1.5), Led("far", 30.0, 0.0, 1.5)]
    a = RollingShutterRenderer(CameraModel(), leds, MOUNT, seed=11).render(still(0, 0, 0), 7.0)
    b = RollingShutterRenderer(CameraModel(), leds, MOUNT, seed=11).render(still(0, 0, 0), 7.0)
    assert [t.id for t in a.truth.leds] == ["near"]
    np.testing.assert_array_equal(a.image, b.image)
    assert a.image.shape == (600, 800) and a.image.dtype == np.uint8


# -- covers (occlusion) --------------------------------------------------------------------------------------
def test_a_cover_hides_the_part_of_the_disk_it_is_over() -> None:
    led = Led("A", 0.0, 0.0, 1.5, diameter_m=0.2, frequency_hz=5000.0)
    renderer = RollingShutterRenderer(FLAT, [led], MOUNT, seed=3)
    pose = still(0.0, 0.0, 0.0)
    bare = renderer.render(pose, 1.0).image.astype(np.float64) - FLAT.black_level_dn
    # Yaw 0: world +x is image +u. Half covered on the +x side, then all of it.
    half = renderer.render(pose, 1.0, covers=[LedCover(0, 0.0, 0.5)]).image.astype(np.float64)
    full = renderer.render(pose, 1.0, covers=[LedCover(0, 0.0, 1.0)]).image.astype(np.float64)
    half -= FLAT.black_level_dn
    full -= FLAT.black_level_dn
    u = round(renderer.output_intrinsics.cx_px)
    assert half[:, : u - 3].sum() == pytest.approx(bare[:, : u - 3].sum(), rel=1e-6)
    assert half[:, u + 3 :].sum() == pytest.approx(0.0, abs=1e-6)
    assert half.sum() == pytest.approx(0.5 * bare.sum(), rel=0.03)
    # All of it but the blur of the cover's edge where it touches the rim.
    assert full.sum() < 0.002 * bare.sum()
    # A cover of another LED changes nothing here.
    other = renderer.render(pose, 1.0, covers=[LedCover(1, 0.0, 0.5)]).image.astype(np.float64)
    np.testing.assert_array_equal(other - FLAT.black_level_dn, bare)
