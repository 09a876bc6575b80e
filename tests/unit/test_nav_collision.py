"""The collision monitor: stop and slow zones on the way, and a person stepping in front of the robot."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from agent.navigation.collision import CollisionMonitor, Zone
from agent.navigation.config import NavConfig
from agent.navigation.controller import STOP, Command
from drivers.sim.raycast import cast_rays

CONFIG = NavConfig()
# A URG-04LX's 682 beams (steps 44..725 of 1024, front at 384).
ANGLES: npt.NDArray[np.float64] = (np.arange(44, 726, dtype=np.float64) - 384.0) * (2.0 * math.pi / 1024)
MIN_M, MAX_M = 0.02, 5.6


def _scan_of_circle(x: float, y: float, radius: float) -> np.ndarray:
    """Ranges from a laser at the origin facing +x to a circle (a person), no return elsewhere."""
    ranges = cast_rays((0.0, 0.0), ANGLES, np.zeros((0, 4)), np.array([[x, y, radius]]), MAX_M)
    return np.where(np.isfinite(ranges), ranges, 0.0)


def test_an_obstacle_ahead_in_the_stop_zone_stops_forward_motion_but_not_backing_away() -> None:
    monitor = CollisionMonitor(CONFIG)
    gap = CONFIG.stop_margin_m / 2
    monitor.assess(0.0, ANGLES, _scan_of_circle(CONFIG.radius_m + gap + 0.2, 0.0, 0.2), MIN_M, MAX_M)
    assert monitor.verdict.zone(forward=True) is Zone.STOP
    assert monitor.filter(Command(0.2, 0.3)) == STOP
    assert monitor.filter(Command(-0.05, 0.0)) == Command(-0.05, 0.0)
    assert monitor.filter(Command(0.0, 1.0)) == Command(0.0, 1.0)  # turning in place sweeps nothing new


def test_the_slow_zone_scales_the_speed_down_with_the_gap() -> None:
    monitor = CollisionMonitor(CONFIG)
    speeds = []
    for gap in (0.5, 0.25, 0.15, 0.1):
        monitor.assess(0.0, ANGLES, _scan_of_circle(CONFIG.radius_m + gap + 0.2, 0.0, 0.2), MIN_M, MAX_M)
        speeds.append(monitor.filter(Command(0.2, 0.0)).v_mps)
    assert speeds[0] == 0.2
    assert speeds[0] > speeds[1] > speeds[2] > speeds[3] > 0.0


def test_an_obstacle_beside_the_way_or_behind_does_not_stop_forward_motion() -> None:
    monitor = CollisionMonitor(CONFIG)
    beside = _scan_of_circle(0.1, CONFIG.radius_m + 0.25, 0.2)  # 5 cm off the footprint, to the left
    monitor.assess(0.0, ANGLES, beside, MIN_M, MAX_M)
    assert monitor.filter(Command(0.2, 0.0)) == Command(0.2, 0.0)


def test_a_person_stepping_in_front_is_stopped_for_from_the_first_scan_that_shows_them() -> None:
    """The robot drives at 0.2 m/s; a person steps out from the side into its way 0.25 m ahead. Scans
    come every 0.1 s; the monitor must command zero velocity from the scan in which the person first
    appears in the stop zone, i.e. within one scan period (+10 ms) of their stepping in."""
    period_s = 0.1
    monitor = CollisionMonitor(CONFIG)
    monitor.filter(Command(0.2, 0.0))
    robot_x = 0.0
    person_x = 1.0
    stepped_in_at = 0.43  # between two scans
    stopped_at = None
    for k in range(1, 20):
        t = k * period_s
        person_y = 1.0 if t < stepped_in_at else 0.0
        if t - period_s < stepped_in_at <= t:  # they step in right in front: the stop zone
            person_x = robot_x + CONFIG.radius_m + CONFIG.stop_margin_m / 2 + 0.2
        ranges = _scan_of_circle(person_x - robot_x, person_y, 0.2)
        command = monitor.on_scan(t, ANGLES, ranges, MIN_M, MAX_M)
        if command == STOP:
            stopped_at = t
            break
        assert t < stepped_in_at  # never stopped for nothing
        robot_x += command.v_mps * period_s
    assert stopped_at is not None
    assert stopped_at - stepped_in_at <= period_s + 0.010
    assert monitor.filter(Command(0.2, 0.0)) == STOP  # and it holds until a scan says otherwise
