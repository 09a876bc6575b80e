"""``vlp-agent eval nav`` end to end on a small world: the JSON keys, goals reached, no collisions."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from agent.cli import main

# Two 3 x 3 m rooms joined by a 0.8 m door, a box in the first, a person standing in the second.
WORLD = """
name = "two-rooms"
[robot]
start = { x_m = 1.0, y_m = 1.0, yaw_deg = 0.0 }
[led_defaults]
z_m = 2.6
[[led_grids]]
x0_m = 0.75
y0_m = 0.75
nx = 4
ny = 2
dx_m = 1.5
dy_m = 1.5
signatures = [
    { id = "A", frequency_hz = 1500.0, duty = 0.5 },
    { id = "B", frequency_hz = 2500.0, duty = 0.3 },
    { id = "C", frequency_hz = 3500.0, duty = 0.6 },
]
[[rooms]]
x_min_m = 0.0
y_min_m = 0.0
x_max_m = 3.0
y_max_m = 3.0
doors = [{ side = "east", offset_m = 1.5, width_m = 0.8 }]
[[rooms]]
x_min_m = 3.0
y_min_m = 0.0
x_max_m = 6.0
y_max_m = 3.0
doors = [{ side = "west", offset_m = 1.5, width_m = 0.8 }]
[[polygons]]
points = [[1.8, 2.0], [2.2, 2.0], [2.2, 2.4], [1.8, 2.4]]
[[people]]
name = "pat"
tag_id = "0415AB9C3D"
path = [[5.0, 0.8]]
"""

KEYS = (
    "goals",
    "reached",
    "success_rate",
    "collisions",
    "path_ratio_median",
    "plan_ms_median",
    "clearance_m_min",
)


def test_eval_nav_drives_to_random_goals_without_collisions(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    world = tmp_path / "two-rooms.toml"
    world.write_text(WORLD, encoding="utf-8")
    assert main(["eval", "nav", "--world", str(world), "--goals", "3", "--seed", "1", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    for key in KEYS:
        assert key in summary
    assert summary["goals"] == 3
    assert summary["reached"] == 3, summary["failures"]
    assert summary["collisions"] == 0
    assert summary["clearance_m_min"] > 0.0
    assert 1.0 <= summary["path_ratio_median"] <= 1.3
    assert summary["final_error_m_max"] <= 0.10
    assert summary["map_source"].startswith("truth")


def test_eval_nav_refuses_no_goals(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["eval", "nav", "--goals", "0"]) != 0
    assert "--goals: must be at least 1" in capsys.readouterr().err
