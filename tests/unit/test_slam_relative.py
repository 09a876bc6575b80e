"""Scan-to-scan point-to-line matching (agent.slam.relative): a corridor is measured across, not along."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np

from agent.slam.grid import surface_normals
from agent.slam.pose import between
from agent.slam.relative import match_relative


def _seen_from(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """World points in the frame of a robot at ``pose``."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    d = points - pose[:2]
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)


def _scan(points: np.ndarray, pose: np.ndarray, max_range: float) -> np.ndarray:
    """The world points within ``max_range`` of ``pose``, in its frame, in beam (bearing) order."""
    local = _seen_from(points, pose)
    local = local[np.hypot(local[:, 0], local[:, 1]) <= max_range]
    return local[np.argsort(np.arctan2(local[:, 1], local[:, 0]))]


def _match(points: np.ndarray, before: np.ndarray, after: np.ndarray, guess: np.ndarray):
    reference = _scan(points, before, 6.0)
    normals = surface_normals(reference, max_thickness_m=0.03, radius_per_m=0.1)
    return match_relative(reference, normals, _scan(points, after, 6.0), guess)


def _corridor() -> np.ndarray:
    x = np.arange(-30.0, 30.0, 0.05)
    return np.vstack([np.stack([x, np.full_like(x, 1.0)], 1), np.stack([x, np.full_like(x, -1.2)], 1)])


def test_a_corridor_is_measured_across_and_left_at_the_guess_along() -> None:
    before, after = np.array([0.0, 0.0, 0.0]), np.array([0.8, 0.1, 0.03])
    truth = between(before, after)
    guess = truth + np.array([0.3, -0.06, 0.02])  # 0.3 m too long, 6 cm and 1.1 deg off across
    found = _match(_corridor(), before, after, guess)
    assert abs(found.pose[1] - truth[1]) < 0.01 and abs(found.pose[2] - truth[2]) < 0.003
    assert abs(found.pose[0] - guess[0]) < 0.02  # the walls say nothing along the corridor
    info = found.information
    assert info[1, 1] > 50.0 and info[0, 0] < 1e-6 * info[1, 1]  # across: every pair; along: none
    assert np.all(np.linalg.eigvalsh(info) > -1e-9)


def test_a_room_is_measured_in_every_direction() -> None:
    t = np.arange(0.0, 4.0, 0.05)
    room = np.vstack(
        [
            np.stack([t - 2.0, np.full_like(t, -1.5)], 1),
            np.stack([t - 2.0, np.full_like(t, 1.5)], 1),
            np.stack([np.full_like(t[:60], -2.0), t[:60] - 1.5], 1),
            np.stack([np.full_like(t[:60], 2.0), t[:60] - 1.5], 1),
        ]
    )
    before, after = np.array([-0.3, 0.1, 0.2]), np.array([0.2, -0.1, 0.35])
    truth = between(before, after)
    found = _match(room, before, after, truth + np.array([0.08, -0.06, 0.03]))
    np.testing.assert_allclose(found.pose, truth, atol=0.01)
    assert np.min(np.linalg.eigvalsh(found.information[:2, :2])) > 20.0


def test_no_shared_surface_gives_no_information() -> None:
    reference = _scan(_corridor(), np.zeros(3), 6.0)
    normals = surface_normals(reference, max_thickness_m=0.03, radius_per_m=0.1)
    elsewhere = np.stack([np.full(50, 4.0), np.linspace(3.0, 5.0, 50)], axis=1)  # a wall beyond the corridor
    found = match_relative(reference, normals, elsewhere, np.zeros(3))
    assert found.pairs < 3 and not found.information.any()
    np.testing.assert_array_equal(found.pose, np.zeros(3))


def test_a_junction_pulls_back_a_step_the_filter_put_far_off_along_the_corridor() -> None:
    """A cross wall 3 m ahead fixes the corridor's length: a step 0.35 m too long (the front end's snap
    onto its map) is pulled back once the first iterations pair within the coarse bound."""
    y = np.arange(-1.2, 1.0, 0.05)
    world = np.vstack([_corridor(), np.stack([np.full_like(y, 3.0), y], 1)])
    world = world[world[:, 0] <= 3.0]
    before, after = np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.05, 0.01])
    truth = between(before, after)
    guess = truth + np.array([-0.35, -0.05, 0.0])
    fine = _match(world, before, after, guess)
    assert abs(fine.pose[0] - truth[0]) > 0.2  # the junction's pairs are outside the fine bound
    reference = _scan(world, before, 6.0)
    normals = surface_normals(reference, max_thickness_m=0.03, radius_per_m=0.1)
    found = match_relative(
        reference, normals, _scan(world, after, 6.0), guess, coarse_iterations=5, anchor=1.0
    )
    np.testing.assert_allclose(found.pose, truth, atol=0.02)
    assert np.min(np.linalg.eigvalsh(found.information[:2, :2])) > 10.0


def test_the_filter_does_not_import_scipy_spatial_until_relative_edges_run() -> None:
    # scipy.spatial costs the process ~29 MB of peak RSS: on Intel that alone broke issue 20's 120 MB line
    # (111 -> 138 MB) while relative edges were off.
    code = "import sys, agent.commands.eval_slam, agent.slam.rbpf; print('scipy.spatial' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
