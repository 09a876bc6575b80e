"""The global-consistency figure: the relation error over every pair of poses far apart."""

from __future__ import annotations

import math

import numpy as np

from agent.slam.metrics import far_relation_error, far_relation_pairs, turn_ratio, turning_point
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


def _turns_on_the_spot(offset: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(odometry, laser poses): a drive of 1 m steps and turns of ±30° on the spot about the odometry's
    point, the laser at ``offset`` (x, y) from it, its poses with 1 cm / 0.2° of match noise."""
    mount = np.array([offset[0], offset[1], 0.0])
    odometry = [np.zeros(3)]
    for k in range(60):
        turn = math.radians(30.0) * (-1) ** k
        step = np.array([1.0, 0.0, 0.05]) if k % 4 == 0 else np.array([0.0, 0.0, turn])
        odometry.append(compose(odometry[-1], step))
    base = np.array(odometry)
    laser = compose(base, mount[None, :])
    laser[:, :2] += rng.normal(0.0, 0.01, (laser.shape[0], 2))
    laser[:, 2] += rng.normal(0.0, math.radians(0.2), laser.shape[0])
    return base, laser


def test_the_turning_point_is_where_the_odometry_turns_about() -> None:
    """``turning_point``: the laser 9 cm ahead of (and 2 cm left of) the point the odometry turns about
    (Intel's laser sits ~9.4 cm ahead of its odometry's) is found within 1.5 cm from the turns on the spot;
    a trajectory that is the odometry's own gives (0, 0); too few turns give None."""
    rng = np.random.default_rng(1)
    base, laser = _turns_on_the_spot(np.array([0.09, 0.02]), rng)
    found = turning_point(base, laser)
    assert found is not None and np.allclose(found, [0.09, 0.02], atol=0.015), found
    same = turning_point(base, base)
    assert same is not None and np.allclose(same, 0.0, atol=1e-9)
    assert turning_point(base[:8], laser[:8]) is None


def test_turn_ratio_is_how_much_the_estimate_turns_against_the_reference() -> None:
    """``turn_ratio``: 1 for the reference itself, 0.99 for a trajectory whose every turn is 1 % short;
    steps that turn less than the threshold do not count; NaN with fewer than ``min_turns`` turns."""
    rng = np.random.default_rng(2)
    base, _ = _turns_on_the_spot(np.zeros(2), rng)
    steps = between(base[:-1], base[1:])
    short = [base[0]]
    for step in steps:
        short.append(compose(short[-1], step * np.array([1.0, 1.0, 0.99 if abs(step[2]) >= 0.3 else 0.5])))
    assert turn_ratio(base, base) == 1.0
    assert math.isclose(turn_ratio(base, np.array(short)), 0.99, rel_tol=1e-9)
    assert math.isnan(turn_ratio(base[:2], base[:2]))
    assert math.isnan(turn_ratio(base[:8], base[:8])) and turn_ratio(base[:8], base[:8], min_turns=5) == 1.0
