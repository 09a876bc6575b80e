"""``vlp-agent sim --robots N``: the pure parts (how close two robots came, from their truths; the world
each robot gets) and its usage errors. The whole run takes minutes: docs/fleet.md gives its figures."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from agent import cli
from agent.commands.sim_fleet import _world_text
from agent.fleet.fleet_score import contacts, separation
from tests.integration.test_agent_accuracy import REPO


def test_separation_interpolates_the_other_robot_over_the_common_span() -> None:
    t_a = np.array([0.0, 1.0, 2.0, 3.0, 4.0])
    xy_a = np.stack([t_a, np.zeros(5)], axis=1)  # east at 1 m/s
    t_b = np.array([0.5, 3.5])
    xy_b = np.array([[4.0, 0.0], [1.0, 0.0]])  # west at 1 m/s
    t, d = separation(t_a, xy_a, t_b, xy_b)
    assert list(t) == [1.0, 2.0, 3.0]
    assert np.allclose(d, [2.5, 0.5, 1.5])
    assert contacts(d, 0.21) == 0 and contacts(d, 0.6) == 1
    assert contacts(np.array([0.1, 0.1, 1.0, 0.1, 1.0]), 0.21) == 2
    assert separation(t_a, xy_a, np.array([9.0, 10.0]), xy_b)[1].size == 0


def test_each_robots_world_has_no_route_and_its_own_start() -> None:
    text = _world_text((REPO / "examples" / "worlds" / "office.toml").read_text(), (6.0, 6.0, math.pi / 2))
    assert "[route]" not in text and "waypoints" not in text
    assert "start = { x_m = 6.000, y_m = 6.000, yaw_deg = 90.000 }" in text
    assert "[[walls]]" in text and "[[places]]" in text


def test_robots_need_one_goal_each(capsys: Any) -> None:
    assert cli.main(["sim", "--robots", "2", "--goal", "1,2", "--seconds", "5"]) == 2
    assert "needs 2 --goal" in capsys.readouterr().err
    assert cli.main(["sim", "--robots", "9", "--seconds", "5"]) == 2
