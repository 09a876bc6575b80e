"""Moving obstacles: a walker seen in consecutive scans is tracked and their next seconds forbidden; the
mapped walls make no tracks."""

from __future__ import annotations

import math

import numpy as np

from agent.navigation.config import NavConfig
from agent.navigation.costmap import Costmap, GridSpec
from agent.navigation.moving import MovingObstacles
from drivers.sim.raycast import cast_rays

SPEC = GridSpec((0.0, 0.0), 0.05, (80, 160))  # 8 x 4 m
ANGLES = np.linspace(-2.0, 2.0, 682)
WALLS = np.array([[0.0, 0.2, 8.0, 0.2], [0.0, 3.8, 8.0, 3.8]])  # a corridor


def _costmap() -> Costmap:
    occupied = np.zeros(SPEC.shape, bool)
    occupied[[4, 76], :] = True
    return Costmap(SPEC, occupied, np.zeros(SPEC.shape, bool), NavConfig())


def _points(person: tuple[float, float]) -> np.ndarray:
    """A scan from (1, 2) facing +x of the corridor with a person (radius 0.2) in it, map frame."""
    ranges = cast_rays((1.0, 2.0), ANGLES, WALLS, np.array([[*person, 0.2]]), 5.6)
    hit = np.isfinite(ranges)
    return np.stack(
        [1.0 + ranges[hit] * np.cos(ANGLES[hit]), 2.0 + ranges[hit] * np.sin(ANGLES[hit])], axis=1
    )


def test_a_walker_is_tracked_and_their_way_ahead_forbidden() -> None:
    costmap = _costmap()
    moving = MovingObstacles(horizon_s=3.0)
    for k in range(6):  # walking towards the robot at 0.8 m/s, scans at 10 Hz
        moving.update(0.1 * k, _points((5.0 - 0.08 * k, 2.5)), costmap.static_distance_m(), SPEC)
    (track,) = moving.moving()
    assert math.isclose(track.vx_mps, -0.8, abs_tol=0.25) and abs(track.vy_mps) < 0.2
    costmap.set_predicted(moving.sweeps(SPEC))
    ahead = costmap.cost_at(np.array([[3.5, 2.5], [2.5, 2.5]]))
    assert np.all(np.isinf(ahead))  # where they will be within 3 s
    assert np.isfinite(costmap.cost_at(np.array([[2.0, 1.0]]))[0])  # beside their way: free


def test_walls_and_a_person_standing_still_make_no_sweep() -> None:
    costmap = _costmap()
    moving = MovingObstacles()
    for k in range(6):
        moving.update(0.1 * k, _points((4.0, 2.5)), costmap.static_distance_m(), SPEC)
    assert len(moving.tracks) == 1  # the person, not the walls
    assert not moving.moving()
    assert not moving.sweeps(SPEC).any()
