"""The pose graph's front-end edges: how much of a match's departure from odometry widens an edge
(``LoopClosureConfig.correction_odometry_sigmas``)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from agent.slam.grid import surface_normals
from agent.slam.loops import LoopClosureConfig, LoopConstraint, chain_poses, edge_covariances, optimize_graph
from agent.slam.matcher import DistanceField, MatcherConfig, line_information, match_with_residuals
from agent.slam.motion import OdometryNoise
from agent.slam.pose import between, wrap_angle
from agent.slam.rbpf import voxel_indices
from tests.unit.test_slam_loops import _square
from tests.unit.test_slam_matcher import GEOMETRY, RES, _mapped_corridor


def test_a_departure_the_odometry_noise_explains_does_not_draw_a_loop_correction() -> None:
    # The front end's heading drifts 0.3 deg a metre; at the first corner (edge 10: a 90 deg turn over
    # 1 m) the wheels slipped 10 deg, well inside what the motion model allows a 90 deg turn (~29 deg),
    # and the match got the turn right (within its drift). A true loop 0 -> end.
    true_motions = _square()
    front_end = true_motions.copy()
    front_end[1:, 2] += math.radians(0.3)
    odometry = true_motions.copy()
    odometry[10, 2] += math.radians(10.0)
    path = chain_poses(np.zeros(3), front_end)
    truth = chain_poses(np.zeros(3), true_motions)
    n = path.shape[0]
    loops = [LoopConstraint(0, n - 1, between(truth[0], truth[n - 1]), 1.0)]
    sigmas = OdometryNoise().sigmas(odometry)

    def kink(poses: np.ndarray) -> float:
        # The worst edge's heading error after the optimisation.
        moved = between(poses[:-1], poses[1:])
        return float(np.max(np.abs(wrap_angle(moved[:, 2] - true_motions[1:, 2]))))

    whole = optimize_graph(path, front_end, loops, LoopClosureConfig(), odometry_motions=odometry)
    config = LoopClosureConfig(correction_odometry_sigmas=1.0)
    beyond = optimize_graph(path, front_end, loops, config, odometry_motions=odometry, odometry_sigmas=sigmas)
    # The whole departure widens edge 10 to 5 deg: a quarter of the loop's 12 deg of heading goes there.
    assert kink(whole.poses) > math.radians(2.5)
    # Beyond the odometry's noise there is none: the correction is spread, every edge within 0.3 deg.
    assert kink(beyond.poses) < math.radians(0.35)
    # Without the sigmas handed in the option changes nothing.
    same = optimize_graph(path, front_end, loops, config, odometry_motions=odometry)
    np.testing.assert_allclose(same.poses, whole.poses, atol=1e-9)


def test_a_departure_beyond_the_odometry_noise_still_widens_its_edge() -> None:
    # A straight run of 1 m steps (the model allows ~11 deg of heading each); at edge 10 the match turned
    # the robot 40 deg against its wheels: 29 deg beyond one sigma, the edge is still the loose one.
    true_motions = np.tile(np.array([1.0, 0.0, 0.0]), (21, 1))
    true_motions[0] = 0.0
    front_end = true_motions.copy()
    front_end[10, 2] += math.radians(40.0)
    path = chain_poses(np.zeros(3), front_end)
    truth = chain_poses(np.zeros(3), true_motions)
    loops = [LoopConstraint(0, 20, between(truth[0], truth[20]), 1.0)]
    config = LoopClosureConfig(correction_odometry_sigmas=1.0)
    result = optimize_graph(
        path,
        front_end,
        loops,
        config,
        odometry_motions=true_motions,
        odometry_sigmas=OdometryNoise().sigmas(true_motions),
    )
    assert np.hypot(*(result.poses[:, :2] - truth[:, :2]).T).max() < 0.1


def test_the_key_loads_and_reaches_the_filters_graph() -> None:
    from agent.commands.eval_slam import front_end, log_config
    from agent.config import SlamConfig, parse_config
    from agent.runtime.mapper import front_end_filter
    from agent.slam.proposal import ProposalConfig
    from drivers.errors import ConfigError
    from tests.helpers import REAL_ROBOT

    laser = REAL_ROBOT + '[laser]\nbackend = "urg"\nurl = "/dev/ttyACM0"\n'
    config = parse_config(laser + "[slam]\nloop_correction_odometry_sigmas = 2.0\n").slam
    loop = front_end_filter(config, ProposalConfig())["loop_closure"]
    assert loop == LoopClosureConfig(correction_odometry_sigmas=2.0)
    assert front_end_filter(SlamConfig(), ProposalConfig())["loop_closure"] == LoopClosureConfig()
    assert front_end("radish").loop_correction_odometry_sigmas is None
    assert front_end("breezyslam").loop_correction_odometry_sigmas is None
    radish = log_config("radish")
    assert radish.loop_closure == LoopClosureConfig()
    assert log_config("radish", loop_closure=False).loop_closure is None
    with pytest.raises(ConfigError):
        parse_config(laser + "[slam]\nloop_correction_odometry_sigmas = -1\n")


def test_an_edge_from_the_lines_information_is_loose_along_a_corridor_and_tight_across() -> None:
    """A corridor whose walls are mapped on alternate metres, matched point to line. Its endpoints beyond
    ~3 m have no surface normal (the beams land more than the normals' neighbourhood apart on the walls, as
    ACES's 1 deg beams do at grazing angles): each is matched point to point and pulled along the wall
    towards the mapped patches, and the match's Σ J Jᵀ counts that as information along the corridor. The
    lines' information (the endpoints with a normal only, ``matcher.line_information``) has none there;
    the edge built from it (``edge_information`` "normals") is loose along the corridor, tight across it
    and in heading."""
    scan, rect, obstacles = _mapped_corridor()
    x_cells = rect.origin_m(GEOMETRY)[0] + (np.arange(obstacles.shape[2]) + 0.5) * RES
    obstacles[0][:, (np.floor(x_cells) % 2) == 1] = False
    field = DistanceField.from_obstacles(obstacles, rect.origin_m(GEOMETRY), RES, 0.6)
    kept = voxel_indices(scan.hit_xy, 0.1, 200)
    points = scan.hit_xy[kept]
    normals = surface_normals(scan.hit_xy, kept)
    has = np.hypot(normals[:, 0], normals[:, 1]) > 0.5
    assert 0.3 < has.mean() < 0.9
    config = MatcherConfig()
    ix = np.zeros(1, dtype=np.int64)
    start = np.array([[0.3, 0.05, 0.02]])
    prior = np.diag([2.0, 2.0, 0.0])
    result, res = match_with_residuals(
        field, ix, points, start, config, prior, normals_xy=normals, along_weight=0.0
    )
    bound = config.stages[-1][0]
    lines = line_information(res, normals, result.poses, bound)[0]
    assert result.information[0, 0, 0] > 2.0  # the patches' pulls: "information" along the corridor
    assert lines[0, 0] < 0.5 and lines[1, 1] > 20.0 and lines[2, 2] > 20.0
    # Where every endpoint has a normal it is the point-to-line match's own Σ J Jᵀ over its inliers.
    alone, alone_res = match_with_residuals(
        field, ix, points[has], start, config, prior, normals_xy=normals[has], along_weight=0.0
    )
    inlier = (alone_res.gate < bound)[0]
    jx, jy, rx, ry = alone_res.jx[0], alone_res.jy[0], alone_res.rx[0], alone_res.ry[0]
    jac = np.stack([jx, jy, jy * rx - jx * ry], axis=1)[inlier]
    np.testing.assert_allclose(
        line_information(alone_res, normals[has], alone.poses, bound)[0], jac.T @ jac, rtol=1e-6, atol=1e-6
    )
    # The edge into node 1 (heading +90 deg from node 0: the corridor along node 0's y).
    edge = LoopClosureConfig(edge_match_sigma_m=0.1)
    motions = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, math.pi / 2]])

    def sigmas(information: np.ndarray) -> np.ndarray:
        return np.sqrt(np.diag(edge_covariances(motions, np.stack([np.zeros((3, 3)), information]), edge)[0]))

    by_lines, by_match = sigmas(lines), sigmas(result.information[0])
    # Loose along the corridor (up to ``edge_max_sigma``), a few centimetres across it and ~1 deg in heading
    # (the normals' endpoints lie within ~3 m, mostly ahead: the two are correlated).
    assert by_lines[1] > 0.25 and by_lines[0] < 0.06 and by_lines[2] < 0.02
    assert by_match[1] < by_lines[1] / 4  # the match's own: nearly as tight along the corridor as across


def test_an_edge_from_its_match_can_sit_on_its_departure_from_odometry() -> None:
    """``edge_departure_floor``: the match's covariance is added to the edge's sigmas as the odometry
    departure widened them (``correction_share``), not to ``motion_sigma``."""
    motions = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    information = np.zeros((3, 3, 3))
    information[1:] = np.diag([1e8, 1e8, 1e8])  # a sure match: its covariance next to nothing
    floor = np.array([[0.03, 0.03, 0.01], [0.03, 0.03, 0.2]])  # edge 2: the match turned 0.4 rad
    config = LoopClosureConfig(edge_match_sigma_m=0.1)
    plain = edge_covariances(motions, information, config)
    widened = edge_covariances(motions, information, config, floor)
    np.testing.assert_allclose(np.sqrt(np.diag(plain[1])), config.motion_sigma, rtol=1e-4)
    np.testing.assert_allclose(np.sqrt(np.diag(widened[1])), floor[1], rtol=1e-4)
    odometry = motions.copy()
    odometry[2, 2] = 0.4
    path = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    loops = [LoopConstraint(0, 2, np.array([2.0, 0.0, 0.1]), 1.0)]
    on = replace(config, edge_departure_floor=True)
    spread = optimize_graph(
        path, motions, loops, config, odometry_motions=odometry, node_information=information
    )
    onto_turn = optimize_graph(
        path, motions, loops, on, odometry_motions=odometry, node_information=information
    )
    # The loop's 0.1 rad goes on the edge whose match departed from odometry, not a third on each edge
    # (and on the loop factor).
    turn = [float(wrap_angle(between(r.poses[1], r.poses[2])[2])) for r in (spread, onto_turn)]
    assert turn[0] < 0.04 and turn[1] > 0.09


def test_the_graph_keys_load_and_reach_the_filters_graph() -> None:
    from agent.config import SlamConfig, parse_config
    from agent.runtime.mapper import front_end_filter
    from agent.slam.proposal import ProposalConfig
    from drivers.errors import ConfigError
    from tests.helpers import REAL_ROBOT

    laser = REAL_ROBOT + '[laser]\nbackend = "urg"\nurl = "/dev/ttyACM0"\n'
    config = parse_config(laser + "[slam]\nloop_accept_graph_chi2 = 30\n").slam
    loop = front_end_filter(config, ProposalConfig())["loop_closure"]
    assert loop == LoopClosureConfig(accept_graph_chi2=30.0)
    off = parse_config(laser + "[slam]\nloop_accept_graph_chi2 = 0\n").slam
    assert front_end_filter(off, ProposalConfig())["loop_closure"].accept_graph_chi2 is None
    assert parse_config(laser).slam.loop_accept_graph_chi2 == LoopClosureConfig().accept_graph_chi2 == 16.3
    assert front_end_filter(SlamConfig(), ProposalConfig())["loop_closure"] == LoopClosureConfig()
    with pytest.raises(ConfigError):
        parse_config(laser + "[slam]\nloop_accept_graph_chi2 = -1\n")
    snaps = parse_config(laser + "[slam]\nloop_snap_forward_m = 0.3\n").slam
    assert front_end_filter(snaps, ProposalConfig())["loop_closure"].snap_forward_m == 0.3
    none = parse_config(laser + "[slam]\nloop_snap_forward_m = 0\n").slam
    assert front_end_filter(none, ProposalConfig())["loop_closure"].snap_forward_m is None
    assert parse_config(laser).slam.loop_snap_forward_m == LoopClosureConfig().snap_forward_m == 0.15
    with pytest.raises(ConfigError):
        parse_config(laser + "[slam]\nloop_snap_forward_m = -0.1\n")


def test_the_final_optimisation_key_loads_and_reaches_the_filter() -> None:
    from agent.commands.eval_slam import front_end
    from agent.config import parse_config
    from agent.runtime.mapper import front_end_filter
    from agent.slam.proposal import ProposalConfig
    from agent.slam.scan_chain import ScanChainConfig
    from drivers.errors import ConfigError
    from tests.helpers import REAL_ROBOT

    laser = REAL_ROBOT + '[laser]\nbackend = "urg"\nurl = "/dev/ttyACM0"\n'
    on = parse_config(laser).slam
    assert on.loop_final_scan_chain is True
    assert front_end_filter(on, ProposalConfig())["loop_closure"].final_scan_chain == ScanChainConfig()
    off = parse_config(laser + "[slam]\nloop_final_scan_chain = false\n").slam
    assert front_end_filter(off, ProposalConfig())["loop_closure"].final_scan_chain is None
    with pytest.raises(ConfigError):
        parse_config(laser + '[slam]\nloop_final_scan_chain = "yes"\n')
    # eval slam: on for the recorded logs, off for the simulated robot.
    assert front_end("radish").loop_final_scan_chain and front_end("breezyslam").loop_final_scan_chain
    assert not front_end("simulated").loop_final_scan_chain
