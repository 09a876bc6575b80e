"""Rao-Blackwellized particle filter SLAM (GMapping's scheme; the seed's Algorithm 1), on an occupancy grid.

Per accepted scan (``process``):

1. gate: bad scans are rejected with a counted reason (``agent.slam.scan.ScanGate``);
2. update gating: the filter only works once the odometry since the last update exceeds
   ``linear_update_m`` or ``angular_update_rad``; in between, the pose is the best particle's ⊕ odometry;
3. proposal: each particle is scan-matched against its own map and sampled around the match
   (``agent.slam.proposal``), its weight multiplied by eta; for ``shared_field_updates`` after a
   resampling, the particles drawn from one parent are matched against the heaviest one's map;
4. absolute fixes (VLP) taken since the last update, carried forward by odometry and fused
   (``agent.slam.fix.fuse_fixes``), join the proposal as a third factor (so eta includes them); only when
   there is too little to match do they weight the particles alone: w_i *= N(z_fix; x_i, Sigma_fix);
5. N_eff = 1 / sum_i w_i^2 (normalised weights); below ``resample_threshold`` * N, systematic resampling;
6. the scan is integrated into each surviving particle's map at its pose (duplicates share one copy);
7. loop closure (``RbpfConfig.loop_closure``, ``agent.slam.loops``): the update becomes a pose-graph node;
   every few updates its scan is searched against the map of old nodes, and a closure optimises the graph
   and rebuilds the maps at the optimised poses (one map shared by all particles, which keep their spread).

Maps (``map_mode``): ``per_particle`` keeps one map per particle in copy-on-write tiles (GMapping: each
particle's map is conditioned on its own trajectory), ``shared`` keeps the seed's single map for all
particles, integrated at the best particle's pose: far less memory and work, but a particle cannot
recover from a map the others have already bent.

Update gating defaults are 0.25 m / 0.2 rad, four times denser than slam_gmapping's 1.0 m / 0.5 rad:
at 1 m the odometry between two updates of a URG-04LX rover drifts by several centimetres and degrees,
more than a 5 cm grid can absorb, and matches between scans that far apart overlap less
(``docs/slam.md`` has the measurements).
"""

from __future__ import annotations

import collections
import dataclasses
import enum
import itertools
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from agent.slam.fix import PoseFix, PoseMeasurement, fuse_fixes, pending_fixes_log_likelihood
from agent.slam.grid import (
    GridGeometry,
    LogOddsModel,
    ScanPoints,
    TiledMaps,
    TileRect,
    integrate_scans,
    prepare_scan,
    surface_normals,
)
from agent.slam.lattice import fit_grid_phase, phase_of
from agent.slam.loops import (
    GraphState,
    LoopClosureConfig,
    LoopConstraint,
    Verdict,
    edge_covariances,
    find_loop,
    judge_loop,
    odometry_forward_at_snaps,
    optimize_graph,
    robot_frame_information,
    yaw_doubt,
)
from agent.slam.malloc import trim_heap
from agent.slam.matcher import DistanceField, line_information
from agent.slam.motion import OdometryNoise, sample_motion
from agent.slam.pose import between, compose, inverse, transform_bounds, transform_points, wrap_angle
from agent.slam.posegraph import AbsoluteFactors, GraphResult
from agent.slam.proposal import (
    ProposalConfig,
    ProposalResult,
    improved_proposal,
    scan_normals,
    travel_reversed,
)
from agent.slam.relative import RelativeMatch, match_relative
from agent.slam.scan import LaserGeometry, Rejection, ScanGate
from agent.slam.scan_chain import scan_chain

FloatArray = npt.NDArray[np.float64]
# A relative edge's step counts as the one its match started from within these (x, y metres, yaw radians).
_SAME_STEP = np.array([0.01, 0.01, 0.005])
_SAME_STEP.flags.writeable = False
IntArray = npt.NDArray[np.int64]
Int8Array = npt.NDArray[np.int8]
BoolArray = npt.NDArray[np.bool_]

log = logging.getLogger(__name__)


class MapMode(enum.StrEnum):
    PER_PARTICLE = "per_particle"
    SHARED = "shared"


@dataclass(frozen=True)
class RbpfConfig:
    particles: int = 30
    map_mode: MapMode = MapMode.PER_PARTICLE
    grid: GridGeometry = field(default_factory=GridGeometry)
    log_odds: LogOddsModel = field(default_factory=LogOddsModel)
    noise: OdometryNoise = field(default_factory=OdometryNoise)
    proposal: ProposalConfig = field(default_factory=ProposalConfig)
    linear_update_m: float = 0.25
    angular_update_rad: float = 0.2
    resample_threshold: float = 0.5
    min_range_m: float = 0.1
    max_usable_range_m: float = 5.5
    match_voxel_m: float = 0.1
    max_match_points: int = 200
    field_margin_m: float = 0.6
    # For this many filter updates after a resampling, the particles drawn from one parent match against
    # one distance field: the map of the heaviest of them. Their maps are the parent's and the few scans
    # each has added since, at poses the proposal drew a few centimetres apart, so the heaviest one's
    # stands for them all, and an update computes a field per lineage instead of per particle (Intel: 20
    # fields an update against 29; the transforms and their masks are a third of the filter's CPU). Past
    # it each particle has its own field again: the longer a lineage shares one, the more its particles
    # follow their leader (the office, which resamples every ~40 updates, sharing until the next
    # resampling: 9 of 24 seeds over 3 cm, against 7 before). 0 or 1: a field per distinct map.
    # docs/slam.md, "The filter", *One distance field per lineage*.
    shared_field_updates: int = 20
    initial_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    deskew: bool = True
    # How far short of its endpoint a beam's free space stops (metres); None: half a cell. The swept fan
    # is rasterised with its edge pixels (cv2.fillPoly), and range noise puts half the hits on a wall
    # short of it, so with half a cell a wall that lies on a cell boundary has the cell in front of it
    # cleared about as often as hit: it comes out one cell thick on the far side, half a cell off, and a
    # trajectory settles there (the simulated office, whose walls all lie on 5 cm boundaries:
    # docs/slam.md, "Open problems").
    free_margin_m: float | None = None
    # The correlative search of ``proposal.search`` (for the leading particle, its correction moving every
    # particle's start) runs at the first ``search_updates`` filter updates and at an update whose odometry
    # increment reaches ``search_increment_m`` or ``search_increment_rad`` (after a gap in the scans), where
    # odometry's error can be past Gauss-Newton's reach (exp1's first update: odometry 17 deg, the scans
    # ~5 deg); None runs it at every update. Run at every update, its one correction for all particles
    # moves every lineage into the leader's basin: exp1's loop closes for 5 of 24 seeds, against 18 of 24
    # with the default; the simulated office is the same either way (ate_m over 24 seeds: mean 0.041 m and
    # worst 0.059 m with the default, 0.043 and 0.079 every update). docs/slam.md, "Open problems".
    search_updates: int | None = 1
    search_increment_m: float = 1.0
    search_increment_rad: float = 0.5
    # Also run it where the motion model's heading deviation for the increment (stt |dθ| + srt d) reaches
    # that of a straight ``search_increment_m`` (srt × it): an increment just short of both thresholds,
    # Intel's 0.93 m steps turning 10°, leaves odometry's heading as far from the scans as one past them
    # (Intel seed 4, record 890: Gauss-Newton from the prior settled 16° off, the search's start 0.3°).
    # False (the default): the two thresholds alone; measured on Intel and ACES seeds 0-5 and not adopted
    # (ACES seed 1 0.121 -> 0.252 m: docs/slam.md, "Loop closure", *Intel's 50-record relations*).
    search_heading_doubt: bool = False
    # And again where an update that ran without it matched the leading particle poorly: fewer than this
    # fraction of its endpoints within the last stage's bound (``MatchResult.inlier_fraction``). The update
    # is then proposed afresh with the search (with ``ProposalConfig.keep_better_start``, as the radish logs
    # run, each particle still keeps the prior's match where the search's start is worse). 0 (the default):
    # never.
    search_below_inliers: float = 0.0
    # Filter updates of trajectory history kept for ``trajectory()`` (about 1.2 KB each at 30 particles);
    # the oldest go first. 10 000 updates are 2.5 km of driving at 0.25 m per update, 12 MB: bounded on
    # board, and more than any log here needs (Intel: 897). None keeps everything.
    history_limit: int | None = 10_000
    # Loop closure against the map built long ago, into a pose graph (``agent.slam.loops``); None: off.
    loop_closure: LoopClosureConfig | None = field(default_factory=LoopClosureConfig)
    # The direction-of-travel check (``proposal.travel_reversed``): at an update whose odometry translation
    # reaches ``REVERSAL_MIN_M`` soon after a standstill (``REVERSAL_WINDOW_M``), the leading particle is
    # matched from the odometry's prediction and from the one with the translation reversed, and where the
    # reversed match's truncated energy is below this ratio times the other's, every particle takes the
    # reversed increment, at this update and at the next ones until the check runs again.
    # None: off (the default: wheel odometry knows which way it turned). For odometry rebuilt from
    # unsigned increments (the radish logs: FR079's robot backs 3 m out of a room at records 1372-1400
    # while its odometry drives on forward). docs/slam.md, "Scan matching".
    reversal_ratio: float | None = None
    # Move the grid's lattice (``GridGeometry.phase_m``) at the first scan so that the walls it sees along
    # the map's axes run through cell centres (``agent.slam.lattice``): a wall on a cell boundary comes
    # out ragged and the trajectory settles up to half a cell off (docs/slam.md, "The grid", *The grid's
    # phase*). With ``seed_map`` the saved map's own phase is kept instead (its cells line up).
    # False: the lattice as ``grid`` gives it.
    grid_phase_from_walls: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        if self.reversal_ratio is not None and not 0.0 < self.reversal_ratio <= 1.0:
            raise ValueError("reversal_ratio must be in (0, 1] (or None)")
        if self.particles < 1:
            raise ValueError("particles must be >= 1")
        if not 0.0 < self.resample_threshold <= 1.0:
            raise ValueError("resample_threshold must be in (0, 1]")
        if self.history_limit is not None and self.history_limit < 1:
            raise ValueError("history_limit must be at least 1 (or None)")


class StepKind(enum.StrEnum):
    UNINITIALIZED = "uninitialized"  # localization only: no fix to start from yet
    REJECTED = "rejected"
    FIRST = "first"
    GATED = "gated"
    UPDATED = "updated"


@dataclass(frozen=True)
class StepResult:
    """What one scan did. ``odometry``: the odometry pose the filter took for the scan, with dropped pose
    jumps taken out (continuous across them; what a pose is carried by between filter updates)."""

    kind: StepKind
    pose: FloatArray
    rejection: Rejection | None = None
    n_eff: float | None = None
    resampled: bool = False
    matched: int = 0
    odometry: FloatArray | None = None


@dataclass
class FilterStats:
    scans: int = 0
    updates: int = 0
    resamples: int = 0
    match_failures: int = 0
    reversals: int = 0  # checks that reversed the direction of travel (RbpfConfig.reversal_ratio)
    turns_in_place: int = 0  # checks that found no net translation (the robot turned round: IN_PLACE_RATIO)
    searches_on_doubt: int = 0  # updates proposed again with the search (RbpfConfig.search_below_inliers)
    fixes_applied: int = 0
    loop_checks: int = 0
    loop_closures: int = 0
    loop_rebuilds: int = 0
    loop_ms: float = 0.0  # time spent on loop search, optimisation and map rebuilds
    # The final optimisation (RbpfSlam.finish): the chain's steps the scans measured (-1: not run).
    final_scan_edges: int = -1
    # Candidates found, by ``loops.Verdict`` value (accepted, agrees, inconsistent, worse).
    loop_verdicts: collections.Counter[str] = field(default_factory=collections.Counter)
    n_eff: collections.deque[float] = field(default_factory=lambda: collections.deque(maxlen=10_000))


def systematic_resample(weights: FloatArray, rng: np.random.Generator) -> IntArray:
    """Low-variance resampling: u_i = (u_0 + i) / N, u_0 ~ U[0, 1); pick j with c_{j-1} <= u_i < c_j."""
    n = weights.size
    positions = (rng.random() + np.arange(n)) / n
    cumulative = np.cumsum(weights)
    cumulative[-1] = 1.0
    indices: IntArray = np.searchsorted(cumulative, positions, side="right").astype(np.int64)
    return np.minimum(indices, n - 1)


def sweep_offsets(laser: LaserGeometry, dt_s: float, motion: FloatArray) -> FloatArray | None:
    """Where the base was at each beam of a sweep, relative to the base at the scan's time, assuming the
    ``motion`` (odometry over the ``dt_s`` before the scan) went on at a constant twist: offset(tau) =
    twist * tau, tau the beam's time. None when the laser has no beam timing or dt is not positive."""
    if laser.beam_time_s is None or dt_s <= 0.0:
        return None
    twist = np.asarray(motion, dtype=np.float64) / dt_s
    offsets: FloatArray = twist[None, :] * laser.beam_time_s[:, None]
    return offsets


def voxel_indices(points_xy: FloatArray, voxel_m: float, max_points: int) -> IntArray:
    """Indices of one point per voxel (the first in beam order), then an even stride down to
    ``max_points``."""
    if points_xy.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    keys = np.floor(points_xy / voxel_m).astype(np.int64)
    _, first = np.unique(keys[:, 0] * 1_000_003 + keys[:, 1], return_index=True)
    kept: IntArray = np.sort(first).astype(np.int64)
    if kept.shape[0] > max_points:
        kept = kept[np.linspace(0, kept.shape[0] - 1, max_points).round().astype(np.int64)]
    return kept


def voxel_filter(points_xy: FloatArray, voxel_m: float, max_points: int) -> FloatArray:
    """The points :func:`voxel_indices` keeps."""
    kept: FloatArray = points_xy[voxel_indices(points_xy, voxel_m, max_points)]
    return kept


# Cells of map windows integrated in one pass (``RbpfSlam._integrate``): bounds the scratch memory.
_INTEGRATE_CELLS = 2_000_000
# (RbpfSlam._lineage_age where no lineage shares a field: before the first resampling, after a rebuild.)
_NO_LINEAGE = 1 << 30
# The direction-of-travel check (RbpfConfig.reversal_ratio) runs at updates that translate at least
# REVERSAL_MIN_M (below it the two predictions are within the match's first robust bound of each other
# anyway), and only within REVERSAL_WINDOW_M of odometry path after a standstill: a robot changes its
# direction of travel only from rest, so the check is not run where the odometry shows it moving on (ACES,
# one record per ~1 m: a corridor update whose forward match fitted badly was once reversed, 2 m off, and
# seed 0 went from 0.28 to 0.48 m). A standstill is a record whose odometry moved slower than
# REVERSAL_STOP_M_S since the record before (FR079 cruises at ~0.4 m/s; every one of its backward runs
# follows a record under 0.065 m/s within the 8 before it). The direction the check chose holds until it
# runs again; at each check the odometry's direction is the default. Where the filter searches, a
# reversal must also beat the forward side's best fit from a correlative search around its prediction
# (``proposal.travel_reversed``: ACES seed 5, record 275, a forward match stuck in a local minimum was
# reversed and the map ended 10.9 m off).
REVERSAL_MIN_M = 0.1
REVERSAL_WINDOW_M = 1.0
REVERSAL_STOP_M_S = 0.07
# At the first update after a standstill the check also tries the turn without the translation
# (``proposal.travel_reversed``'s ``in_place_ratio``): the robot may have stopped and turned round within
# that update, its net translation anywhere between the odometry's and the reversed one, and a match from
# either end may settle short of it and put the scan into the map that far off, which the next updates'
# checks then read against (``tests/unit/test_slam_travel.py``: 5 cm forward, then backing, against
# predictions of +25 and -25 cm; with the two hypotheses alone the robot was followed with its odometry,
# 2.3-2.5 m off, in 25 of 42 variants of matcher schedules, search triggers and standstills, with this in
# none). Its ratio is looser than the reversal's: a wrong call costs the odometry's step, not twice it
# (docs/slam.md, "Scan matching", *The turn in place*).
IN_PLACE_RATIO = 0.75


def _no_wait() -> None:
    return None


class RbpfSlam:
    """The filter. Feed it scans with their odometry; read the pose, the map and the trajectory."""

    def __init__(self, laser: LaserGeometry, config: RbpfConfig | None = None) -> None:
        self.laser = laser
        self.config = config or RbpfConfig()
        cfg = self.config
        self.rng = np.random.default_rng(cfg.seed)
        self.gate = ScanGate(laser)
        self._without_search = dataclasses.replace(cfg.proposal, search=None)
        self._search_heading_doubt = cfg.noise.srt * cfg.search_increment_m  # (search_heading_doubt)
        n = cfg.particles
        self.poses: FloatArray = np.tile(np.asarray(cfg.initial_pose, dtype=np.float64), (n, 1))
        self.log_weights: FloatArray = np.zeros(n)
        rows = n if cfg.map_mode is MapMode.PER_PARTICLE else 1
        self.maps = TiledMaps(cfg.grid, rows)
        # Particles with the same group id have identical maps (duplicates after resampling).
        self._groups: IntArray = np.zeros(n, dtype=np.int64)
        # Particles with the same _field_lineage id were drawn from one parent at the last resampling,
        # _lineage_age updates ago (shared_field_updates); a rebuilt map ends every lineage.
        self._field_lineage: IntArray = np.zeros(n, dtype=np.int64)
        self._lineage_age = _NO_LINEAGE
        self._started = False
        # Odometry as the filter sees it: C ⊕ o for the odometry o it is given, C taking out the pose jumps
        # it dropped, so that it stays continuous.
        self._odom_correction: FloatArray = np.zeros(3)
        self._update_odom: FloatArray | None = None  # (corrected) odometry at the last filter update
        self._last_odom: FloatArray | None = None  # (corrected) odometry of the last accepted scan
        self._last_t_s: float | None = None  # the time of the last accepted scan
        # The direction of travel (RbpfConfig.reversal_ratio): +1 the odometry's, -1 reversed; and the
        # odometry path since the last standstill.
        self._direction = 1.0
        self._since_stop_m = 0.0
        self._stood_since_update = False  # a standstill since the last update (IN_PLACE_RATIO)
        self._update_share = 1.0  # the share of the odometry's translation this update took (history)
        self._pending_fixes: list[tuple[PoseFix, FloatArray]] = []
        # Per update: poses (P, 3) after resampling, parent index of each in the previous update, time,
        # odometry. Bounded by ``history_limit`` on board; the oldest entries go first.
        limit = cfg.history_limit
        self.history_poses: collections.deque[FloatArray] = collections.deque(maxlen=limit)
        self.history_parents: collections.deque[IntArray] = collections.deque(maxlen=limit)
        self.history_t_s: collections.deque[float] = collections.deque(maxlen=limit)
        self.history_odom: collections.deque[FloatArray] = collections.deque(maxlen=limit)
        # ... the share of the odometry's translation each update took (+1, -1 reversed, 0 turned round in
        # place: ``_update_share``), and the odometry path since the last standstill then
        # (``_since_stop_m``): the pose graph's odometry steps and where it trusts their length
        # (LoopClosureConfig.snap_forward_m).
        self.history_share: collections.deque[float] = collections.deque(maxlen=limit)
        self.history_since_stop_m: collections.deque[float] = collections.deque(maxlen=limit)
        # trajectory()'s last walk: (absolute update of its first row, _history_edits then, the particle
        # index at every update, the poses); the history's first row's absolute update; rewrites counted.
        self._lineage: tuple[int, int, list[int], FloatArray] | None = None
        self._history_first = 0
        self._history_edits = 0
        # Called between the stages of a filter update (the distance field, the proposal, the map): where
        # the agent's runtime lets a camera frame on its hot path go first (agent.runtime.hotpath). It may
        # raise to leave the update (the agent's SLAM process does when the agent stops): the filter is
        # then half-way through it and takes no more scans, but its maps are whole, those from before the
        # update (a loop closure's rebuild is put in place only once built).
        self.give_way: Callable[[], None] = _no_wait
        self.stats = FilterStats()
        # Loop closure: per node (filter update) its scan (for a map rebuild), its endpoints (for the old
        # map) and its motion from the node before along the leading lineage, with that lineage's scan
        # match information (robot frame; zeros where it failed: ``edge_match_sigma_m``); the loop
        # factors found.
        self._node_scans: list[ScanPoints] = []
        self._node_hits: list[FloatArray] = []
        self._node_motions: list[FloatArray] = []
        self._node_information: list[FloatArray] = []
        # With LoopClosureConfig.edge_information "scan": the last node's endpoints and their normals
        # (the next node's relative match's reference), and per node its step from that match (NaN where
        # it failed or was not run: the filter's step stands).
        self._scan_reference: tuple[FloatArray, FloatArray] | None = None
        self._node_scan_motions: list[FloatArray] = []
        self._node_scan_guesses: list[FloatArray] = []  # the filter's step each was matched from
        self._node_normals: list[npt.NDArray[np.float32] | None] = []  # each node's scan's normals
        self._loops: list[LoopConstraint] = []
        # Known-area links the graph already agreed with (loops.Verdict.NEAR): not in the graph's
        # optimisations while the filter runs, but factors of the final one (``finish``).
        self._near_loops: list[LoopConstraint] = []
        self._last_agreement = 0  # the last node a loop match agreed with the graph at (or closed)
        # The last node a known-area link (LoopClosureConfig.hypotheses) was judged at without being acted
        # on: the rule waits known_area_after_m from here too.
        self._known_area_judged = 0
        self._last_check = 0  # the last node a loop check ran at
        self._pending: list[LoopConstraint] = []  # links that disagreed with the graph, unconfirmed
        self._anchored = 0  # nodes up to here hold graph-optimised poses in the history
        # VLP fixes fused at a node stay in the graph as absolute factors: (node, mean, sigma).
        self._node_fix: PoseMeasurement | None = None
        self._fix_factors: list[tuple[int, FloatArray, FloatArray]] = []
        # A saved map this one continues (``seed_map``): its stored window, put back under every rebuild.
        self._prior: tuple[TileRect, Int8Array, BoolArray] | None = None

    # -- public API --------------------------------------------------------------------------------------
    @property
    def weights(self) -> FloatArray:
        w = np.exp(self.log_weights - self.log_weights.max())
        normalised: FloatArray = w / w.sum()
        return normalised

    @property
    def best_index(self) -> int:
        return int(np.argmax(self.log_weights))

    def pose(self, odom_pose: FloatArray | None = None) -> FloatArray:
        """The best particle's pose, moved on by the odometry since the last update if ``odom_pose``."""
        if odom_pose is None:
            return self._pose_at(None)
        return self._pose_at(self._corrected(odom_pose))

    def add_fix(self, fix: PoseFix, odom_pose: FloatArray) -> None:
        """Queue an absolute fix taken when the odometry read ``odom_pose``; at the next filter update it is
        carried there by the odometry in between (with that motion's noise) and joins the proposal."""
        self._pending_fixes.append((fix, self._corrected(odom_pose)))

    def _corrected(self, odom_pose: FloatArray) -> FloatArray:
        return compose(self._odom_correction, np.asarray(odom_pose, dtype=np.float64))

    def _pose_at(self, odom: FloatArray | None) -> FloatArray:
        best: FloatArray = self.poses[self.best_index]
        if odom is None or self._update_odom is None:
            return best.copy()
        return compose(best, between(self._update_odom, odom))

    def process(self, t_s: float, ranges_m: FloatArray, odom_pose: FloatArray) -> StepResult:
        """One scan with the odometry pose of the robot base at the scan's time."""
        cfg = self.config
        self.stats.scans += 1
        raw = np.asarray(odom_pose, dtype=np.float64)
        rejection = self.gate.check(t_s, np.asarray(ranges_m), raw)
        if rejection is not None:
            if rejection is Rejection.POSE_JUMP and self._last_odom is not None:
                # Drop the jump: from now on C ⊕ o continues from the last good scan's odometry.
                self._odom_correction = compose(self._last_odom, inverse(raw))
            odometry = self._corrected(raw)
            return StepResult(StepKind.REJECTED, self._pose_at(odometry), rejection, odometry=odometry)
        odom = self._corrected(raw)
        beam_offsets = None
        if cfg.deskew and self._last_odom is not None and self.gate.previous_t_s is not None:
            beam_offsets = sweep_offsets(
                self.laser, t_s - self.gate.previous_t_s, between(self._last_odom, odom)
            )
        if self._last_odom is not None and self._last_t_s is not None:
            moved = between(self._last_odom, odom)
            step_m = math.hypot(moved[0], moved[1])
            if step_m < REVERSAL_STOP_M_S * (t_s - self._last_t_s):
                self._since_stop_m = 0.0
                self._stood_since_update = True
            else:
                self._since_stop_m += step_m
        self._last_odom = odom
        self._last_t_s = t_s
        increment = np.zeros(3)
        if self._started:
            assert self._update_odom is not None
            increment = between(self._update_odom, odom)
            if (
                math.hypot(increment[0], increment[1]) < cfg.linear_update_m
                and abs(increment[2]) < cfg.angular_update_rad
            ):
                return StepResult(StepKind.GATED, self._pose_at(odom), odometry=odom)
        # Only scans that reach the filter are prepared (most are gated away).
        scan = prepare_scan(
            ranges_m,
            self.laser.angles_rad,
            self.laser.mount,
            max(self.laser.min_range_m, cfg.min_range_m),
            self.laser.no_return_m,
            cfg.max_usable_range_m,
            cfg.grid.resolution_m / 2.0 if cfg.free_margin_m is None else cfg.free_margin_m,
            beam_offsets,
        )
        if not self._started:
            self._started = True
            if cfg.grid_phase_from_walls and self._prior is None:
                self._fit_grid_phase(scan)
            self._integrate(scan, np.zeros(cfg.particles, dtype=np.int64), fresh=True)
            self._update_odom = odom
            self._record(t_s, odom, np.arange(cfg.particles))
            self._add_node(scan, np.arange(cfg.particles), None, None)
            return StepResult(StepKind.FIRST, self._pose_at(None), odometry=odom)
        return self._update(t_s, scan, odom, increment)

    def trajectory(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(times (U,), poses (U, 3), odometry (U, 3)) at every filter update along the ancestry of the
        current best particle: the path its map was built from."""
        if not self.history_poses:
            return np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))
        n = len(self.history_poses)
        first = self._history_first
        cached = (
            self._lineage if self._lineage is not None and self._lineage[1] == self._history_edits else None
        )
        index = self.best_index
        out = np.zeros((n, 3))
        lineage = [0] * n
        for k in range(n - 1, -1, -1):
            if cached is not None:
                # Where this walk meets the last one's lineage, the rest is the last one's: the parents
                # never change, and the poses only where _apply rewrites them (the cache is dropped then).
                j = first + k - cached[0]
                if 0 <= j < len(cached[2]) and cached[2][j] == index:
                    out[: k + 1] = cached[3][j - k : j + 1]
                    lineage[: k + 1] = cached[2][j - k : j + 1]
                    break
            out[k] = self.history_poses[k][index]
            lineage[k] = index
            index = int(self.history_parents[k][index])
        self._lineage = (first, self._history_edits, lineage, out.copy())
        return np.array(self.history_t_s), out, np.array(self.history_odom)

    def mean_trajectory(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """As :meth:`trajectory`, but at every update the mean over the current particles' ancestries,
        each weighted by its particle's current weight (the yaw a circular mean): the posterior mean of
        the path, where :meth:`trajectory` is one sample of it. Why (docs/slam.md, "Open problems", the
        office's lineages): where the scans leave the pose a band of a cell's width (walls on the grid's
        cell boundaries), each lineage random-walks in it with its draws, independently of the others,
        and the weights (effective sample size ~20-28 of 30 on the office) cannot tell them apart; the
        mean takes that walk out, the map's own frame error stays. Not the path any one map was built
        from. O(updates x particles) per call."""
        if not self.history_poses:
            return np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))
        n = len(self.history_poses)
        weights = self.weights
        index = np.arange(len(weights))
        out = np.zeros((n, 3))
        for k in range(n - 1, -1, -1):
            poses = self.history_poses[k][index]
            out[k, :2] = weights @ poses[:, :2]
            out[k, 2] = np.arctan2(weights @ np.sin(poses[:, 2]), weights @ np.cos(poses[:, 2]))
            index = self.history_parents[k][index]
        return np.array(self.history_t_s), out, np.array(self.history_odom)

    def map_window(
        self, particle: int | None = None
    ) -> tuple[npt.NDArray[np.float32], tuple[float, float]] | None:
        """The known part of a particle's map (default: the best) as log-odds (rows = y) and the world
        position of its first cell's lower-left corner; None before the first scan."""
        index = self.best_index if particle is None else particle
        row = index if self.config.map_mode is MapMode.PER_PARTICLE else 0
        rect = self.maps.extent(row)
        if rect is None:
            return None
        stored = self.maps.gather([row], rect)[0]
        return self.config.log_odds.to_log_odds(stored), rect.origin_m(self.config.grid)

    def memory_bytes(self) -> int:
        return self.maps.memory_bytes()

    def seed_map(self, log_odds: npt.NDArray[np.float32], origin_m: tuple[float, float]) -> None:
        """Start from a saved map (lifelong mapping): ``log_odds`` (rows = y, this grid's cell size) with
        its first cell's lower-left corner at ``origin_m``, clamped to the model's limits, becomes every
        particle's map before the first scan; its unknown cells (0) stay unknown. It is also the base a loop
        closure rebuilds the map on (the nodes only hold this run's scans). With
        ``grid_phase_from_walls`` (the default) this grid takes the saved map's phase first, so its cells
        line up exactly; without, cells are placed on the nearest cell of this grid."""
        if self._started:
            raise ValueError("seed_map comes before the first scan")
        if self.config.grid_phase_from_walls:
            # The saved map's own lattice (RbpfConfig.grid_phase_from_walls): its cells line up exactly.
            res = self.config.grid.resolution_m
            self._set_grid(
                dataclasses.replace(
                    self.config.grid, phase_m=(phase_of(origin_m[0], res), phase_of(origin_m[1], res))
                )
            )
        cfg = self.config
        grid, model = cfg.grid, cfg.log_odds
        res = grid.resolution_m
        h, w = log_odds.shape
        x0, y0 = origin_m
        rect = TileRect.covering(
            grid, (x0 + res / 2, y0 + res / 2), (x0 + (w - 0.5) * res, y0 + (h - 0.5) * res)
        )
        rx, ry = rect.origin_m(grid)
        col0, row0 = round((x0 - rx) / res), round((y0 - ry) / res)
        window = self.maps.gather([0], rect)[0]
        counts = np.clip(
            np.round(np.asarray(log_odds, dtype=np.float64) / model.step),
            model.counts(model.minimum),
            model.counts(model.maximum),
        ).astype(np.int8)
        # The part of the saved map inside this grid's extent (a map is never larger in practice).
        r_lo, c_lo = max(0, -row0), max(0, -col0)
        r_hi, c_hi = min(h, window.shape[0] - row0), min(w, window.shape[1] - col0)
        if r_lo >= r_hi or c_lo >= c_hi:
            raise ValueError("the saved map lies outside the grid's extent")
        known = np.zeros(window.shape, dtype=bool)
        part = counts[r_lo:r_hi, c_lo:c_hi]
        target = (slice(row0 + r_lo, row0 + r_hi), slice(col0 + c_lo, col0 + c_hi))
        known[target] = part != 0
        window[known] = part[part != 0]
        t = grid.tile_cells
        touched: BoolArray = np.any(
            known.reshape(known.shape[0] // t, t, known.shape[1] // t, t), axis=(1, 3)
        )
        self._prior = (rect, window[None].copy(), touched[None].copy())
        self._put_prior()

    def _fit_grid_phase(self, scan: ScanPoints) -> None:
        """Before the first scan is mapped: the lattice through the walls it sees from the start pose
        (``RbpfConfig.grid_phase_from_walls``); an axis without a clear wall offset keeps its phase."""
        cfg = self.config
        start = np.asarray(cfg.initial_pose, dtype=np.float64)
        # The normals turned by the start's heading alone: directions, not points.
        turned = transform_points((0.0, 0.0, start[2]), surface_normals(scan.hit_xy))
        fit = fit_grid_phase(transform_points(start, scan.hit_xy), turned, cfg.grid.resolution_m)
        old_x, old_y = cfg.grid.phase_m
        phase_x = old_x if fit.phase_m[0] is None else fit.phase_m[0]
        phase_y = old_y if fit.phase_m[1] is None else fit.phase_m[1]
        log.info(
            "grid phase (%.4f, %.4f) m from the first scan's walls (resultant %.2f / %.2f, %d / %d votes)",
            phase_x,
            phase_y,
            fit.resultant[0],
            fit.resultant[1],
            fit.votes[0],
            fit.votes[1],
        )
        self._set_grid(dataclasses.replace(cfg.grid, phase_m=(phase_x, phase_y)))

    def _set_grid(self, grid: GridGeometry) -> None:
        """Use ``grid`` from now on: only before anything is mapped (the maps hold cells, not points)."""
        self.config = dataclasses.replace(self.config, grid=grid)
        self.maps.geometry = grid

    def _put_prior(self) -> None:
        if self._prior is None:
            return
        rect, window, touched = self._prior
        self.maps.scatter([0], rect, window.copy(), touched)
        if self.maps.maps > 1:
            self.maps.share(np.zeros(self.maps.maps - 1, dtype=np.int64), np.arange(1, self.maps.maps))

    # -- internals -----------------------------------------------------------------------------------
    def _map_rows(self, particles: IntArray) -> IntArray:
        if self.config.map_mode is MapMode.PER_PARTICLE:
            return particles
        return np.zeros_like(particles)

    def _match_points(self, scan: ScanPoints) -> tuple[FloatArray, FloatArray | None]:
        """The endpoints to match (voxel-filtered) and, unless matching is point to point, their surface
        normals."""
        kept = voxel_indices(scan.hit_xy, self.config.match_voxel_m, self.config.max_match_points)
        if self.config.proposal.along_surface_weight == 1.0:
            return scan.hit_xy[kept], None
        return scan.hit_xy[kept], scan_normals(scan, kept, self.config.proposal)

    def _field(self, predicted: FloatArray, points_xy: FloatArray) -> tuple[DistanceField, IntArray]:
        cfg = self.config
        lo, hi = transform_bounds(predicted, points_xy[None, :, :])
        lo -= cfg.field_margin_m
        hi += cfg.field_margin_m
        rect = TileRect.covering(cfg.grid, (float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1])))
        first, window_index = self._field_owners()
        rows = self._map_rows(first)
        if cfg.map_mode is MapMode.SHARED:
            rows = rows[:1]
            window_index = np.zeros(cfg.particles, dtype=np.int64)
        # Crop the tile-aligned windows to the box the points can reach: the transform costs per cell.
        origin = rect.origin_m(cfg.grid)
        res = cfg.grid.resolution_m
        h, w = rect.shape[0] * cfg.grid.tile_cells, rect.shape[1] * cfg.grid.tile_cells
        c0 = min(max(int((lo[0] - origin[0]) / res), 0), w - 1)
        r0 = min(max(int((lo[1] - origin[1]) / res), 0), h - 1)
        c1 = min(max(int(np.ceil((hi[0] - origin[0]) / res)), c0 + 1), w)
        r1 = min(max(int(np.ceil((hi[1] - origin[1]) / res)), r0 + 1), h)
        occupied = cfg.log_odds.counts(cfg.log_odds.occupied)

        def window(k: int) -> Int8Array:
            # One map at a time: the whole stack of windows (and its masks) is never held.
            return self.maps.gather(rows[k : k + 1], rect)[0, r0:r1, c0:c1]

        field_cap = max(max(stage[0] for stage in cfg.proposal.matcher.stages), cfg.proposal.outlier_m)
        field = DistanceField.from_log_odds(
            rows.shape[0],
            (r1 - r0, c1 - c0),
            window,
            occupied,
            (origin[0] + c0 * res, origin[1] + r0 * res),
            res,
            field_cap + res,
        )
        if cfg.proposal.matcher.medial_window_cells > 0:
            field = dataclasses.replace(field, medial_window_cells=cfg.proposal.matcher.medial_window_cells)
        return field, window_index

    def _field_owners(self) -> tuple[IntArray, IntArray]:
        """Whose map each distance field is made of (F,), and each particle's field (P,): one field per
        distinct map, or per lineage for ``shared_field_updates`` after a resampling (the heaviest
        particle's map; of equal weights, the first's)."""
        if self._lineage_age < self.config.shared_field_updates:
            order = np.lexsort((-self.log_weights, self._field_lineage))
            _keys, first_sorted, window_index = np.unique(
                self._field_lineage[order], return_index=True, return_inverse=True
            )
            first = order[first_sorted]
            inverse = np.empty_like(order)
            inverse[order] = np.asarray(window_index, dtype=np.int64).reshape(-1)
            return first.astype(np.int64), inverse
        _groups, first, window_index = np.unique(self._groups, return_index=True, return_inverse=True)
        return first.astype(np.int64), np.asarray(window_index, dtype=np.int64).reshape(-1)

    def _proposal_for(self, increment: FloatArray) -> ProposalConfig:
        """The proposal's settings for this update: with the correlative search only where it is due
        (``RbpfConfig.search_updates``, ``search_increment_*``)."""
        cfg = self.config
        if cfg.proposal.search is None or cfg.search_updates is None:
            return cfg.proposal
        if (
            self.stats.updates < cfg.search_updates
            or math.hypot(increment[0], increment[1]) >= cfg.search_increment_m
            or abs(increment[2]) >= cfg.search_increment_rad
            # (the motion model's heading deviation for the increment: its spread's yaw)
            or (cfg.search_heading_doubt and cfg.noise.spread(increment)[2] >= self._search_heading_doubt)
        ):
            return cfg.proposal
        return self._without_search

    def _update(self, t_s: float, scan: ScanPoints, odom: FloatArray, increment: FloatArray) -> StepResult:
        cfg = self.config
        points, normals = self._match_points(scan)
        flip = np.array([-1.0, -1.0, 1.0])
        check = (
            cfg.reversal_ratio is not None
            and math.hypot(increment[0], increment[1]) >= REVERSAL_MIN_M
            and self._since_stop_m <= REVERSAL_WINDOW_M
        )
        # The turn without the translation is a hypothesis only where the robot stood still since the last
        # update (IN_PLACE_RATIO).
        in_place_ratio = IN_PLACE_RATIO if self._stood_since_update else None
        self._stood_since_update = False
        if check:
            self._direction = 1.0  # the odometry's direction, unless the scan clearly says otherwise
        elif self._direction < 0:
            increment = increment * flip
        self._update_share = self._direction
        fixes_weighted = False
        if points.shape[0] < cfg.proposal.matcher.min_inliers:
            # Too little structure to match: move by the motion model only, keep the weights.
            self.poses = sample_motion(self.poses, increment, cfg.noise, self.rng)
            proposal_log_eta = np.zeros(cfg.particles)
            matched = np.zeros(cfg.particles, dtype=bool)
            information = None
        else:
            predicted = compose(self.poses, increment[None, :])
            lead = self.best_index
            # The field also covers the lead's reversed prediction where the direction is checked.
            reach = predicted
            if check:
                reach = np.vstack([predicted, compose(self.poses[lead], increment * flip)[None, :]])
            field, window_index = self._field(reach, points)
            self.give_way()
            if check:
                assert cfg.reversal_ratio is not None
                travel = travel_reversed(
                    field,
                    int(window_index[lead]),
                    points,
                    self.poses[lead],
                    increment,
                    cfg.noise,
                    cfg.proposal,
                    cfg.reversal_ratio,
                    normals,
                    in_place_ratio,
                )
                log.debug(
                    "travel check at update %d: energy forward %.4f, reversed %.4f, in place %.4f: share %g",
                    self.stats.updates,
                    travel.energy_forward,
                    travel.energy_reversed,
                    travel.energy_in_place,
                    travel.share,
                )
                if travel.share != 1.0:
                    # Reversed, the direction holds until the next check; turned round in place, the
                    # odometry's (the next update is checked again: it is within the window).
                    increment = increment * np.array([travel.share, travel.share, 1.0])
                    predicted = compose(self.poses, increment[None, :])
                    self._direction = -1.0 if travel.reversed else 1.0
                    self._update_share = travel.share
                    self.stats.reversals += int(travel.reversed)
                    self.stats.turns_in_place += int(not travel.reversed)
            measurement = None
            if self._pending_fixes:
                # The fixes join the proposal (and so eta): see ``improved_proposal``.
                heading = float(predicted[self.best_index, 2])
                measurement = fuse_fixes(self._pending_fixes, odom, cfg.noise, heading)
                self._node_fix = measurement
                fixes_weighted = True

            def propose(proposal: ProposalConfig) -> ProposalResult:
                return improved_proposal(
                    field,
                    window_index,
                    points,
                    self.poses,
                    increment,
                    cfg.noise,
                    proposal,
                    self.rng,
                    self.log_weights,
                    normals,
                    measurement,
                )

            proposal = self._proposal_for(increment)
            result = propose(proposal)
            lead_inliers = float(result.match.inlier_fraction[self.best_index])
            if (
                proposal.search is None
                and cfg.proposal.search is not None
                and lead_inliers < cfg.search_below_inliers
            ):
                # (RbpfConfig.search_below_inliers: the match from the prior explained too little.)
                log.debug(
                    "update %d: the lead matched %.2f without the search", self.stats.updates, lead_inliers
                )
                self.stats.searches_on_doubt += 1
                result = propose(cfg.proposal)
            self.poses = result.poses
            proposal_log_eta = result.log_eta
            matched = result.matched
            match_information = result.match.information
            lc_edges = self.config.loop_closure
            if lc_edges is not None and lc_edges.edge_information == "normals" and normals is not None:
                # The front-end edges' covariances from the endpoints with a surface normal only
                # (LoopClosureConfig.edge_information), the match's normals or the information's own.
                line_normals = normals
                if lc_edges.edge_normal_radius_per_m is not None:
                    line_normals = surface_normals(
                        scan.hit_xy,
                        voxel_indices(scan.hit_xy, cfg.match_voxel_m, cfg.max_match_points),
                        max_thickness_m=lc_edges.edge_normal_thickness_m,
                        radius_per_m=lc_edges.edge_normal_radius_per_m,
                        origin_xy=scan.origin_xy,
                    )
                match_information = line_information(
                    result.residuals, line_normals, result.match.poses, cfg.proposal.matcher.stages[-1][0]
                )
            information = np.where(matched[:, None, None], match_information, 0.0)
            # The field (up to ~27 MB for 30 maps of a 15 m scan's box) is done with: not held through
            # the map integration and a loop closure's rebuild below.
            del field, result
            self.give_way()
        self.stats.match_failures += int(np.count_nonzero(~matched))
        self.log_weights = self.log_weights + proposal_log_eta
        if self._pending_fixes:
            if not fixes_weighted:
                self.log_weights = self.log_weights + pending_fixes_log_likelihood(
                    self.poses, self._pending_fixes, odom, cfg.noise
                )
            self.stats.fixes_applied += len(self._pending_fixes)
            self._pending_fixes.clear()
        self.log_weights -= self.log_weights.max()
        w = self.weights
        n_eff = float(1.0 / np.sum(w * w))
        self.stats.n_eff.append(n_eff)
        resampled = n_eff < cfg.resample_threshold * cfg.particles
        if resampled:
            parents = systematic_resample(w, self.rng)
            self.stats.resamples += 1
            self.poses = self.poses[parents]
            self.log_weights = np.zeros(cfg.particles)
            if cfg.map_mode is MapMode.PER_PARTICLE:
                self.maps.select(parents)
        else:
            parents = np.arange(cfg.particles)
        self._integrate(scan, parents, fresh=False)
        if resampled and cfg.map_mode is MapMode.PER_PARTICLE:
            self._field_lineage = self._groups.copy()  # (the copies of one parent: _integrate's groups)
            self._lineage_age = 0
        else:
            self._lineage_age += 1
        self._update_odom = odom
        self._record(t_s, odom, parents)
        self.stats.updates += 1
        self._add_node(scan, parents, points, information)
        trim_heap()  # a no-op unless this process asked for it (agent.slam.malloc.tune_malloc)
        return StepResult(
            StepKind.UPDATED,
            self._pose_at(None),
            None,
            n_eff,
            resampled,
            int(np.count_nonzero(matched)),
            odom,
        )

    def _integrate(self, scan: ScanPoints, parents: IntArray, fresh: bool) -> None:
        """Integrate the scan into every distinct map. After resampling, particles with the same parent
        have the same pose and the same map: integrate once and let the copies share the result."""
        cfg = self.config
        if cfg.map_mode is MapMode.SHARED:
            targets = np.array([self.best_index])
            rows = np.array([0])
            groups = np.zeros(cfg.particles, dtype=np.int64)
        else:
            _, targets, groups = np.unique(parents, return_index=True, return_inverse=True)
            targets = targets.astype(np.int64)
            rows = targets
        groups = np.asarray(groups, dtype=np.int64).reshape(-1)
        if fresh and cfg.map_mode is MapMode.PER_PARTICLE:
            targets = np.array([0])
            rows = np.array([0])
            groups = np.zeros(cfg.particles, dtype=np.int64)
        local = np.vstack([scan.hit_xy, scan.fan_xy, np.array([scan.origin_xy])])
        lo, hi = transform_bounds(self.poses[targets], local[None, :, :])
        lo -= cfg.grid.resolution_m
        hi += cfg.grid.resolution_m
        rect = TileRect.covering(cfg.grid, (float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1])))
        # A few maps at a time: each window, its codes and its update are about one byte per cell, and a
        # 15 m scan's window is 640 x 640 cells (for 30 maps at once, 36 MB passing through the heap).
        t = cfg.grid.tile_cells
        chunk = max(1, _INTEGRATE_CELLS // (rect.shape[0] * rect.shape[1] * t * t))
        for k in range(0, rows.shape[0], chunk):
            part = slice(k, k + chunk)
            windows = self.maps.gather(rows[part], rect)
            touched = integrate_scans(
                windows,
                rect.origin_m(cfg.grid),
                cfg.grid.resolution_m,
                self.poses[targets[part]],
                scan,
                cfg.log_odds,
                t,
            )
            self.maps.scatter(rows[part], rect, windows, touched)
        if cfg.map_mode is MapMode.PER_PARTICLE:
            copies = np.flatnonzero(rows[groups] != np.arange(cfg.particles))
            self.maps.share(rows[groups[copies]], copies)
        self._groups = groups

    # -- loop closure -------------------------------------------------------------------------------
    def _add_node(
        self,
        scan: ScanPoints,
        parents: IntArray,
        points: FloatArray | None,
        information: FloatArray | None,
    ) -> None:
        """A graph node for this update; ``information``: each particle's scan match information (world
        frame, before resampling: indexed by ``parents``), None where nothing was matched."""
        lc = self.config.loop_closure
        if lc is None:
            return
        if len(self._node_scans) + 1 != len(self.history_poses):
            return  # the history was cut (history_limit): node indices no longer line up
        best = self.best_index
        motion = np.zeros(3)
        if len(self.history_poses) > 1:
            parent_pose = self.history_poses[-2][int(parents[best])]
            motion = between(parent_pose, self.history_poses[-1][best])
        self._node_scans.append(scan)
        self._node_hits.append(voxel_filter(scan.hit_xy, lc.resolution_m, 400))
        self._node_motions.append(motion)
        node_information = np.zeros((3, 3))
        if information is not None:
            node_information = robot_frame_information(
                information[int(parents[best])], float(self.history_poses[-1][best, 2])
            )
        if lc.edge_information == "scan":
            relative, scan_motion = self._relative_edge(scan, motion, len(self.history_poses) > 1)
            if relative.any() or not lc.edge_scan_fallback:
                node_information = relative
            self._node_scan_motions.append(scan_motion)
            self._node_scan_guesses.append(motion)
        self._node_information.append(node_information)
        j = len(self._node_scans) - 1
        if self._node_fix is not None:
            variance = 1.0 / np.maximum(np.diag(self._node_fix.information), 1e-12)
            self._fix_factors.append((j, self._node_fix.mean.copy(), np.sqrt(variance)))
            self._node_fix = None
        if points is None or j % lc.check_every != 0:
            return
        if lc.idle_updates is not None and j - self._last_agreement > lc.idle_updates:
            odom = np.array(list(itertools.islice(self.history_odom, self._last_check, None)))
            if float(np.sum(np.hypot(*np.diff(odom[:, :2], axis=0).T))) < lc.idle_path_m:
                return
        self._last_check = j
        t0 = time.perf_counter()
        self.stats.loop_checks += 1
        _, path, _ = self.trajectory()
        since = self._last_agreement
        # The path's steps since the last agreement, once: their sum, and the sum of those since the last
        # known-area judgement (a contiguous tail of the same values: the same sums as two separate
        # diffs of the path).
        steps = np.hypot(*np.diff(path[since:, :2], axis=0).T)
        travelled = float(np.sum(steps))
        odometry = np.array(list(itertools.islice(self.history_odom, since, None)))
        doubt = yaw_doubt(
            between(path[since:-1], path[since + 1 :]), between(odometry[:-1], odometry[1:]), lc
        )
        known_since = max(since, self._known_area_judged)
        known_travelled = float(np.sum(steps[known_since - since :]))
        found = find_loop(path, self._node_hits, points, j, lc, travelled, doubt, known_travelled)
        if found is not None:
            self._judge(path, found)
        self.stats.loop_ms += (time.perf_counter() - t0) * 1e3

    def _relative_edge(
        self, scan: ScanPoints, motion: FloatArray, has_parent: bool
    ) -> tuple[FloatArray, FloatArray]:
        """This node's scan matched point to line against the last node's (LoopClosureConfig.
        edge_information "scan"): its information in this node's robot frame (zeros where it failed) and
        its step (NaN where it failed); the scan's endpoints and normals become the next reference."""
        lc = self.config.loop_closure
        assert lc is not None
        radius = lc.edge_normal_radius_per_m if lc.edge_normal_radius_per_m is not None else 0.1
        information = np.zeros((3, 3))
        step = np.full(3, np.nan)
        if has_parent and self._scan_reference is not None:
            reference, normals = self._scan_reference
            found, step = self._relative_step(reference, normals, self._node_hits[-1], motion)
            if np.isfinite(step[0]):
                information = robot_frame_information(found.information, float(found.pose[2]))
        normals = surface_normals(
            scan.hit_xy,
            max_thickness_m=lc.edge_normal_thickness_m,
            radius_per_m=radius,
            origin_xy=scan.origin_xy,
        )
        self._scan_reference = (scan.hit_xy, normals)
        # Kept per node (float32) only where edges may be matched again (edge_scan_mean).
        self._node_normals.append(normals.astype(np.float32) if lc.edge_scan_mean else None)
        return information, step

    def _rematch_relative(self, motions: FloatArray, recent: IntArray) -> None:
        """The relative matches (``_relative_edge``) of the ``recent`` nodes from ``motions`` where the
        step they started from differs from it (another lineage leads now)."""
        lc = self.config.loop_closure
        assert lc is not None
        for k in recent.tolist():
            if k < 1 or self._node_normals[k - 1] is None:
                continue
            guess = self._node_scan_guesses[k]
            if np.all(np.abs(guess - motions[k]) < _SAME_STEP):
                continue
            normals = self._node_normals[k - 1]
            assert normals is not None
            reference = self._node_scans[k - 1].hit_xy
            _, step = self._relative_step(
                reference, normals.astype(np.float64), self._node_hits[k], motions[k]
            )
            self._node_scan_guesses[k] = motions[k].copy()
            self._node_scan_motions[k] = step

    def _relative_step(
        self, reference: FloatArray, normals: FloatArray, hits: FloatArray, guess: FloatArray
    ) -> tuple[RelativeMatch, FloatArray]:
        """``hits`` matched against the last node's ``reference`` endpoints from ``guess``
        (``relative.match_relative`` with the loop closure's settings), and its step: NaN where it failed
        (too few pairs, or it turned or shifted the filter's step by more than ``edge_scan_max_turn_rad`` /
        ``edge_scan_max_shift_m``)."""
        lc = self.config.loop_closure
        assert lc is not None
        found = match_relative(
            reference,
            normals,
            hits,
            guess,
            bound_m=lc.edge_scan_bound_m,
            coarse_iterations=lc.edge_scan_coarse_iterations,
            anchor=lc.edge_scan_anchor,
        )
        pose, pairs = found.pose, found.pairs
        turn = abs(float(wrap_angle(pose[2] - guess[2])))
        shift = float(np.hypot(pose[0] - guess[0], pose[1] - guess[1]))
        if pairs >= 3 and turn <= lc.edge_scan_max_turn_rad and shift <= lc.edge_scan_max_shift_m:
            return found, np.asarray(pose, dtype=np.float64)
        return found, np.full(3, np.nan)

    def _judge(self, path: FloatArray, found: LoopConstraint) -> None:
        """Judge a candidate (``loops.judge_loop``); an accepted one joins the graph and is applied."""
        lc = self.config.loop_closure
        assert lc is not None
        motions, odometry_motions, absolute = self._graph_inputs(path)
        judgement = judge_loop(
            path,
            self._node_hits,
            motions,
            self._loops,
            found,
            lc,
            absolute,
            odometry_motions,
            self._pending,
            np.array(self._node_information),
            self.config.noise.sigmas(odometry_motions) if lc.correction_odometry_sigmas is not None else None,
        )
        self.stats.loop_verdicts[judgement.verdict.value] += 1
        if found.known_area and judgement.verdict is not Verdict.ACCEPTED:
            self._known_area_judged = found.j
        if judgement.verdict is Verdict.NEAR:
            self._near_loops.append(found)
        log.debug(
            "loop %d -> %d: %s (innovation chi2 %.1f, residual %.1f, scans %.4f -> %.4f)",
            found.i,
            found.j,
            judgement.verdict.value,
            judgement.innovation_chi2,
            judgement.residual_chi2,
            judgement.score_before,
            judgement.score_after,
        )
        if judgement.verdict is Verdict.AGREES:
            # A true link, kept for the next optimisation, but nothing to correct now.
            self._loops.append(found)
            self.stats.loop_closures += 1
            self._last_agreement = found.j  # the drift since is measured from here
            return
        if judgement.verdict is Verdict.UNCONFIRMED:
            self._pending = [p for p in self._pending if found.j - p.j <= lc.confirm_nodes] + [found]
            return
        if judgement.verdict is not Verdict.ACCEPTED or judgement.result is None:
            return
        for partner in judgement.partners:
            self._pending.remove(partner)
            self._loops.append(partner)
        self._loops.append(found)
        self._last_agreement = found.j
        self.stats.loop_closures += 1
        self._node_motions = list(motions)
        self.give_way()
        self._apply(path, judgement.result)

    def finish(self) -> bool:
        """The final optimisation (``LoopClosureConfig.final_scan_chain``): the pose graph with its chain
        measured scan to scan and every loop factor and fix, applied to the history, the particles and the
        map as a loop closure is. For the end of a log or of a mapping run, before the map is saved; the
        filter may go on after it. Returns whether it ran (off, no loop factor yet, or a history that no
        longer lines up with the graph: it does not)."""
        lc = self.config.loop_closure
        loops = self._loops + self._near_loops
        if lc is None or lc.final_scan_chain is None or not loops:
            return False
        try:
            state = self.graph_state()
        except ValueError as exc:
            log.info("no final optimisation: %s", exc)
            return False
        t0 = time.perf_counter()
        chain, measured = scan_chain(self._node_hits, state.motions, lc.final_scan_chain)
        result = optimize_graph(state.path, chain, loops, lc, state.absolute)
        self.stats.final_scan_edges = int(np.count_nonzero(measured))
        self._node_motions = list(chain)
        self._apply(state.path, result)
        elapsed_s = time.perf_counter() - t0
        self.stats.loop_ms += elapsed_s * 1e3
        log.info(
            "final optimisation in %.2f s: %d of %d steps measured scan to scan, %d loop factors, "
            "chi2 %.1f -> %.1f",
            elapsed_s,
            self.stats.final_scan_edges,
            max(len(chain) - 1, 0),
            len(loops),
            result.chi2_initial,
            result.chi2_final,
        )
        return True

    def graph_state(self) -> GraphState:
        """The loop closure's pose graph as it stands (``loops.GraphState``): the nodes along the current
        best particle's ancestry, the chain's steps as the next optimisation would take them, the
        odometry's, the loop factors and the fixes' absolute factors. Raises ``ValueError`` when the
        filter runs without loop closure or its history no longer lines up with the graph's nodes
        (``history_limit`` reached)."""
        if self.config.loop_closure is None:
            raise ValueError("this filter runs without loop closure: it keeps no pose graph")
        path = self.trajectory()[1]
        if path.shape[0] != len(self._node_scans):
            raise ValueError(
                f"the history ({path.shape[0]} updates) no longer lines up with the graph's "
                f"{len(self._node_scans)} nodes (history_limit reached)"
            )
        motions, odometry_motions, absolute = self._graph_inputs(path)
        return GraphState(path, motions, odometry_motions, tuple(self._loops), absolute)

    def _graph_inputs(self, path: FloatArray) -> tuple[FloatArray, FloatArray, AbsoluteFactors | None]:
        """The chain's motions (since the last optimisation: the leading lineage's ancestry, the front
        end's best account), the odometry's motions beside them, and the VLP fixes' absolute factors."""
        motions = np.array(self._node_motions)
        recent = np.arange(self._anchored + 1, path.shape[0])
        motions[recent] = between(path[recent - 1], path[recent])
        lc = self.config.loop_closure
        if lc is not None and lc.edge_scan_mean and len(self._node_scan_motions) == motions.shape[0]:
            # The relative matches' steps in place of the filter's (LoopClosureConfig.edge_scan_mean).
            # Only where the two disagree by more than the edge's own covariance (edge_scan_gate_chi2):
            # the front end's snap onto its map, not the relative match's own noise.
            # Only where the chain's step is the one the relative match started from (the leading
            # lineage then): another lineage's step was matched from another guess.
            # A recent node whose lineage's step is not the one its relative match started from is
            # matched again from this one.
            self._rematch_relative(motions, recent)
            scan_motions = np.array(self._node_scan_motions)
            guesses = np.array(self._node_scan_guesses)
            same = np.all(np.abs(guesses - motions) < _SAME_STEP, axis=1)
            measured = np.isfinite(scan_motions[:, 0]) & same
            if lc.edge_scan_gate_chi2 > 0.0 and motions.shape[0] > 1:
                gap = np.where(measured[:, None], scan_motions - motions, 0.0)
                gap[:, 2] = wrap_angle(gap[:, 2])
                covariance = edge_covariances(motions, np.array(self._node_information), lc)
                chi2 = np.zeros(motions.shape[0])
                chi2[1:] = np.einsum(
                    "ki,ki->k", gap[1:], np.linalg.solve(covariance, gap[1:, :, None])[..., 0]
                )
                measured &= chi2 > lc.edge_scan_gate_chi2
            log.debug("edges from the relative matches' steps: %s", np.flatnonzero(measured).tolist())
            motions[measured] = scan_motions[measured]
        odometry = np.array(self.history_odom)
        odometry_motions = np.zeros_like(odometry)
        odometry_motions[1:] = between(odometry[:-1], odometry[1:])
        # In the direction of travel the filter took them in (reversed where the scans said so).
        odometry_motions[:, :2] *= np.array(self.history_share)[:, None]
        if lc is not None and lc.snap_forward_m is not None:
            since = np.array(self.history_since_stop_m)
            steady = np.zeros(since.shape[0], dtype=bool)
            steady[1:] = (since[1:] >= lc.snap_steady_m) & (since[:-1] >= lc.snap_steady_m)
            motions = odometry_forward_at_snaps(motions, odometry_motions, steady, lc.snap_forward_m)
        absolute = None
        if self._fix_factors:
            absolute = AbsoluteFactors(
                np.array([f[0] for f in self._fix_factors], dtype=np.int64),
                np.array([f[1] for f in self._fix_factors]),
                np.array([f[2] for f in self._fix_factors]),
            )
        return motions, odometry_motions, absolute

    def _apply(self, path: FloatArray, result: GraphResult) -> None:
        """Put the history, the particles and the maps on the optimised poses."""
        lc = self.config.loop_closure
        assert lc is not None
        optimised = result.poses
        shift = np.abs(optimised - path)
        if (
            float(np.max(np.hypot(shift[:, 0], shift[:, 1]))) < lc.apply_min_shift_m
            and float(np.max(np.abs(wrap_angle(shift[:, 2])))) < lc.apply_min_shift_rad
        ):
            return
        self.stats.loop_rebuilds += 1
        log.debug(
            "loop closure %d: chi2 %.1f -> %.1f, %d factors downweighted",
            len(self._loops),
            result.chi2_initial,
            result.chi2_final,
            result.downweighted,
        )
        last = optimised.shape[0] - 1
        self.poses = compose(optimised[last], between(path[last], self.poses))
        for k in range(last):
            self.history_poses[k][:] = optimised[k]
        self.history_poses[last][:] = self.poses
        self._anchored = last
        self._history_edits += 1  # the history's poses were rewritten: trajectory's cache is stale
        self._rebuild_maps(optimised)

    def _rebuild_maps(self, poses: FloatArray) -> None:
        """One map from every node's scan at its pose, shared by all particles. Built in one window over
        every node's box (a byte a cell: Intel ~1 MB, at most the table's 16 MB) instead of a table
        gather and a copy-on-write scatter per node: the same cells updated in the same order, the same
        map (checked on Intel's first 400 records), each rebuild 7-35 % less CPU."""
        cfg = self.config
        if not self._node_scans:
            self.maps.clear()
            self._put_prior()
            self._groups = np.zeros(cfg.particles, dtype=np.int64)
            self._lineage_age = _NO_LINEAGE
            return
        t = cfg.grid.tile_cells
        rects = []
        for k, scan in enumerate(self._node_scans):
            local = np.vstack([scan.hit_xy, scan.fan_xy, np.array([scan.origin_xy])])
            lo, hi = transform_bounds(poses[k][None, :], local[None, :, :])
            lo -= cfg.grid.resolution_m
            hi += cfg.grid.resolution_m
            rects.append(
                TileRect.covering(cfg.grid, (float(lo[0]), float(lo[1])), (float(hi[0]), float(hi[1])))
            )
        whole = TileRect(
            min(r.ty0 for r in rects),
            min(r.tx0 for r in rects),
            max(r.ty1 for r in rects),
            max(r.tx1 for r in rects),
        )
        row = np.array([0])
        # Built aside, the maps left as they are until it is whole: a give_way that raises (the agent's
        # SLAM process stopping) leaves the maps from before this loop closure, not half a map.
        window = self._prior_window(whole)
        touched = np.zeros((1, *whole.shape), dtype=bool)
        for k, (scan, rect) in enumerate(zip(self._node_scans, rects, strict=True)):
            ty, tx = rect.ty0 - whole.ty0, rect.tx0 - whole.tx0
            tiles = (slice(None), slice(ty, ty + rect.shape[0]), slice(tx, tx + rect.shape[1]))
            cells = (
                slice(None),
                slice(ty * t, (ty + rect.shape[0]) * t),
                slice(tx * t, (tx + rect.shape[1]) * t),
            )
            # Integrated in place through the view of the node's cells (one window: integrate_scans'
            # whole-stack operations run on its rows as they lie), not into a copy written back.
            touched[tiles] |= integrate_scans(
                window[cells],
                rect.origin_m(cfg.grid),
                cfg.grid.resolution_m,
                poses[k][None, :],
                scan,
                cfg.log_odds,
                t,
            )
            if k % 64 == 63:
                self.give_way()
        self.maps.clear()
        self._put_prior()
        self._groups = np.zeros(cfg.particles, dtype=np.int64)
        self._lineage_age = _NO_LINEAGE
        self.maps.scatter(row, whole, window, touched)
        if self.maps.maps > 1:
            self.maps.share(np.zeros(self.maps.maps - 1, dtype=np.int64), np.arange(1, self.maps.maps))

    def _prior_window(self, whole: TileRect) -> Int8Array:
        """Map 0 over ``whole`` as it is after ``maps.clear()`` and ``_put_prior()`` (the saved map's cells,
        unknown elsewhere), shape (1, h*T, w*T), without clearing the maps."""
        t = self.config.grid.tile_cells
        window = np.zeros((1, whole.shape[0] * t, whole.shape[1] * t), dtype=np.int8)
        if self._prior is None:
            return window
        rect, prior, _ = self._prior  # the prior's untouched tiles are unknown (0) in its window too
        ty0, tx0 = max(rect.ty0, whole.ty0), max(rect.tx0, whole.tx0)
        ty1, tx1 = min(rect.ty1, whole.ty1), min(rect.tx1, whole.tx1)
        if ty0 < ty1 and tx0 < tx1:
            rows, cols = slice(ty0 * t, ty1 * t), slice(tx0 * t, tx1 * t)  # in cells of the whole grid

            def within(r: TileRect) -> tuple[int, slice, slice]:
                dy, dx = r.ty0 * t, r.tx0 * t
                return 0, slice(rows.start - dy, rows.stop - dy), slice(cols.start - dx, cols.stop - dx)

            window[within(whole)] = prior[within(rect)]
        return window

    def _record(self, t_s: float, odom: FloatArray, parents: IntArray) -> None:
        if self.history_poses.maxlen is not None and len(self.history_poses) == self.history_poses.maxlen:
            self._history_first += 1  # the oldest entry goes
        self.history_poses.append(self.poses.copy())
        self.history_parents.append(np.asarray(parents, dtype=np.int64))
        self.history_t_s.append(t_s)
        self.history_odom.append(odom.copy())
        self.history_share.append(self._update_share)
        self.history_since_stop_m.append(self._since_stop_m)
