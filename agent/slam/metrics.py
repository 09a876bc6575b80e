"""Accuracy and map-quality measures.

* :func:`relative_pose_error`: the relative-pose metric of ``reference/slam.md`` §1.5 (Kümmerle et al.
  2009, local relations) in Cartographer's variant: for each relation (i, j) with reference motion
  D* = ref_i⁻¹ ⊕ ref_j and estimated motion D = est_i⁻¹ ⊕ est_j, the error is E = D ⊕ D*⁻¹
  (``compute_relations_metrics_main.cc``: (pose1⁻¹ pose2) expected⁻¹); translational error |E.t|,
  rotational error |E.yaw|; mean and sample standard deviation (n - 1), absolute and squared.
* :func:`wall_thickness`: how many occupied cells a wall is thick, measured across it.
* :func:`absolute_trajectory_error`: RMS position error after nothing but a common start (for simulation,
  where the map frame is the world frame).
* :func:`far_relation_error`: the relative-pose error over every pair of poses further apart than a
  distance (10 m by default) in the reference: whether the map holds together across a building, which the
  consecutive and fixed-span relations cannot show when the far pairs are few.
* :func:`turning_point`: where the odometry turns about, seen from the trajectory's frame (the laser's,
  moved by its configured mount), fitted at the turns on the spot: a mount the configuration does not
  hold (the radish logs give none; Intel's odometry turns about a point 9-10 cm behind the laser).
* :func:`turn_ratio`: how much the estimate turns against the reference at the reference's turns (a
  scale of turning that the relations average away).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import numpy.typing as npt

from agent.slam.pose import between, compose, inverse, transform_points

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True)
class RelativePoseError:
    n: int
    trans_error_m_mean: float
    trans_error_m_std: float
    trans_error_m2_mean: float
    trans_error_m2_std: float
    rot_error_deg_mean: float
    rot_error_deg_std: float
    rot_error_deg2_mean: float
    rot_error_deg2_std: float

    def as_dict(self) -> dict[str, float | int]:
        return asdict(self)


def _mean_std(values: FloatArray) -> tuple[float, float]:
    if values.size == 0:
        return (math.nan, math.nan)
    std = float(np.std(values, ddof=1)) if values.size > 1 else 0.0
    return float(np.mean(values)), std


def relative_pose_error(
    reference: FloatArray, estimate: FloatArray, pairs: npt.NDArray[np.int64] | None = None
) -> RelativePoseError:
    """The metric over ``pairs`` (M, 2) of indices into both pose arrays (N, 3); default every pair of
    consecutive poses (i, i + 1), the relations used for the radish logs."""
    if reference.shape != estimate.shape or reference.ndim != 2 or reference.shape[1] != 3:
        raise ValueError(
            f"need two (N, 3) pose arrays of the same shape, got {reference.shape}, {estimate.shape}"
        )
    if pairs is None:
        idx = np.arange(reference.shape[0] - 1)
        pairs = np.stack([idx, idx + 1], axis=1)
    expected = between(reference[pairs[:, 0]], reference[pairs[:, 1]])
    measured = between(estimate[pairs[:, 0]], estimate[pairs[:, 1]])
    error = compose(measured, inverse(expected))
    trans = np.hypot(error[:, 0], error[:, 1])
    rot = np.degrees(np.abs(error[:, 2]))
    t_mean, t_std = _mean_std(trans)
    t2_mean, t2_std = _mean_std(trans**2)
    r_mean, r_std = _mean_std(rot)
    r2_mean, r2_std = _mean_std(rot**2)
    return RelativePoseError(
        int(pairs.shape[0]), t_mean, t_std, t2_mean, t2_std, r_mean, r_std, r2_mean, r2_std
    )


def far_relation_pairs(
    reference: FloatArray, min_distance_m: float = 10.0, max_poses: int = 800
) -> npt.NDArray[np.int64]:
    """Every pair (i, j), i < j, of poses at least ``min_distance_m`` apart in the reference, among at most
    ``max_poses`` poses taken at an even stride (the pairs grow with the square of the poses: FR079's 4791
    would be 11 million)."""
    n = reference.shape[0]
    kept = np.unique(np.linspace(0, n - 1, min(n, max_poses)).round().astype(np.int64)) if n else np.zeros(0)
    xy = reference[kept, :2]
    d = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    i, j = np.nonzero(np.triu(d >= min_distance_m, k=1))
    return np.stack([kept[i], kept[j]], axis=1).astype(np.int64)


def far_relation_error(
    reference: FloatArray, estimate: FloatArray, min_distance_m: float = 10.0, max_poses: int = 800
) -> RelativePoseError:
    """:func:`relative_pose_error` over :func:`far_relation_pairs` (n = 0 and NaN means when the
    reference never goes that far)."""
    pairs = far_relation_pairs(reference, min_distance_m, max_poses)
    if pairs.shape[0] == 0:
        nan = math.nan
        return RelativePoseError(0, nan, nan, nan, nan, nan, nan, nan, nan)
    return relative_pose_error(reference, estimate, pairs)


def absolute_trajectory_error(truth: FloatArray, estimate: FloatArray) -> float:
    """RMS of the position differences (metres) between two (N, >=2) trajectories in one frame."""
    d = truth[:, :2] - estimate[:, :2]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1)))) if d.size else math.nan


def rigid_alignment(truth: FloatArray, estimate: FloatArray) -> tuple[float, float, float]:
    """The rotation and translation (dx, dy, angle) that move the estimate's positions onto the truth's
    in least squares (Horn's closed form in the plane, no scale): what the ATE of the TUM RGB-D benchmark
    aligns before it measures."""
    a, b = estimate[:, :2], truth[:, :2]
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    h = (a - ma).T @ (b - mb)
    angle = math.atan2(float(h[0, 1] - h[1, 0]), float(h[0, 0] + h[1, 1]))
    c, s = math.cos(angle), math.sin(angle)
    tx = float(mb[0] - (c * ma[0] - s * ma[1]))
    ty = float(mb[1] - (s * ma[0] + c * ma[1]))
    return tx, ty, angle


def aligned_trajectory_error(truth: FloatArray, estimate: FloatArray) -> float:
    """:func:`absolute_trajectory_error` after :func:`rigid_alignment`: how well the trajectory holds
    together, whatever frame it was built in (without absolute fixes, a map's frame is only as good as its
    first metres)."""
    if estimate.shape[0] == 0:
        return math.nan
    moved = transform_points(rigid_alignment(truth, estimate), estimate[:, :2])
    return absolute_trajectory_error(truth, moved)


@dataclass(frozen=True)
class WallThickness:
    """For every occupied cell, the occupied cells on the line through it across the wall, within
    ``reach_cells`` on each side. A cell is *thin* when those are at most 2 and all touch it (a wall one
    or two cells thick, no ghost copy beside it); ``thin_fraction`` is the share of thin cells."""

    occupied_cells: int
    thin_fraction: float
    median_count: float


def wall_thickness(occupied: BoolArray, reach_cells: int = 3) -> WallThickness:
    """Thickness of walls across their direction.

    The wall direction at a cell is the one of four (0, 45, 90, 135 deg) along which the most occupied
    cells lie within ``reach_cells``; across it (the perpendicular one of the four) the count c and the
    contiguous run r through the cell are taken. Thin: c <= 2 and c == r.
    """
    # uint8 throughout (counts stay below 2 * reach + 2): a whole building's map is millions of cells.
    occ = occupied.astype(np.uint8)
    h, w = occ.shape
    pad = reach_cells
    padded = np.pad(occ, pad)

    def shifted(dy: int, dx: int, k: int) -> npt.NDArray[np.uint8]:
        return padded[pad + k * dy : pad + k * dy + h, pad + k * dx : pad + k * dx + w]

    directions = [(0, 1), (1, 1), (1, 0), (1, -1)]
    count = np.empty((4, h, w), dtype=np.uint8)
    run_length = np.empty((4, h, w), dtype=np.uint8)
    alive = np.empty((h, w), dtype=np.uint8)
    for d, (dy, dx) in enumerate(directions):
        total = count[d]
        run = run_length[d]
        total[...] = occ
        run[...] = occ
        for sign in (1, -1):
            alive[...] = occ
            for k in range(1, reach_cells + 1):
                cell = shifted(sign * dy, sign * dx, k)
                total += cell
                alive &= cell
                run += alive
    along = np.argmax(count, axis=0)
    across = (along + 2) % 4
    rows, cols = np.nonzero(occupied)
    c = count[across[rows, cols], rows, cols]
    r = run_length[across[rows, cols], rows, cols]
    if c.size == 0:
        return WallThickness(0, math.nan, math.nan)
    return WallThickness(int(c.size), float(np.mean((c <= 2) & (c == r))), float(np.median(c)))


# turning_point: an update turns on the spot where its odometry translates at most this and turns at least
# this; a trajectory motion farther than TURN_MAX_MOTION_M is not a turn in place (a jump, a bad match).
TURN_MAX_ODOMETRY_M = 0.03
TURN_MIN_RAD = 0.2
TURN_MAX_MOTION_M = 0.25


def turning_point(odometry: FloatArray, estimate: FloatArray, min_turns: int = 10) -> FloatArray | None:
    """The point (x forward, y left; metres, (2,)) the odometry turns about, in the frame of the estimated
    poses, from two (N, 3) trajectories of the same records; None with fewer than ``min_turns`` turns on
    the spot.

    At a record whose odometry turns on the spot (``TURN_MAX_ODOMETRY_M``, ``TURN_MIN_RAD``) the
    estimate's frame, if it sits at m from the turning point, moves by t = (R(θ) - I) m (θ its own turn):
    m is the least-squares fit over those records. (R - I)ᵀ(R - I) = 2 (1 - cos θ) I, so the fit is
    Σ (R - I)ᵀ t / Σ 2 (1 - cos θ)."""
    odo = between(odometry[:-1], odometry[1:])
    motion = between(estimate[:-1], estimate[1:])
    turns = (
        (np.hypot(odo[:, 0], odo[:, 1]) <= TURN_MAX_ODOMETRY_M)
        & (np.abs(odo[:, 2]) >= TURN_MIN_RAD)
        & (np.hypot(motion[:, 0], motion[:, 1]) <= TURN_MAX_MOTION_M)
    )
    if int(np.count_nonzero(turns)) < min_turns:
        return None
    t = motion[turns, :2]
    c, s = np.cos(motion[turns, 2]) - 1.0, np.sin(motion[turns, 2])
    # (R - I)ᵀ t with R - I = [[c, -s], [s, c]].
    rhs = np.array([np.sum(c * t[:, 0] + s * t[:, 1]), np.sum(-s * t[:, 0] + c * t[:, 1])])
    out: FloatArray = rhs / float(np.sum(c * c + s * s))
    return out


def turn_ratio(
    reference: FloatArray, estimate: FloatArray, min_turn_rad: float = 0.3, min_turns: int = 10
) -> float:
    """Σ θ θ* / Σ θ*² over the consecutive records whose reference turns at least ``min_turn_rad`` (θ the
    estimate's turn, θ* the reference's): 1 where the estimate turns as much as the reference on average,
    below where it turns less; NaN with fewer than ``min_turns`` such records (FR079, whose records are
    0.2 rad apart at most turns, has 2). A turning scale that the relations do not show
    (each record's error is a fraction of a degree), but which a stretch of turns on the spot in one
    direction carries into every relation across it."""
    ref = between(reference[:-1], reference[1:])[:, 2]
    est = between(estimate[:-1], estimate[1:])[:, 2]
    turns = np.abs(ref) >= min_turn_rad
    if int(np.count_nonzero(turns)) < max(min_turns, 1):
        return math.nan
    return float(np.sum(est[turns] * ref[turns]) / np.sum(ref[turns] ** 2))
