"""Simulated laser logs (``agent.slam.simlog``): scans that agree with the world, odometry that errs the way
its error model says, VLP fixes with the stated noise, only where the camera sees two LEDs."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from agent.slam.grid import prepare_scan
from agent.slam.pose import between, transform_points, wrap_angle
from agent.slam.rbpf import sweep_offsets
from agent.slam.simlog import (
    VlpFixModel,
    WheelErrorModel,
    WheelGeometry,
    laser_geometry,
    leds_in_view,
    nominal_geometry,
    simulate_log,
    wheel_calibration_runs,
)
from calibration.wheels import Run, fit_wheels
from drivers.sim.raycast import walls_array
from drivers.sim.world import Pose2D
from drivers.sim.worldfile import load_world

OFFICE = Path(__file__).resolve().parents[2] / "examples" / "worlds" / "office.toml"


@pytest.fixture(scope="module")
def world():  # type: ignore[no-untyped-def]
    return load_world(OFFICE)


@pytest.fixture(scope="module")
def run(world):  # type: ignore[no-untyped-def]
    return simulate_log(world, 20.0, seed=3)


def distance_to_walls(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    a, b = segments[None, :, :2], segments[None, :, 2:]
    e = b - a
    q = points[:, None, :] - a
    s = np.clip((q * e).sum(-1) / np.maximum((e * e).sum(-1), 1e-12), 0.0, 1.0)
    return np.hypot(*(q - s[..., None] * e).transpose(2, 0, 1)).min(axis=1)


def test_laser_geometry_is_the_worlds_urg(world) -> None:  # type: ignore[no-untyped-def]
    g = laser_geometry(world)
    assert g.beams == 682
    assert g.angles_rad[0] == pytest.approx(-(384 - 44) * 2 * math.pi / 1024)
    assert g.angles_rad[-1] == pytest.approx((725 - 384) * 2 * math.pi / 1024)
    assert g.beam_time_s is not None
    assert g.beam_time_s[-1] == 0.0  # the scan is stamped with its last beam
    assert g.beam_time_s[0] == pytest.approx(-681 * 0.1 / 1024)
    assert g.min_range_m == 0.02 and g.no_return_m == pytest.approx(5.601)


def test_scans_lie_on_the_walls_at_the_true_pose(world, run) -> None:  # type: ignore[no-untyped-def]
    log, truth = run.log, run.truth
    assert len(log) == 200  # 10 Hz for 20 s
    segments = walls_array(world.walls)
    g = log.geometry
    residuals = []
    for i in range(1, len(log), 7):
        motion = between(truth[i - 1], truth[i])
        offsets = sweep_offsets(g, log.records[i].t_s - log.records[i - 1].t_s, motion)
        scan = prepare_scan(
            log.records[i].ranges_m, g.angles_rad, g.mount, 0.1, g.no_return_m, 5.5, 0.0, offsets
        )
        residuals.append(distance_to_walls(transform_points(truth[i], scan.hit_xy), segments))
    d = np.concatenate(residuals)
    # 10 mm range noise; people walk about, so a few endpoints are on them, not on walls.
    assert np.median(d) < 0.01
    assert np.mean(d < 0.03) > 0.9


def test_odometry_errs_as_its_model_says(world) -> None:  # type: ignore[no-untyped-def]
    exact = WheelErrorModel(left_scale=1.0, right_scale=1.0, track_scale=1.0, slip_m_per_sqrt_m=0.0)
    perfect = simulate_log(world, 15.0, wheel_errors=exact, seed=3)
    biased = simulate_log(
        world, 15.0, wheel_errors=dataclasses.replace(WheelErrorModel(), slip_m_per_sqrt_m=0.0)
    )
    np.testing.assert_allclose(perfect.truth, biased.truth)  # the truth does not depend on the odometry
    # Perfect wheels: odometry is the truth up to the 4096-tick encoders.
    np.testing.assert_allclose(perfect.odometry_in_world()[:, :2], perfect.truth[:, :2], atol=0.002)
    # The default wheels over-count by 0.5 %, the right one 0.2 % less than the left: on the first 15 s,
    # a straight leg east (the autopilot's small steering turns cancel), the odometry veers right by
    # 0.002 d / track (times the 1 % it over-counts every turn).
    driven = np.sum(np.hypot(*np.diff(biased.truth[:, :2], axis=0).T))
    counted = np.sum(np.hypot(*np.diff(biased.log.odometry_poses()[:, :2], axis=0).T))
    assert counted / driven == pytest.approx(1.005, abs=0.001)
    heading_error = wrap_angle(biased.odometry_in_world()[-1, 2] - biased.truth[-1, 2])
    assert heading_error == pytest.approx(-0.002 * 1.01 / world.robot.track_m * driven, rel=0.1)
    # Slip is a random walk: two seeds' odometry differ by about its size.
    one, other = (simulate_log(world, 15.0, seed=seed).odometry_in_world() for seed in (1, 2))
    spread = np.hypot(*(one[-1, :2] - other[-1, :2]))
    assert 0.002 < spread < 0.2


def test_calibrated_wheels_take_out_the_scale_errors(world) -> None:  # type: ignore[no-untyped-def]
    """`calibrate wheels`' runs on the simulated wheels, fitted by the step's own fit: the radius the
    odometry then uses makes the mean wheel count right (the default wheels over-count 0.6 % and 0.4 %),
    the track is the effective one; the same drive's odometry with it counts the distance within 0.1 %,
    while the nominal geometry's, logged beside it, is the uncalibrated robot's."""
    errors = WheelErrorModel()
    fit = fit_wheels([Run(*r) for r in wheel_calibration_runs(world, errors, np.random.default_rng(0))])
    radius, track = world.robot.wheel_radius_m, world.robot.track_m
    assert fit.wheel_radius_m == pytest.approx(radius / 1.005, rel=2e-3)
    assert fit.track_m == pytest.approx(track, rel=2e-3)
    calibrated = simulate_log(
        world,
        15.0,
        wheel_errors=errors,
        wheel_geometry=WheelGeometry(fit.wheel_radius_m, fit.track_m),
        seed=3,
    )
    driven = np.sum(np.hypot(*np.diff(calibrated.truth[:, :2], axis=0).T))
    counted = np.sum(np.hypot(*np.diff(calibrated.log.odometry_poses()[:, :2], axis=0).T))
    assert counted / driven == pytest.approx(1.0, abs=0.001)
    uncalibrated = calibrated.with_nominal_odometry().odometry_poses()
    assert np.sum(np.hypot(*np.diff(uncalibrated[:, :2], axis=0).T)) / driven == pytest.approx(
        1.005, abs=0.001
    )
    # Without a geometry the robot is the uncalibrated one: both odometries are the nominal geometry's.
    nominal = simulate_log(world, 15.0, wheel_errors=errors, seed=3)
    assert nominal.geometry == nominal_geometry(world, errors)
    np.testing.assert_array_equal(nominal.nominal_odometry, nominal.log.odometry_poses())
    np.testing.assert_allclose(nominal.nominal_odometry, uncalibrated, atol=1e-12)


def test_fixes_have_the_stated_noise_where_two_leds_are_seen(world, run) -> None:  # type: ignore[no-untyped-def]
    model = VlpFixModel()
    assert (
        len(run.fixes) == 201 and run.frames_without_fix == 0 and run.no_fix_reasons == {}
    )  # 10 Hz; two LEDs always in view
    assert min(run.fix_leds) >= 2
    times = np.array([f.t_s for f in run.fixes])
    poses = np.array([[f.fix.x_m, f.fix.y_m, f.fix.yaw_rad] for f in run.fixes], dtype=np.float64)
    e = poses - run.fix_truth
    e[:, 2] = wrap_angle(e[:, 2])
    assert np.diff(times) == pytest.approx(0.1)
    # Noise of 5 mm and 0.3 deg, plus the mean survey error of the LEDs in view (3 mm per LED).
    assert np.std(e[:, 0]) == pytest.approx(model.sigma_xy_m, rel=0.35)
    assert np.std(e[:, 2]) == pytest.approx(model.sigma_yaw_rad, rel=0.35)
    assert np.max(np.hypot(e[:, 0], e[:, 1])) < 0.03


def test_an_led_counts_only_inside_the_sensor(world) -> None:  # type: ignore[no-untyped-def]
    led = world.leds[0]
    lens_height = led.z_m - world.robot.camera_mount.z_m
    half_width_m = world.camera.sensor_width_px / 2 * world.camera.pixel_size_m / world.camera.focal_length_m
    reach = half_width_m * lens_height  # ~2.1 m ahead of the lens at the LEDs' height
    below = Pose2D(led.x_m, led.y_m, 0.0)
    assert 0 in leds_in_view(world, below, (led,))
    assert leds_in_view(world, Pose2D(led.x_m - 0.9 * reach, led.y_m, 0.0), (led,)) == [0]
    assert leds_in_view(world, Pose2D(led.x_m - 1.1 * reach, led.y_m, 0.0), (led,)) == []
    # Turned by 90 degrees the same offset is across the sensor's shorter side: out of view.
    assert leds_in_view(world, Pose2D(led.x_m - 0.9 * reach, led.y_m, math.pi / 2), (led,)) == []


def test_no_fix_without_enough_leds(world) -> None:  # type: ignore[no-untyped-def]
    blind = simulate_log(world, 3.0, fixes=VlpFixModel(min_leds=99), seed=1)
    assert blind.fixes == () and blind.frames_without_fix == 31
    assert blind.no_fix_reasons == {"fewer than 99 LEDs in view": 31}


def test_a_world_without_a_route_is_refused(world) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ValueError, match="no route"):
        simulate_log(dataclasses.replace(world, route=()), 10.0)
    with pytest.raises(ValueError, match="positive"):
        simulate_log(world, 0.0)
