"""The trajectory at the records between filter updates (agent.slam.replay.poses_per_record): each update's
record takes the update's pose, and a record between two updates carries the correction the filter made at
the second in proportion to the odometry's motion up to it, turns included."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.slam.pose import compose
from agent.slam.replay import blend_between, motion_shares, poses_per_record


def _straight(n: int, step_m: float, turn_rad: float = 0.0) -> np.ndarray:
    """Odometry of n records, each step_m forward and turn_rad left of the one before."""
    poses = np.zeros((n, 3))
    for i in range(1, n):
        poses[i] = compose(poses[i - 1], (step_m, 0.0, turn_rad))
    return poses


def test_shares_follow_the_motion_and_count_turns_on_the_spot() -> None:
    shares = motion_shares(_straight(5, 0.1), metres_per_rad=1.25)
    np.testing.assert_allclose(shares, [0.0, 0.25, 0.5, 0.75, 1.0])
    # Two records of driving, then two of turning on the spot worth as much at 1 m a radian.
    path = np.array([[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [0.2, 0, 0.1], [0.2, 0, 0.2]], dtype=float)
    np.testing.assert_allclose(motion_shares(path, 1.0), [0.0, 0.25, 0.5, 0.75, 1.0])
    # Back and forth counts as motion both ways, not as the net displacement.
    there_and_back = np.array([[0, 0, 0], [0.1, 0, 0], [0.0, 0, 0]], dtype=float)
    np.testing.assert_allclose(motion_shares(there_and_back, 1.0), [0.0, 0.5, 1.0])
    # Standing still: nothing driven yet.
    np.testing.assert_array_equal(motion_shares(np.zeros((3, 3)), 1.0), np.zeros(3))


def test_headings_blend_on_the_circle() -> None:
    forward = np.array([[0.0, 0.0, math.pi - 0.1]])
    backward = np.array([[1.0, 2.0, -math.pi + 0.1]])
    out = blend_between(forward, backward, np.array([0.5]))
    np.testing.assert_allclose(out[0, :2], [0.5, 1.0])
    assert abs(abs(out[0, 2]) - math.pi) < 1e-9  # through pi, not through 0


def test_a_correction_at_the_next_update_is_shared_by_the_records_before_it() -> None:
    odometry = _straight(9, 0.1, turn_rad=0.05)  # updates at records 0, 4 and 8
    updates = [0, 4, 8]
    truth = _straight(9, 0.1, turn_rad=0.06)  # odometry under-reads every turn by a sixth
    path = truth[updates]
    poses = poses_per_record(odometry, updates, path, odometry[updates], metres_per_rad=1.25)
    np.testing.assert_allclose(poses[updates], path, atol=1e-12)
    # Carried forward alone, the record just before an update misses nearly all of its correction ...
    forward = poses_per_record(odometry, updates, path, odometry[updates], 1.25, blend=False)
    np.testing.assert_allclose(forward[updates], path, atol=1e-12)
    between = [1, 2, 3, 5, 6, 7]
    blended_error = np.abs(poses[between] - truth[between]).max()
    forward_error = np.abs(forward[between] - truth[between]).max()
    assert blended_error < forward_error / 4
    # ... blended, its heading is the truth's to within the odometry's error over the last step.
    assert abs(poses[3, 2] - truth[3, 2]) <= 0.01 + 1e-12
    assert abs(forward[3, 2] - truth[3, 2]) == pytest.approx(0.03)


def test_records_outside_the_updates() -> None:
    odometry = _straight(8, 0.1)
    updates = [2, 5]
    path = odometry[updates] + np.array([0.0, 0.05, 0.01])
    poses = poses_per_record(odometry, updates, path, odometry[updates], metres_per_rad=1.25)
    # Before the first update: the odometry itself. After the last: carried forward from it.
    np.testing.assert_array_equal(poses[:2], odometry[:2])
    np.testing.assert_allclose(poses[6], compose(path[1], (0.1, 0.0, 0.0)), atol=1e-12)
    # No updates at all: the odometry.
    np.testing.assert_array_equal(
        poses_per_record(odometry, [], np.zeros((0, 3)), np.zeros((0, 3)), 1.25), odometry
    )
