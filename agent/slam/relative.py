"""Scan-to-scan point-to-line matching: a relative measurement of one filter update's motion.

The front end matches each scan against its particle's whole map, so a step where the map's far walls
come back into view (a corridor's junction after a long run along it) snaps the pose by the whole
corridor's length error, and that map match's information says the step is measured tightly. Matched
against the scan before it instead, the step's information is only what the two scans share: a
corridor whose ends are out of view is measured across, not along (docs/slam.md, "Loop closure",
``LoopClosureConfig.edge_information = "scan"``).

Pure numpy (and a k-d tree) in, numpy out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class RelativeMatch:
    """``pose``: scan k's base in scan k-1's base frame (x, y, yaw) after the point-to-line iterations;
    ``information``: sum g gᵀ over the pairs within the bound at ``pose`` (3, 3, in scan k-1's frame:
    the same form as a map match's world-frame information), g = (n, p' × n), n the reference's unit
    normal and p' the endpoint's offset from scan k's base turned into scan k-1's frame; ``pairs``: how
    many pairs it counts."""

    pose: FloatArray
    information: FloatArray
    pairs: int


def _pairs(
    tree: cKDTree,
    reference_xy: FloatArray,
    normals_xy: FloatArray,
    scan_xy: FloatArray,
    pose: FloatArray,
    max_pair_m: float,
    bound_m: float,
) -> tuple[FloatArray, FloatArray]:
    """Per pair within ``max_pair_m`` of a reference endpoint that has a normal, and within ``bound_m``
    of its line: g (K, 3) and the signed offset across the line (K,)."""
    c, s = math.cos(float(pose[2])), math.sin(float(pose[2]))
    rx = c * scan_xy[:, 0] - s * scan_xy[:, 1]
    ry = s * scan_xy[:, 0] + c * scan_xy[:, 1]
    moved = np.stack([rx + pose[0], ry + pose[1]], axis=1)
    distance, index = tree.query(moved, distance_upper_bound=max_pair_m)
    found = np.isfinite(distance)
    index = np.where(found, index, 0)
    n = normals_xy[index]
    has = found & ((n[:, 0] != 0.0) | (n[:, 1] != 0.0))
    offset = np.einsum("ki,ki->k", moved - reference_xy[index], n)
    keep = has & (np.abs(offset) < bound_m)
    n, offset = n[keep], offset[keep]
    g = np.stack([n[:, 0], n[:, 1], rx[keep] * n[:, 1] - ry[keep] * n[:, 0]], axis=1)
    return g, offset


def match_relative(
    reference_xy: FloatArray,
    reference_normals_xy: FloatArray,
    scan_xy: FloatArray,
    guess: FloatArray,
    iterations: int = 10,
    max_pair_m: float = 0.5,
    bound_m: float = 0.15,
    anchor: float = 5.0,
    coarse_iterations: int = 0,
    coarse_bound_m: float = 0.5,
) -> RelativeMatch:
    """Point-to-line ICP of ``scan_xy`` (scan k's endpoints, its base frame) against ``reference_xy``
    (scan k-1's, its base frame) with the reference's unit normals ((R, 2), (0, 0) where none:
    ``grid.surface_normals``), from ``guess`` (scan k in scan k-1's frame, the filter's step).

    Each iteration pairs every endpoint with its nearest reference endpoint within ``max_pair_m`` that
    has a normal, keeps the pairs whose offset across that line is below ``bound_m``, and takes a
    Gauss-Newton step of Σ r² + ``anchor`` |pose - guess|² (H + ``anchor`` I) δ = -(Σ g r + ``anchor``
    (pose - guess)): a direction the lines do not fix (along a corridor: information near zero) stays at
    the guess instead of sliding, one they fix (information in the tens) goes where they say. The first
    ``coarse_iterations`` pair within and bound by ``coarse_bound_m`` instead (a step the filter's
    match put tens of centimetres off, its snap onto a junction, is outside the fine bound). The returned
    information is the undamped Σ g gᵀ at the final pose (zeros with fewer than 3 pairs)."""
    reference_xy = np.asarray(reference_xy, dtype=np.float64)
    normals = np.asarray(reference_normals_xy, dtype=np.float64)
    scan_xy = np.asarray(scan_xy, dtype=np.float64)
    start = np.asarray(guess, dtype=np.float64)
    pose = start.copy()
    if reference_xy.shape[0] == 0 or scan_xy.shape[0] == 0:
        return RelativeMatch(pose, np.zeros((3, 3)), 0)
    # Imported here: scipy.spatial adds ~29 MB to the process's peak RSS, which the filter's default path,
    # with relative edges off, must not pay (issue 20's 120 MB line on Intel).
    from scipy.spatial import cKDTree

    tree = cKDTree(reference_xy)
    for it in range(coarse_iterations + iterations):
        coarse = it < coarse_iterations
        g, offset = _pairs(
            tree,
            reference_xy,
            normals,
            scan_xy,
            pose,
            max(max_pair_m, coarse_bound_m) if coarse else max_pair_m,
            max(bound_m, coarse_bound_m) if coarse else bound_m,
        )
        if offset.size < 3:
            break
        h = g.T @ g + anchor * np.eye(3)
        step = -np.linalg.solve(h, g.T @ offset + anchor * (pose - start))
        pose = pose + step
        if not coarse and float(np.hypot(step[0], step[1])) < 1e-4 and abs(float(step[2])) < 1e-5:
            break
    g, offset = _pairs(tree, reference_xy, normals, scan_xy, pose, max_pair_m, bound_m)
    if offset.size < 3:
        return RelativeMatch(pose, np.zeros((3, 3)), int(offset.size))
    information: FloatArray = g.T @ g
    return RelativeMatch(pose, 0.5 * (information + information.T), int(offset.size))
