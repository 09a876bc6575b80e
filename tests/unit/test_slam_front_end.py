"""The scan match's front end as ``[slam]`` keys (issue 20): what ``vlp-agent eval slam`` measured for a
source is what the agent's filter runs when its config says so, and the defaults are the robot's own
laser's (the URG logs: ``eval slam --format breezyslam``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from agent.commands.eval_slam import (
    MATCH_MIN_TRANSLATION_INFORMATION,
    NORMAL_RADIUS_PER_M,
    NORMAL_THICKNESS_M,
    front_end,
    log_config,
    log_odds_model,
    log_proposal,
)
from agent.config import MountConfig, SlamConfig, parse_config
from agent.runtime.mapper import RbpfMapper, front_end_noise, front_end_proposal
from agent.slam.motion import OdometryNoise
from agent.slam.proposal import ProposalConfig
from agent.slam.simlog import MOTION_NOISE
from drivers.errors import ConfigError
from drivers.samples import Scan
from tests.helpers import REAL_ROBOT

LASER = REAL_ROBOT + '[laser]\nbackend = "urg"\nurl = "/dev/ttyACM0"\n'


def test_the_defaults_are_the_filters_and_the_urg_logs() -> None:
    assert front_end("breezyslam") == SlamConfig()
    assert front_end_proposal(SlamConfig(), ProposalConfig()) == ProposalConfig()
    assert front_end_noise(SlamConfig()) == OdometryNoise()


def test_eval_slam_sets_each_source_through_the_agents_function() -> None:
    radish = log_proposal("radish", ProposalConfig())
    assert radish.matcher.min_inliers == 10 and radish.matcher.min_inlier_fraction == 0.0
    assert radish.keep_better_start and radish.along_surface_weight == 0.0
    assert (
        radish.failed_match_draw == "grid"
        and log_proposal("breezyslam", ProposalConfig()).failed_match_draw == "motion"
    )
    # One iteration fewer in the wide stages for the radish logs' proposal match (and the direction check,
    # which matches with it); the loop closure's matcher keeps its own (eval_slam.MATCH_ITERATIONS).
    assert [n for _bound, n in radish.matcher.stages] == [3, 3, 4]
    assert [b for b, _n in radish.matcher.stages] == [b for b, _n in ProposalConfig().matcher.stages]
    assert log_proposal("breezyslam", ProposalConfig()).matcher.stages == ProposalConfig().matcher.stages
    assert SlamConfig().match_iterations == (4, 4, 4)
    simulated = log_proposal("simulated", ProposalConfig())
    assert simulated.degenerate_noise_scale == 0.3
    assert simulated.matcher == ProposalConfig().matcher and not simulated.keep_better_start
    assert front_end_noise(front_end("simulated")) == MOTION_NOISE
    assert front_end_noise(front_end("radish")) == OdometryNoise()


def test_the_keys_load_and_reach_the_filter() -> None:
    text = LASER + (
        "[slam]\nalong_surface_weight = 0.0\ndegenerate_noise_scale = 0.3\nmatch_min_inliers = 10\n"
        'match_min_inlier_fraction = 0.0\nmatch_both_starts = true\nfailed_match_draw = "grid"\n'
        "miss_log_odds = -0.1\nsearch_increment_rad = 0.19\nsearch_yaw_rad = 0.45\n"
        "search_below_inliers = 0.5\nshared_field_updates = 5\n"
        "odometry_noise = [0.03, 0.05, 0.03, 0.05]\nfree_margin_m = 0.1\nreversal_ratio = 0.5\n"
        "match_gate_residual = true\nprocess = false\n"
        f"normal_radius_per_m = {NORMAL_RADIUS_PER_M['radish']}\n"
        f"normal_thickness_m = {NORMAL_THICKNESS_M['radish']}\n"
        f"match_min_translation_information = {MATCH_MIN_TRANSLATION_INFORMATION['radish']}\n"
        "match_medial_window_cells = 3\ngrid_phase_from_walls = false\nmatch_iterations = [3, 3, 4]\n"
    )
    config = parse_config(text).slam
    radish = dataclasses.replace(
        front_end("radish"), degenerate_noise_scale=0.3, match_gate_residual=True, match_medial_window_cells=3
    )
    assert [getattr(config, f) for f in _FRONT_END_KEYS] == [getattr(radish, f) for f in _FRONT_END_KEYS]
    assert front_end_noise(config) == MOTION_NOISE

    mapper = RbpfMapper(config, MountConfig(), lambda t_ns: (0.0, 0.0, 0.0))
    step = mapper.update(_room_scan(), (0.0, 0.0, 0.0))
    assert step.kind == "first"
    built = mapper.slam.config
    radish_proposal = log_proposal("radish", ProposalConfig())
    assert built.proposal == dataclasses.replace(
        radish_proposal,
        degenerate_noise_scale=0.3,
        matcher=dataclasses.replace(radish_proposal.matcher, gate_on_residual=True, medial_window_cells=3),
    )
    # The filter's distance fields take the straight-wall test from the matcher's key.
    field, _windows = mapper.slam._field(np.zeros((1, 3)), np.array([[1.0, 0.0]]))
    assert field.medial_window_cells == 3
    assert built.noise == MOTION_NOISE
    assert built.free_margin_m == 0.1
    assert not built.grid_phase_from_walls and built.grid.phase_m == (0.0, 0.0)
    assert SlamConfig().grid_phase_from_walls and log_config("radish").grid_phase_from_walls
    assert built.log_odds == log_odds_model("radish") and built.search_increment_rad == 0.19
    assert built.search_below_inliers == 0.5 and log_config("breezyslam").search_below_inliers == 0.0
    assert built.shared_field_updates == 5 and log_config("radish").shared_field_updates == 20
    assert built.proposal.search is not None and built.proposal.search.yaw_range_rad == 0.45
    assert built.reversal_ratio == 0.5 == front_end("radish").reversal_ratio
    assert SlamConfig().free_margin_m is None and front_end("breezyslam").free_margin_m is None
    assert SlamConfig().reversal_ratio is None and front_end("breezyslam").reversal_ratio is None


_FRONT_END_KEYS = (
    "along_surface_weight",
    "degenerate_noise_scale",
    "match_min_inliers",
    "match_min_inlier_fraction",
    "match_both_starts",
    "match_gate_residual",
    "failed_match_draw",
    "miss_log_odds",
    "search_increment_rad",
    "search_yaw_rad",
    "search_below_inliers",
    "reversal_ratio",
    "normal_radius_per_m",
    "normal_thickness_m",
    "match_min_translation_information",
    "match_medial_window_cells",
    "match_iterations",
)


@pytest.mark.parametrize(
    ("line", "key"),
    [
        ("along_surface_weight = 1.5", "slam.along_surface_weight"),
        ("degenerate_noise_scale = 0.0", "slam.degenerate_noise_scale"),
        ("match_min_inliers = 0", "slam.match_min_inliers"),
        ("match_min_inlier_fraction = -0.1", "slam.match_min_inlier_fraction"),
        ('match_both_starts = "yes"', "slam.match_both_starts"),
        ('match_gate_residual = "yes"', "slam.match_gate_residual"),
        ('failed_match_draw = "anywhere"', "slam.failed_match_draw"),
        ("miss_log_odds = 0.1", "slam.miss_log_odds"),
        ("search_increment_rad = 0", "slam.search_increment_rad"),
        ("search_yaw_rad = 4.0", "slam.search_yaw_rad"),
        ("search_below_inliers = 1.5", "slam.search_below_inliers"),
        ("shared_field_updates = -1", "slam.shared_field_updates"),
        ("shared_field_updates = 2.5", "slam.shared_field_updates"),
        ("odometry_noise = [0.1, 0.2]", "slam.odometry_noise"),
        ("odometry_noise = [0.1, -0.2, 0.1, 0.2]", "slam.odometry_noise"),
        ("free_margin_m = -0.01", "slam.free_margin_m"),
        ('grid_phase_from_walls = "yes"', "slam.grid_phase_from_walls"),
        ("reversal_ratio = 0", "slam.reversal_ratio"),
        ("reversal_ratio = 1.5", "slam.reversal_ratio"),
        ("normal_radius_per_m = -0.1", "slam.normal_radius_per_m"),
        ("normal_thickness_m = 0", "slam.normal_thickness_m"),
        ("match_min_translation_information = -1", "slam.match_min_translation_information"),
        ("match_medial_window_cells = -1", "slam.match_medial_window_cells"),
        ("match_medial_window_cells = 1.5", "slam.match_medial_window_cells"),
        ("match_iterations = [3, 3]", "slam.match_iterations"),
        ("match_iterations = [3, 0, 4]", "slam.match_iterations"),
        ("match_iterations = [3, 2.5, 4]", "slam.match_iterations"),
        ("match_iterations = [3, 3, 21]", "slam.match_iterations"),
    ],
)
def test_a_bad_value_names_its_key(line: str, key: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(LASER + f"[slam]\n{line}\n")
    assert info.value.key == key


def _room_scan() -> Scan:
    """One URG sweep in a 4 m x 3 m room, the laser in its middle."""
    angles = np.linspace(-2.0, 2.0, 400)
    ranges = np.minimum(
        2.0 / np.maximum(np.abs(np.cos(angles)), 1e-6), 1.5 / np.maximum(np.abs(np.sin(angles)), 1e-6)
    )
    return Scan(
        np.round(ranges * 1000.0).astype(np.int32), -2.0, float(angles[1] - angles[0]), 20, 5600, 0, 0
    )
