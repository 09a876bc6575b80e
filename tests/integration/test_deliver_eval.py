"""``vlp-agent eval deliver`` end to end on a small world: from a place in one room to a place in the other
and back, every end met within 0.10 m, no contact; unknown places are refused with the known ones named."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from agent.cli import main
from tests.integration.test_nav_eval import WORLD

PLACES = """
[[places]]
name = "desk"
x_m = 1.0
y_m = 1.0
[[places]]
name = "shelf"
x_m = 4.5
y_m = 2.2
yaw_deg = 90
"""


def test_eval_deliver_makes_its_trips(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    world = tmp_path / "two-rooms.toml"
    world.write_text(WORLD + PLACES, encoding="utf-8")
    args = ["eval", "deliver", "--world", str(world), "--from", "desk", "--to", "shelf", "--trips", "2"]
    assert main([*args, "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert (s["trips"], s["trips_made"], s["ends"], s["ends_met"]) == (2, 2, 4, 4), s["legs"]
    assert [leg["place"] for leg in s["legs"]] == ["shelf", "desk", "shelf", "desk"]
    assert s["end_error_m_max"] <= 0.10 and s["collisions"] == 0
    assert s["first_leg"]["place"] == "desk"


def test_eval_deliver_names_the_places_it_knows(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    world = tmp_path / "two-rooms.toml"
    world.write_text(WORLD + PLACES, encoding="utf-8")
    assert main(["eval", "deliver", "--world", str(world), "--from", "desk", "--to", "kitchen"]) != 0
    err = capsys.readouterr().err
    assert "--to" in err and "'kitchen'" in err and "desk, shelf" in err


def test_eval_deliver_explores_first_and_drives_on_the_map_it_saved(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from agent.exploration.topology import from_geojson, named_places
    from agent.slam.mapio import load_map, load_topology

    world = tmp_path / "two-rooms.toml"
    world.write_text(WORLD + PLACES, encoding="utf-8")
    args = ["eval", "deliver", "--world", str(world), "--from", "desk", "--to", "shelf", "--trips", "1"]
    args += ["--explore", "frontier", "--explore-map", "truth-pose", "--map-dir", str(tmp_path / "m")]
    assert main([*args, "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    explored = s["exploration"]
    assert explored["complete"] is True and explored["explored_fraction"] >= 0.95
    assert s["map_source"] == "the map an exploration built"
    assert (s["trips_made"], s["ends_met"]) == (1, 2), s["legs"]
    assert s["end_error_m_max"] <= 0.10 and s["collisions"] == 0
    assert load_map(Path(explored["map"])).pixels.size > 0
    places = named_places(from_geojson(load_topology(Path(explored["topology"]))))
    assert places["desk"] == (1.0, 1.0) and places["shelf"] == (4.5, 2.2)
