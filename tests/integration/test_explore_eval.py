"""``vlp-agent eval explore`` end to end on the shipped two-room world: the JSON keys, explored to the end
and saying so, no collisions, the picture written; and a run cut short says why instead of "complete"."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from agent.cli import main
from agent.commands.eval_explore import FRONTIER, TARGET
from agent.shipped import WORLDS

KEYS = (
    "explored_fraction",
    "complete",
    "stopped_reason",
    "ate_m",
    "path_length_m",
    "decisions",
    "decision_ms_median",
    "collisions",
)


def test_eval_explore_explores_two_rooms_to_completion(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    png = tmp_path / "explore.png"
    world = str(WORLDS / "two_rooms.toml")
    argv = ["eval", "explore", "--world", world, "--seed", "0", "--json", "--png", str(png)]
    assert main(argv) == 0
    captured = capsys.readouterr()
    summary = json.loads(captured.out)
    for key in KEYS:
        assert key in summary
    assert summary["explored_fraction"] >= 0.95
    assert summary["complete"] is True
    assert summary["stopped_reason"].startswith("complete: no reachable frontier left")
    assert summary["collisions"] == 0
    assert summary["ate_m"] <= 0.05
    assert summary["decisions"] >= 1 and summary["path_length_m"] > 1.0
    assert "explored" in captured.err  # progress goes to stderr, the JSON alone to stdout
    picture = cv2.imread(str(png))
    assert picture is not None and picture.shape[1] >= 800
    assert np.all(picture == np.array(TARGET, np.uint8), axis=2).any()  # the targets are drawn


def test_a_run_cut_short_is_not_complete(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    png = tmp_path / "short.png"
    world = str(WORLDS / "two_rooms.toml")
    argv = ["eval", "explore", "--world", world, "--budget-s", "3", "--json", "--png", str(png)]
    assert main(argv) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["complete"] is False
    assert summary["stopped_reason"].startswith("time budget of 3 s spent (exploring")
    assert summary["explored_fraction"] < 0.95
    picture = cv2.imread(str(png))
    assert np.all(picture == np.array(FRONTIER, np.uint8), axis=2).any()  # frontiers left, drawn


def test_eval_explore_with_sp2atm_writes_its_topology_beside_the_picture(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from agent.commands.eval_explore import HTM_PLACE, HTM_REGION
    from agent.exploration.htm import NodeKind
    from agent.exploration.topology import from_geojson
    from agent.slam.mapio import load_topology

    png = tmp_path / "sp2atm.png"
    world = str(WORLDS / "two_rooms.toml")
    argv = ["eval", "explore", "--world", world, "--explorer", "sp2atm", "--json", "--png", str(png)]
    assert main(argv) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["explorer"] == "sp2atm" and summary["complete"] is True
    assert summary["explored_fraction"] >= 0.95 and summary["collisions"] == 0
    topology = Path(summary["topology"])
    assert topology == tmp_path / "sp2atm.topology.geojson"
    htm = from_geojson(load_topology(topology))
    kinds = [n.kind for n in htm.nodes.values()]
    assert kinds.count(NodeKind.PLACE) == summary["htm_places"] >= 2
    assert kinds.count(NodeKind.REGION) == summary["regions"] >= 2  # the two rooms (and the passage)
    assert htm.done  # complete: nothing possible left
    picture = cv2.imread(str(png))
    for colour in (HTM_PLACE, HTM_REGION):
        assert np.all(picture == np.array(colour, np.uint8), axis=2).any()
