"""``vlp-agent eval slam``: run the SLAM filter on a recorded laser log, or on the simulated robot, as fast
as it goes.

Prints the speed (per filter update, wall time, real-time factor, peak memory) and, for logs that carry
reference poses (radish), the relative-pose error against them (``reference/slam.md`` §1.5, every pair of
consecutive reference poses); writes the map as ROS map_server PGM + YAML, a PNG of it, and a PNG of the
trajectory over the map.

With ``--world`` the log is made by driving the simulated robot along the world's route
(``agent.slam.simlog``: scans with the world's laser noise, wheel odometry with its errors, optionally VLP
fixes from rendered frames through the VLP pipeline, ``agent.commands.sim_fixes``), and the report adds the
absolute trajectory error against the simulation's truth.
"""

from __future__ import annotations

import argparse
import math
import resource
import sys
import textwrap
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from agent.commands.args import dumps_json, positive_seconds
from agent.commands.eval_slam_options import (
    add_research_options,
    apply_research_options,
    check_research_options,
)

if TYPE_CHECKING:
    from agent.slam.metrics import RelativePoseError

FORMATS = ("breezyslam", "radish", "mcap")
# Usable range per format: the URG-04LX reaches 5.6 m; the radish SICK logs reach far, but beams longer
# than this add little and cost window area.
DEFAULT_MAX_RANGE_M = {"breezyslam": 5.5, "radish": 15.0, "simulated": 5.5, "mcap": 5.5}
# Weight of an endpoint's offset along its surface in the scan match (ProposalConfig.along_surface_weight):
# point to line for the radish SICK logs (1 deg beams out to 15 m sample far walls sparsely and at grazing
# angles, and those pull point-to-point matches along themselves: Intel 0.045-0.058 m / 0.9-1.5 deg
# instead of 0.056-0.067 m / 1.1-2.0 deg over three seeds), point to point for the URG logs and the
# simulated robot (exp1 closes its loop for 3 seeds in 6, none with point to line; the office's ATE is
# lower). docs/slam.md has the runs.
# The span_* relations: pairs of scans this many apart (tens of metres on the radish logs).
DEFAULT_SPAN_SCANS = 50
DEFAULT_ALONG_SURFACE_WEIGHT = {"breezyslam": 1.0, "radish": 0.0, "simulated": 1.0, "mcap": 1.0}
# Formats with one scan per ~1 m (the radish logs): there a failed match's fallback to the motion model
# scatters a particle by ~6 deg of heading (slam_gmapping's noise over 1 m) and its map is built there, so
# a match is trusted on 10 endpoints within the matcher's last bound whatever their share of the scan (at a
# corner half the scan sees past the map); and the correlative search, which runs at nearly every update
# there, gives each particle a second start beside the prior's, the lower truncated energy winning
# (Intel seeds 0-5: 2 -> 5 of 6 within 0.15 m). The URG logs and the simulated robot update every 0.25 m
# and keep the filter's defaults: with these, exp1's loop no longer closed for seed 0 and the office's
# seed 0 went from 2.6 to 3.8 cm. docs/slam.md, "Scan matching". A particle whose match fails is drawn near
# the odometry prediction, where its weight was taken, not from the whole motion model (~13 deg of heading
# over 1 m: Intel seed 2, 1.47 -> 0.14 m; exp1's loop closed 2 of 6 seeds with it instead of 5): "The
# filter", a failed match.
SPARSE_SCAN_FORMATS = ("radish",)
# ProposalConfig.degenerate_noise_scale per format: the simulated robot's motion model (simlog.MOTION_NOISE)
# is three to ten times its odometry's real error, and along the office's corridors, where the scans say
# little about the distance driven, every draw took a step of that spread that no weight could judge (the
# matched step length erred 0.2-0.7 cm per 0.25 m update, odometry's 0.05-0.19 cm). With 0.3 of that spread
# where the scan does not hold the pose, office seeds 8-23 (not tuned on) went from mean 3.51 to 2.86 cm,
# 9 to 4 of 16 over 3 cm; seeds 0-7 from 2.63 to 2.98 (docs/slam.md, "Scan matching"). The logs keep the
# paper's draw (1): on the radish logs 0.15 took ACES from 2 to 3 of 6 seeds within 0.15 m (mean 0.186 ->
# 0.149 m) and Intel's 50-record spans to 6 of 6 within 0.21 m, but ACES seed 5, Intel seeds 1 and 3 and
# FR079 seed 0 (0.197 -> 0.318 m) got worse, and 0.3 / 0.5 moved the losses to other seeds: a draw
# (docs/slam.md, "Open problems", ACES; ``eval slam --degenerate-noise-scale K`` to run it).
DEGENERATE_NOISE_SCALE = {"breezyslam": 1.0, "radish": 1.0, "simulated": 0.3, "mcap": 1.0}
# RbpfConfig.free_margin_m per format (None: half a cell, every format). 0.1 m took the simulated office
# from mean 2.90 to 1.61 cm (7 to 1 of 24 seeds over 3 cm), but only because its walls all lie on the 5 cm
# grid's cell boundaries: with the walls a quarter cell or half a cell off them it did worse than half a
# cell (seeds 0-7 mean 2.54 / 2.15 cm against 2.05 / 0.82), and exp1 closed its loop for 3 of 6 seeds
# against 5 (docs/slam.md, "Open problems"): a real building's walls fall anywhere in a cell.
FREE_MARGIN_M: dict[str, float | None] = {"breezyslam": None, "radish": None, "simulated": None, "mcap": None}

# The log-odds a swept (free) cell loses per scan (grid.LogOddsModel.miss; the filter's default -0.4) per
# format. The radish logs' 1 deg beams reach a corridor's walls at grazing angles: a wall cell is a hit
# for the one or two scans that see it side-on and is passed through by the many that look along the
# corridor (a pose a few centimetres off puts their beams across it), so at -0.4 one hit outlived two
# misses and ACES's corridor walls went free; the match then slid along the corridor to the nearest
# remaining obstacle (0.2-0.45 m per update in the inner corridors, the same updates at every seed). At
# -0.1 one hit outlives four misses, two hits twelve (GMapping keeps a cell as an obstacle at 10 % hits
# among its visits). ACES seeds 0 / 1: ate_aligned_m 0.278 / 0.253 -> 0.169 / 0.111 m (docs/slam.md,
# "Measurements"). The URG logs and the simulated robot (0.35 deg beams, 0.25 m updates) keep -0.4.
# The correlative search on the SPARSE_SCAN_FORMATS logs also runs at every update a turn triggers (just
# under the 0.2 rad angular update gate; the default is 0.5 rad): FR079's odometry turns 10-22 deg off
# GMapping's within single 0.2 rad updates while the robot turns on the spot (records 771-819), beyond
# Gauss-Newton's reach from the prior, and the whole building after was folded by 45 deg. FR079 seed 0
# ate_aligned_m 7.68 -> 3.59 m (GMapping 3.58 m). Its yaw window there is +-0.45 rad instead of 0.2: the
# same on FR079, Intel seeds 0 / 1 0.114 / 0.067 m against 0.080 / 0.167 with 0.2 (0.127 / 0.108 before
# either), ACES seeds 0 / 1 0.278 / 0.121 against 0.183 / 0.123; docs/slam.md, Measurements.
SPARSE_SEARCH_INCREMENT_RAD = 0.19
SPARSE_SEARCH_YAW_RAD = 0.45
# ... and again at an update that ran without it where the leading particle's match explained fewer than
# half its endpoints (RbpfConfig.search_below_inliers): Intel's 0.93 m step turning 10 deg at record 890
# (seed 4) is short of both thresholds, and Gauss-Newton from the prior settled 16 deg off. Fires 1-2
# times a run on Intel, 1-5 on FR079, once in 12 ACES seeds. Intel seeds 0-11: ate_aligned_m within 0.15 m
# at 12 of 12 (11 without), the 50-record spans within 0.21 m at 11 of 12 (9), worst 0.220 m (0.256);
# docs/slam.md, Measurements. The URG logs (exp1: 4 of 6 loops closed with it, 6 without) and the
# simulated robot, updating every 0.25 m, keep it off.
SPARSE_SEARCH_BELOW_INLIERS = 0.5
MISS_LOG_ODDS = {"breezyslam": -0.4, "radish": -0.1, "simulated": -0.4, "mcap": -0.4}
# RbpfConfig.reversal_ratio per format (None: off). The radish logs' odometry is rebuilt from the logs'
# increments without their sign: FR079's reference drives backwards in 249 steps, its odometry in 2 (it
# drives on forward), 8.7 m in all, 3.1 m of it at records 1372-1400, where the robot backs out of a room
# into the corridor and the match, 0.6 m per update from the prediction, followed the odometry: the rooms
# east of there were mapped 5-10 m south. The lead particle's match from the reversed prediction has a
# truncated energy 0.07-0.3 of the forward one's at the true reversals there (0.69 or more at every update
# of the whole log without a backward step of the reference's, and a false reversal costs twice the
# step), hence 0.5; the check runs only after a standstill (rbpf.REVERSAL_WINDOW_M). FR079 seed 0
# ate_aligned_m 3.586 -> 0.197 m. Wheel odometry (the URG logs, the simulated robot, a recording) knows
# its sign. docs/slam.md, "Scan matching".
REVERSAL_RATIO: dict[str, float | None] = {"breezyslam": None, "radish": 0.5, "simulated": None, "mcap": None}
# The pose graph's front-end edges widened only by the match's departure from odometry beyond K of the
# motion model's sigmas (``[slam] loop_correction_odometry_sigmas``). Unset for every source: K = 1 on the
# radish logs (their odometry is rebuilt and as bad as the model says) takes Intel's 50-record relations
# to 6 of 6 seeds within 0.21 m but ACES seed 1 from 0.121 to 0.186 m; K = 0.5 folds Intel seed 3
# (0.709 m), K = 1.5 puts seed 4 at 0.289 m and ACES seed 1 at 0.208 m (docs/slam.md, "Loop closure").
LOOP_CORRECTION_ODOMETRY_SIGMAS: dict[str, float | None] = {
    "breezyslam": None,
    "radish": None,
    "simulated": None,
    "mcap": None,
}
# MatcherConfig.gate_on_residual per format ([slam] match_gate_residual; it acts only point to line, the
# radish logs'). Off everywhere: on ACES it takes the inner corridors' along-track shortening at some
# records (seed 0 without loop closure, record 300: -0.39 -> -0.13 m) but not others, and the runs it
# changes are a draw: ACES seeds 0-5 0.189 / 0.141 / 0.244 / 0.201 / 0.195 / 0.250 m against 0.190 / 0.121
# / 0.176 / 0.218 / 0.240 / 0.207 (docs/slam.md, "Open problems", ACES).
MATCH_GATE_RESIDUAL = {"breezyslam": False, "radish": False, "simulated": False, "mcap": False}
# The scan's surface normals per format (ProposalConfig.normal_radius_per_m / normal_thickness_m, [slam]
# normal_radius_per_m / normal_thickness_m; they act only point to line, the radish logs'), and the
# degeneracy-aware match steps (MatcherConfig.min_translation_information, [slam]
# match_min_translation_information; 0 off). The fixed 0.25 m and off everywhere: on ACES, normals at 0.1 x
# range and 3 cm with the steps at 2 gave seeds 0-5 0.126 / 0.201 / 0.150 / 0.141 / 0.208 / 0.209 m
# against 0.190 / 0.121 / 0.176 / 0.218 / 0.240 / 0.207, and Intel seeds 0 / 1 0.085 / 0.081 m against
# 0.074 / 0.075; the steps alone at 2: ACES 0.184 / 0.201 / 0.131 / 0.109 / 0.171 / 0.173 m, Intel seeds 0-5
# 0.127 / 0.130 / 0.168 / 0.152 / 0.167 / 0.147 m against 0.074 / 0.075 / 0.079 / 0.069 / 0.117 / 0.079
# (docs/slam.md, "Scan matching", *Normals at range*).
NORMAL_RADIUS_PER_M = {"breezyslam": 0.0, "radish": 0.0, "simulated": 0.0, "mcap": 0.0}
NORMAL_THICKNESS_M = {"breezyslam": 0.015, "radish": 0.015, "simulated": 0.015, "mcap": 0.015}
MATCH_MIN_TRANSLATION_INFORMATION = {"breezyslam": 0.0, "radish": 0.0, "simulated": 0.0, "mcap": 0.0}
# MatcherConfig.medial_window_cells per format ([slam] match_medial_window_cells; eval slam
# --medial-window-cells W): a wall's straightness judged over the 7 x 7 cells around it (3), so that a wall on
# a cell boundary mapped in patches is measured to the boundary. Off everywhere: it cures the office's walls,
# all on 5 cm boundaries (seeds 0-23 mean 2.90 -> 1.02 cm, 7 -> 2 of 24 over 3 cm), and hurts walls anywhere
# else (the office moved half a cell, seeds 0 / 16 / 1: 0.85 / 0.86 / 0.88 -> 3.06 / 3.17 / 3.10 cm), exp1's
# loop (3 of 6 closed), Intel seeds 0 / 3, ACES seed 1 and FR079 (0.197 -> 0.464 m). docs/slam.md, "Scan
# matching", *Walls on cell boundaries*.
MATCH_MEDIAL_WINDOW_CELLS = {"breezyslam": 0, "radish": 0, "simulated": 0, "mcap": 0}
# The proposal match's Gauss-Newton iterations per stage ([slam] match_iterations): 3 / 3 / 4 for the radish
# logs, 4 / 4 / 4 elsewhere. A wide stage never converges within its count (its steps halve an iteration,
# and the next stage starts with a step larger than the last one taken), so its last iteration buys little:
# on Intel seeds 0-5 3 / 3 / 4 gave 0.066-0.077 m against 0.064-0.081, ACES 0.086-0.136 against
# 0.089-0.141, FR079 0.078-0.131 against 0.075-0.106 (GMapping 2.2-5.4), 5-6 % less CPU. Not for the
# others: the simulated office's worst seed of 24 went 1.68 -> 2.70 cm, and the direction-of-travel test's
# robot that stops and backs (tests/unit/test_slam_travel.py, the search at every update) was followed
# with its odometry (docs/slam.md, "Scan matching", *The match's iterations*).
MATCH_ITERATIONS = {
    "breezyslam": (4, 4, 4),
    "radish": (3, 3, 4),
    "simulated": (4, 4, 4),
    "mcap": (4, 4, 4),
}
# The final optimisation at the end of the log (``[slam] loop_final_scan_chain``): on for the recorded
# logs, whose front-end steps are 2-5 cm from a registration of the two scans alone and bend towards the
# wheels (ACES seeds 0-11: 12 of 12 within 0.15 m against 6; exp1's loop 23 of 24 seeds against 19);
# off for the simulated robot, whose steps lie within 3 mm of the truth and whose loop factors (1.6 cm
# median error) bend them: the office's ATE 0.9 -> 3-4 cm with it (docs/slam.md, "Loop closure", *The
# final optimisation*).
FINAL_SCAN_CHAIN = {"breezyslam": True, "radish": True, "simulated": False, "mcap": True}


def front_end(source_format: str) -> Any:
    """The ``[slam]`` front-end keys (an ``agent.config_slam.SlamConfig``, its other keys at their defaults)
    ``source_format`` is run with: ``DEFAULT_ALONG_SURFACE_WEIGHT``, ``DEGENERATE_NOISE_SCALE``,
    ``FREE_MARGIN_M``, ``MISS_LOG_ODDS``, ``REVERSAL_RATIO``, ``LOOP_CORRECTION_ODOMETRY_SIGMAS``,
    ``MATCH_GATE_RESIDUAL``, ``NORMAL_RADIUS_PER_M``, ``NORMAL_THICKNESS_M``,
    ``MATCH_MIN_TRANSLATION_INFORMATION``, ``MATCH_MEDIAL_WINDOW_CELLS``, ``MATCH_ITERATIONS``,
    ``FINAL_SCAN_CHAIN``, the
    simulated robot's motion model (``simlog.MOTION_NOISE``) and, for ``SPARSE_SCAN_FORMATS``, a match
    trusted on 10 endpoints whatever their share, from both starts, a failed match drawn near the
    odometry prediction and the correlative search at turns over a wider yaw window and where the lead
    matched poorly without it. The
    agent's defaults are the URG's (``breezyslam``); a config for another robot sets these keys to the
    values its source was measured with (``examples/sim.toml``: ``simulated``'s)."""
    import dataclasses

    from agent.config_slam import SlamConfig

    config = SlamConfig(
        along_surface_weight=DEFAULT_ALONG_SURFACE_WEIGHT[source_format],
        degenerate_noise_scale=DEGENERATE_NOISE_SCALE[source_format],
        free_margin_m=FREE_MARGIN_M[source_format],
        miss_log_odds=MISS_LOG_ODDS[source_format],
        reversal_ratio=REVERSAL_RATIO[source_format],
        loop_correction_odometry_sigmas=LOOP_CORRECTION_ODOMETRY_SIGMAS[source_format],
        match_gate_residual=MATCH_GATE_RESIDUAL[source_format],
        normal_radius_per_m=NORMAL_RADIUS_PER_M[source_format],
        normal_thickness_m=NORMAL_THICKNESS_M[source_format],
        match_min_translation_information=MATCH_MIN_TRANSLATION_INFORMATION[source_format],
        match_medial_window_cells=MATCH_MEDIAL_WINDOW_CELLS[source_format],
        match_iterations=MATCH_ITERATIONS[source_format],
        loop_final_scan_chain=FINAL_SCAN_CHAIN[source_format],
    )
    if source_format == "simulated":
        from agent.slam.simlog import MOTION_NOISE

        noise = MOTION_NOISE
        config = dataclasses.replace(config, odometry_noise=(noise.srr, noise.srt, noise.str, noise.stt))
    if source_format not in SPARSE_SCAN_FORMATS:
        return config
    return dataclasses.replace(
        config,
        match_min_inliers=10,
        match_min_inlier_fraction=0.0,
        match_both_starts=True,
        failed_match_draw="grid",
        search_increment_rad=SPARSE_SEARCH_INCREMENT_RAD,
        search_yaw_rad=SPARSE_SEARCH_YAW_RAD,
        search_below_inliers=SPARSE_SEARCH_BELOW_INLIERS,
    )


def log_odds_model(source_format: str) -> Any:
    """The grid's inverse sensor model for ``source_format`` (``MISS_LOG_ODDS``)."""
    from agent.runtime.mapper import front_end_log_odds

    return front_end_log_odds(front_end(source_format))


def log_proposal(source_format: str, proposal: Any) -> Any:
    """``proposal`` (a ``ProposalConfig``) with the front end ``source_format`` gets (``front_end``), set
    by the function the agent's filters are built with (``agent.runtime.mapper.front_end_proposal``)."""
    from agent.runtime.mapper import front_end_proposal

    return front_end_proposal(front_end(source_format), proposal)


def add_parser(subparsers: Any) -> None:
    p: argparse.ArgumentParser = subparsers.add_parser(
        "slam",
        help="run the SLAM filter on a recorded laser log; report speed (and accuracy where the log has "
        "reference poses); write the map and trajectory",
        description=textwrap.dedent(
            """\
            Run the particle-filter SLAM on a recorded log as fast as it goes. Reports update time
            (median, p95), wall time, real-time factor and peak memory; for radish logs also the
            relative-pose error against the log's GMapping-corrected poses over every pair of
            consecutive scans (trans_error_m_*, rot_error_deg_*), next to raw odometry's, and over
            pairs --span scans apart (span_*: whether the trajectory holds together over a building,
            which the consecutive pairs cannot show; 500 on FR079 spans most of it), over every pair
            of reference poses further apart than 10 m (relation_over_10m_m, _deg: the map's global
            consistency in one figure), and the RMS position error after the best rigid alignment
            onto the reference poses (ate_aligned_m). Writes map.yaml and the map.<stamp>.pgm it names
            (ROS map_server), map.png and trajectory.png into --out.

            With --world, drives the simulated robot along the world's route and reports the absolute
            trajectory error against the simulation's truth (ate_m), with VLP fixes in the filter or
            without. The simulated wheels err like real ones; by default their odometry is that of a
            robot through `vlp-agent calibrate wheels` (the step's runs simulated on the same wheels and
            fitted by its own fit), and ate_uncalibrated_m gives the same drive with the design's
            geometry (--wheels nominal: that one only).

            --log also takes a flight recording (MCAP, `vlp-agent sim --record`; the format is found by
            its magic bytes): the scans the live SLAM took with the odometry each went with (every scan
            with the fusion's wheel odometry when SLAM was off), the map started where the live one
            did, its VLP fixes in the filter with --vlp-fixes. A vlp-agent sim recording holds the
            simulation's truth (/sim/truth): the ATE against it (ate_m, ...); a robot's has none, and
            no ATE. A cut or corrupt recording is read up to where it stops being readable, and the
            output says where (recording.stopped)."""
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--log",
        metavar="FILE",
        help="the log file (needs --format), or a flight recording (.mcap, or the name its files were "
        "written under)",
    )
    source.add_argument(
        "--world",
        metavar="FILE",
        help="drive the simulated robot along this world's route instead (a world TOML file)",
    )
    p.add_argument("--format", choices=FORMATS, help="log format (with --log)")
    p.add_argument(
        "--seconds",
        type=positive_seconds,
        default=300.0,
        metavar="N",
        help="with --world: seconds of simulated driving (default: 300)",
    )
    p.add_argument(
        "--vlp-fixes",
        action="store_true",
        help="with --world: VLP fixes at 10 Hz as absolute measurements in the filter; the map starts at "
        "the first fix (where they come from: --fix-source); with a flight recording: the VLP fixes the "
        "live SLAM took",
    )
    p.add_argument(
        "--fix-source",
        choices=("pipeline", "model"),
        default="pipeline",
        help="with --vlp-fixes: 'pipeline' (default) renders the camera's frames and runs the VLP pipeline "
        "on them, the world's errors included; 'model' takes the true pose plus the LED survey error and "
        "Gaussian noise (5 mm, 0.3 deg, when two LEDs are in view), much faster",
    )
    p.add_argument(
        "--wheels",
        choices=("calibrated", "nominal"),
        default="calibrated",
        help="with --world: the odometry's wheel radius and track. 'calibrated' (default): what "
        "`vlp-agent calibrate wheels` finds for the simulated robot's wheels (its runs simulated, measured "
        "to the millimetre and the tenth of a degree); the run is then replayed with the nominal ones too "
        "(ate_uncalibrated_m). 'nominal': the design's, as an uncalibrated robot",
    )
    p.add_argument("--particles", type=int, default=30, help="number of particles (default: 30)")
    p.add_argument(
        "--odometry-noise",
        type=float,
        nargs=4,
        metavar=("SRR", "SRT", "STR", "STT"),
        help="motion model noise in GMapping's terms (default: 0.1 0.2 0.1 0.2, slam_gmapping's; with "
        "--world "
        "0.03 0.05 0.03 0.05, the simulated robot's)",
    )
    p.add_argument(
        "--map-mode",
        choices=("per_particle", "shared"),
        default="per_particle",
        help="one copy-on-write map per particle (default), or one map shared by all particles",
    )
    p.add_argument("--linear-update", type=float, metavar="M", help="filter update every M metres (0.25)")
    p.add_argument("--angular-update", type=float, metavar="RAD", help="... or every RAD radians (0.2)")
    p.add_argument(
        "--max-range", type=float, metavar="M", help="usable range (5.5 breezyslam and --world, 15 radish)"
    )
    p.add_argument(
        "--loop-closure",
        choices=("on", "off"),
        default="on",
        help="match scans against the map built long ago and optimise the pose graph (default: on)",
    )
    add_research_options(p)
    p.add_argument("--scans", type=int, metavar="N", help="use only the first N scans of the log")
    p.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    p.add_argument(
        "--span",
        type=int,
        default=DEFAULT_SPAN_SCANS,
        metavar="N",
        help=f"scans between the two poses of the span_* relations (default: {DEFAULT_SPAN_SCANS})",
    )
    p.add_argument(
        "--out", metavar="DIR", help="where to write the map and pictures (default: ./eval-slam-LOG)"
    )
    p.add_argument("--json", action="store_true", help="print the results as one JSON object on stdout")


def log_config(source_format: str, seed: int = 0, particles: int = 30, loop_closure: bool = True) -> Any:
    """The filter's configuration for a recorded log with every option at its default (what
    ``eval slam --log FILE --format F --seed S`` runs; ``benchmarks/slam_vs_gmapping.py`` runs the same)."""

    from agent.runtime.mapper import front_end_filter
    from agent.slam.rbpf import RbpfConfig

    defaults = RbpfConfig()
    keys = front_end_filter(front_end(source_format), defaults.proposal)
    if not loop_closure:
        keys["loop_closure"] = None
    return RbpfConfig(
        particles=particles, **keys, max_usable_range_m=DEFAULT_MAX_RANGE_M[source_format], seed=seed
    )


def _fix_error(simulated: Any) -> float:
    """Mean distance of the fixes from the true base pose at their own times (metres)."""
    xy = np.array([(f.fix.x_m, f.fix.y_m) for f in simulated.fixes])
    return float(np.mean(np.hypot(*(xy - simulated.fix_truth[:, :2]).T)))


def _progress(done: int, total: int, slam: Any) -> None:
    print(f"  scan {done}/{total}, {slam.stats.updates} updates", file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    import dataclasses

    from agent import figure
    from agent.slam.fix import TimedFix
    from agent.slam.logs import SlamLog, read_log
    from agent.slam.malloc import tune_malloc
    from agent.slam.mapio import save_map, write_png
    from agent.slam.metrics import (
        absolute_trajectory_error,
        aligned_trajectory_error,
        far_relation_error,
        relative_pose_error,
        turn_ratio,
        turning_point,
        wall_thickness,
    )
    from agent.slam.motion import OdometryNoise
    from agent.slam.pose import between, compose
    from agent.slam.rbpf import MapMode, RbpfConfig
    from agent.slam.render import MapPath, map_picture, occupancy_image
    from agent.slam.replay import replay
    from drivers.errors import ConfigError

    tune_malloc()  # as the agent's SLAM process does (agent.slam.malloc): what is measured is what runs
    if args.particles < 1:
        raise ConfigError("--particles", "must be at least 1")
    check_research_options(args)  # before a log is read or a world driven
    simulated = None
    fixes: tuple[TimedFix, ...] = ()
    recording_summary: dict[str, Any] | None = None
    recorded_start: tuple[float, float, float] | None = None
    recorded_truth: npt.NDArray[np.float64] | None = None
    if args.world is not None:
        from agent.slam.simlog import (
            WheelErrorModel,
            WheelGeometry,
            simulate_log,
            wheel_calibration_runs,
        )
        from calibration.wheels import Run as WheelRun
        from calibration.wheels import fit_wheels
        from drivers.sim.worldfile import load_world

        if args.format is not None:
            raise ConfigError("--format", "is for --log; --world makes its own log")
        world = load_world(args.world)
        if not world.route:
            raise ConfigError("route", "the world has no route for the robot to drive", args.world)
        source = None
        if args.vlp_fixes and args.fix_source == "pipeline":
            from agent.commands.sim_fixes import PipelineFixes

            source = PipelineFixes(world, seed=args.seed)
        errors = WheelErrorModel()
        geometry = None
        if args.wheels == "calibrated":
            runs = wheel_calibration_runs(world, errors, np.random.default_rng(args.seed))
            fit = fit_wheels([WheelRun(*r) for r in runs])
            geometry = WheelGeometry(fit.wheel_radius_m, fit.track_m)
        simulated = simulate_log(
            world, args.seconds, wheel_errors=errors, wheel_geometry=geometry, fixes=source, seed=args.seed
        )
        log: SlamLog = simulated.log
        source_format = "simulated"
        source_name = str(args.world)
        if args.vlp_fixes:
            fixes = simulated.fixes
    elif args.format == "mcap" or (args.format is None and _is_recording(args.log)):
        from agent.recording.slam_log import slam_log_from_recording

        recordings, recording_summary = _read_recording(Path(args.log))
        recorded = slam_log_from_recording(recordings, str(args.log))
        log = recorded.log
        source_format = "mcap"
        source_name = str(args.log)
        # No ground truth in a recording (vlp-agent sim --truth writes it to a CSV file): no ATE.
        recording_summary.update(
            odometry=recorded.odometry,
            scans_left_out=recorded.skipped,
            truth="/sim/truth" if recorded.truth is not None else None,
        )
        recorded_truth = recorded.truth
        recorded_start = recorded.start_pose
        if args.vlp_fixes:
            fixes = recorded.fixes
    else:
        if args.format is None:
            raise ConfigError("--format", "is needed with --log (breezyslam or radish)")
        if args.vlp_fixes:
            raise ConfigError("--vlp-fixes", "is for --world (recorded logs carry no fixes)")
        log = read_log(args.log, args.format)
        source_format = args.format
        source_name = str(args.log)
    if args.scans is not None:
        log = log.sliced(0, args.scans)
    if len(log) < 2:
        raise ConfigError("--log", f"needs at least 2 scans, has {len(log)}", source_name)
    if args.span < 1:
        raise ConfigError("--span", f"must be at least 1 scan, got {args.span}")
    defaults = RbpfConfig()
    from agent.runtime.mapper import front_end_filter

    filter_keys = front_end_filter(front_end(source_format), defaults.proposal)
    if args.loop_closure == "off":
        filter_keys["loop_closure"] = None
    if args.odometry_noise:
        filter_keys["noise"] = OdometryNoise(*args.odometry_noise)
    filter_options = apply_research_options(args, filter_keys)
    initial_pose = defaults.initial_pose
    reference = log.reference_poses()
    if simulated is not None:
        initial_pose = simulated.start_pose(from_fix=bool(fixes))
    elif recorded_start is not None:
        initial_pose = recorded_start
    config = RbpfConfig(
        particles=args.particles,
        map_mode=MapMode(args.map_mode),
        **filter_keys,
        **filter_options,
        linear_update_m=args.linear_update if args.linear_update is not None else defaults.linear_update_m,
        angular_update_rad=args.angular_update
        if args.angular_update is not None
        else defaults.angular_update_rad,
        max_usable_range_m=args.max_range
        if args.max_range is not None
        else DEFAULT_MAX_RANGE_M[source_format],
        initial_pose=initial_pose,
        seed=args.seed,
    )
    long_run = not args.json or sys.stderr.isatty()
    result = replay(log, config, _progress if long_run else None, progress_every_s=5.0, fixes=fixes)
    slam = result.slam
    peak_rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0

    summary: dict[str, Any] = {
        "log": source_name,
        "format": source_format,
        "scans": len(log),
        "particles": config.particles,
        "map_mode": config.map_mode.value,
        "odometry_noise": [config.noise.srr, config.noise.srt, config.noise.str, config.noise.stt],
        "proposal_temperature": config.proposal.proposal_temperature,
        "along_surface_weight": config.proposal.along_surface_weight,
        "degenerate_noise_scale": config.proposal.degenerate_noise_scale,
        "medial_window_cells": config.proposal.matcher.medial_window_cells,
        # The lattice the map was built on (RbpfConfig.grid_phase_from_walls: fitted to the first scan).
        "grid_phase_m": [round(p, 4) for p in slam.config.grid.phase_m],
        **{
            key: None if config.loop_closure is None else getattr(config.loop_closure, key)
            for key in (
                "edge_match_sigma_m",
                "edge_information",
                "edge_departure_floor",
                "edge_normal_radius_per_m",
                "edge_scan_mean",
                "edge_scan_gate_chi2",
                "edge_scan_coarse_iterations",
                "edge_scan_anchor",
                "edge_scan_fallback",
                "edge_judge_plain",
            )
        },
        "updates": slam.stats.updates,
        "update_ms_median": _round(np.median(result.update_ms)) if result.update_ms.size else None,
        "update_ms_p95": _round(np.percentile(result.update_ms, 95)) if result.update_ms.size else None,
        "update_ms_max": _round(np.max(result.update_ms)) if result.update_ms.size else None,
        "wall_s": _round(result.wall_s),
        "cpu_s": _round(result.cpu_s),
        "log_duration_s": _round(log.duration_s),
        "realtime_factor": _round(log.duration_s / result.wall_s) if result.wall_s > 0 else None,
        "peak_rss_mb": _round(peak_rss_mb),
        "map_tiles": slam.maps.tiles_in_use(),
        "map_mb": _round(slam.maps.used_bytes() / 1e6),
        "resamples": slam.stats.resamples,
        "match_failures": slam.stats.match_failures,
        "reversals": slam.stats.reversals,
        "turns_in_place": slam.stats.turns_in_place,
        "searches_on_doubt": slam.stats.searches_on_doubt,
        "loop_closure": args.loop_closure,
        "loop_checks": slam.stats.loop_checks,
        "loop_closures": slam.stats.loop_closures,
        "loop_rebuilds": slam.stats.loop_rebuilds,
        "loop_agreeing": slam.stats.loop_verdicts.get("near", 0),
        "final_scan_edges": slam.stats.final_scan_edges,
        "loop_s": _round(slam.stats.loop_ms / 1e3),
        "rejected": dict(result.rejections),
    }
    if recording_summary is not None:
        summary["recording"] = recording_summary
        summary["vlp_fixes"] = bool(fixes)
        summary["fixes_used"] = slam.stats.fixes_applied
        if recorded_truth is not None:
            truth = recorded_truth[: len(log)]
            position_error = np.hypot(*(result.poses[:, :2] - truth[:, :2]).T)
            summary.update(
                ate_m=_round(absolute_trajectory_error(truth, result.poses), 4),
                ate_aligned_m=_round(aligned_trajectory_error(truth, result.poses), 4),
                ate_online_m=_round(absolute_trajectory_error(truth, result.online_poses), 4),
                ate_max_m=_round(float(position_error.max()), 4),
                final_error_m=_round(float(position_error[-1]), 4),
            )
    # Where the odometry turns about, in the filter's frame (the laser's moved by its configured mount), from
    # the turns on the spot: a mount the configuration does not hold (docs/slam.md, "Loop closure", Intel).
    turning = turning_point(log.odometry_poses(), result.poses)
    summary["turning_point_m"] = None if turning is None else [_round(float(v), 4) for v in turning]
    if reference is not None:
        odometry = log.odometry_poses()
        error = relative_pose_error(reference, result.poses)
        summary.update(
            relations=error.n,
            trans_error_m_std=_round(error.trans_error_m_std, 4),
            rot_error_deg_std=_round(error.rot_error_deg_std, 3),
            **_relation_means("", error, relative_pose_error(reference, odometry)),
        )
        far = far_relation_error(reference, result.poses)
        odometry_far = far_relation_error(reference, odometry)
        summary.update(
            ate_aligned_m=_round(aligned_trajectory_error(reference, result.poses), 4),
            odometry_ate_aligned_m=_round(aligned_trajectory_error(reference, odometry), 4),
            relations_over_10m=far.n,
            relation_over_10m_m=_round(far.trans_error_m_mean, 4),
            relation_over_10m_deg=_round(far.rot_error_deg_mean, 3),
            odometry_relation_over_10m_m=_round(odometry_far.trans_error_m_mean, 4),
            turn_ratio=_round(turn_ratio(reference, result.poses), 4),
            odometry_turn_ratio=_round(turn_ratio(reference, odometry), 4),
        )
        if len(log) > args.span:
            first = np.arange(len(log) - args.span)
            pairs = np.stack([first, first + args.span], axis=1)
            summary.update(
                span_scans=args.span,
                **_relation_means(
                    "span_",
                    relative_pose_error(reference, result.poses, pairs),
                    relative_pose_error(reference, odometry, pairs),
                ),
            )
    if simulated is not None:
        truth = simulated.truth[: len(log)]
        position_error = np.hypot(*(result.poses[:, :2] - truth[:, :2]).T)
        odometry_world = simulated.odometry_in_world()[: len(log)]
        summary.update(
            world=str(args.world),
            seconds=_round(log.records[-1].t_s),
            distance_m=_round(simulated.distance_m),
            vlp_fixes=bool(fixes),
            fixes_used=slam.stats.fixes_applied,
            fix_source=(
                "pipeline (rendered frames through agent.vlp, 10 Hz)"
                if args.fix_source == "pipeline"
                else "model (agent.slam.simlog.VlpFixModel: 5 mm, 0.3 deg, 10 Hz, >= 2 LEDs in view)"
            )
            if fixes
            else None,
            fixes_offered=len(simulated.fixes),
            fix_error_m_mean=_round(_fix_error(simulated), 4) if simulated.fixes else None,
            camera_instants_without_fix=simulated.frames_without_fix,
            no_fix_reasons=simulated.no_fix_reasons,
            ate_m=_round(absolute_trajectory_error(truth, result.poses), 4),
            ate_aligned_m=_round(aligned_trajectory_error(truth, result.poses), 4),
            ate_online_m=_round(absolute_trajectory_error(truth, result.online_poses), 4),
            ate_mean_m=_round(absolute_trajectory_error(truth, result.mean_poses), 4),
            ate_max_m=_round(float(position_error.max()), 4),
            final_error_m=_round(float(position_error[-1]), 4),
            odometry_ate_m=_round(absolute_trajectory_error(truth, odometry_world), 4),
            wheels=args.wheels,
            wheel_radius_m=_round(simulated.geometry.radius_m, 6),
            wheel_track_m=_round(simulated.geometry.track_m, 6),
        )
        if args.wheels == "calibrated":
            # The same drive as an uncalibrated robot would have logged it (same scans and wheel readings,
            # the nominal geometry), through the same filter.
            nominal_fixes = simulated.nominal_fixes if fixes else ()
            nominal_config = dataclasses.replace(
                config, initial_pose=simulated.start_pose(from_fix=bool(fixes), nominal=True)
            )
            nominal = replay(simulated.with_nominal_odometry(), nominal_config, fixes=nominal_fixes)
            summary["ate_uncalibrated_m"] = _round(absolute_trajectory_error(truth, nominal.poses), 4)

    window = slam.map_window()
    default_out = f"eval-slam-{Path(source_name).stem}" + ("-vlp" if fixes else "")
    out = Path(args.out) if args.out else Path(default_out)
    if window is not None:
        log_odds, origin = window
        image = occupancy_image(log_odds, origin, config.grid.resolution_m)
        walls = wall_thickness(image.occupied_mask())
        summary["wall_thin_fraction"] = _round(walls.thin_fraction, 3)
        files = save_map(image, out / "map.yaml", comment=f"vlp-agent eval slam {source_name}")
        odometry = log.odometry_poses()
        start_pose = result.poses[0] if simulated is None else simulated.truth[0]
        truth_paths: list[MapPath] = []
        if simulated is not None:
            truth_paths.append(
                MapPath("truth (simulator)", simulated.truth[: len(log)], figure.TRUTH, figure.TRUTH_WIDTH_PX)
            )
        elif recorded_truth is not None:
            truth_paths.append(
                MapPath("truth (recorded)", recorded_truth[: len(log)], figure.TRUTH, figure.TRUTH_WIDTH_PX)
            )
        elif reference is not None:  # a simulated log's reference poses are the truth drawn above
            truth_paths.append(
                MapPath(
                    "reference poses (log)",
                    compose(start_pose, between(reference[0], reference)),
                    figure.TRUTH,
                    figure.TRUTH_WIDTH_PX,
                )
            )
        estimate = MapPath("SLAM estimate", result.poses, figure.SLAM)
        odometry_path = MapPath(
            "wheel odometry", compose(start_pose, between(odometry[0], odometry)), figure.ODOMETRY
        )
        name = Path(source_name).name
        write_png(
            out / "map.png",
            map_picture(image, [*truth_paths, estimate], f"map.png: SLAM map of {name}"),
        )
        write_png(
            out / "trajectory.png",
            map_picture(
                image,
                [*truth_paths, odometry_path, estimate],
                f"trajectory.png: paths over the SLAM map of {name}",
            ),
        )
        summary["files"] = [
            str(files.yaml),
            str(files.image),
            str(out / "map.png"),
            str(out / "trajectory.png"),
        ]

    if args.json:
        print(dumps_json(summary, sort_keys=True))
    else:
        _print_table(summary)
    return 0


def _is_recording(log: str) -> bool:
    from agent.recording.reader import is_mcap

    return is_mcap(Path(log))


def _read_recording(path: Path) -> tuple[list[Any], dict[str, Any]]:
    """The files of a flight recording, read up to where one stops being readable, and what was read."""
    from agent.recording.reader import read_recordings
    from drivers.errors import ConfigError

    try:
        recordings = read_recordings(path)
    except FileNotFoundError as exc:
        raise ConfigError("--log", str(exc)) from exc
    cut = next((r for r in recordings if r.stopped_at is not None), None)
    if cut is not None:
        print(
            f"vlp-agent eval slam: {cut.path} is readable up to byte {cut.stopped_at} of "
            f"{cut.path.stat().st_size} ({cut.error}); using what is before it",
            file=sys.stderr,
        )
    return recordings, {
        "files": [str(r.path) for r in recordings],
        "messages": sum(len(r.messages) for r in recordings),
        "complete": cut is None and all(r.complete for r in recordings),
        "stopped": None
        if cut is None
        else {"file": str(cut.path), "at_byte": cut.stopped_at, "error": cut.error},
    }


def _relation_means(
    prefix: str, slam: RelativePoseError, odometry: RelativePoseError
) -> dict[str, float | None]:
    """The mean translational and rotational errors of the filter's and raw odometry's relations, keyed
    ``{prefix}trans_error_m_mean`` ... ``odometry_{prefix}rot_error_deg_mean``."""
    return {
        f"{prefix}trans_error_m_mean": _round(slam.trans_error_m_mean, 4),
        f"{prefix}rot_error_deg_mean": _round(slam.rot_error_deg_mean, 3),
        f"odometry_{prefix}trans_error_m_mean": _round(odometry.trans_error_m_mean, 4),
        f"odometry_{prefix}rot_error_deg_mean": _round(odometry.rot_error_deg_mean, 3),
    }


def _round(value: float, digits: int = 2) -> float | None:
    value = float(value)
    return round(value, digits) if math.isfinite(value) else None


def _print_table(s: dict[str, Any]) -> None:
    print(f"vlp-agent eval slam: {s['log']} ({s['format']}, {s['scans']} scans, {s['log_duration_s']} s)")
    print(f"  particles          {s['particles']} ({s['map_mode']} maps)")
    print(
        f"  filter updates     {s['updates']}, {s['resamples']} resamplings, "
        f"{s['match_failures']} failed matches, {s['reversals']} odometry translations reversed "
        f"({s['turns_in_place']} dropped: turned round in place), "
        f"{s['searches_on_doubt']} proposed again with the search"
    )
    print(
        f"  update time        median {s['update_ms_median']} ms, p95 {s['update_ms_p95']} ms, "
        f"max {s['update_ms_max']} ms"
    )
    print(
        f"  whole log          {s['wall_s']} s wall, {s['cpu_s']} s CPU, {s['realtime_factor']} x real time"
    )
    print(
        f"  memory             peak RSS {s['peak_rss_mb']} MB; "
        f"maps {s['map_mb']} MB in {s['map_tiles']} tiles"
    )
    print(
        f"  loop closure       {s['loop_closure']}: {s['loop_closures']} closures in {s['loop_checks']} "
        f"checks, {s['loop_rebuilds']} map rebuilds, {s['loop_s']} s"
    )
    final = (
        f"{s['final_scan_edges']} steps measured scan to scan, {s['loop_closures']} + {s['loop_agreeing']} "
        "loop factors"
        if s["final_scan_edges"] >= 0
        else "not run (no loop factor, or off)"
    )
    print(f"  final optimisation {final}")
    rejected = ", ".join(f"{k} {v}" for k, v in sorted(s["rejected"].items())) or "none"
    print(f"  rejected scans     {rejected}")
    if "ate_m" in s:
        fixes = (
            f"{s['fixes_used']} VLP fixes ({s['fix_source']}; mean error {s['fix_error_m_mean']} m)"
            if s["vlp_fixes"]
            else "no VLP fixes"
        )
        print(f"  simulated drive    {s['seconds']} s, {s['distance_m']} m, {fixes}")
        print(
            f"  trajectory error   ATE {s['ate_m']} m (online {s['ate_online_m']} m, max {s['ate_max_m']} m, "
            f"final {s['final_error_m']} m; raw odometry {s['odometry_ate_m']} m)"
        )
        print(f"                     {s['ate_aligned_m']} m after a rigid alignment onto the truth")
        wheels = f"{s['wheels']} wheels (radius {s['wheel_radius_m']} m, track {s['wheel_track_m']} m)"
        if s.get("ate_uncalibrated_m") is not None:
            wheels += f"; with the nominal ones ATE {s['ate_uncalibrated_m']} m"
        print(f"  odometry           {wheels}")
    if "trans_error_m_mean" in s:
        print(
            f"  relative error     {s['trans_error_m_mean']} ± {s['trans_error_m_std']} m, "
            f"{s['rot_error_deg_mean']} ± {s['rot_error_deg_std']} deg over {s['relations']} relations"
        )
        print(
            f"  (raw odometry      {s['odometry_trans_error_m_mean']} m, "
            f"{s['odometry_rot_error_deg_mean']} deg)"
        )
    if "ate_aligned_m" in s:
        print(
            f"  against reference  ATE {s['ate_aligned_m']} m after a rigid alignment "
            f"(raw odometry {s['odometry_ate_aligned_m']} m)"
        )
        print(
            f"  pairs over 10 m    {s['relation_over_10m_m']} m, {s['relation_over_10m_deg']} deg over "
            f"{s['relations_over_10m']} pairs (raw odometry {s['odometry_relation_over_10m_m']} m)"
        )
    if "span_trans_error_m_mean" in s:
        label = f"over {s['span_scans']} scans"
        print(
            f"  {label:<19}{s['span_trans_error_m_mean']} m, {s['span_rot_error_deg_mean']} deg "
            f"(raw odometry {s['odometry_span_trans_error_m_mean']} m, "
            f"{s['odometry_span_rot_error_deg_mean']} deg)"
        )
    if s.get("turn_ratio") is not None:
        print(
            f"  turns              {s['turn_ratio']} of the reference's where it turns 0.3 rad or more "
            f"(raw odometry {s['odometry_turn_ratio']})"
        )
    if s.get("turning_point_m") is not None:
        x_m, y_m = s["turning_point_m"]
        print(f"  odometry turns     about ({x_m}, {y_m}) m in the filter's frame (turns on the spot)")
    if "wall_thin_fraction" in s:
        print(
            f"  walls              {s['wall_thin_fraction']:.0%} of occupied cells in walls "
            "at most 2 cells thick, no ghost copy beside them"
        )
    for path in s.get("files", []):
        print(f"  wrote              {path}")
