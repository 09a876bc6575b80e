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
