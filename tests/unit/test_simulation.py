"""The simulation core: laser geometry against a box room, differential-drive kinematics, pose history."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.sim.raycast import cast_rays, walls_array
from drivers.sim.simulation import Simulation
from drivers.sim.world import Person, Pose2D, RobotSpec, Wall, World

BOX = (Wall(0, 0, 4, 0), Wall(4, 0, 4, 2), Wall(4, 2, 0, 2), Wall(0, 2, 0, 0))


class ManualClock:
    """A clock the test moves by hand."""

    def __init__(self, t: float = 100.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def run(sim: Simulation, clock: ManualClock, seconds: float, step_s: float = 0.05) -> None:
    for _ in range(round(seconds / step_s)):
        clock.t += step_s
        sim.advance()


# -- raycast -------------------------------------------------------------------------------------------------
def test_rays_from_inside_a_box_hit_the_walls_at_the_right_distance() -> None:
    segments = walls_array(BOX)
    angles = np.array([0.0, math.pi / 2, math.pi, -math.pi / 2, math.atan2(1.0, 3.0)])
    ranges = cast_rays((1.0, 1.0), angles, segments)
    np.testing.assert_allclose(ranges, [3.0, 1.0, 1.0, 1.0, math.hypot(3.0, 1.0)])


def test_rays_leave_through_a_gap_and_respect_max_range() -> None:
    segments = walls_array((Wall(0, 0, 1.5, 0), Wall(2.5, 0, 4, 0), *BOX[1:]))  # 1 m gap in the south wall
    ranges = cast_rays((2.0, 1.0), np.array([-math.pi / 2, 0.0]), segments, max_range_m=1.5)
    assert ranges[0] == math.inf  # through the gap
    assert ranges[1] == math.inf  # the east wall is 2 m away, beyond max range
    assert cast_rays((2.0, 1.0), np.array([0.0]), segments)[0] == pytest.approx(2.0)


def test_people_block_rays_in_front_of_walls() -> None:
    segments = walls_array(BOX)
    circles = np.array([[2.5, 1.0, 0.2]])
    ranges = cast_rays((1.0, 1.0), np.array([0.0, math.pi]), segments, circles)
    np.testing.assert_allclose(ranges, [1.3, 1.0])


def test_simulated_laser_sees_the_box_from_its_mount() -> None:
    world = World("box", walls=BOX, robot=RobotSpec(start=Pose2D(1.0, 1.0, math.pi / 2)))
    sim = Simulation(world, clock=ManualClock())
    # The laser sits 0 m forward by default; beams are in the laser frame (0 = straight ahead = +y here).
    ranges = sim.laser_ranges_m(np.array([0.0, -math.pi / 2]))
    np.testing.assert_allclose(ranges, [1.0, 3.0])


def test_a_walking_person_shows_up_in_the_scan() -> None:
    person = Person("p", "T1", ((3.0, 0.5), (3.0, 1.5)), speed_mps=1.0, radius_m=0.2)
    clock = ManualClock()
    world = World("box", walls=BOX, robot=RobotSpec(start=Pose2D(1.0, 0.5, 0.0)), people=(person,))
    sim = Simulation(world, clock=clock)
    assert sim.laser_ranges_m(np.array([0.0]))[0] == pytest.approx(1.8)  # person at (3, 0.5)
    clock.t += 1.0  # walked 1 m to (3, 1.5): out of the beam
    assert sim.laser_ranges_m(np.array([0.0]))[0] == pytest.approx(3.0)


# -- kinematics ----------------------------------------------------------------------------------------------
def test_equal_wheel_speeds_drive_a_straight_line() -> None:
    clock = ManualClock()
    robot = RobotSpec(start=Pose2D(0.5, -0.2, math.radians(30)))
    sim = Simulation(World("open", robot=robot), clock=clock)
    wheel = 5.0
    sim.set_wheel_velocity(wheel, wheel)
    run(sim, clock, 2.0)
    # The wheels ramp up at max_wheel_accel_radps2, then roll: distance = r (w t - w^2 / (2 a)).
    ramp = wheel**2 / (2 * robot.max_wheel_accel_radps2)
    distance = robot.wheel_radius_m * (wheel * 2.0 - ramp)
    pose = sim.pose()
    assert pose.x_m == pytest.approx(0.5 + distance * math.cos(math.radians(30)), abs=1e-3)
    assert pose.y_m == pytest.approx(-0.2 + distance * math.sin(math.radians(30)), abs=1e-3)
    assert pose.yaw_rad == pytest.approx(math.radians(30), abs=1e-9)
    left, right = sim.wheels().position_rad
    assert left == pytest.approx(right) and left * robot.wheel_radius_m == pytest.approx(distance, abs=1e-3)


def test_opposite_wheel_speeds_turn_in_place() -> None:
    clock = ManualClock()
    robot = RobotSpec(start=Pose2D(1.0, 2.0, 0.0))
    sim = Simulation(World("open", robot=robot), clock=clock)
    sim.set_wheel_velocity(-2.0, 2.0)
    run(sim, clock, 1.0)
    pose = sim.pose()
    assert (pose.x_m, pose.y_m) == pytest.approx((1.0, 2.0), abs=1e-9)
    left, right = sim.wheels().position_rad
    # yaw = r (theta_r - theta_l) / track, and it turned counter-clockwise.
    expected = robot.wheel_radius_m * (right - left) / robot.track_m
    assert expected > 0.7
    assert math.remainder(pose.yaw_rad - expected, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
    _, _, omega = sim.body_motion()
    assert omega == pytest.approx(robot.wheel_radius_m * 4.0 / robot.track_m)


def test_wheel_speed_is_limited() -> None:
    clock = ManualClock()
    sim = Simulation(World("open"), clock=clock)
    sim.set_wheel_velocity(100.0, 100.0)
    run(sim, clock, 1.0)
    assert sim.wheels().velocity_radps == pytest.approx((6.6, 6.6))


def test_body_velocity_command_maps_to_wheels() -> None:
    clock = ManualClock()
    sim = Simulation(World("open"), clock=clock)
    sim.set_body_velocity(0.1, 0.5)
    run(sim, clock, 1.0)
    v, _, omega = sim.body_motion()
    assert (v, omega) == pytest.approx((0.1, 0.5))


# -- pose history --------------------------------------------------------------------------------------------
def test_pose_at_interpolates_between_recorded_states() -> None:
    clock = ManualClock(10.0)
    sim = Simulation(World("open"), clock=clock)
    sim.set_wheel_velocity(5.0, 5.0)
    run(sim, clock, 0.5)  # past the ramp: constant speed from here
    t_a = clock.t
    a = sim.pose()
    run(sim, clock, 0.2)
    t_b = clock.t
    b = sim.pose()
    speed = 5.0 * 0.033
    assert b.x_m - a.x_m == pytest.approx(speed * (t_b - t_a), rel=1e-6)
    for w in (0.0, 0.123, 0.5, 0.999):
        t = t_a + w * (t_b - t_a)
        assert sim.pose_at(t).x_m == pytest.approx(a.x_m + w * (b.x_m - a.x_m), abs=1e-9)
    assert sim.pose_at(t_b) == sim.pose()
    assert sim.pose_at(0.0) == sim.pose_at(sim.t_start)  # before the history: its oldest pose


def test_pose_at_follows_yaw_across_the_wrap() -> None:
    clock = ManualClock()
    sim = Simulation(World("open", robot=RobotSpec(start=Pose2D(0.0, 0.0, 2.0))), clock=clock)
    sim.set_wheel_velocity(-3.0, 3.0)  # counter-clockwise, ~1.24 rad/s once the wheels are up to speed
    run(sim, clock, 0.3)
    crossed = False
    t_prev, yaw_prev = clock.t, sim.pose().yaw_rad
    for _ in range(150):
        run(sim, clock, 0.01, step_s=0.01)
        yaw_now = sim.pose().yaw_rad
        crossed |= yaw_prev > 3.0 and yaw_now < -3.0
        # Constant yaw rate: halfway in time is halfway in (unwrapped) angle.
        expected = yaw_prev + math.remainder(yaw_now - yaw_prev, 2 * math.pi) / 2
        got = sim.pose_at(t_prev + 0.005).yaw_rad
        assert math.remainder(got - expected, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
        t_prev, yaw_prev = clock.t, yaw_now
    assert crossed
