"""The pose graph's chain measured by the scans alone: each node's scan registered against the scan before
it, for the final optimisation (``RbpfSlam.finish``).

The front end's step between two updates is its particle's match against that particle's whole map, with
the odometry as a prior. Two things bend it that a registration of the two scans alone does not have:
where the scans say little along a corridor, the step leans towards the wheels' (on ACES the steps the
seeds share disagree with the reference's by 5 cm RMS forward, correlated 0.80 with the odometry's own
disagreement, while a registration of the two scans alone lands within 2.3 cm of ours and 4.8 cm of the
reference's: the reference leans the other way); and where the map's far walls come back into view, the
whole map's accumulated error lands on one step (a snap). A chain of scan-to-scan registrations carries
neither, but alone it drifts like any odometry; joined with the loop factors the front end found it
holds the building together (docs/slam.md, "Loop closure", *The final optimisation*).

The registration is a trimmed point-to-point ICP (Besl and McKay 1992; the closed-form 2-D rotation of
the pairs' cross-covariance): every endpoint of the newer scan paired with its nearest endpoint of the
older within a distance that shrinks stage by stage, from the front end's step. Nearest neighbours come
from OpenCV's FLANN k-d tree (OpenCV is already loaded; scipy.spatial's would add ~29 MB to the process's
peak memory). Pure numpy (and that call) in, numpy out.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True)
class ScanChainConfig:
    """``stages``: (pairing distance m, at most this many iterations) in turn, each stage left early
    once an iteration moves the pose by less than ``converged_m`` and ``converged_rad``. A registration
    is kept when every iteration had ``min_pairs`` pairs, at least ``min_inlier_fraction`` of the newer
    scan's endpoints end within the last stage's distance of the older's, and it lies within
    ``max_shift_m`` / ``max_turn_rad`` of the front end's step (beyond, a wrong minimum); otherwise the
    chain keeps the front end's step."""

    stages: tuple[tuple[float, int], ...] = ((0.3, 5), (0.15, 5), (0.08, 5))
    converged_m: float = 1e-4
    converged_rad: float = 1e-5
    min_pairs: int = 20
    min_inlier_fraction: float = 0.5
    max_shift_m: float = 0.5
    max_turn_rad: float = 0.3

    def __post_init__(self) -> None:
        if not self.stages or any(d <= 0.0 or n < 1 for d, n in self.stages):
            raise ValueError(f"stages must be (distance > 0 m, iterations >= 1) pairs, got {self.stages}")
        if self.min_pairs < 3:
            raise ValueError(f"min_pairs must be at least 3, got {self.min_pairs}")
        if not 0.0 <= self.min_inlier_fraction <= 1.0:
            raise ValueError(f"min_inlier_fraction must be in [0, 1], got {self.min_inlier_fraction}")
        if self.max_shift_m <= 0.0 or self.max_turn_rad <= 0.0:
            raise ValueError("max_shift_m and max_turn_rad must be above 0")


def _moved(points_xy: FloatArray, pose: tuple[float, float, float]) -> FloatArray:
    """``pose.transform_points`` for one pose given as floats: the same points, without its broadcasting
    over stacks of poses, which costs this loop a fifth more (Intel's chain 0.53 -> 0.65 s)."""
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    out: FloatArray = points_xy @ np.array([[c, s], [-s, c]]) + np.array([x, y])
    return out


# FLANN's single k-d tree (exact for 2-D points: every neighbour checked that could be nearer).
_KD_TREE = {"algorithm": 4, "leaf_max_size": 10}
_SEARCH = {"checks": 32}


def _nearest(moved: FloatArray, tree: Any) -> tuple[FloatArray, npt.NDArray[np.int32]]:
    """Each point's distance to its nearest reference endpoint (m) and that endpoint's index."""
    index, squared = tree.knnSearch(moved.astype(np.float32), 1, params=_SEARCH)
    return np.sqrt(squared[:, 0].astype(np.float64)), index[:, 0]


def register_pair(
    reference_xy: FloatArray, scan_xy: FloatArray, guess: FloatArray, config: ScanChainConfig
) -> tuple[FloatArray, float] | None:
    """(scan's base in the reference's base frame (3,), inlier fraction) of ``scan_xy`` (its endpoints in
    its base frame) registered on ``reference_xy`` (the older scan's, in its own) from ``guess``; None
    where it is not kept (:class:`ScanChainConfig`)."""
    reference = np.asarray(reference_xy, dtype=np.float64).reshape(-1, 2)
    scan = np.asarray(scan_xy, dtype=np.float64).reshape(-1, 2)
    if reference.shape[0] < config.min_pairs or scan.shape[0] < config.min_pairs:
        return None
    # (cv2.flann_Index: in OpenCV's Python module, missing from its type stubs)
    tree = cv2.flann_Index(np.ascontiguousarray(reference, dtype=np.float32), _KD_TREE)  # type: ignore[attr-defined]
    x, y, yaw = (float(v) for v in guess)
    for distance_m, iterations in config.stages:
        for _ in range(iterations):
            moved = _moved(scan, (x, y, yaw))
            distance, index = _nearest(moved, tree)
            paired = distance < distance_m
            if int(np.count_nonzero(paired)) < config.min_pairs:
                return None
            a, b = moved[paired], reference[index[paired]]
            count = a.shape[0]
            sum_a, sum_b = a.sum(axis=0), b.sum(axis=0)
            h = a.T @ b - np.outer(sum_a, sum_b) / count  # the pairs' cross-covariance (times count)
            # The rotation taking the pairs' a onto b (2-D Kabsch, in closed form), then the translation.
            turn = math.atan2(float(h[0, 1] - h[1, 0]), float(h[0, 0] + h[1, 1]))
            c, s = math.cos(turn), math.sin(turn)
            ax, ay = float(sum_a[0]) / count, float(sum_a[1]) / count
            tx = float(sum_b[0]) / count - (c * ax - s * ay)
            ty = float(sum_b[1]) / count - (s * ax + c * ay)
            # The correction applied in the reference frame: pose <- (tx, ty, turn) ⊕ pose.
            x, y = c * x - s * y + tx, s * x + c * y + ty
            yaw = math.atan2(math.sin(yaw + turn), math.cos(yaw + turn))
            if abs(turn) < config.converged_rad and math.hypot(tx, ty) < config.converged_m:
                break
    distance, _ = _nearest(_moved(scan, (x, y, yaw)), tree)
    inliers = float(np.count_nonzero(distance < config.stages[-1][0])) / scan.shape[0]
    turned = math.atan2(math.sin(yaw - float(guess[2])), math.cos(yaw - float(guess[2])))
    if (
        inliers < config.min_inlier_fraction
        or math.hypot(x - float(guess[0]), y - float(guess[1])) > config.max_shift_m
        or abs(turned) > config.max_turn_rad
    ):
        return None
    return np.array([x, y, yaw]), inliers


def scan_chain(
    hits: Sequence[FloatArray], steps: FloatArray, config: ScanChainConfig
) -> tuple[FloatArray, BoolArray]:
    """(chain (N, 3), measured (N,)): ``steps`` (N, 3; node k in node k-1's frame, row 0 unused: the
    front end's chain) with each step k >= 1 replaced by node k's endpoints ``hits[k]`` registered on node
    k-1's from it, where the registration is kept; ``measured`` says where."""
    steps = np.asarray(steps, dtype=np.float64)
    if len(hits) != steps.shape[0]:
        raise ValueError(f"{len(hits)} scans for a chain of {steps.shape[0]} nodes")
    chain = steps.copy()
    measured = np.zeros(steps.shape[0], dtype=bool)
    for k in range(1, steps.shape[0]):
        found = register_pair(hits[k - 1], hits[k], steps[k], config)
        if found is not None:
            chain[k] = found[0]
            measured[k] = True
    return chain, measured
