"""The types of the ``[slam]`` section and of a sensor's mount, apart from :mod:`agent.config` (which
re-exports them): the SLAM process (:mod:`agent.runtime.slam_worker`) receives a :class:`SlamConfig` and a
:class:`MountConfig` and, unpickling them, imports only this module, not the whole config reader with the
navigation, exploration and world-file modules (and the libraries they load) that it has no use for.
Standard library only."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from pathlib import Path

__all__ = ["MountConfig", "SlamConfig", "SlamMode"]


class SlamMode(enum.StrEnum):
    MAPPING = "mapping"  # build a map (RBPF SLAM)
    CONTINUE = "continue"  # go on building a saved map (RBPF SLAM seeded with it: lifelong mapping)
    LOCALIZATION = "localization"  # localize on a saved map (MCL)


@dataclass(frozen=True)
class MountConfig:
    """Where a sensor sits on the base (x forward, y left, z up; metres) and how it is turned (radians)."""

    x_m: float = 0.0
    y_m: float = 0.0
    z_m: float = 0.0
    yaw_rad: float = 0.0
    roll_rad: float = 0.0
    pitch_rad: float = 0.0


@dataclass(frozen=True)
class SlamConfig:
    enabled: bool = True
    mode: SlamMode = SlamMode.MAPPING
    map: Path | None = None  # the saved map (map_server YAML) to localize on or to continue
    particles: int = 30
    map_mode: str = "per_particle"
    resolution_m: float = 0.05
    linear_update_m: float = 0.25
    angular_update_rad: float = 0.2
    laser_mount: MountConfig | None = None
    queue_size: int = 4
    map_dir: Path | None = None
    save_interval_s: float = 30.0  # the map saved this often while mapping (0: only at the end / on request)
    sigma_xy_m: float = 0.03
    sigma_yaw_rad: float = math.radians(1.0)
    seed: int = 0
    process: bool = True  # the filter in a child process (agent.runtime.slam_worker), not the agent's
    # The scan match's front end (docs/slam.md, "Scan matching"; docs/config.md). The defaults are the
    # filter's own, which are what the robot's laser (a URG-04LX, an update every 0.25 m: exp1, `eval slam
    # --format breezyslam`) was measured with; `eval slam` runs each other source with its own
    # (agent.commands.eval_slam.FRONT_END), which a config can set here.
    along_surface_weight: float = 1.0  # ProposalConfig.along_surface_weight: 1 point to point, 0 to line
    degenerate_noise_scale: float = 1.0  # ProposalConfig.degenerate_noise_scale: 1 the paper's draw
    match_min_inliers: int = 20  # MatcherConfig.min_inliers
    match_min_inlier_fraction: float = 0.1  # MatcherConfig.min_inlier_fraction
    match_both_starts: bool = False  # ProposalConfig.keep_better_start
    # The match's robust kernel judges an endpoint by its point-to-line residual, not its distance to the
    # nearest obstacle (MatcherConfig.gate_on_residual; only where along_surface_weight < 1)
    match_gate_residual: bool = False
    # The scan's surface normals (ProposalConfig.normal_radius_per_m, normal_thickness_m): a point's
    # neighbourhood reaches max(0.25 m, normal_radius_per_m x its range); a line when at most
    # normal_thickness_m thick
    normal_radius_per_m: float = 0.0
    normal_thickness_m: float = 0.015
    # Degeneracy-aware match steps (MatcherConfig.min_translation_information; 0 off): the scan does not
    # move the pose along a translation direction whose information is below this
    match_min_translation_information: float = 0.0
    # The distance field's straight-wall test (MatcherConfig.medial_window_cells): 0 a wall cell's four
    # neighbours; W > 0 the square of W cells either way around it (a wall on a cell boundary mapped in
    # patches, as grazing views map it, is measured to its boundary)
    match_medial_window_cells: int = 0
    # Gauss-Newton iterations in each of the proposal match's three stages, wide to fine (the stages'
    # bounds 0.5, 0.25, 0.12 m: MatcherConfig.stages); the loop closure's matches keep 4 / 4 / 4
    match_iterations: tuple[int, int, int] = (4, 4, 4)
    # Where a particle whose match fails is drawn (ProposalConfig.failed_match_draw): "motion" (the whole
    # motion model) or "grid" (near the odometry prediction, where its weight was taken)
    failed_match_draw: str = "motion"
    # The log-odds a swept (free) cell loses per scan (grid.LogOddsModel.miss)
    miss_log_odds: float = -0.4
    # The correlative search runs at an update whose turn since the last reaches this
    # (RbpfConfig.search_increment_rad), over +-search_yaw_rad (SearchConfig.yaw_range_rad)
    search_increment_rad: float = 0.5
    search_yaw_rad: float = 0.2
    # ... and again at an update that ran without it where the leading particle's match explained fewer
    # than this fraction of its endpoints (RbpfConfig.search_below_inliers); 0: never
    search_below_inliers: float = 0.0
    # For this many filter updates after a resampling, the particles drawn from one parent match against
    # one distance field, the heaviest one's map (RbpfConfig.shared_field_updates); 0: a field per map
    shared_field_updates: int = 20
    # The direction-of-travel check (RbpfConfig.reversal_ratio): the scan may reverse an update's odometry
    # translation when the reversed prediction's match energy is below this ratio of the forward one's;
    # None: off (wheel odometry knows its sign; the radish logs' rebuilt odometry does not)
    reversal_ratio: float | None = None
    # The pose graph widens a front-end edge only by the match's departure from odometry beyond this many
    # of the motion model's sigmas of that increment (loops.LoopClosureConfig.correction_odometry_sigmas);
    # None: by the whole departure (wheel odometry; the radish logs' rebuilt odometry is as bad as the
    # model says)
    loop_correction_odometry_sigmas: float | None = None
    # A loop link is rejected when it raises the optimised pose graph's chi² by more than this over the
    # graph without it (loops.LoopClosureConfig.accept_graph_chi2: a link that slid along a corridor and
    # bends the chain to fit); None (the key at 0): not tested
    loop_accept_graph_chi2: float | None = 16.3
    # A front-end step whose forward component departs from the odometry's by more than this (m) while the
    # robot drives steadily takes the odometry's in the pose graph (loops.LoopClosureConfig.snap_forward_m:
    # the front end's snap onto an older part of its map along a corridor); None (the key at 0): the
    # match's step everywhere
    loop_snap_forward_m: float | None = 0.15
    # The final optimisation where the filter is finished (RbpfSlam.finish: the end of a log replayed by
    # eval slam): the pose graph's chain measured scan to scan (loops.LoopClosureConfig.final_scan_chain);
    # False: the graph as the filter left it. The agent's live mapper does not finish its filter yet.
    loop_final_scan_chain: bool = True
    # How far short of its endpoint a beam's free space stops (RbpfConfig.free_margin_m); None: half a cell
    free_margin_m: float | None = None
    # The grid's lattice moved at the first scan so that the walls it sees along the map's axes run through
    # cell centres (RbpfConfig.grid_phase_from_walls, agent.slam.lattice); False: the lattice as it is
    grid_phase_from_walls: bool = True
    # The motion model (motion.OdometryNoise: srr, srt, str, stt); None: slam_gmapping's
    odometry_noise: tuple[float, float, float, float] | None = None
