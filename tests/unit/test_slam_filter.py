"""The particle filter, localization and fixes on a synthetic room with ground truth.

The robot drives a loop around a box in an 8 m x 6 m room; scans come from exact ray casting plus range
noise, odometry from the true motion with a heading bias and noise, so raw odometry drifts while the
truth is known.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from agent.slam.fix import PoseFix, fix_log_likelihood, fuse_fixes, pending_fixes_log_likelihood
from agent.slam.grid import GridGeometry, LogOddsModel, TileRect, integrate_scans, prepare_scan
from agent.slam.logs import LogFormat, LogRecord, SlamLog
from agent.slam.loops import LoopClosureConfig
from agent.slam.mapio import load_map, save_map
from agent.slam.matcher import DistanceField, MatcherConfig
from agent.slam.mcl import MclConfig, MclLocalizer
from agent.slam.metrics import absolute_trajectory_error
from agent.slam.motion import OdometryNoise, motion_log_density, sample_motion
from agent.slam.pose import between, compose, inverse
from agent.slam.proposal import ProposalConfig, degenerate_scaling, improved_proposal, laplace_log_eta
from agent.slam.rbpf import MapMode, RbpfConfig, RbpfSlam, StepKind, systematic_resample
from agent.slam.render import occupancy_image
from agent.slam.replay import replay
from agent.slam.scan import LaserGeometry, Rejection
from drivers.sim.raycast import cast_rays

ROOM = (
    np.array(
        [
            (-4.0, -3.0, 4.0, -3.0),
            (4.0, -3.0, 4.0, 3.0),
            (4.0, 3.0, -4.0, 3.0),
            (-4.0, 3.0, -4.0, -3.0),
            (-0.5, -0.5, 1.0, -0.5),
            (1.0, -0.5, 1.0, 0.8),
            (1.0, 0.8, -0.5, 0.8),
            (-0.5, 0.8, -0.5, -0.5),
            (-4.0, 1.5, -3.2, 2.3),
            (2.8, -3.0, 3.3, -2.2),
        ]
    )
    + 0.025
)
LASER = LaserGeometry(np.radians(np.linspace(-120.0, 120.0, 341)), 0.02, 5.6, (0.1, 0.0, 0.0))


def drive(seed: int = 0, step_m: float = 0.05) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(times, true poses, odometry poses, ranges) for one loop around the box."""
    corners = [(-2.5, -1.8), (2.5, -1.8), (2.5, 2.0), (-2.5, 2.0), (-2.5, -1.8)]
    truth = [np.array([-2.5, -1.8, 0.0])]
    for (x0, y0), (x1, y1) in itertools.pairwise(corners):
        heading = math.atan2(y1 - y0, x1 - x0)
        while abs(((truth[-1][2] - heading) + math.pi) % (2 * math.pi) - math.pi) > 1e-9:
            turn = ((heading - truth[-1][2]) + math.pi) % (2 * math.pi) - math.pi
            truth.append(compose(truth[-1], np.array([0.0, 0.0, float(np.clip(turn, -0.1, 0.1))])))
        for _ in range(round(math.hypot(x1 - x0, y1 - y0) / step_m)):
            truth.append(compose(truth[-1], np.array([step_m, 0.0, 0.0])))
    poses = np.array(truth)
    rng = np.random.default_rng(seed)
    odometry = [poses[0].copy()]
    for a, b in itertools.pairwise(poses):
        u = between(a, b)
        # 3 % scale error, 2 deg per metre of heading bias, noise: raw odometry drifts visibly.
        noisy = u + np.array([0.03 * u[0], 0.0, math.radians(2.0) * abs(u[0])])
        noisy += rng.standard_normal(3) * np.array([0.002, 0.001, 0.002])
        odometry.append(compose(odometry[-1], noisy))
    ranges = []
    for pose in poses:
        laser = compose(pose, np.array(LASER.mount))
        r = cast_rays((laser[0], laser[1]), LASER.angles_rad + laser[2], ROOM, None, 5.6)
        r = np.where(np.isfinite(r), r + rng.standard_normal(r.size) * 0.01, 0.0)
        ranges.append(r)
    times = np.arange(len(poses)) * 0.1
    return times, poses, np.array(odometry), np.array(ranges)


@pytest.fixture(scope="module")
def loop() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return drive()


def run_filter(loop: tuple[np.ndarray, ...], config: RbpfConfig) -> tuple[RbpfSlam, np.ndarray]:
    times, _truth, odometry, ranges = loop
    slam = RbpfSlam(LASER, config)
    estimate = []
    for t, odom, r in zip(times, odometry, ranges, strict=True):
        slam.process(float(t), r, odom)
        estimate.append(slam.pose(odom))
    return slam, np.array(estimate)


# -- the filter ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("mode", [MapMode.PER_PARTICLE, MapMode.SHARED])
def test_slam_follows_the_truth_where_odometry_drifts(loop: tuple[np.ndarray, ...], mode: MapMode) -> None:
    _times, truth, odometry, _ = loop
    start = tuple(float(v) for v in truth[0])
    slam, estimate = run_filter(loop, RbpfConfig(particles=8, map_mode=mode, initial_pose=start))
    odometry_in_world = compose(truth[0], between(odometry[0], odometry))
    assert absolute_trajectory_error(truth, odometry_in_world) > 0.25
    assert absolute_trajectory_error(truth, estimate) < 0.05
    # The loop closes: back at the start, the estimate is where the truth is.
    assert np.hypot(*(estimate[-1, :2] - truth[-1, :2])) < 0.06
    assert slam.stats.updates > 50
    assert slam.stats.match_failures < slam.stats.updates  # nearly every particle matched


def test_shared_map_needs_less_memory(loop: tuple[np.ndarray, ...]) -> None:
    start = tuple(float(v) for v in loop[1][0])
    short = tuple(a[:150] for a in loop)
    per_particle, _ = run_filter(short, RbpfConfig(particles=8, initial_pose=start))
    shared, _ = run_filter(short, RbpfConfig(particles=8, map_mode=MapMode.SHARED, initial_pose=start))
    assert shared.maps.maps == 1
    assert shared.maps.tiles_in_use() < per_particle.maps.tiles_in_use()
    assert shared.maps.used_bytes() < per_particle.maps.used_bytes()


def test_bad_scans_are_rejected_counted_and_survived(loop: tuple[np.ndarray, ...]) -> None:
    times, truth, odometry, ranges = loop
    slam = RbpfSlam(LASER, RbpfConfig(particles=4, initial_pose=tuple(float(v) for v in truth[0])))
    nan_scan = ranges[30].copy()
    nan_scan[5] = np.nan
    jumped = compose(odometry[40], np.array([5.0, 0.0, 0.0]))
    bad = {
        20: (times[20], np.zeros_like(ranges[20]), odometry[20], Rejection.NO_RETURNS),
        30: (times[30], nan_scan, odometry[30], Rejection.NON_FINITE),
        35: (times[35], ranges[35][:-1], odometry[35], Rejection.BEAM_COUNT),
        38: (times[36] - 0.05, ranges[38], odometry[38], Rejection.TIME_BACKWARDS),
        40: (times[40], ranges[40], jumped, Rejection.POSE_JUMP),
    }
    for i in range(len(times)):
        if i in bad:
            t, r, o, reason = bad[i]
            result = slam.process(float(t), r, o)
            assert result.kind is StepKind.REJECTED and result.rejection is reason
        else:
            # After the jump the odometry stays shifted by 5 m: the filter must take the jump out.
            o = compose(jumped, between(odometry[40], odometry[i])) if i > 40 else odometry[i]
            result = slam.process(float(times[i]), ranges[i], o)
            assert result.kind is not StepKind.REJECTED
    assert dict(slam.gate.counts) == {reason: 1 for *_, reason in bad.values()}
    assert slam.stats.updates > 50  # it carried on
    assert np.hypot(*(slam.pose()[:2] - truth[-1, :2])) < 0.5  # and the 5 m jump did not move it


def test_resampling_is_systematic() -> None:
    rng = np.random.default_rng(1)
    weights = np.array([0.5, 0.25, 0.125, 0.125])
    counts = np.bincount(systematic_resample(weights, rng), minlength=4)
    assert counts.tolist() == [2, 1, 0, 1] or counts.tolist() == [2, 1, 1, 0]
    big = np.bincount(systematic_resample(np.full(1000, 1e-3), rng), minlength=1000)
    assert (big == 1).all()  # equal weights: every particle survives exactly once


def test_motion_model_spread_and_density() -> None:
    noise = OdometryNoise()
    rng = np.random.default_rng(2)
    increment = np.array([0.5, 0.0, 0.2])
    samples = sample_motion(np.zeros((20000, 3)), increment, noise, rng)
    sig = noise.sigmas(increment)  # sigma_x = 0.1*0.5 + 0.1*0.2, sigma_yaw = 0.2*0.2 + 0.2*0.5
    np.testing.assert_allclose(sig, [0.07, 0.035, 0.14])
    rel = between(np.zeros(3), samples)
    np.testing.assert_allclose(rel.mean(axis=0), increment, atol=0.005)
    np.testing.assert_allclose(rel.std(axis=0), sig, rtol=0.05)
    density = motion_log_density(
        np.zeros((1, 3)), np.array([[increment, increment + np.array([0.07, 0.0, 0.0])]]), increment, noise
    )
    np.testing.assert_allclose(density[0], [0.0, -0.5])


def test_closed_form_eta_is_the_integral() -> None:
    """``eta_integral="laplace"``: log ∫ exp(l(x) / T) p(x | x', u) dx in closed form, against a dense
    grid sum of the same integrand (the likelihood a quadratic around the match, as the proposal has it)."""
    noise = OdometryNoise()
    previous = np.array([[0.3, -0.2, 0.4]])
    increment = np.array([0.3, 0.02, 0.1])
    # A match 4 cm short of odometry and 1 degree off: the motion model's tail, as after a wheel slip.
    centre = compose(previous[0], increment + np.array([-0.04, 0.005, 0.017]))[None, :]
    l0 = np.array([-30.0])
    l_grad = np.array([[40.0, -25.0, 10.0]])
    l_hess = np.array([[[4.0e4, 5.0e3, 0.0], [5.0e3, 2.0e3, 1.0e3], [0.0, 1.0e3, 9.0e4]]])  # a corridor in y
    temperature = 40.0
    closed = laplace_log_eta(previous, centre, increment, noise, l0, l_grad, l_hess, temperature, None)
    axes = [np.linspace(-0.25, 0.25, 101), np.linspace(-0.25, 0.25, 101), np.linspace(-0.2, 0.2, 81)]
    delta = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    log_lik = l0[0] + delta @ l_grad[0] - 0.5 * np.einsum("ki,ij,kj->k", delta, l_hess[0], delta)
    log_motion = motion_log_density(previous, (centre[0] + delta)[None], increment, noise)[0]
    log_f = log_lik / temperature + log_motion
    volume = float(np.prod([a[1] - a[0] for a in axes]))
    numeric = log_f.max() + np.log(np.exp(log_f - log_f.max()).sum() * volume)
    assert closed[0] == pytest.approx(numeric, abs=0.02)


def test_degenerate_directions_draw_less_spread() -> None:
    """``degenerate_scaling``: a draw's covariance M C Mᵀ is the posterior's with the prior k times tighter:
    along a corridor (no scan information) the spread shrinks by k, across it and in heading (the scan's)
    it barely changes, whatever the corridor's direction and the prior's units."""
    rng = np.random.default_rng(3)
    prior = np.diag([1.0e3, 2.0e3, 5.0e4])  # the motion prior's information, x y yaw
    angle = 0.7  # the corridor runs along (cos, sin) of this
    c, s = math.cos(angle), math.sin(angle)
    across = np.array([-s, c, 0.0])
    scan = 1.0e6 * np.outer(across, across) + np.diag([0.0, 0.0, 1.0e7])
    k = 0.3
    m = degenerate_scaling(scan[None], prior[None], k)[0]
    posterior = np.linalg.inv(scan + prior)
    tighter = np.linalg.inv(scan + prior / k**2)
    drawn = m @ posterior @ m.T
    along = np.array([c, s, 0.0])
    assert along @ drawn @ along == pytest.approx(along @ tighter @ along, rel=0.02)
    assert along @ drawn @ along == pytest.approx(k**2 * (along @ posterior @ along), rel=0.05)
    assert across @ drawn @ across == pytest.approx(across @ posterior @ across, rel=0.06)
    assert drawn[2, 2] == pytest.approx(posterior[2, 2], rel=0.06)
    # No scan information at all: every direction k times the prior's spread; k = 1: the identity.
    assert degenerate_scaling(np.zeros((1, 3, 3)), prior[None], k)[0] == pytest.approx(k * np.eye(3))
    random_info = rng.standard_normal((2, 3, 3))
    random_info = random_info @ np.swapaxes(random_info, 1, 2)
    assert degenerate_scaling(random_info, np.stack([prior, prior]), 1.0) == pytest.approx(
        np.stack([np.eye(3), np.eye(3)]), abs=1e-9
    )


def test_a_failed_match_can_draw_where_its_weight_was_taken() -> None:
    """``failed_match_draw="grid"``: a particle whose match fails is drawn from the Gaussian fitted on the
    grid around the odometry prediction (its steps the motion model's deviations, clamped), where its eta
    was taken, so the draw stays near the prediction and leans to where the scan fits; the motion model's
    draw (the default) spreads 0.2 rad here and ignores the scan. The prediction is one clamped grid step
    (0.05 rad) short of the heading that puts the scan on the wall, and every match fails
    (``min_inliers`` above the scan's size)."""
    obstacles = np.zeros((1, 120, 120), dtype=bool)
    previous = np.tile([-1.0, 0.0, -0.05], (400, 1))
    increment = np.array([1.0, 0.0, 0.0])
    noise = OdometryNoise(0.1, 0.2, 0.1, 0.2)  # slam_gmapping's: sigma_yaw 0.2 rad over 1 m
    predicted = compose(previous[0], increment)
    wall_x = predicted[0] + 2.0  # seen 2 m straight ahead at heading 0
    obstacles[0, :, int((wall_x + 3.0) / 0.05)] = True
    field = DistanceField.from_obstacles(obstacles, (-3.0, -3.0), 0.05, 0.6)
    points = np.column_stack([np.full(41, 2.0), np.linspace(-1.0, 1.0, 41)])
    failing = MatcherConfig(min_inliers=1000)
    offsets = {}
    for draw in ("grid", "motion"):
        config = ProposalConfig(search=None, matcher=failing, failed_match_draw=draw)
        result = improved_proposal(
            field,
            np.zeros(400, dtype=np.int64),
            points,
            previous,
            increment,
            noise,
            config,
            np.random.default_rng(5),
            np.zeros(400),
        )
        assert not result.matched.any()
        offsets[draw] = between(np.tile(predicted, (400, 1)), result.poses)
    assert np.mean(offsets["grid"][:, 2]) > 0.03  # towards the wall's heading (+0.05)
    assert abs(np.mean(offsets["motion"][:, 2])) < 0.03  # around the prediction
    assert np.std(offsets["grid"][:, 2]) < 0.25 * np.std(offsets["motion"][:, 2])


def test_slam_with_degenerate_noise_scale(loop: tuple[np.ndarray, ...]) -> None:
    _times, truth, _odometry, _ = loop
    start = tuple(float(v) for v in truth[0])
    proposal = ProposalConfig(degenerate_noise_scale=0.3)
    _slam, estimate = run_filter(loop, RbpfConfig(particles=8, initial_pose=start, proposal=proposal))
    assert absolute_trajectory_error(truth, estimate) < 0.05


@pytest.mark.parametrize("radius_per_m", [None, 0.1])
def test_slam_records_the_lines_information_for_its_edges(
    loop: tuple[np.ndarray, ...], radius_per_m: float | None
) -> None:
    """``LoopClosureConfig.edge_information`` "normals" (point to line): each node's recorded information
    is Σ g gᵀ over its match's inliers with a unit normal (the match's own, or with
    ``edge_normal_radius_per_m`` the information's own), so its translation block's trace counts them."""
    _times, truth, _odometry, _ = loop
    lc = LoopClosureConfig(
        edge_match_sigma_m=0.1, edge_information="normals", edge_normal_radius_per_m=radius_per_m
    )
    proposal = ProposalConfig(along_surface_weight=0.0)
    config = RbpfConfig(
        particles=8, initial_pose=tuple(float(v) for v in truth[0]), proposal=proposal, loop_closure=lc
    )
    slam, estimate = run_filter(loop, config)
    assert absolute_trajectory_error(truth, estimate) < 0.05
    info = np.array(slam._node_information[1:])
    counts = np.trace(info[:, :2, :2], axis1=1, axis2=2)
    np.testing.assert_allclose(counts, np.round(counts), atol=1e-6)  # whole endpoints, each |n|² = 1
    assert np.all(counts <= config.max_match_points) and np.median(counts) >= 20
    assert np.all(np.linalg.eigvalsh(info) > -1e-6)


def test_slam_records_relative_edges_from_scan_to_scan_matches(loop: tuple[np.ndarray, ...]) -> None:
    """``LoopClosureConfig.edge_information`` "scan": each node's recorded information is the point-to-line
    information of its scan matched against the node before's (whole unit normals counted), and the
    relative match's step (``edge_scan_mean``) is within centimetres of the true step."""
    _times, truth, _odometry, _ = loop
    lc = LoopClosureConfig(edge_match_sigma_m=0.1, edge_information="scan", edge_scan_mean=True)
    config = RbpfConfig(particles=8, initial_pose=tuple(float(v) for v in truth[0]), loop_closure=lc)
    slam, estimate = run_filter(loop, config)
    assert absolute_trajectory_error(truth, estimate) < 0.05
    info = np.array(slam._node_information[1:])
    counts = np.trace(info[:, :2, :2], axis1=1, axis2=2)
    np.testing.assert_allclose(counts, np.round(counts), atol=1e-6)
    assert np.median(counts) >= 20 and np.all(np.linalg.eigvalsh(info) > -1e-6)
    steps = np.array(slam._node_scan_motions[1:])
    measured = np.isfinite(steps[:, 0])
    assert measured.mean() > 0.9
    filter_steps = np.array(slam._node_scan_guesses[1:])
    gap = np.hypot(*(steps[measured, :2] - filter_steps[measured, :2]).T)
    assert np.median(gap) < 0.02


def test_slam_with_closed_form_eta(loop: tuple[np.ndarray, ...]) -> None:
    _times, truth, _odometry, _ = loop
    proposal = ProposalConfig(eta_integral="laplace")
    config = RbpfConfig(particles=8, proposal=proposal, initial_pose=tuple(float(v) for v in truth[0]))
    _slam, estimate = run_filter(loop, config)
    assert absolute_trajectory_error(truth, estimate) < 0.05


# -- absolute fixes -------------------------------------------------------------------------------------


def test_fix_likelihood_with_and_without_yaw() -> None:
    poses = np.array([[1.0, 2.0, 0.0], [1.1, 2.0, 0.5], [3.0, 2.0, 0.0]])
    fix = PoseFix(1.0, 2.0, None, np.diag([0.01**2, 0.01**2]))
    ll = fix_log_likelihood(poses, fix)
    assert ll[0] == 0.0 and ll[1] == pytest.approx(-0.5 * 100.0) and ll[2] < ll[1]
    with_yaw = PoseFix(1.0, 2.0, 0.0, np.diag([0.01**2, 0.01**2, 0.1**2]))
    assert fix_log_likelihood(poses[:2], with_yaw)[1] == pytest.approx(-0.5 * (100.0 + 25.0))
    with pytest.raises(ValueError):
        PoseFix(0.0, 0.0, None, np.eye(3))


def test_fix_is_moved_along_odometry() -> None:
    # Fix at (0, 0) facing +x; then the robot drove 1 m forward. A particle at (1, 0) now agrees, one at
    # (0, 0) does not; the motion model's noise for that metre widens the fix.
    fix = PoseFix(0.0, 0.0, None, np.diag([1e-4, 1e-4]))
    poses = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.05, 0.0]])
    ll = pending_fixes_log_likelihood(
        poses,
        [(fix, np.array([5.0, 5.0, 1.0]))],
        np.array([5.0 + math.cos(1.0), 5.0 + math.sin(1.0), 1.0]),
        OdometryNoise(),
    )
    assert ll[0] == pytest.approx(0.0, abs=1e-9)
    assert ll[1] < ll[2] < ll[0]


def test_a_fix_pulls_the_particles_to_it(loop: tuple[np.ndarray, ...]) -> None:
    times, truth, odometry, ranges = loop
    start = tuple(float(v) for v in truth[0])
    slam = RbpfSlam(LASER, RbpfConfig(particles=12, initial_pose=start, seed=4))
    for i in range(60):
        slam.process(float(times[i]), ranges[i], odometry[i])
    # A tight fix (1 mm), 4 cm away from where the scans put the robot: it joins the proposal, so the
    # particles move to it (weighting alone could not: every particle is about 4 cm from it).
    fix = PoseFix(float(truth[59, 0]) + 0.04, float(truth[59, 1]), None, np.diag([1e-6, 1e-6]))

    def distance_to_fix(poses: np.ndarray, now: np.ndarray) -> np.ndarray:
        at_fix = compose(poses, inverse(between(odometry[59], now))[None, :])
        return np.hypot(at_fix[:, 0] - fix.x_m, at_fix[:, 1] - fix.y_m)

    assert distance_to_fix(slam.poses, odometry[59]).min() > 0.02
    slam.add_fix(fix, odometry[59])
    for i in range(60, 80):
        result = slam.process(float(times[i]), ranges[i], odometry[i])
        if result.kind is StepKind.UPDATED:
            break
    assert slam.stats.fixes_applied == 1
    assert np.median(distance_to_fix(slam.poses, odometry[i])) < 0.01


def test_fixes_carried_forward_fuse_into_one_measurement() -> None:
    noise = OdometryNoise()
    # Two fixes of a robot driving along x, 0.1 m apart by odometry; now it is 0.2 m past the first.
    cov = np.diag([0.005**2, 0.005**2, math.radians(0.3) ** 2])
    fixes = [
        (PoseFix(1.0, 2.0, 0.0, cov), np.array([10.0, 0.0, 0.0])),
        (PoseFix(1.1, 2.0, 0.0, cov), np.array([10.1, 0.0, 0.0])),
    ]
    measurement = fuse_fixes(fixes, np.array([10.2, 0.0, 0.0]), noise, 0.0)
    np.testing.assert_allclose(measurement.mean, [1.2, 2.0, 0.0], atol=1e-9)
    covariance = np.linalg.inv(measurement.information)
    # Tighter than one fix carried 0.2 m by odometry, looser than the two fixes' own noise averaged.
    assert covariance[0, 0] < 0.005**2 + (noise.srr * 0.2) ** 2
    assert covariance[0, 0] > 0.005**2 / 2
    # A fix without yaw gives a position-only measurement, carried along the filter's heading.
    position_only = fuse_fixes(
        [(PoseFix(1.0, 2.0, None, cov[:2, :2]), np.array([10.0, 0.0, 0.0]))],
        np.array([10.0, 0.2, math.pi / 2]),
        noise,
        math.pi / 2,
    )
    np.testing.assert_allclose(position_only.mean[:2], [1.0, 2.2], atol=1e-9)
    assert position_only.information[2, 2] == 0.0
    assert position_only.log_likelihood(np.array([1.0, 2.2, 3.0])) == pytest.approx(0.0)


def test_a_fix_is_widened_by_the_odometry_it_is_carried_over_not_by_the_motion_floor() -> None:
    # The motion model's floor (5 mm, 0.002 rad) keeps one update's motion density proper; carrying a fix
    # over no motion adds nothing, over a stretch what that stretch's odometry can err (docs/slam.md, "VLP
    # fixes: the carried covariance").
    noise = OdometryNoise(0.03, 0.05, 0.03, 0.05)
    cov = np.diag([0.002**2, 0.003**2, math.radians(0.3) ** 2])
    odom = np.array([10.0, 0.0, 0.0])
    at_scan = fuse_fixes([(PoseFix(1.0, 2.0, 0.0, cov), odom)], odom, noise, 0.0)
    np.testing.assert_allclose(np.linalg.inv(at_scan.information), cov, rtol=1e-9)
    fix = PoseFix(1.0, 2.0, None, cov[:2, :2])
    poses = np.array([[1.0, 2.004, 0.0]])
    assert pending_fixes_log_likelihood(poses, [(fix, odom)], odom, noise)[0] == pytest.approx(
        fix_log_likelihood(poses, fix)[0]
    )
    # 4 cm on: the odometry's spread for 4 cm (1.2 mm along, 0.36 mm across), far below the floor.
    moved = np.array([0.04, 0.0, 0.0])
    carried = fuse_fixes([(PoseFix(1.0, 2.0, 0.0, cov), odom)], compose(odom, moved), noise, 0.0)
    spread = noise.spread(moved)
    np.testing.assert_allclose(spread, [0.0012, 0.00036, 0.002])
    assert np.linalg.inv(carried.information)[0, 0] == pytest.approx(0.002**2 + 0.0012**2, rel=1e-9)
    assert np.linalg.inv(carried.information)[0, 0] < 0.002**2 + noise.floor_m**2
    # The floor is all that sets sigmas apart from spread.
    increments = np.array([[0.0, 0.0, 0.0], moved, [0.3, -0.1, 0.4], [-1.0, 0.2, -2.0]])
    np.testing.assert_array_equal(
        noise.sigmas(increments),
        np.maximum(noise.spread(increments), [noise.floor_m, noise.floor_m, noise.floor_rad]),
    )


def test_without_structure_to_match_fixes_still_weigh(loop: tuple[np.ndarray, ...]) -> None:
    times, truth, odometry, ranges = loop
    start = tuple(float(v) for v in truth[0])
    slam = RbpfSlam(LASER, RbpfConfig(particles=12, initial_pose=start, resample_threshold=1e-6, seed=4))
    for i in range(60):
        slam.process(float(times[i]), ranges[i], odometry[i])
    fix = PoseFix(float(truth[59, 0]) + 0.04, float(truth[59, 1]), None, np.diag([1e-6, 1e-6]))
    slam.add_fix(fix, odometry[59])
    # A scan with barely any returns (above the gate's minimum, below the matcher's): the particles move
    # by the motion model, and the fix can only reweight them.
    sparse = np.zeros_like(ranges[60])
    sparse[::25] = ranges[60][::25]
    far = compose(odometry[59], np.array([0.3, 0.0, 0.0]))
    result = slam.process(float(times[60]), sparse, far)
    assert result.kind is StepKind.UPDATED and result.matched == 0
    agreement = pending_fixes_log_likelihood(slam.poses, [(fix, odometry[59])], far, OdometryNoise())
    assert np.ptp(agreement) > 1.0
    assert slam.best_index == int(np.argmax(agreement))


# -- localization on a saved map ---------------------------------------------------------------------------


def true_map(loop: tuple[np.ndarray, ...], tmp_path: Path) -> Path:
    """The room mapped from the true poses, saved and reloaded as map_server files."""
    _times, truth, _, ranges = loop
    geometry, model = GridGeometry(), LogOddsModel()
    rect = TileRect.covering(geometry, (-5.0, -4.0), (5.0, 4.0))
    windows = np.zeros((1, rect.shape[0] * 32, rect.shape[1] * 32), dtype=np.int8)
    for pose, r in zip(truth[::4], ranges[::4], strict=True):
        scan = prepare_scan(r, LASER.angles_rad, LASER.mount, 0.1, 5.6, 5.5, 0.025)
        integrate_scans(windows, rect.origin_m(geometry), 0.05, pose[None, :], scan, model, 32)
    image = occupancy_image(model.to_log_odds(windows[0]), rect.origin_m(geometry), 0.05)
    return save_map(image, tmp_path / "room.yaml").yaml


def test_localization_from_a_position_only_fix(loop: tuple[np.ndarray, ...], tmp_path: Path) -> None:
    times, truth, odometry, ranges = loop
    occupancy = load_map(true_map(loop, tmp_path))
    mcl = MclLocalizer(LASER, occupancy, MclConfig(particles=40, seed=3))
    first = mcl.process(float(times[0]), ranges[0], odometry[0])
    assert first.kind is StepKind.UNINITIALIZED
    # A VLP fix 7 cm off the truth, 10 cm sigma, no heading: headings start spread round the circle.
    mcl.initialize(
        PoseFix(float(truth[5, 0]) + 0.05, float(truth[5, 1]) - 0.05, None, np.diag([0.01, 0.01])),
        odometry[5],
    )
    errors = []
    for i in range(5, 200):
        mcl.process(float(times[i]), ranges[i], odometry[i])
        errors.append(np.hypot(*(mcl.pose(odometry[i])[:2] - truth[i, :2])))
    errors_after_start = np.array(errors[40:])  # a few updates to pick the heading
    assert errors_after_start.max() < 0.05
    assert np.mean(errors_after_start) < 0.02
    assert mcl.spread_m() < 0.05


def test_history_can_be_bounded_for_long_runs(loop: tuple[np.ndarray, ...]) -> None:
    start = tuple(float(v) for v in loop[1][0])
    short = tuple(a[:120] for a in loop)
    slam, _estimate = run_filter(short, RbpfConfig(particles=3, initial_pose=start, history_limit=5))
    times, poses, odometry = slam.trajectory()
    assert slam.stats.updates > 5
    assert poses.shape == (5, 3) and times.shape == (5,) and odometry.shape == (5, 3)
    np.testing.assert_allclose(poses[-1], slam.poses[slam.best_index])


def test_mean_trajectory_weighs_each_ancestry() -> None:
    """mean_trajectory(): at every update the weighted mean over the current particles' ancestries
    (a particle that left no descendant counts nothing), the yaw averaged on the circle (across ±pi)."""
    slam = RbpfSlam(LASER, RbpfConfig(particles=2))
    slam.history_poses.extend(
        [
            np.array([[0.0, 0.0, 3.0], [9.0, 9.0, 0.0]]),
            np.array([[1.0, 0.0, -3.0], [2.0, 1.0, 3.1]]),
        ]
    )
    slam.history_parents.extend([np.array([0, 1]), np.array([0, 0])])  # both descend from particle 0
    slam.history_t_s.extend([0.0, 1.0])
    slam.history_odom.extend([np.zeros(3), np.ones(3)])
    slam.log_weights = np.log(np.array([0.25, 0.75]))
    times, poses, odometry = slam.mean_trajectory()
    np.testing.assert_allclose(poses[0], [0.0, 0.0, 3.0])
    np.testing.assert_allclose(poses[1, :2], [1.75, 0.75])
    sin = 0.25 * math.sin(-3.0) + 0.75 * math.sin(3.1)
    yaw = math.atan2(sin, 0.25 * math.cos(-3.0) + 0.75 * math.cos(3.1))
    assert abs(poses[1, 2] - yaw) < 1e-12 and abs(abs(yaw) - math.pi) < 0.1
    np.testing.assert_array_equal(times, [0.0, 1.0])
    np.testing.assert_array_equal(odometry[1], np.ones(3))
    slam.log_weights = np.array([0.0, -800.0])  # one particle: its own ancestry
    np.testing.assert_allclose(slam.mean_trajectory()[1], slam.trajectory()[1], atol=1e-12)


@pytest.mark.parametrize("limit", [None, 7])
def test_trajectory_reuses_its_last_walk_exactly(loop: tuple[np.ndarray, ...], limit: int | None) -> None:
    """trajectory() reuses the last walk's lineage where the new one joins it: after every scan (the
    history shifting under a limit, the particles resampling) it is the plain ancestry walk, bit for bit."""
    times, truth, odometry, ranges = (a[:90] for a in loop)
    start = tuple(float(v) for v in truth[0])
    config = RbpfConfig(particles=4, initial_pose=start, history_limit=limit, resample_threshold=1.0)
    slam = RbpfSlam(LASER, config)
    for t, odom, r in zip(times, odometry, ranges, strict=True):
        slam.process(float(t), r, odom)
        _times, poses, _odometry = slam.trajectory()
        index = slam.best_index
        walked = np.zeros((len(slam.history_poses), 3))
        for k in range(len(slam.history_poses) - 1, -1, -1):
            walked[k] = slam.history_poses[k][index]
            index = int(slam.history_parents[k][index])
        assert np.array_equal(poses, walked)
    assert slam.stats.resamples > 0 and slam._lineage is not None


def test_idle_loop_checks_wait_for_the_path(loop: tuple[np.ndarray, ...]) -> None:
    start = tuple(float(v) for v in loop[1][0])
    short = tuple(a[:120] for a in loop)

    def checks(loops: LoopClosureConfig) -> int:
        slam, _ = run_filter(short, RbpfConfig(particles=3, initial_pose=start, loop_closure=loops))
        return slam.stats.loop_checks

    every = checks(LoopClosureConfig())
    assert every > 3
    # Idle from the start: a check only where the odometry path since the last one reaches the bound.
    assert checks(LoopClosureConfig(idle_updates=0, idle_path_m=0.0)) == every
    assert 0 < checks(LoopClosureConfig(idle_updates=0, idle_path_m=1.0)) < every
    assert checks(LoopClosureConfig(idle_updates=0, idle_path_m=1e6)) == 0
    # Not idle yet: every check runs.
    assert checks(LoopClosureConfig(idle_updates=10_000, idle_path_m=1e6)) == every


def test_replay_with_a_bounded_history(loop: tuple[np.ndarray, ...]) -> None:
    times, truth, odometry, ranges = loop
    records = tuple(
        LogRecord(i + 1, float(t), r, o, p)
        for i, (t, r, o, p) in enumerate(
            zip(times[:150], ranges[:150], odometry[:150], truth[:150], strict=True)
        )
    )
    log = SlamLog("synthetic", LogFormat.SIMULATED, LASER, records)
    start = tuple(float(v) for v in truth[0])
    assert RbpfConfig().history_limit is not None  # bounded by default, for the robot
    full = replay(log, RbpfConfig(particles=3, initial_pose=start, history_limit=None))
    short = replay(log, RbpfConfig(particles=3, initial_pose=start, history_limit=4))
    assert full.slam.stats.updates > 10 and len(short.slam.history_poses) == 4
    # The last updates' records are placed the same way; the ones before the kept history fall back
    # to the odometry.
    last_kept = len(records) - 1
    np.testing.assert_allclose(short.poses[last_kept], full.poses[last_kept])
    np.testing.assert_allclose(short.poses[1], odometry[1])
    with pytest.raises(ValueError, match="history_limit"):
        RbpfConfig(history_limit=0)


def test_the_correlative_search_runs_where_it_is_due() -> None:
    # By default (search_updates=1) only at the first update and after a large odometry increment; with
    # None at every update.
    searched: list[bool] = []
    every = RbpfSlam(LASER, RbpfConfig(particles=4, search_updates=None))
    first = RbpfSlam(LASER, RbpfConfig(particles=4))
    assert first.config.search_updates == 1
    step = np.array([0.3, 0.0, 0.05])
    for slam in (every, first):
        for updates, increment in ((0, step), (1, step), (5, step), (5, np.array([1.2, 0.0, 0.0]))):
            slam.stats.updates = updates
            searched.append(slam._proposal_for(increment).search is not None)
        slam.stats.updates = 5
        searched.append(slam._proposal_for(np.array([0.0, 0.0, -0.6])).search is not None)
    assert searched == [True] * 5 + [True, False, False, True, True]
    # The search-free settings are the filter's own otherwise.
    assert first._proposal_for(step).matcher == first.config.proposal.matcher


def test_the_search_can_also_be_due_on_odometry_heading_doubt() -> None:
    # search_heading_doubt: an increment just short of both thresholds (Intel's 0.93 m turning 10 deg)
    # leaves odometry's heading as doubtful as a straight search_increment_m, and gets the search too.
    short = np.array([0.9, 0.1, 0.18])
    small = np.array([0.3, 0.0, 0.05])
    searched = []
    for doubt in (False, True):
        slam = RbpfSlam(LASER, RbpfConfig(particles=4, search_increment_rad=0.19, search_heading_doubt=doubt))
        slam.stats.updates = 5
        searched += [slam._proposal_for(increment).search is not None for increment in (short, small)]
        assert slam._proposal_for(np.array([1.0, 0.0, 0.0])).search is not None
    assert searched == [False, False, True, False]


@pytest.mark.parametrize(
    ("threshold", "inliers", "again"), [(0.5, 0.3, True), (0.5, 0.9, False), (0.0, 0.3, False)]
)
def test_an_update_the_lead_matched_poorly_without_the_search_is_proposed_again_with_it(
    loop: tuple[np.ndarray, ...],
    monkeypatch: pytest.MonkeyPatch,
    threshold: float,
    inliers: float,
    again: bool,
) -> None:
    # RbpfConfig.search_below_inliers: an update that ran without the correlative search and whose lead
    # matched fewer than that fraction of its endpoints is proposed afresh, with the search (Intel: Gauss-
    # Newton from a prior 16 deg off settles there with few endpoints explained). Each unsearched proposal
    # here is made to report `inliers` for every particle.
    import agent.slam.rbpf as rbpf_module

    real = rbpf_module.improved_proposal
    searched: list[bool] = []

    def proposal(*args: object, **kwargs: object) -> object:
        result = real(*args, **kwargs)
        config = args[6]
        assert isinstance(config, ProposalConfig)
        searched.append(config.search is not None)
        if config.search is not None:
            return result
        fraction = np.full_like(result.match.inlier_fraction, inliers)
        return dataclasses.replace(result, match=dataclasses.replace(result.match, inlier_fraction=fraction))

    monkeypatch.setattr(rbpf_module, "improved_proposal", proposal)
    times, truth, odometry, ranges = (a[:60] for a in loop)
    start = tuple(float(v) for v in truth[0])
    config = RbpfConfig(particles=4, initial_pose=start, search_below_inliers=threshold)
    slam, _estimate = run_filter((times, truth, odometry, ranges), config)
    later = searched[1:]  # the first update searches anyway (search_updates)
    assert searched[0] and slam.stats.updates >= 5
    if again:
        # Each update: the proposal without the search, then again with it.
        assert later == [False, True] * (slam.stats.updates - 1)
        assert slam.stats.searches_on_doubt == slam.stats.updates - 1
    else:
        assert later == [False] * (slam.stats.updates - 1) and slam.stats.searches_on_doubt == 0


def test_each_node_keeps_its_scan_match_information_for_the_graph(loop: tuple[np.ndarray, ...]) -> None:
    # LoopClosureConfig.edge_match_sigma_m: the graph's front-end edges from each node's own match.
    _times, truth, _odometry, _ = loop
    start = tuple(float(v) for v in truth[0])
    short = tuple(a[:120] for a in loop)
    loops = LoopClosureConfig(edge_match_sigma_m=0.1)
    slam, estimate = run_filter(short, RbpfConfig(particles=3, initial_pose=start, loop_closure=loops))
    information = np.array(slam._node_information)
    assert information.shape == (slam.stats.updates + 1, 3, 3)
    np.testing.assert_array_equal(information[0], 0.0)  # the first scan: nothing matched
    np.testing.assert_allclose(information, information.transpose(0, 2, 1), atol=1e-6)
    # The room's walls hold every matched node in every direction.
    held = np.linalg.eigvalsh(information[1:])[:, 0] > 1.0
    assert np.count_nonzero(held) >= 0.9 * (information.shape[0] - 1)
    assert absolute_trajectory_error(truth[:120], estimate) < 0.05


@pytest.mark.parametrize("shared", [0, 3])
def test_particles_of_one_lineage_share_a_distance_field_for_a_few_updates(
    loop: tuple[np.ndarray, ...], monkeypatch: pytest.MonkeyPatch, shared: int
) -> None:
    # RbpfConfig.shared_field_updates: for that many updates after a resampling, the particles drawn from
    # one parent are matched against one field (the heaviest one's map); otherwise one field per distinct
    # map: the copies of one parent share one at the update right after the resampling (their maps are
    # the same), and every particle has its own after an update that did not resample.
    import agent.slam.rbpf as rbpf_module

    real = rbpf_module.improved_proposal
    fields: list[np.ndarray] = []

    def proposal(*args: object, **kwargs: object) -> object:
        window_index = args[1]
        assert isinstance(window_index, np.ndarray)
        fields.append(window_index.copy())
        return real(*args, **kwargs)

    monkeypatch.setattr(rbpf_module, "improved_proposal", proposal)
    times, truth, odometry, ranges = (a[:150] for a in loop)
    config = RbpfConfig(
        particles=8,
        initial_pose=tuple(float(v) for v in truth[0]),
        resample_threshold=0.9,
        shared_field_updates=shared,
    )
    slam = RbpfSlam(LASER, config)
    lineage: np.ndarray | None = None  # the parents of the last resampling
    since = 0  # updates since it
    shared_later = 0  # updates that shared fields between particles whose maps differ
    for t, odom, r in zip(times, odometry, ranges, strict=True):
        before = len(fields)
        step = slam.process(float(t), r, odom)
        if step.kind is not StepKind.UPDATED:
            continue
        assert len(fields) == before + 1
        windows = fields[-1]
        if lineage is not None and 0 < since <= max(shared, 1):
            # One field per lineage, exactly.
            same_window = windows[:, None] == windows[None, :]
            np.testing.assert_array_equal(same_window, lineage[:, None] == lineage[None, :])
            shared_later += since > 1 and np.unique(lineage).size < config.particles
        elif lineage is not None and since > 0:
            assert np.unique(windows).size == config.particles  # each its own map, each its own field
        if step.resampled:
            lineage = np.unique(slam._groups, return_inverse=True)[1].reshape(-1)
            since = 0
        since += 1
    assert slam.stats.resamples >= 3
    assert (shared_later > 0) == (shared > 1)


def test_a_lineage_field_is_made_of_its_heaviest_particle_s_map() -> None:
    slam = RbpfSlam(LASER, RbpfConfig(particles=6, shared_field_updates=5))
    slam._field_lineage = np.array([0, 0, 1, 1, 1, 2])
    slam._lineage_age = 2
    slam.log_weights = np.array([-3.0, -1.0, -2.0, 0.0, 0.0, -5.0])
    owners, windows = slam._field_owners()
    # Lineage 1's two heaviest weigh the same: the first of them.
    np.testing.assert_array_equal(owners, [1, 3, 5])
    np.testing.assert_array_equal(windows, [0, 0, 1, 1, 1, 2])
    slam._lineage_age = 5  # past shared_field_updates: a field per distinct map
    slam._groups = np.array([0, 1, 2, 2, 3, 4])
    owners, windows = slam._field_owners()
    np.testing.assert_array_equal(owners, [0, 1, 2, 4, 5])
    np.testing.assert_array_equal(windows, [0, 1, 2, 2, 3, 4])
