"""SP2ATM's admissible space tree, first level: branches from one scan's gaps."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.exploration.admissible_tree import GapKind, scan_branches, to_world

ANGLES = np.linspace(-math.radians(120), math.radians(120), 682)
MAX_M = 5.6
RADIUS = 0.105


def _room_scan(door_half_m: float, room_half_m: float = 2.0) -> np.ndarray:
    """The laser at the centre of a square room (walls at +-room_half_m) with a door of half-width
    ``door_half_m`` in the east wall; beyond the door nothing within range (0: no return)."""
    ranges = np.empty_like(ANGLES)
    for i, a in enumerate(ANGLES):
        c, s = math.cos(a), math.sin(a)
        t = min(
            room_half_m / abs(c) if abs(c) > 1e-12 else math.inf,
            room_half_m / abs(s) if abs(s) > 1e-12 else math.inf,
        )
        x, y = t * c, t * s
        through_door = c > 0 and abs(x - room_half_m) < 1e-9 and abs(y) < door_half_m
        ranges[i] = 0.0 if through_door else t
    return ranges


def test_an_open_door_gives_one_branch_through_it() -> None:
    branches = scan_branches(ANGLES, _room_scan(0.5), MAX_M, RADIUS)
    assert len(branches) == 1
    branch = branches[0]
    assert branch.kind is GapKind.OPEN
    tip_x, tip_y = branch.tip_m
    assert tip_x > 2.0 and abs(tip_y) < 0.2  # beyond the door, on its axis
    assert branch.length_m == pytest.approx(math.hypot(tip_x, tip_y))


def test_a_door_narrower_than_the_robot_gives_no_branch() -> None:
    assert scan_branches(ANGLES, _room_scan(0.09), MAX_M, RADIUS) == []


def test_a_closed_room_gives_no_branch() -> None:
    assert scan_branches(ANGLES, _room_scan(0.0), MAX_M, RADIUS) == []


def test_mismatched_scans_are_refused() -> None:
    with pytest.raises(ValueError):
        scan_branches(ANGLES, np.zeros(3), MAX_M, RADIUS)


def test_tips_go_to_the_world_frame() -> None:
    x, y = to_world((1.0, 2.0, math.pi / 2), (3.0, 0.0))
    assert (x, y) == pytest.approx((1.0, 5.0))
