"""Doors that open and close during a run (``[[doors]]``, docs/world.md): the schedule, the laser and the
collision checks see a closed door as a wall, a door waits for the robot to leave the doorway, and the
world file's mistakes are ConfigErrors naming the key. Named places (``[[places]]``) load and are checked."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from drivers.errors import ConfigError
from drivers.sim.simulation import Simulation
from drivers.sim.world import Door, Pose2D, RobotSpec, Wall, World, door_scheduled_closed
from drivers.sim.worldfile import load_world, parse_world

REPO = Path(__file__).resolve().parents[2]
# A 4 x 2 m box with a 1 m doorway in its east wall (x = 4, y 0.5..1.5); the door closes at 10 s.
WALLS = (
    Wall(0, 0, 4, 0),
    Wall(4, 0, 4, 0.5),
    Wall(4, 1.5, 4, 2),
    Wall(4, 2, 0, 2),
    Wall(0, 2, 0, 0),
)
DOOR = Door("east", 4.0, 0.5, 4.0, 1.5, closes_at_s=10.0)


class Clock:
    def __init__(self) -> None:
        self.t = 50.0

    def __call__(self) -> float:
        return self.t


START = Pose2D(1.0, 1.0, 0.0)


def world(door: Door = DOOR, start: Pose2D = START) -> World:
    return World("doors", walls=WALLS, doors=(door,), robot=RobotSpec(start=start))


@pytest.mark.parametrize(
    ("closes", "opens", "closed_at"),
    [
        (10.0, None, [False, False, True, True]),  # open, then closed for good
        (None, 10.0, [True, True, False, False]),  # closed, then open
        (10.0, 20.0, [False, False, True, False]),  # open, closed 10..20 s, open
        (20.0, 10.0, [True, True, False, True]),  # closed, open 10..20 s, closed
        (None, None, [False, False, False, False]),  # never closes: a doorway
    ],
)
def test_the_schedule(closes: float | None, opens: float | None, closed_at: list[bool]) -> None:
    door = Door("d", 0, 0, 1, 0, closes, opens)
    assert [door_scheduled_closed(door, t) for t in (0.0, 9.9, 15.0, 25.0)] == closed_at


def test_the_laser_sees_through_an_open_door_and_stops_at_a_closed_one() -> None:
    clock = Clock()
    sim = Simulation(world(), clock)
    east = np.array([0.0])
    assert math.isinf(sim.laser_ranges_m(east)[0])  # through the doorway, nothing within range
    assert sim.doors_closed() == {"east": False}
    clock.t += 10.5
    assert sim.laser_ranges_m(east)[0] == pytest.approx(3.0)  # the laser sits on the base's centre
    assert sim.doors_closed() == {"east": True}
    assert sim.door_events() == [(pytest.approx(10.0, abs=0.01), "east", True)]


def test_a_closed_door_is_a_wall_to_the_collision_check() -> None:
    clock = Clock()
    sim = Simulation(world(), clock)
    wall_open, _ = sim.clearances_m(3.9, 1.0)
    assert wall_open > 0.3  # the nearest wall is the jamb, 0.5 m away less the footprint
    clock.t += 11.0
    wall_closed, _ = sim.clearances_m(3.9, 1.0)
    assert wall_closed < 0.0  # the footprint overlaps the closed door
    assert len(sim.segments()) == len(WALLS) + 1


def test_a_door_waits_for_the_robot_to_leave_the_doorway() -> None:
    clock = Clock()
    sim = Simulation(world(start=Pose2D(4.0, 1.0, 0.0)), clock)
    clock.t += 12.0
    assert sim.doors_closed() == {"east": False}  # the robot stands in the doorway
    sim.set_body_velocity(-0.2, 0.0)  # back out, west
    for _ in range(40):
        clock.t += 0.05
        sim.advance()
    assert sim.pose().x_m < 4.0 - 0.15
    assert sim.doors_closed() == {"east": True}
    ((t_s, name, closed),) = sim.door_events()
    assert name == "east" and closed and t_s > 12.0


def test_a_door_closed_at_the_start_is_closed_from_the_first_scan() -> None:
    clock = Clock()
    sim = Simulation(world(Door("east", 4.0, 0.5, 4.0, 1.5, opens_at_s=5.0)), clock)
    assert sim.laser_ranges_m(np.array([0.0]))[0] == pytest.approx(3.0)
    clock.t += 6.0
    assert math.isinf(sim.laser_ranges_m(np.array([0.0]))[0])


# -- the world file ------------------------------------------------------------------------------------------
BOX_TOML = """
[robot]
start = { x_m = 1.0, y_m = 1.0, yaw_rad = 0.0 }
[[walls]]
points = [[4.0, 0.5], [4.0, 0.0], [0.0, 0.0], [0.0, 2.0], [4.0, 2.0], [4.0, 1.5]]
"""


def test_doors_and_places_load() -> None:
    w = parse_world(
        BOX_TOML
        + """
[[doors]]
name = "east"
points = [[4.0, 0.5], [4.0, 1.5]]
closes_at_s = 10
opens_at_s = 20
[[places]]
name = "desk"
x_m = 3.0
y_m = 1.0
yaw_deg = 90
"""
    )
    assert w.doors == (Door("east", 4.0, 0.5, 4.0, 1.5, 10.0, 20.0),)
    assert len(w.places) == 1 and w.places[0].name == "desk"
    assert w.places[0].yaw_rad == pytest.approx(math.pi / 2)


@pytest.mark.parametrize(
    ("extra", "key", "words"),
    [
        ("[[doors]]\npoints = [[4.0, 0.5], [4.0, 0.5]]\n", "doors[0].points", "differ"),
        ("[[doors]]\npoints = [[4.0, 0.5]]\n", "doors[0].points", "at least 2"),
        ("[[doors]]\npoints = [[4.0, 0.5], [4.0, 1.5]]\ncloses_at_s = -1\n", "doors[0].closes_at_s", ">= 0"),
        (
            "[[doors]]\npoints = [[4.0, 0.5], [4.0, 1.5]]\ncloses_at_s = 5\nopens_at_s = 5\n",
            "doors[0].opens_at_s",
            "differ",
        ),
        ("[[doors]]\npoints = [[4.0, 0.5], [4.0, 1.5]]\nshuts_at_s = 5\n", "doors[0].shuts_at_s", ""),
        (
            "[[doors]]\nname = 'a'\npoints = [[4.0, 0.5], [4.0, 1.5]]\n"
            "[[doors]]\nname = 'a'\npoints = [[3.0, 0.5], [3.0, 1.5]]\n",
            "doors[1].name",
            "already",
        ),
        # Closed at the start across the robot.
        ("[[doors]]\npoints = [[1.0, 0.0], [1.0, 2.0]]\nopens_at_s = 5\n", "robot.start", "door"),
        # The route crosses a door that closes.
        (
            "[[doors]]\npoints = [[4.0, 0.5], [4.0, 1.5]]\ncloses_at_s = 5\n"
            "[route]\nwaypoints = [[1, 1], [5, 1]]\n",
            "route.waypoints[0]",
            "wall",
        ),
        ("[[places]]\nname = 'p'\nx_m = 0.05\ny_m = 1.0\n", "places[0].x_m", "overlap"),
        ("[[places]]\nx_m = 1.0\ny_m = 1.0\n", "places[0].name", "missing"),
        (
            "[[places]]\nname = 'p'\nx_m = 1.0\ny_m = 1.0\n[[places]]\nname = 'p'\nx_m = 2.0\ny_m = 1.0\n",
            "places[1].name",
            "already",
        ),
    ],
)
def test_mistakes_name_the_key(extra: str, key: str, words: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_world(BOX_TOML + extra)
    assert info.value.key == key, str(info.value)
    assert words in str(info.value)


def test_the_ward_has_its_closing_door_and_places() -> None:
    ward = load_world(REPO / "examples" / "worlds" / "ward.toml")
    assert [d.name for d in ward.doors] == ["E3"] and ward.doors[0].closes_at_s is not None
    assert {"W1", "E1b", "E2"} <= {p.name for p in ward.places}
