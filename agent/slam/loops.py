"""Loop closure: the current scan matched against the map built long ago, as a constraint in a pose graph.

The particle filter is the front end: each filter update is a node of the graph, tied to the one before by
the leading lineage's own motion (scan-matched, locally good). Every ``check_every`` updates the scan of
the newest node j is matched against a map drawn from the scans of the nodes around the nearest old node
i (at least ``min_separation`` updates back, within ``search_radius_m`` of where the graph puts j): an
exhaustive correlative search over ±``search_xy_m`` and ±``search_yaw_rad`` on a coarse lattice (each
rotation's points computed once, translations as whole-cell shifts), refined by Gauss-Newton
(``agent.slam.matcher.match``). A match that puts at least ``min_inlier_fraction`` of the endpoints on the
old walls is a candidate, judged by :func:`judge_loop` (do the newest scans show the map coming apart
there, does it say more than its own noise, does the graph take it, do the scans fit better after): a
link the graph already agrees with joins it without an optimisation; one that passes every test joins it
and the graph (``agent.slam.posegraph``) is optimised with every loop factor so far (Huber kernel: a
wrong one pulls with bounded force); the others are dropped. What the filter does with
the result (rebuild its map at the optimised poses) is ``RbpfSlam``'s business; this module is pure.
"""

from __future__ import annotations

import enum
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from typing import Literal

import cv2
import numpy as np
import numpy.typing as npt

from agent.slam.matcher import DistanceField, MatcherConfig, MatchResult, match, world_points
from agent.slam.pose import between, compose, transform_points, wrap_angle
from agent.slam.posegraph import (
    AbsoluteFactors,
    GraphResult,
    RelativeFactors,
    optimize,
    relative_residuals,
    sqrt_information,
)
from agent.slam.scan_chain import ScanChainConfig

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LoopClosureConfig:
    check_every: int = 3
    # While nothing closes: once ``idle_updates`` updates have passed since a link last agreed with the
    # graph or closed, a check runs only where the odometry path since the last check reaches
    # ``idle_path_m`` (a robot turning on the spot, or creeping, is not checked every ``check_every``
    # updates). None (the default): every ``check_every`` updates. Measured for issue 20 and not adopted:
    # docs/slam.md, "Speed and memory beside GMapping".
    idle_updates: int | None = None
    idle_path_m: float = 2.0
    min_separation: int = 40  # updates between the two nodes
    window_path_m: float = 5.0  # the old map: the nodes within this path length of node i
    # The search window grows with the distance driven since the last closure (the graph's drift):
    # xy = min(search_xy_m + xy_per_m * d, max_search_xy_m), yaw likewise; old nodes are looked for
    # within xy + ``search_radius_m`` of where the graph puts the new one.
    search_xy_m: float = 1.0
    xy_per_m: float = 0.05
    max_search_xy_m: float = 4.0
    search_yaw_rad: float = 0.15
    yaw_per_m: float = 0.005
    max_search_yaw_rad: float = 0.6
    search_radius_m: float = 3.0
    # Old windows searched per check: the nearest old node's, then those of the next nearest nodes at
    # least ``2 * window_path_m`` of path from every window taken (a revisit after metres of drift is
    # often nearer a different pass through the building than to the place the graph puts it), up to
    # this many; the best unambiguous match among them wins.
    max_windows: int = 3
    # Coarse lattice on a coarse field, then a fine one around the best coarse pose, then Gauss-Newton.
    coarse_resolution_m: float = 0.2
    coarse_yaw_step_rad: float = 0.04
    coarse_truncate_m: float = 0.4
    resolution_m: float = 0.05
    fine_yaw_step_rad: float = 0.01
    truncate_m: float = 0.3
    min_inlier_fraction: float = 0.75
    # Accepted only when the best coarse cost is at most this share of the best one elsewhere (at least
    # ``distinct_xy_m`` or ``distinct_yaw_rad`` away): a corridor or a row of like rooms has a second
    # answer nearly as good.
    max_ambiguity: float = 0.6
    distinct_xy_m: float = 0.6
    distinct_yaw_rad: float = 0.15
    # Judged at the fine resolution over the old map's known area (0: off, the coarse tests above): the
    # ``hypotheses`` best coarse poses of each window, each at least ``distinct_*`` from the ones before
    # (the coarse lattice then only proposes, as a branch-and-bound's coarse levels only bound), are each
    # refined (fine lattice, Gauss-Newton) and scored over the endpoints that land where the old scans'
    # beams reached (an old wall, or the free space a beam crossed to it: :func:`known_fit`); endpoints
    # in space the old window never saw say nothing either way (the revisit sees what the first pass did
    # not). The best (least cost over its known endpoints) is the candidate when its cost is below
    # ``known_ambiguity`` of every other refined hypothesis's at least ``distinct_*`` away, it has at
    # least the matcher's ``min_inliers`` inliers, and they are at least ``min_inlier_fraction`` of its
    # known endpoints. The cost no longer carries the floor of the endpoints no pose can place (each
    # truncated), so its ratios are lower than the coarse test's: on exp1 (seeds 0 and 1) the true links
    # came out at 0.08-0.17, every wrong best with the inliers to pass at 0.56 or more.
    # The search window is taken as the graph's 3-sigma box around where it puts the new node (x, y:
    # xy / 3 each, yaw: yaw / 3): a candidate whose offset from there has a squared Mahalanobis distance
    # above ``prior_chi2`` (chi²(3)'s 99 % quantile) lies in the box's corners, beyond what the drift
    # allows, and is dropped (only with ``hypotheses``). The factor is then measured against the scan of
    # the window's node nearest the match alone (where that match fails, the window's).
    # With ``known_area_fallback`` (the default) the rule is scoped to what the coarse tests cannot do:
    # it runs only where they found no candidate (every window ambiguous, or too few endpoints on the old
    # walls), and its link acts only where it disagrees with the graph by more than its own noise (the
    # innovation above ``agree_chi2``, :func:`judge_loop`'s NEAR: a link the graph already agrees with is
    # counted, not added: it would change nothing but add a match's noise). False: the rule replaces the
    # coarse tests and its links are judged as theirs are: 4 closes exp1's loop for 6 of 6 seeds (0-5) but
    # makes Intel, ACES and the office worse (docs/slam.md, "Open problems", exp1's loop, seed 1).
    # ``known_area_after_m``: with the fallback, the rule runs only once the front end has driven this far
    # since a link last joined the graph (a long loop's first return, where the window is at its widest
    # and the coarse ambiguity test at its weakest: exp1's 25 m). On Intel (seed 0) known-area links
    # found after 1-17 m, where the coarse tests were ambiguous, disagreed with a graph that was right
    # (innovations of 11-3300, 20 acted on: ate_aligned_m 0.074 -> 0.338 m). All three scopes together,
    # N = 4: exp1 closes for 6 of 6 seeds (0-5); Intel seeds 0-3, ACES 0-1 and the office 0-3 as with 0
    # (held-out Intel seed 4: ate_aligned_m 0.117 -> 0.124 m); but the office's held-out seeds 10, 14, 18
    # and 22 acted on known-area links and rebuilt (0.026-0.029 -> 0.146 / 0.156 / 0.043 / 0.119 m; 11 of
    # 24 over 3 cm against 7) until ``known_area_verify_ratio`` (below) refused those links. With it and
    # 4, SLAMCHECK's whole table holds (exp1 6 of 6, the office identical at every seed, ACES seed 2
    # 0.176 -> 0.139 m); its searches cost 3-6 % of our CPU on exp1 (cpu_ratio beside GMapping 0.44-0.46
    # off, 0.46-0.485 on, three alternating runs at load 1; 0.497-0.508 at load 3-5 before slam-cpu-13's
    # exact speed-ups). The default since session 13 (docs/slam.md, "Loop closure"; 0 turns it off).
    hypotheses: int = 4
    known_area_fallback: bool = True
    known_area_after_m: float = 20.0
    # A known-area link acts only where the newest scans show the map come apart by at least this (the
    # judge's ``fit_m`` for its links: their matches are the ones the coarse tests found ambiguous, so
    # they need the scans' plainer word). exp1 (seeds 1, 2): 0.20-0.25 m; Intel seed 0's first return
    # (66 m, a link that took ate_aligned_m 0.074 -> 0.120 m): 0.10 m.
    known_area_fit_m: float = 0.15
    # ... and only where the graph's correction brings the newest scans onto the old walls plainly: their
    # score at the optimised poses at most this share of their score before (the judge's ``verify_ratio``
    # for its links; squared distances, so 0.25 is the median endpoint's distance halved). Without it the
    # office's seeds 10, 14, 18 and 22 acted on one link each (i 25 -> j 93-105, 0.04-0.37 m off the
    # truth where the graph was 0.02-0.04 m off) whose newest scans lay nowhere near the old window
    # (median at the truncation, 0.3 m, before and after: "comes apart" and "no worse" both held by
    # saturation); exp1's links (seeds 1, 2) take the median from 0.25 / 0.20 m to 0.05 m.
    known_area_verify_ratio: float = 0.25
    known_ambiguity: float = 0.3
    prior_chi2: float = 11.34
    # Standard deviations of the factors (x, y in the first node's frame; yaw).
    motion_sigma: tuple[float, float, float] = (0.03, 0.03, 0.01)
    loop_sigma: tuple[float, float, float] = (0.05, 0.05, 0.01)
    # A loop factor's covariance is diag(loop_sigma²) plus the match's own, s² (Σ J Jᵀ)⁻¹ with s this
    # (an endpoint's residual, inflated for neighbouring endpoints that err together): where the old walls
    # fix a direction poorly (along a corridor) the factor then says little in it instead of pulling the
    # graph to wherever the match slid. None (the default): loop_sigma alone. With the front end's edges at
    # 3 cm / 0.01 rad it let Intel fold (seed 0: ate_aligned_m 0.26 -> 2.02 m): docs/slam.md.
    match_sigma_m: float | None = None
    huber: float = 3.0
    # A front-end edge's yaw standard deviation grows with how far the scan match moved it from odometry:
    # sigma_yaw = max(motion_sigma yaw, share * |yaw_match - yaw_odometry|) (likewise in x, y): where the
    # match turned the robot by 10 deg against its wheels, either the wheels slipped or the match failed,
    # and a loop's correction belongs there rather than spread over every edge.
    correction_share: float = 0.5
    # A front-end edge whose forward step (x in node k-1's frame) departs from the odometry's by more than
    # ``snap_forward_m`` while the robot drives steadily (at least ``snap_steady_m`` of odometry since its
    # last standstill at both of the edge's nodes) takes the odometry's forward step: a snap. Along a
    # corridor the walls hardly fix the match's position along the way, and the front end can jump in one
    # step onto an older part of its map that carries the corridor's whole length error (ACES's record
    # 329: 0.52 m short in one 1 m step); no loop link spans the corridor to move that jump, and widening
    # the edge's sigma lets the graph keep it (``correction_share``). Over one steady metre the wheels'
    # forward step errs by centimetres. Near a standstill it does not: where a log's odometry does not
    # know the direction of travel (FR079's, rebuilt: 48 of its 1550 steps 0.2-0.7 m off, each a reversal
    # or a back-and-forth between two updates) the match is right. The odometry there is taken in the
    # direction the filter took it (``RbpfConfig.reversal_ratio``). None: the match's step everywhere.
    # Measured for issue 20: docs/slam.md, "Open problems" (session 24).
    snap_forward_m: float | None = 0.15
    snap_steady_m: float = 1.0
    # ... counting only the part of that departure the odometry's own noise does not explain
    # (``correction_odometry_sigmas`` = k set, and the filter's motion model's sigmas of each odometry
    # increment handed in, ``OdometryNoise.sigmas``): the edge is widened by share * max(0, |match -
    # odometry| - k sigma_odometry) per component. Where the wheels are as bad as the motion model says
    # (Intel's and ACES's rebuilt odometry: on-the-spot turns 5-14 deg off), a match that departs from them
    # by that much is no sign that the match failed, and a loop's correction put on such an edge bends the
    # trajectory there (a heading kink that every later node inherits until the next loop). None (the
    # default): the whole departure. Measured for issue 20: docs/slam.md, "Loop closure".
    correction_odometry_sigmas: float | None = None
    # A front-end edge's covariance from its own scan match instead (``edge_match_sigma_m`` set; the
    # filter then records each node's match information, :func:`edge_covariances`): the edge k-1 -> k
    # is diag(motion_sigma²) plus the covariance of node k's match against its particle's map,
    # (Σ J Jᵀ / s² + diag(edge_max_sigma)⁻²)⁻¹ in node k's frame, s this (an endpoint's residual,
    # inflated for neighbouring endpoints that err together): a match the walls hold is tight in every
    # direction whatever odometry said (an on-the-spot turn where the wheels slipped 10 deg), a corridor's
    # is loose along the corridor, a failed match is ``edge_max_sigma`` loose. ``correction_share`` then
    # widens only the loop search (:func:`yaw_doubt`), not the edges. None (the default): the edges as
    # above. Measured for issue 20: docs/slam.md, "Open problems".
    edge_match_sigma_m: float | None = None
    edge_max_sigma: tuple[float, float, float] = (0.3, 0.3, 0.1)
    # Which information of node k's match the edge's covariance is built from (with
    # ``edge_match_sigma_m``): "match", the match's own Σ J Jᵀ over its inliers; "normals", the
    # point-to-line information of the inliers that have a surface normal only (Σ g gᵀ, g = (n, p' × n):
    # ``matcher.line_information``; where the filter matches point to point, without normals, the
    # match's). On ACES an endpoint without a normal (60-75 % of an inner corridor's) is pulled along a
    # side wall the map holds in patches, and Σ J Jᵀ counts that pull as information along the corridor
    # (19-42 where scan-to-scan ICP has 1-6): the edge is then as tight along the corridor as across, and
    # a loop closure cannot spread the corridor's length error along it. The heading block is the lines'
    # too (each line's endpoints' lever arm), with its coupling to the translation across the lines.
    # Opt-in: on ACES (s 0.02-0.1) seeds 0, 3, 4 gain 0.03-0.11 m but seeds 1 and 5 lose up to 0.13 m (only
    # 15-25 endpoints of a scan have a normal, so nearly every edge is loose in some direction and a loop's
    # correction spreads over the whole chain); FR079 seed 0 0.197 -> 0.387 m at s = 0.02. Measured for
    # issue 20: docs/slam.md, "Loop closure" and "Open problems" (ACES).
    # "scan": the information of a relative measurement instead, node k's scan matched point to line
    # against node k-1's scan (``relative.match_relative``, the reference's normals as below, 0.1 × range
    # where ``edge_normal_radius_per_m`` is unset): only what the two scans share, so a corridor whose
    # ends are out of view is loose along it, and a step where the map's far walls come back into view
    # (the front end's snap by the whole corridor's length error, ACES record 329) is not made tight by
    # the map having seen them. Measured for issue 20: docs/slam.md, "Open problems" (ACES).
    edge_information: Literal["match", "normals", "scan"] = "match"
    # ... and, with "scan", the edge's mean from that match too (True) rather than the filter's step
    # (False, the default): the filter's step where the two scans do not fix a direction (damped).
    edge_scan_mean: bool = False
    # ... only at the edges where the two steps differ by more than this squared Mahalanobis distance
    # under the edge's covariance (0: every edge the relative match measured).
    edge_scan_gate_chi2: float = 0.0
    # ... the relative match's bound on a pair's offset across its line (m); a relative match that
    # turns or shifts the filter's step by more than these failed (a wrong minimum: the filter's heading
    # is held by the whole map), and its edge is the filter's (``edge_max_sigma`` loose).
    edge_scan_max_turn_rad: float = 0.05
    # ... with this many first iterations pairing within 0.5 m (``relative.match_relative``'s coarse
    # bound), so that a step the filter put tens of centimetres off is still pulled back.
    edge_scan_coarse_iterations: int = 0
    # ... and the weight of its pull towards the filter's step (per m², rad²; ``match_relative``'s anchor).
    edge_scan_anchor: float = 5.0
    # ... and where the relative match failed (too few pairs, or past the guards), the front end's own
    # match's information (True) rather than none (``edge_max_sigma`` loose; False, the default).
    edge_scan_fallback: bool = False
    # With ``edge_match_sigma_m``: a candidate's consistency tests (:func:`judge_loop`: its residual after
    # the optimisation, the loops it leaves off) on the chain without the edges' covariances (True: the
    # sigmas widened by the departure from odometry), the accepted graph with them. Loose edges let the
    # chain absorb a wrong link (FR079 seed 0, relative edges: 12 -> 75, innovation χ² 7007, residual 1.0
    # where the plain chain leaves 233). False (the default): the edges' covariances throughout.
    edge_judge_plain: bool = False
    edge_scan_max_shift_m: float = 0.5
    edge_scan_bound_m: float = 0.15
    # ... with "normals", the surface normals the information is taken from: the match's own (None, the
    # default), or the scan's normals estimated for the information alone from a neighbourhood of
    # max(0.25 m, this × range) and up to ``edge_normal_thickness_m`` thick (``grid.surface_normals``; the
    # match keeps its own normals). At the radish defaults only 24-40 % of ACES's inner corridors'
    # endpoints get a normal (1 deg beams 0.1-0.5 m apart on a wall at a grazing angle, centimetre range
    # noise); at 0.1 and 3 cm 61-81 %.
    edge_normal_radius_per_m: float | None = None
    edge_normal_thickness_m: float = 0.03
    # ... on a floor of each edge's own ``motion_sigma`` widened by ``correction_share`` of its departure
    # from odometry (the edges without ``edge_match_sigma_m``) instead of ``motion_sigma``: the match's
    # covariance adds where the scan is weak (a corridor's length), the departure where the match turned
    # against the wheels. False: ``motion_sigma``.
    edge_departure_floor: bool = False
    # The final optimisation (``RbpfSlam.finish``, at the end of a log or a mapping run): the graph with
    # its chain's steps measured by the scans alone, each node's scan registered against the one before
    # it (``scan_chain.scan_chain``: point to point, from the front end's step; where a registration is
    # not kept, the front end's step), held at ``motion_sigma`` (not widened by the departure from
    # odometry), with every loop factor and fix the filter gathered; run only where the graph has a loop
    # factor (a chain alone drifts like odometry: the front end's map match drifts less). None: off.
    # ACES seeds 0-5 (offline, on the final graphs): 0.159 -> 0.112 m mean; FR079 0.117 -> 0.077; Intel
    # 0.083 -> 0.080 (docs/slam.md, "Loop closure", *The final optimisation*).
    final_scan_chain: ScanChainConfig | None = field(default_factory=ScanChainConfig)
    # An optimisation that moves no node by more than this leaves the filter as it is (its map rebuild
    # costs a whole map's integration); the loop factor stays for the next one.
    apply_min_shift_m: float = 0.05
    apply_min_shift_rad: float = 0.01
    # Judging a candidate before it joins the graph (:func:`judge_loop`):
    # * where the scans fit the old map (``fit_m`` below), the link's innovation (the match against where
    #   the graph already puts j seen from i) as a squared Mahalanobis distance under the loop factor's
    #   own covariance: below ``agree_chi2`` the graph agrees within the match's noise and a correction
    #   would only add that noise (the office: 38 such links, one of them 6.6 cm off the truth, doubled
    #   the ATE): the link joins the graph for later optimisations but triggers none. 11.34 is chi²(3)'s
    #   99 % quantile.
    agree_chi2: float = 11.34
    # * the graph must take it: after a tentative optimisation with it, its own squared residual at most
    #   this (Huber's threshold squared: a link the kernel down-weights is one the other factors
    #   contradict), and no earlier loop factor pushed past it that was not already;
    accept_chi2: float = 9.0
    # * optionally (``accept_graph_chi2`` set), the whole graph must take it: the optimised graph's
    #   chi² with it at most this much above the graph's without it. A link that slid along a corridor
    #   can fit its own factor and every earlier loop's by bending the chain: the graph puts it on one
    #   loose edge (an on-the-spot turn whose match departed from odometry) far beyond Huber's threshold
    #   (ACES seed 4, link 192 -> 363, 1.40 m off the reference: the graph's chi² 2.5 -> 147.9, one edge
    #   down-weighted; every true link there and at seed 0 adds at most 0.7, one behind the bad link 11.7).
    #   chi²(3)'s 99.9 % quantile is 16.3. None: not tested.
    accept_graph_chi2: float | None = 16.3
    # * the scans must agree: the newest ``verify_nodes`` nodes' endpoints against the old map at the
    #   optimised poses score at most ``verify_ratio`` of their score at the current ones (mean truncated
    #   squared distance, truncated at ``truncate_m``).
    verify_nodes: int = 5
    verify_ratio: float = 1.0
    # * the map must come apart there: the newest ``verify_nodes`` scans against the old map at the current
    #   poses, RMS truncated distance, at least ``fit_m``. Below it the scans already lie on the old walls
    #   and a link that says otherwise slid (the office, seed 7: one link 19 cm along a corridor, among 37
    #   that agreed with the graph, the scans at 2.7 cm RMS; accepted, the ATE went from 3.7 to 7.5 cm).
    fit_m: float = 0.05
    # * optionally (``require_confirmation``) confirmed, RRR's clustering with PCM's pairwise test: acted
    #   on only together with another such link found within ``confirm_nodes`` updates before it that
    #   agrees with it: z_b against z_a carried by the graph's short chains i_b -> i_a and j_a -> j_b,
    #   squared Mahalanobis distance under twice the loop factor's covariance plus ``chain_sigma`` per
    #   chain edge, at most ``pairwise_chi2``. Off: on Intel (seed 0) it lost true links that no second
    #   one followed soon enough, and the drift they would have taken out grew until two wrong links
    #   from one old window (15 deg off) confirmed each other (ate_aligned_m 1.53 m). Pending links that
    #   agree with an accepted one still join the graph with it.
    require_confirmation: bool = False
    confirm_nodes: int = 30
    pairwise_chi2: float = 7.81
    chain_sigma: tuple[float, float, float] = (0.01, 0.01, 0.003)
    matcher: MatcherConfig = field(default_factory=MatcherConfig)


_LATTICE_INDICES = 1 << 16  # lattice_search: (rotations, translations, points) indices per batch (0.5 MB)


@dataclass(frozen=True)
class LoopConstraint:
    i: int
    j: int
    z: FloatArray  # x_j in x_i's frame
    inlier_fraction: float
    # The match's covariance of z (3 x 3, in x_i's frame; LoopClosureConfig.match_sigma_m), or None.
    covariance: FloatArray | None = None
    # Found by the known-area rule where the coarse tests found nothing (LoopClosureConfig.hypotheses
    # with known_area_fallback): acted on only where it disagrees with the graph (judge_loop, NEAR).
    known_area: bool = False


def old_map_field(
    poses: FloatArray,
    hits: list[FloatArray],
    nodes: range,
    resolution_m: float,
    cap_m: float,
    cover_poses: bool = False,
) -> DistanceField:
    """Distance field of the scan endpoints of ``nodes`` placed at their poses (one window); it spans the
    endpoints, and with ``cover_poses`` the nodes' positions too (the beams' whole length:
    :func:`known_cells`)."""
    world = np.vstack([transform_points(poses[k], hits[k]) for k in nodes])
    extent = np.vstack([world, poses[nodes.start : nodes.stop, :2]]) if cover_poses else world
    # x and y apart: a min over the first axis of (K, 2) pairs runs a two-element inner loop per row,
    # ~25x slower than two contiguous reductions (same values).
    lo = np.array([extent[:, 0].min(), extent[:, 1].min()]) - 4 * resolution_m
    hi = np.array([extent[:, 0].max(), extent[:, 1].max()]) + 4 * resolution_m
    shape = np.ceil((hi - lo) / resolution_m).astype(np.int64)
    obstacles = np.zeros((1, int(shape[1]), int(shape[0])), dtype=bool)
    cells = np.floor((world - lo) / resolution_m).astype(np.int64)
    obstacles[0, cells[:, 1], cells[:, 0]] = True
    return DistanceField.from_obstacles(obstacles, (float(lo[0]), float(lo[1])), resolution_m, cap_m)


@dataclass(frozen=True)
class Lattice:
    """Costs (R, T) of a pose lattice: rotations ``yaw_rad`` (R,) by translations ``dx_m``, ``dy_m`` (T,)
    around a centre."""

    yaw_rad: FloatArray
    dx_m: FloatArray
    dy_m: FloatArray
    costs: FloatArray

    def best(self) -> tuple[int, int]:
        r, t = np.unravel_index(int(np.argmin(self.costs)), self.costs.shape)
        return int(r), int(t)

    def pose(self, centre: FloatArray, r: int, t: int) -> FloatArray:
        pose: FloatArray = centre + np.array([self.dx_m[t], self.dy_m[t], self.yaw_rad[r]])
        return pose

    def best_elsewhere(self, r: int, t: int, xy_m: float, yaw_rad: float) -> float:
        """The least cost at least ``xy_m`` or ``yaw_rad`` away from (r, t)."""
        far = (np.hypot(self.dx_m - self.dx_m[t], self.dy_m - self.dy_m[t])[None, :] > xy_m) | (
            np.abs(self.yaw_rad - self.yaw_rad[r])[:, None] > yaw_rad
        )
        return float(np.min(self.costs[far])) if np.any(far) else math.inf


def lattice_search(
    field: DistanceField,
    points_xy: FloatArray,
    centre: FloatArray,
    xy_m: float,
    yaw_rad: float,
    yaw_step_rad: float,
    truncate_m: float,
) -> Lattice:
    """Mean truncated squared distance min(d, c)² of the points at every lattice pose around ``centre``
    (translations in whole cells of the field, rotations by ``yaw_step_rad``); each rotation's points are
    computed once, and one rotation at a time bounds the memory. A point's cell is clamped into the
    field: the field is padded by its edge cells (and the points' cells clamped to within the lattice's
    reach of it first, which lands every shifted point where clamping each would), so that each lattice
    pose is one offset into the flat table of squared distances, one add and one gather per point and
    pose."""
    _u, h, w = field.distance_m.shape
    res = field.resolution_m
    reach = max(round(xy_m / res), 0)
    shifts = np.arange(-reach, reach + 1)
    sy, sx = (a.ravel() for a in np.meshgrid(shifts, shifts, indexing="ij"))
    n_yaw = max(round(yaw_rad / yaw_step_rad), 0)
    yaw_offsets = np.arange(-n_yaw, n_yaw + 1) * yaw_step_rad
    truncated = np.minimum(field.distance_m[0], np.float32(truncate_m))
    pad = 2 * reach
    flat = np.pad(truncated * truncated, pad, mode="edge").reshape(-1)
    width = w + 2 * pad
    side = shifts.size
    costs = np.empty((yaw_offsets.size, sx.size))
    candidates = np.tile(centre, (yaw_offsets.size, 1))
    candidates[:, 2] += yaw_offsets
    # A few rotations at a time (their (r, S, N) indices within ~0.5 MB): per rotation the Python-level
    # calls cost as much as the gather on the loop windows' small lattices. The indices are built for
    # the column shifts only (from the lowest row shift); row shift b reads them through the view of the
    # table b rows on (flat[k:][i] is flat[i + k]): the same cells, with no index array per
    # translation, and the costs of translations b * S .. b * S + S - 1 (t = row shift * S + column
    # shift) are each a mean over the same N values in the same order.
    per = max(1, _LATTICE_INDICES // max(side * points_xy.shape[0], 1))
    for r0 in range(0, yaw_offsets.size, per):
        r1 = min(r0 + per, yaw_offsets.size)
        wx, wy, _, _ = world_points(candidates[r0:r1], points_xy)
        col = np.floor((wx - field.origin_m[0]) / res).astype(np.int64) + 1
        row = np.floor((wy - field.origin_m[1]) / res).astype(np.int64) + 1
        col = np.clip(col, -reach, w - 1 + reach) + (pad - reach)
        row = np.clip(row, -reach, h - 1 + reach) + (pad - reach)
        lowest = (row * width + col)[:, None, :] + np.arange(side)[None, :, None]  # (r, S, N)
        # Each mean as np.mean computes it (the float32 sum, divided in place by the count as an intp
        # scalar), without its Python-level argument handling (a few us a call, side calls per rotation:
        # on exp1's small lattices ~3 % of the filter's CPU).
        count = np.intp(lowest.shape[2])
        for b in range(side):
            total = np.add.reduce(flat[b * width :][lowest], axis=2)
            np.true_divide(total, count, out=total, casting="unsafe")
            costs[r0:r1, b * side : (b + 1) * side] = total
    return Lattice(
        yaw_offsets.astype(np.float64), (sx * res).astype(np.float64), (sy * res).astype(np.float64), costs
    )


def _refine(
    old: DistanceField, points_xy: FloatArray, start: FloatArray, config: LoopClosureConfig
) -> MatchResult:
    """A coarse candidate refined against one old window: the fine lattice around ``start``, then
    Gauss-Newton from its best pose (one pose: ``MatchResult`` rows of one)."""
    best = _fine_best(old, points_xy, start, config)
    return match(old, np.zeros(1, dtype=np.int64), points_xy, best[None, :], config.matcher)


def _fine_best(
    old: DistanceField, points_xy: FloatArray, start: FloatArray, config: LoopClosureConfig
) -> FloatArray:
    """The best pose of the fine lattice around ``start`` (a coarse candidate) against ``old``."""
    fine = lattice_search(
        old,
        points_xy,
        start,
        config.coarse_resolution_m,
        config.coarse_yaw_step_rad,
        config.fine_yaw_step_rad,
        config.truncate_m,
    )
    return fine.pose(start, *fine.best())


def _refine_batch(
    old: DistanceField, points_xy: FloatArray, starts: FloatArray, config: LoopClosureConfig
) -> MatchResult:
    """:func:`_refine` of each of ``starts`` (P, 3), the Gauss-Newton runs as one batch that stops each
    pose where its own run would (``MatcherConfig.per_pose_convergence``; each pose's rows depend on that
    pose alone), so row k is ``_refine(old, points_xy, starts[k], config)``'s. With degeneracy-aware steps
    (``min_translation_information``) one pose's weak direction changes every pose's step: one at a
    time then."""
    bests = [_fine_best(old, points_xy, start, config) for start in starts]
    if config.matcher.min_translation_information > 0.0:
        ones = [match(old, np.zeros(1, dtype=np.int64), points_xy, b[None, :], config.matcher) for b in bests]
        return MatchResult(*(np.concatenate([getattr(o, f.name) for o in ones]) for f in fields(MatchResult)))
    matcher = replace(config.matcher, per_pose_convergence=True)
    return match(old, np.zeros(len(bests), dtype=np.int64), points_xy, np.array(bests), matcher)


def find_loop(
    poses: FloatArray,
    hits: list[FloatArray],
    match_points: FloatArray,
    j: int,
    config: LoopClosureConfig,
    travelled_m: float = 0.0,
    yaw_doubt_rad: float = 0.0,
    known_area_travelled_m: float | None = None,
) -> LoopConstraint | None:
    """A loop factor for node j (its endpoints to match: ``match_points``, in the robot frame) against
    the old nodes' map, or None (no old node near, or no match good and unambiguous enough).
    ``travelled_m``: the distance driven since the last closure, and ``yaw_doubt_rad``: the heading the
    front end may have lost since (see :func:`yaw_doubt`), which widen the search.
    ``known_area_travelled_m``: the distance that gates the known-area rule (``known_area_after_m``;
    the filter's: since the last closure or the last known-area link it judged and did not act on;
    None: ``travelled_m``)."""
    old_end = j - config.min_separation
    if old_end < 0 or match_points.shape[0] < config.matcher.min_inliers:
        return None
    # A heading lost d metres ago moves the position by about d * angle / 2.
    xy_m = min(
        config.search_xy_m + config.xy_per_m * travelled_m + 0.5 * yaw_doubt_rad * travelled_m,
        config.max_search_xy_m,
    )
    yaw_rad = min(
        config.search_yaw_rad + config.yaw_per_m * travelled_m + yaw_doubt_rad, config.max_search_yaw_rad
    )
    distance = np.hypot(*(poses[: old_end + 1, :2] - poses[j, :2]).T)
    reach = xy_m + config.search_radius_m
    if float(distance.min()) > reach:
        log.debug("node %d: no old node within %.1f m", j, reach)
        return None
    search = _LoopSearch(poses, hits, match_points, j, config, xy_m, yaw_rad, distance, reach)
    if config.hypotheses > 0 and not config.known_area_fallback:
        return _find_loop_known(search)
    # The coarse tests' lattices, one per window, are the known-area rule's too (the same windows, field
    # and search): handed on, not rebuilt.
    lattices: dict[int, Lattice] = {}
    found = _find_loop_coarse(search, lattices)
    known_travelled = travelled_m if known_area_travelled_m is None else known_area_travelled_m
    if found is None and config.hypotheses > 0 and known_travelled >= config.known_area_after_m:
        known = _find_loop_known(search, lattices)
        if known is not None:
            return replace(known, known_area=True)
    return found


@dataclass(frozen=True, eq=False)
class _LoopSearch:
    """What :func:`find_loop`'s two searches (:func:`_find_loop_coarse`, :func:`_find_loop_known`) share:
    node j's endpoints ``match_points`` (robot frame) against the old nodes' map (``poses``, ``hits``),
    within ±``xy_m`` and ±``yaw_rad`` of node j's pose, in windows around the old nodes within ``reach``
    of it (``distance``: each old node's)."""

    poses: FloatArray
    hits: list[FloatArray]
    match_points: FloatArray
    j: int
    config: LoopClosureConfig
    xy_m: float
    yaw_rad: float
    distance: FloatArray
    reach: float

    @property
    def old_end(self) -> int:
        """The newest node old enough to match against (``min_separation`` before j)."""
        return self.j - self.config.min_separation

    @property
    def cap_m(self) -> float:
        """The fine field's cap: the matcher's first bound or the truncation, and a cell."""
        config = self.config
        return max(config.truncate_m, config.matcher.stages[0][0]) + config.resolution_m

    def windows(self) -> list[tuple[int, range]]:
        """The old windows to search, nearest first: each centre node (:func:`candidate_nodes`) and the
        window's nodes (:func:`window_nodes`)."""
        config = self.config
        centres = candidate_nodes(
            self.poses, self.distance, self.old_end, self.reach, config.window_path_m, config.max_windows
        )
        return [(i, window_nodes(self.poses, i, self.old_end, config.window_path_m)) for i in centres]

    def coarse(self, nodes: range) -> Lattice:
        """The coarse lattice search against the window ``nodes`` (:func:`coarse_lattice`)."""
        return coarse_lattice(
            self.poses, self.hits, self.match_points, self.j, nodes, self.config, self.xy_m, self.yaw_rad
        )


def _find_loop_coarse(
    search: _LoopSearch, lattices: dict[int, Lattice] | None = None
) -> LoopConstraint | None:
    """:func:`find_loop`'s coarse tests: the least coarse cost among the windows whose best is
    unambiguous (``max_ambiguity``), refined, with ``min_inlier_fraction`` of the endpoints on the old
    walls. ``lattices``: where given, each window's coarse lattice is stored in it by its centre node."""
    poses, j, config = search.poses, search.j, search.config
    best: tuple[float, int, range, FloatArray] | None = None
    for i, nodes in search.windows():
        coarse = search.coarse(nodes)
        if lattices is not None:
            lattices[i] = coarse
        found = coarse_best(coarse, poses[j], j, i, config)
        if found is not None and (best is None or found[0] < best[0]):
            best = (found[0], i, nodes, found[1])
    if best is None:
        return None
    _cost, i, nodes, start = best
    old = old_map_field(poses, search.hits, nodes, config.resolution_m, search.cap_m)
    refined = _refine(old, search.match_points, start, config)
    fraction = float(refined.inlier_fraction[0])
    if not refined.ok[0] or fraction < config.min_inlier_fraction:
        log.debug("node %d vs %d: %.2f of the endpoints on the old map", j, i, fraction)
        return None
    covariance = None
    if config.match_sigma_m is not None:
        covariance = match_covariance(refined.information[0], float(poses[i, 2]), config.match_sigma_m)
    return LoopConstraint(i, j, between(poses[i], refined.poses[0]), fraction, covariance)


def candidate_nodes(
    poses: FloatArray, distance: FloatArray, old_end: int, reach_m: float, window_path_m: float, limit: int
) -> list[int]:
    """Old nodes (up to ``old_end``) within ``reach_m`` of the new one (``distance``: each old node's),
    nearest first, each at least ``2 * window_path_m`` of path from those taken before, at most
    ``limit``: the centres of the old windows to search."""
    along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poses[: old_end + 1, :2], axis=0).T))])
    taken: list[int] = []
    for i in np.argsort(distance, kind="stable"):
        if distance[i] > reach_m or len(taken) >= limit:
            break
        if all(abs(along[i] - along[k]) >= 2.0 * window_path_m for k in taken):
            taken.append(int(i))
    return taken


def coarse_lattice(
    poses: FloatArray,
    hits: list[FloatArray],
    match_points: FloatArray,
    j: int,
    nodes: range,
    config: LoopClosureConfig,
    xy_m: float,
    yaw_rad: float,
) -> Lattice:
    """The coarse lattice search of node j's endpoints against the old window ``nodes``, around node j's
    pose."""
    coarse_field = old_map_field(
        poses, hits, nodes, config.coarse_resolution_m, config.coarse_truncate_m + config.coarse_resolution_m
    )
    return lattice_search(
        coarse_field,
        match_points,
        poses[j],
        xy_m,
        yaw_rad,
        config.coarse_yaw_step_rad,
        config.coarse_truncate_m,
    )


def coarse_best(
    coarse: Lattice, centre: FloatArray, j: int, i: int, config: LoopClosureConfig
) -> tuple[float, FloatArray] | None:
    """A coarse lattice's best cost and pose (node j's against the window around node i), or None when
    a pose at least ``distinct_*`` away scores nearly as well (``max_ambiguity``)."""
    r, t = coarse.best()
    elsewhere = coarse.best_elsewhere(r, t, config.distinct_xy_m, config.distinct_yaw_rad)
    if not coarse.costs[r, t] < config.max_ambiguity * elsewhere:
        log.debug(
            "node %d vs %d: ambiguous (%.4f against %.4f elsewhere)", j, i, coarse.costs[r, t], elsewhere
        )
        return None
    return float(coarse.costs[r, t]), coarse.pose(centre, r, t)


def distinct_minima(lattice: Lattice, count: int, xy_m: float, yaw_rad: float) -> list[tuple[int, int]]:
    """The ``count`` least-cost lattice poses (r, t), each more than ``xy_m`` or ``yaw_rad`` from every
    one taken before it (the first is :meth:`Lattice.best`; the second's cost is what
    :meth:`Lattice.best_elsewhere` reports for it), fewer when the lattice runs out."""
    costs = lattice.costs.copy()
    taken: list[tuple[int, int]] = []
    while len(taken) < count:
        flat = int(np.argmin(costs))
        r, t = np.unravel_index(flat, costs.shape)
        if not np.isfinite(costs[r, t]):
            break
        taken.append((int(r), int(t)))
        near = (np.hypot(lattice.dx_m - lattice.dx_m[t], lattice.dy_m - lattice.dy_m[t])[None, :] <= xy_m) & (
            np.abs(lattice.yaw_rad - lattice.yaw_rad[r])[:, None] <= yaw_rad
        )
        costs[near] = math.inf
    return taken


def known_cells(poses: FloatArray, hits: list[FloatArray], nodes: range, field_: DistanceField) -> BoolArray:
    """(H, W) over the cells of ``field_`` (an :func:`old_map_field` of ``nodes`` with ``cover_poses``,
    without its border):
    True where a beam of an old node reached, from the node's position to each of its endpoints (the
    free space it crossed and the wall it hit). Beams without a return are not in ``hits`` and add
    nothing: the known area is, if anything, too small."""
    _u, h, w = field_.distance_m.shape
    known = np.zeros((h - 2, w - 2), dtype=np.uint8)
    origin = np.asarray(field_.origin_m)
    for k in nodes:
        if hits[k].shape[0] == 0:
            continue
        ends = np.floor((transform_points(poses[k], hits[k]) - origin) / field_.resolution_m)
        start = np.floor((poses[k, :2] - origin) / field_.resolution_m)
        segments = np.empty((ends.shape[0], 2, 2), dtype=np.int32)
        segments[:, 0] = start
        segments[:, 1] = ends
        cv2.polylines(known, list(segments), False, 1)
    return known.astype(bool)


@dataclass(frozen=True)
class KnownFit:
    """A scan's endpoints at a pose against an old window: ``inliers`` within the matcher's last bound of
    an old wall, ``conflicts`` in the window's known area but off its walls (where an old beam passed),
    ``unknown`` elsewhere; ``cost``: the mean truncated squared distance over the inliers and conflicts
    (inf when there are none)."""

    inliers: int
    conflicts: int
    unknown: int
    cost: float

    @property
    def inlier_fraction(self) -> float:
        """The inliers' share of the endpoints in the known area."""
        return self.inliers / max(self.inliers + self.conflicts, 1)


def known_fit(
    field_: DistanceField,
    known: BoolArray,
    points_xy: FloatArray,
    pose: FloatArray,
    inlier_m: float,
    truncate_m: float,
) -> KnownFit:
    """How ``points_xy`` (robot frame) at ``pose`` fit the old window (``field_`` and its
    :func:`known_cells`), counted over the known area only."""
    d = point_distances(field_, points_xy, pose)
    wx, wy, _, _ = world_points(pose[None, :], points_xy)
    col = np.floor((wx[0] - field_.origin_m[0]) / field_.resolution_m).astype(np.int64)
    row = np.floor((wy[0] - field_.origin_m[1]) / field_.resolution_m).astype(np.int64)
    inside = (col >= 0) & (col < known.shape[1]) & (row >= 0) & (row < known.shape[0])
    seen = np.zeros(d.shape, dtype=bool)
    seen[inside] = known[row[inside], col[inside]]
    inlier = d < inlier_m
    seen |= inlier
    truncated = np.minimum(d[seen], truncate_m)
    cost = float(np.mean(truncated * truncated)) if truncated.size else math.inf
    n_in = int(inlier.sum())
    return KnownFit(n_in, int(seen.sum()) - n_in, int((~seen).sum()), cost)


@dataclass(frozen=True)
class _Hypothesis:
    i: int
    pose: FloatArray
    fit: KnownFit
    ok: bool
    information: FloatArray


def _find_loop_known(
    search: _LoopSearch, lattices: dict[int, Lattice] | None = None
) -> LoopConstraint | None:
    """:func:`find_loop` with ``config.hypotheses`` > 0: every window's best distinct coarse poses
    refined, and judged over the old window's known area (``LoopClosureConfig.hypotheses``).
    ``lattices``: the coarse tests' lattices by window centre (:func:`_find_loop_coarse`), used where
    present instead of searching again."""
    poses, hits, match_points, j = search.poses, search.hits, search.match_points, search.j
    config, old_end, cap = search.config, search.old_end, search.cap_m
    inlier_m = config.matcher.stages[-1][0]
    refined: list[_Hypothesis] = []
    for i, nodes in search.windows():
        coarse = lattices.get(i) if lattices is not None else None
        if coarse is None:
            coarse = search.coarse(nodes)
        old = old_map_field(poses, hits, nodes, config.resolution_m, cap, cover_poses=True)
        known = known_cells(poses, hits, nodes, old)
        minima = distinct_minima(coarse, config.hypotheses, config.distinct_xy_m, config.distinct_yaw_rad)
        if not minima:
            continue
        m = _refine_batch(
            old, match_points, np.array([coarse.pose(poses[j], r, t) for r, t in minima]), config
        )
        for k in range(len(minima)):
            fit = known_fit(old, known, match_points, m.poses[k], inlier_m, config.truncate_m)
            refined.append(_Hypothesis(i, m.poses[k], fit, bool(m.ok[k]), m.information[k]))
    if not refined:
        return None
    best = min(refined, key=lambda h: h.fit.cost)
    rivals = [
        h.fit.cost
        for h in refined
        if math.hypot(*(h.pose[:2] - best.pose[:2])) > config.distinct_xy_m
        or abs(wrap_angle(float(h.pose[2] - best.pose[2]))) > config.distinct_yaw_rad
    ]
    rival = min(rivals, default=math.inf)
    if not best.fit.cost < config.known_ambiguity * rival:
        log.debug(
            "node %d vs %d: ambiguous (%.4f against %.4f elsewhere, known area)",
            j,
            best.i,
            best.fit.cost,
            rival,
        )
        return None
    offset = best.pose - poses[j]
    prior_chi2 = (offset[0] ** 2 + offset[1] ** 2) / (search.xy_m / 3.0) ** 2 + (
        wrap_angle(float(offset[2])) / (search.yaw_rad / 3.0)
    ) ** 2
    if prior_chi2 > config.prior_chi2:
        log.debug(
            "node %d vs %d: %.1f m from the graph's pose (chi2 %.1f)",
            j,
            best.i,
            math.hypot(*offset[:2]),
            prior_chi2,
        )
        return None
    if (
        not best.ok
        or best.fit.inliers < config.matcher.min_inliers
        or best.fit.inlier_fraction < config.min_inlier_fraction
    ):
        log.debug(
            "node %d vs %d: %d inliers, %.2f of the known endpoints",
            j,
            best.i,
            best.fit.inliers,
            best.fit.inlier_fraction,
        )
        return None
    log.debug(
        "node %d vs %d: %d inliers, %d conflicts, %d unknown, cost %.4f against %.4f, moved %.2f m",
        j,
        best.i,
        best.fit.inliers,
        best.fit.conflicts,
        best.fit.unknown,
        best.fit.cost,
        rival,
        math.hypot(*(best.pose[:2] - poses[j, :2])),
    )
    # The factor relates node j to one old node: measured against that node's scan alone (the nearest
    # one to the match), it does not take in the window's own front-end errors (the other nodes' scans
    # at their drifted poses); where that match fails, the window's.
    i, pose, information = best.i, best.pose, best.information
    nodes = window_nodes(poses, best.i, old_end, config.window_path_m)
    k = nodes.start + int(np.argmin(np.hypot(*(poses[nodes.start : nodes.stop, :2] - pose[:2]).T)))
    single = old_map_field(poses, hits, range(k, k + 1), config.resolution_m, cap)
    alone = match(single, np.zeros(1, dtype=np.int64), match_points, pose[None, :], config.matcher)
    if alone.ok[0]:
        i, pose, information = k, alone.poses[0], alone.information[0]
    covariance = None
    if config.match_sigma_m is not None:
        covariance = match_covariance(information, float(poses[i, 2]), config.match_sigma_m)
    return LoopConstraint(i, j, between(poses[i], pose), best.fit.inlier_fraction, covariance)


@dataclass(frozen=True)
class GraphState:
    """A filter's pose graph as it stands: its nodes' poses (``path``, (N, 3), the leading lineage's, the
    optimised ones where a loop closure put them), each front-end edge's step (``motions[k]``, node k in
    node k-1's frame; row 0 unused), the odometry's step beside it (``odometry_motions``), the loop
    factors, and the VLP fixes' absolute factors: what :func:`optimize_graph` optimises. For diagnosis
    (``benchmarks/slam_error_budget.py``): the graph optimised again with some factors replaced shows
    how much of a trajectory's error each kind of factor carries."""

    path: FloatArray
    motions: FloatArray
    odometry_motions: FloatArray
    loops: tuple[LoopConstraint, ...]
    absolute: AbsoluteFactors | None


def window_nodes(poses: FloatArray, i: int, old_end: int, path_m: float) -> range:
    """The nodes up to ``old_end`` within ``path_m`` of path length of node i (the old map's window)."""
    along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poses[: old_end + 1, :2], axis=0).T))])
    near = np.flatnonzero(np.abs(along - along[i]) <= path_m)
    return range(int(near[0]), int(near[-1]) + 1)


def loop_sqrt_information(loop: LoopConstraint, config: LoopClosureConfig) -> FloatArray:
    """S (3, 3) with SᵀS the loop factor's information: diag(loop_sigma²) plus the match's covariance."""
    covariance = np.diag(np.square(np.asarray(config.loop_sigma)))
    if loop.covariance is not None:
        covariance = covariance + loop.covariance
    return sqrt_information(covariance)


def loop_residual_chi2(poses: FloatArray, loop: LoopConstraint, config: LoopClosureConfig) -> float:
    """The loop factor's squared Mahalanobis residual at ``poses``."""
    factor = RelativeFactors(
        np.array([loop.i]),
        np.array([loop.j]),
        loop.z[None, :],
        np.asarray(config.loop_sigma)[None, :],
        loop_sqrt_information(loop, config)[None, :, :],
    )
    return float(np.sum(relative_residuals(poses, factor) ** 2))


class Verdict(enum.Enum):
    ACCEPTED = "accepted"
    AGREES = "agrees"  # the graph already agrees within the match's noise: nothing to correct
    # A known-area link (LoopConstraint.known_area) the graph already agrees with: counted, not added.
    NEAR = "near"
    FITS = "fits"  # the newest scans lie on the old map already: the link slid, not the map
    UNCONFIRMED = "unconfirmed"  # disagrees with the graph, no other link yet says the same: pending
    INCONSISTENT = "inconsistent"  # the graph will not take it (its residual, or other loops', too large)
    WORSE = "worse"  # the newest scans fit the old map worse at the corrected poses


@dataclass(frozen=True)
class Judgement:
    verdict: Verdict
    innovation_chi2: float
    residual_chi2: float = math.nan
    score_before: float = math.nan
    score_after: float = math.nan
    result: GraphResult | None = None  # the tentative optimisation (ACCEPTED: the one to apply)
    partners: tuple[LoopConstraint, ...] = ()  # the pending links that confirmed it (join the graph too)


def pairwise_chi2(
    poses: FloatArray, a: LoopConstraint, b: LoopConstraint, config: LoopClosureConfig
) -> float:
    """How far two loop links disagree, given the graph's chains between their ends: b's z against a's
    carried to b's nodes, squared Mahalanobis (PCM's pairwise consistency)."""
    predicted = compose(compose(between(poses[b.i], poses[a.i]), a.z), between(poses[a.j], poses[b.j]))
    error = between(predicted, b.z)
    error[2] = wrap_angle(error[2])
    edges = abs(a.i - b.i) + abs(a.j - b.j)
    variance = 2.0 * np.square(np.asarray(config.loop_sigma)) + edges * np.square(
        np.asarray(config.chain_sigma)
    )
    covariance = np.diag(variance)
    for c in (a, b):
        if c.covariance is not None:
            covariance = covariance + c.covariance
    return float(error @ np.linalg.solve(covariance, error))


def point_distances(field_: DistanceField, points_xy: FloatArray, pose: FloatArray) -> FloatArray:
    """Distance (cell lookup, as :func:`lattice_search`) from each of ``points_xy`` (robot frame) at
    ``pose`` to the field's nearest obstacle."""
    _u, h, w = field_.distance_m.shape
    res = field_.resolution_m
    wx, wy, _, _ = world_points(pose[None, :], points_xy)
    col = np.clip(np.floor((wx[0] - field_.origin_m[0]) / res).astype(np.int64) + 1, 0, w - 1)
    row = np.clip(np.floor((wy[0] - field_.origin_m[1]) / res).astype(np.int64) + 1, 0, h - 1)
    distances: FloatArray = field_.distance_m[0][row, col].astype(np.float64)
    return distances


def scan_map_score(
    poses: FloatArray, hits: list[FloatArray], old: range, new: range, config: LoopClosureConfig
) -> float:
    """How well the endpoints of nodes ``new`` lie on the map of nodes ``old``, each at its pose in
    ``poses``: the median of their squared distances truncated at ``truncate_m`` (lower is better; the
    median, because the new scans also see what the old nodes never did)."""
    if not any(hits[k].shape[0] for k in old):
        return math.inf
    cap = config.truncate_m + config.resolution_m
    field_ = old_map_field(poses, hits, old, config.resolution_m, cap)
    distances = [point_distances(field_, hits[k], poses[k]) for k in new if hits[k].shape[0]]
    if not distances:
        return math.inf
    d = np.minimum(np.concatenate(distances), config.truncate_m)
    return float(np.median(d * d))


def judge_loop(
    poses: FloatArray,
    hits: list[FloatArray],
    motions: FloatArray,
    loops: list[LoopConstraint],
    candidate: LoopConstraint,
    config: LoopClosureConfig,
    absolute: AbsoluteFactors | None = None,
    odometry_motions: FloatArray | None = None,
    pending: list[LoopConstraint] | None = None,
    node_information: FloatArray | None = None,
    odometry_sigmas: FloatArray | None = None,
) -> Judgement:
    """Whether ``candidate`` should join the graph of ``poses`` (the front end's), ``motions`` and the
    accepted ``loops``, in this order: a known-area link (``LoopConstraint.known_area``) whose innovation
    is below ``agree_chi2`` is NEAR (counted, neither added nor acted on); the newest ``verify_nodes``
    scans must fit the old map (the nodes around i) badly at the current poses (``fit_m``;
    ``known_area_fit_m`` for a known-area link); where they fit, the map holds together there and
    the link is AGREES (joins the graph, not acted on) when it agrees with the graph within its own
    noise (``agree_chi2``), FITS (dropped: it slid) when not; with ``require_confirmation`` one of the
    ``pending`` links (earlier candidates left UNCONFIRMED, within ``confirm_nodes``) must agree with it;
    the graph optimised with it (and the pending links that agree with it, ``Judgement.partners``) must
    fit it and every earlier loop (``accept_chi2``) and, as a whole, not much worse than without it
    (``accept_graph_chi2``, :func:`graph_bent`); and those scans must fit the old map at the optimised
    poses at least as well as at the current ones (``verify_ratio``; a known-area link's must fit them
    plainly better, ``known_area_verify_ratio``). ``hits``: each node's endpoints in
    its robot frame; ``odometry_motions``, ``node_information``, ``odometry_sigmas``: the chain's sigmas
    (:func:`optimize_graph`)."""
    innovation = loop_residual_chi2(poses, candidate, config)
    if candidate.known_area and innovation < config.agree_chi2:
        return Judgement(Verdict.NEAR, innovation)
    j = candidate.j
    old = window_nodes(poses, candidate.i, j - config.min_separation, config.window_path_m)
    new = range(max(j - config.verify_nodes + 1, old.stop), j + 1)
    score_before = scan_map_score(poses, hits, old, new, config)
    if score_before < (config.known_area_fit_m if candidate.known_area else config.fit_m) ** 2:
        if innovation < config.agree_chi2:
            return Judgement(Verdict.AGREES, innovation, score_before=score_before)
        log.debug("loop %d -> %d: the scans fit the old map already (%.4f)", candidate.i, j, score_before)
        return Judgement(Verdict.FITS, innovation, score_before=score_before)
    partners = [
        p
        for p in (pending or [])
        if candidate.j - p.j <= config.confirm_nodes
        and pairwise_chi2(poses, p, candidate, config) <= config.pairwise_chi2
    ]
    if config.require_confirmation and not partners:
        return Judgement(Verdict.UNCONFIRMED, innovation, score_before=score_before)
    # The consistency tests on the front end's own edges (``edge_judge_plain``) or the edges' covariances.
    judged = None if config.edge_judge_plain else node_information

    def optimise(links: list[LoopConstraint], information: FloatArray | None) -> GraphResult:
        return optimize_graph(
            poses, motions, links, config, absolute, odometry_motions, information, odometry_sigmas
        )

    result = optimise([*loops, *partners, candidate], judged)
    residual = loop_residual_chi2(result.poses, candidate, config)
    bad_after = sum(loop_residual_chi2(result.poses, c, config) > config.accept_chi2 for c in loops)
    # The graph without the candidate, for the loops it already left off: counted only where the verdict
    # turns on that count (with no loop off after, none can be more off than before); None: not computed.
    bad_before: int | None = None
    if residual <= config.accept_chi2 and bad_after > 0:
        before = optimise(list(loops), judged)
        bad_before = sum(loop_residual_chi2(before.poses, c, config) > config.accept_chi2 for c in loops)
    if residual > config.accept_chi2 or (bad_before is not None and bad_after > bad_before):
        log.debug(
            "loop %d -> %d: inconsistent (chi2 %.1f, loops off: %s before it, %d with it)",
            candidate.i,
            candidate.j,
            residual,
            "not computed" if bad_before is None else bad_before,
            bad_after,
        )
        return Judgement(Verdict.INCONSISTENT, innovation, residual, score_before)
    if graph_bent(result, lambda: optimise(list(loops), judged), config.accept_graph_chi2):
        log.debug(
            "loop %d -> %d: inconsistent (the graph's chi2 %.1f with it)", candidate.i, j, result.chi2_final
        )
        return Judgement(Verdict.INCONSISTENT, innovation, residual, score_before)
    if judged is not node_information:
        result = optimise([*loops, *partners, candidate], node_information)
    score_after = scan_map_score(result.poses, hits, old, new, config)
    ratio = config.known_area_verify_ratio if candidate.known_area else config.verify_ratio
    if score_after > ratio * score_before or (candidate.known_area and not math.isfinite(score_before)):
        log.debug("loop %d -> %d: scans fit worse (%.4f -> %.4f)", candidate.i, j, score_before, score_after)
        return Judgement(Verdict.WORSE, innovation, residual, score_before, score_after)
    return Judgement(
        Verdict.ACCEPTED, innovation, residual, score_before, score_after, result, tuple(partners)
    )


def graph_bent(with_it: GraphResult, without_it: Callable[[], GraphResult], limit: float | None) -> bool:
    """Whether a candidate raised the optimised graph's chi² (``with_it``) by more than ``limit`` over
    the graph optimised without it (``LoopClosureConfig.accept_graph_chi2``; None: never). The graph
    without it is optimised only when the chi² with it exceeds the limit (the rise cannot, otherwise)."""
    if limit is None or with_it.chi2_final <= limit:
        return False
    return with_it.chi2_final - without_it().chi2_final > limit


def match_covariance(information: FloatArray, yaw_i_rad: float, sigma_m: float) -> FloatArray:
    """The covariance of a matched pose, s² (Σ J Jᵀ)⁻¹ (``information`` in world x, y, yaw), turned into
    the frame of a node at heading ``yaw_i_rad`` (a relative factor's z = between(x_i, x_j))."""
    c, s = math.cos(yaw_i_rad), math.sin(yaw_i_rad)
    a = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    world = sigma_m**2 * np.linalg.inv(np.asarray(information) + 1e-6 * np.eye(3))
    covariance: FloatArray = a @ world @ a.T
    return 0.5 * (covariance + covariance.T)


def robot_frame_information(information: FloatArray, yaw_rad: float) -> FloatArray:
    """A match's information Σ J Jᵀ (3, 3) in world (x, y, yaw) turned into the robot frame of a pose at
    heading ``yaw_rad``: Aᵀ I A, A = diag(R(yaw), 1) (a robot-frame step δ moves the world pose by A δ)."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    a = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out: FloatArray = a.T @ np.asarray(information, dtype=np.float64) @ a
    return 0.5 * (out + out.T)


def edge_covariances(
    motions: FloatArray,
    node_information: FloatArray,
    config: LoopClosureConfig,
    floor_sigma: FloatArray | None = None,
) -> FloatArray:
    """(N-1, 3, 3) covariances of the front-end edges k-1 -> k (``motions[k]``, node k in node k-1's
    frame, k >= 1) from node k's scan match (``node_information[k]``: Σ J Jᵀ in node k's robot frame,
    :func:`robot_frame_information`; zeros where the match failed): diag(motion_sigma²) + B (Σ J Jᵀ / s²
    + diag(edge_max_sigma)⁻²)⁻¹ Bᵀ with s = ``edge_match_sigma_m`` and B = diag(R(motion yaw), 1), node
    k's frame turned into node k-1's. ``floor_sigma`` ((N-1, 3)): each edge's own sigmas in place of
    ``motion_sigma``."""
    if config.edge_match_sigma_m is None:
        raise ValueError("edge_covariances needs LoopClosureConfig.edge_match_sigma_m")
    info = np.asarray(node_information[1:], dtype=np.float64) / config.edge_match_sigma_m**2
    info = info + np.diag(1.0 / np.square(np.asarray(config.edge_max_sigma)))[None, :, :]
    match_cov = np.linalg.inv(info)
    yaw = np.asarray(motions[1:, 2], dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    b = np.zeros((yaw.size, 3, 3))
    b[:, 0, 0], b[:, 0, 1], b[:, 1, 0], b[:, 1, 1], b[:, 2, 2] = c, -s, s, c, 1.0
    covariance: FloatArray = b @ match_cov @ b.transpose(0, 2, 1)
    covariance = 0.5 * (covariance + covariance.transpose(0, 2, 1))
    if floor_sigma is None:
        return covariance + np.diag(np.square(np.asarray(config.motion_sigma)))[None, :, :]
    floor = np.zeros_like(covariance)
    floor[:, [0, 1, 2], [0, 1, 2]] = np.square(np.asarray(floor_sigma, dtype=np.float64))
    return covariance + floor


def optimize_graph(
    poses: FloatArray,
    motions: FloatArray,
    loops: list[LoopConstraint],
    config: LoopClosureConfig,
    absolute: AbsoluteFactors | None = None,
    odometry_motions: FloatArray | None = None,
    node_information: FloatArray | None = None,
    odometry_sigmas: FloatArray | None = None,
) -> GraphResult:
    """The chain 0 -> 1 -> ... (``motions[k]``: node k in node k-1's frame, k >= 1) plus the loop factors,
    optimised from ``poses``. The chain's sigmas: ``motion_sigma``, widened by ``correction_share`` of
    each edge's departure from ``odometry_motions`` (less ``correction_odometry_sigmas`` times
    ``odometry_sigmas``, (N, 3): the motion model's sigmas of each odometry increment, where both are
    set); or, with ``edge_match_sigma_m`` and
    ``node_information`` (each node's match, robot frame), :func:`edge_covariances`."""
    n = poses.shape[0]
    chain = np.arange(1, n, dtype=np.int64)
    motion_sigma = np.tile(np.asarray(config.motion_sigma), (n - 1, 1))
    from_matches = config.edge_match_sigma_m is not None and node_information is not None
    if odometry_motions is not None and (not from_matches or config.edge_departure_floor):
        gap = np.abs(motions[1:n] - odometry_motions[1:n])
        gap[:, 2] = np.abs(wrap_angle(gap[:, 2]))
        if config.correction_odometry_sigmas is not None and odometry_sigmas is not None:
            gap = np.maximum(gap - config.correction_odometry_sigmas * odometry_sigmas[1:n], 0.0)
        motion_sigma = np.maximum(motion_sigma, config.correction_share * gap)
    i = np.concatenate([chain - 1, np.array([c.i for c in loops], dtype=np.int64)])
    j = np.concatenate([chain, np.array([c.j for c in loops], dtype=np.int64)])
    z = np.vstack([motions[1:n], np.array([c.z for c in loops]).reshape(-1, 3)])
    sigma = np.vstack(
        [
            motion_sigma,
            np.tile(np.asarray(config.loop_sigma), (len(loops), 1)),
        ]
    )
    whitening = None
    if from_matches or any(c.covariance is not None for c in loops):
        whitening = RelativeFactors(i, j, z, sigma).whitening()
    if from_matches:
        assert whitening is not None and node_information is not None
        floor = motion_sigma if config.edge_departure_floor else None
        whitening[: n - 1] = sqrt_information(
            edge_covariances(motions[:n], node_information[:n], config, floor)
        )
    if any(c.covariance is not None for c in loops):
        assert whitening is not None
        whitening[n - 1 :] = np.array([loop_sqrt_information(c, config) for c in loops])
    return optimize(poses, RelativeFactors(i, j, z, sigma, whitening), absolute, huber=config.huber)


def odometry_forward_at_snaps(
    motions: FloatArray, odometry_motions: FloatArray, steady: npt.NDArray[np.bool_], limit_m: float
) -> FloatArray:
    """``motions`` (N, 3; row k node k in node k-1's frame, row 0 unused) with the forward step (x) of each
    edge k whose forward component departs from ``odometry_motions``' by more than ``limit_m`` where
    ``steady[k]`` replaced by the odometry's (a copy; ``LoopClosureConfig.snap_forward_m``)."""
    out = motions.copy()
    snapped = steady[1:] & (np.abs(out[1:, 0] - odometry_motions[1:, 0]) > limit_m)
    out[1:, 0] = np.where(snapped, odometry_motions[1:, 0], out[1:, 0])
    return out


def yaw_doubt(motions: FloatArray, odometry_motions: FloatArray, config: LoopClosureConfig) -> float:
    """Three standard deviations of the heading the chain of ``motions`` may have lost against the
    ``odometry_motions`` beside them: 3 sqrt(sum_k sigma_k²) over the edges whose sigma the graph widened
    (``correction_share`` of the match's turn against odometry, where that exceeds the motion sigma: the
    searches' own drift terms cover the rest)."""
    if motions.shape[0] == 0:
        return 0.0
    gap = config.correction_share * np.abs(wrap_angle(motions[:, 2] - odometry_motions[:, 2]))
    sigma = np.where(gap > config.motion_sigma[2], gap, 0.0)
    return float(3.0 * np.sqrt(np.sum(sigma * sigma)))


def chain_poses(start: FloatArray, motions: FloatArray) -> FloatArray:
    """Poses of the chain from ``start`` by ``motions[1:]``."""
    out = np.zeros_like(motions)
    out[0] = start
    for k in range(1, motions.shape[0]):
        out[k] = compose(out[k - 1], motions[k])
    return out
