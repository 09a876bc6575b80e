"""The laser person detector and the person tracker (agent.following.person)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.following.person import (
    DetectorConfig,
    PersonDetections,
    PersonTracker,
    TrackerConfig,
    detect_people,
)
from drivers.sim.raycast import cast_rays

ANGLES = np.linspace(-math.pi * 2 / 3, math.pi * 2 / 3, 682)
# A 10 x 6 m room round the laser at (2, 3), facing +x.
WALLS = np.array([[0.0, 0.0, 10.0, 0.0], [10.0, 0.0, 10.0, 6.0], [10.0, 6.0, 0.0, 6.0], [0.0, 6.0, 0.0, 0.0]])


def scan(people: list[tuple[float, float, float]], laser=(2.0, 3.0, 0.0)) -> np.ndarray:
    circles = np.array(people) if people else None
    r = cast_rays(laser[:2], ANGLES + laser[2], WALLS, circles, 5.6)
    return np.asarray(r, dtype=np.float64)


def test_a_person_is_found_and_walls_are_not() -> None:
    ranges = scan([(3.5, 3.2, 0.2)])
    # Every wall return is on the static map; the person's are not.
    static = np.isfinite(ranges) & ~(np.abs(ranges - np.hypot(1.5, 0.2)) < 0.3)
    found = detect_people(ANGLES, ranges, (2.0, 3.0, 0.0), static)
    assert len(found) == 1
    assert math.dist(found.centres[0], (3.5, 3.2)) < 0.1
    assert 0.1 <= found.widths_m[0] <= 0.6


def test_without_a_map_wide_walls_are_not_people_but_a_pillar_is() -> None:
    ranges = scan([(3.5, 3.2, 0.2), (4.0, 1.5, 0.05)])  # a person and a thin post (0.1 m)
    found = detect_people(ANGLES, ranges, (2.0, 3.0, 0.0), None)
    # The walls are far wider than a person; the post is narrower than min_width, the person in range.
    assert len(found) == 1
    assert math.dist(found.centres[0], (3.5, 3.2)) < 0.1


def test_a_person_beyond_max_range_is_not_detected() -> None:
    ranges = scan([(7.5, 3.0, 0.2)])
    found = detect_people(ANGLES, ranges, (2.0, 3.0, 0.0), None, DetectorConfig(max_range_m=5.0))
    assert len(found) == 0


def dets(*xy: tuple[float, float]) -> PersonDetections:
    return PersonDetections(np.array(xy, dtype=np.float64).reshape(-1, 2), np.full(len(xy), 0.3))


def test_acquire_takes_the_nearest_inside_the_window() -> None:
    tracker = PersonTracker()
    robot = (0.0, 0.0, 0.0)
    # Nearest overall is behind the robot (outside a 35 degree window ahead); the one ahead is taken.
    assert tracker.acquire(0.0, dets((-1.0, 0.0), (2.0, 0.3), (3.5, -0.2)), robot, 0.0, math.radians(35))
    est = tracker.estimate()
    assert est is not None and est.xy == (2.0, 0.3) and est.track_id == 1
    assert not PersonTracker().acquire(0.0, dets((-1.0, 0.0)), robot, 0.0, math.radians(35))


def test_the_track_follows_a_walker_and_estimates_their_velocity() -> None:
    rng = np.random.default_rng(3)
    tracker = PersonTracker()
    tracker.acquire(0.0, dets((2.0, 0.0)), (0.0, 0.0, 0.0), 0.0, 1.0)
    for k in range(1, 51):
        t = k * 0.1
        truth = (2.0 + 0.7 * t, 0.0)
        assert tracker.update_detections(t, dets(tuple(np.array(truth) + rng.normal(0, 0.05, 2))))
    est = tracker.estimate()
    assert est is not None
    assert math.dist(est.xy, (2.0 + 0.7 * 5.0, 0.0)) < 0.12
    assert abs(est.velocity[0] - 0.7) < 0.15 and abs(est.velocity[1]) < 0.15
    assert np.all(np.linalg.eigvalsh(est.covariance) > 0)


def test_gating_keeps_the_identity_when_a_passer_by_is_nearer_the_robot() -> None:
    tracker = PersonTracker()
    tracker.acquire(0.0, dets((2.0, 0.0)), (0.0, 0.0, 0.0), 0.0, 1.0)
    for k in range(1, 31):
        t = k * 0.1
        user = (2.0 + 0.7 * t, 0.0)
        passer = (1.5 + 0.0 * t, 2.0 - 1.0 * t)  # crosses the line robot-user at t = 2 s
        tracker.update_detections(t, dets(passer, user))
        est = tracker.estimate()
        assert est is not None and math.dist(est.xy, user) < 0.2, t
    assert tracker.track_id == 1


def test_a_track_without_measurements_is_lost_after_the_timeout() -> None:
    tracker = PersonTracker(TrackerConfig(lost_after_s=1.0))
    tracker.acquire(0.0, dets((2.0, 0.0)), (0.0, 0.0, 0.0), 0.0, 1.0)
    assert not tracker.update_detections(0.5, dets((6.0, 3.0)))  # outside the gate
    assert tracker.tracking
    tracker.predict(1.2)
    assert not tracker.tracking and tracker.counts["lost"] == 1
    # Re-acquisition takes the one near where the lost person would be by now, not someone nearer the robot.
    assert tracker.acquire(1.5, dets((1.0, 0.5), (2.3, 0.0)), (0.0, 0.0, 0.0), 0.0, 1.0)
    est = tracker.estimate()
    assert est is not None and est.xy == (2.3, 0.0) and est.track_id == 2


def test_soon_after_a_loss_nobody_far_from_the_lost_person_is_taken() -> None:
    tracker = PersonTracker(TrackerConfig(lost_after_s=1.0, reacquire_s=5.0))
    tracker.acquire(0.0, dets((2.0, 0.0)), (0.0, 0.0, 0.0), 0.0, 1.0)
    tracker.predict(1.2)
    assert not tracker.tracking
    # A passer-by 2.5 m to the side of where the user was: not them, not yet anyone.
    assert not tracker.acquire(1.5, dets((2.0, 2.5)), (0.0, 0.0, 0.0), 0.0, 1.5)
    # Long after the loss the nearest in the window is taken again.
    assert tracker.acquire(7.0, dets((2.0, 2.5)), (0.0, 0.0, 0.0), 0.0, 1.5)


def test_a_bearing_measurement_pulls_the_track_sideways_only() -> None:
    tracker = PersonTracker()
    tracker.acquire(0.0, dets((3.0, 0.0)), (0.0, 0.0, 0.0), 0.0, 1.0)
    before = tracker.estimate()
    assert before is not None
    # The camera says the person is 3 degrees left of where the track has them.
    assert tracker.update_bearing(0.05, (0.0, 0.0), math.radians(3.0), math.radians(1.0))
    after = tracker.estimate()
    assert after is not None
    assert after.xy[1] > before.xy[1] + 0.05
    assert abs(math.hypot(*after.xy) - 3.0) < 0.05  # range is not what a bearing tells
    # A bearing far outside the gate is rejected.
    assert not tracker.update_bearing(0.1, (0.0, 0.0), math.radians(60.0), math.radians(1.0))


def test_a_relocalization_carries_the_track_with_the_robot() -> None:
    """The fused pose jumps (the map frame corrected under the robot): the person keeps their place and
    heading relative to the robot."""
    tracker = PersonTracker()
    assert tracker.acquire(
        0.0, PersonDetections(np.array([[3.0, 1.0]]), np.array([0.3])), (1.0, 1.0, 0.0), 0.0, 1.0
    )
    assert tracker.x is not None
    tracker.x[2:] = (0.7, 0.0)  # walking away along +x
    tracker.reframe((1.0, 1.0, 0.0), (1.5, 0.5, math.pi / 2))
    est = tracker.estimate()
    assert est is not None
    assert est.xy == pytest.approx((1.5, 2.5))  # still 2 m straight ahead of the robot
    assert est.velocity == pytest.approx((0.0, 0.7), abs=1e-12)


def test_an_old_bearing_does_not_age_the_track() -> None:
    """A frame delivered late (its time before the last scan's) must not move the track's last measurement
    back: that dropped a fresh track at the start of a run."""
    tracker = PersonTracker()
    assert tracker.acquire(
        1.0, PersonDetections(np.array([[3.0, 1.0]]), np.array([0.3])), (1.0, 1.0, 0.0), 0.0, 1.0
    )
    assert tracker.update_bearing(0.2, (1.0, 1.0), 0.0, 0.05)
    est = tracker.estimate()
    assert est is not None and est.last_seen_s == 1.0
    tracker.predict(2.0, 1.9)
    assert tracker.tracking
