"""Simulated people as pedestrians: they stop short of the robot standing in their way, after a reaction
time, and walk on when it has gone; a robot behind or beside their way does not stop them; a person who
does not yield walks into it (the contact the simulator must still count)."""

from __future__ import annotations

import math

import pytest

from drivers.sim.pedestrians import STOP_GAP_M, WalkPath
from drivers.sim.simulation import Simulation
from drivers.sim.world import Person, Pose2D, RobotSpec, World


class ManualClock:
    def __init__(self, t: float = 50.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def corridor(robot_at: tuple[float, float], yields: bool = True) -> tuple[Simulation, ManualClock, Person]:
    person = Person("p", "T1", ((0.0, 0.0), (20.0, 0.0)), speed_mps=0.8, radius_m=0.2, yields=yields)
    robot = RobotSpec(start=Pose2D(robot_at[0], robot_at[1], math.pi / 2))
    clock = ManualClock()
    return Simulation(World("open", robot=robot, people=(person,)), clock=clock), clock, person


def gap_m(sim: Simulation, person: Person) -> float:
    px, py = sim.person_position(person)
    pose = sim.pose()
    return math.hypot(px - pose.x_m, py - pose.y_m) - person.radius_m - sim.world.robot.radius_m


def test_a_walker_stops_short_of_the_robot_standing_in_their_way_and_walks_on_when_it_has_gone() -> None:
    sim, clock, person = corridor((5.0, 0.1))
    closest = math.inf
    for _ in range(200):  # 10 s
        clock.t += 0.05
        closest = min(closest, gap_m(sim, person))
    assert sim.person_speed_mps(person) == 0.0
    assert STOP_GAP_M - 0.1 < closest < STOP_GAP_M + 0.15
    stopped_at = sim.person_position(person)
    # The robot drives out of the way (north, 0.6 m), then stops.
    sim.set_body_velocity(0.2, 0.0)
    left = None
    for _ in range(100):
        clock.t += 0.05
        if left is None and sim.pose().y_m > person.radius_m + sim.world.robot.radius_m + 0.1:
            left = clock.t
        if sim.pose().y_m > 0.7:
            sim.set_body_velocity(0.0, 0.0)
        if sim.person_position(person) != stopped_at:
            break
    assert left is not None
    # They react to the robot's going a reaction time late, not before.
    assert clock.t - left >= person.reaction_s - 0.05
    for _ in range(100):
        clock.t += 0.05
    assert sim.person_speed_mps(person) == pytest.approx(0.8)
    assert sim.person_position(person)[0] > 6.0


def test_a_walker_who_does_not_yield_walks_into_the_robot() -> None:
    sim, clock, person = corridor((5.0, 0.1), yields=False)
    closest = math.inf
    for _ in range(200):
        clock.t += 0.05
        closest = min(closest, gap_m(sim, person))
    assert closest < -0.2
    assert sim.person_position(person)[0] == pytest.approx(8.0)


def test_a_robot_beside_or_behind_the_way_does_not_stop_a_walker() -> None:
    for robot_at in ((3.0, 0.6), (-0.45, 0.0)):  # beside their way; just behind where they start
        sim, clock, person = corridor(robot_at)
        for _ in range(100):
            clock.t += 0.05
            assert sim.person_speed_mps(person) == pytest.approx(0.8)
        assert sim.person_position(person)[0] == pytest.approx(4.0)


def test_past_positions_come_from_the_history() -> None:
    sim, clock, person = corridor((15.0, 3.0))
    clock.t += 2.0
    assert sim.person_position(person) == pytest.approx((1.6, 0.0))
    assert sim.person_position(person, clock.t - 1.0) == pytest.approx((0.8, 0.0))


def test_the_way_ahead_follows_the_path_round_its_corners() -> None:
    path = WalkPath(((0.0, 0.0), (2.0, 0.0), (2.0, 2.0)))
    # 1.5 m walked along the first leg; something 0.5 m up the second leg is 1.0 m ahead, less the reach.
    ahead = path.contact_ahead_m(1.5, 3.0, (2.0, 0.5), 0.3)
    assert ahead == pytest.approx(0.5 + 0.5 - 0.3)
    assert path.contact_ahead_m(1.5, 0.5, (2.0, 1.5), 0.3) == math.inf  # beyond the look ahead
