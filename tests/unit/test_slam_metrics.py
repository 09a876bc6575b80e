"""The global-consistency figure: the relation error over every pair of poses far apart."""

from __future__ import annotations

import math

import numpy as np

from agent.slam.metrics import far_relation_error, far_relation_pairs
from agent.slam.pose import between, compose


def _square_loop(side_m: float = 12.0, step_m: float = 0.5) -> np.ndarray:
    poses = []
    pose = np.zeros(3)
    for _ in range(4):
        for _ in range(int(side_m / step_m)):
            poses.append(pose.copy())
            pose = compose(pose, np.array([step_m, 0.0, 0.0]))
        pose = compose(pose, np.array([0.0, 0.0, math.pi / 2]))
    return np.array(poses)


def test_only_pairs_at_least_the_distance_apart_count() -> None:
    reference = _square_loop()
    pairs = far_relation_pairs(reference, 10.0)
    d = np.hypot(*(reference[pairs[:, 0], :2] - reference[pairs[:, 1], :2]).T)
    assert pairs.shape[0] > 100 and np.all(d >= 10.0) and np.all(pairs[:, 0] < pairs[:, 1])
    assert far_relation_pairs(reference, 100.0).shape == (0, 2)
    assert far_relation_error(reference, reference, 100.0).n == 0


def test_a_loop_that_does_not_close_shows_far_apart_and_not_between_neighbours() -> None:
    reference = _square_loop()
    # The same loop with 1 deg too much at every corner: locally fine, the far ends wrong.
    bent = [np.zeros(3)]
    for k in range(1, reference.shape[0]):
        delta = between(reference[k - 1], reference[k])
        if abs(delta[2]) > 1.0:
            delta[2] += math.radians(1.0)
        bent.append(compose(bent[-1], delta))
    estimate = np.array(bent)
    assert far_relation_error(reference, reference).trans_error_m_mean < 1e-9
    far = far_relation_error(reference, estimate)
    assert far.trans_error_m_mean > 0.2 and far.rot_error_deg_mean > 0.5
