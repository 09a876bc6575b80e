"""``vlp-agent eval track`` end to end: on an OTB-style folder written from the synthetic scene (JPEG
frames, a TAB/CRLF 1-based ground truth, so it runs without ../shared), and on the first frames of a real
OTB sequence from ../shared. (The passer-by case is tested on raw frames in
``tests/unit/test_following_meanshift.py``: JPEG's chroma subsampling and blocks blur the passer-by's
2-pixel check, and the difference between the trackers with it, docs/following.md.)"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from agent.cli import main
from agent.commands.eval_track import sre_boxes
from agent.following.synthetic import CrossingScene, crossing_sequence


def _otb_folder(root: Path, scene: CrossingScene) -> Path:
    (root / "img").mkdir(parents=True)
    lines = []
    for i, (image, box) in enumerate(crossing_sequence(scene), start=1):
        cv2.imwrite(str(root / "img" / f"{i:04d}.jpg"), image, [cv2.IMWRITE_JPEG_QUALITY, 90])
        x, y, w, h = box
        lines.append(f"{x + 1:.0f}\t{y + 1:.0f}\t{w:.0f}\t{h:.0f}")  # OTB: 1-based, TAB, CRLF
    (root / "groundtruth_rect.txt").write_bytes(("\r\n".join(lines) + "\r\n").encode())
    return root


def _run(capsys: pytest.CaptureFixture[str], *args: str) -> dict:
    assert main(["eval", "track", *args, "--json"]) == 0
    return dict(json.loads(capsys.readouterr().out))


def test_eval_track_on_a_synthetic_otb_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = _otb_folder(tmp_path / "Crossing", CrossingScene(seed=1, passer=False))
    full = _run(capsys, "--sequence", str(folder))
    colour = _run(capsys, "--sequence", str(folder), "--tracker", "colour")
    for summary in (full, colour):
        for key in ("precision_20px", "success_auc", "fps", "frames", "mean_centre_error_px"):
            assert isinstance(summary[key], (int, float)), key
        assert summary["frames"] == 60 and summary["fps"] > 0
        assert [t["target"] for t in summary["targets"]] == ["Crossing"]
    assert full["tracker"] == "full" and colour["tracker"] == "colour"
    # The boxes read back 1-based and compared 0-based: a walker alone is tracked all the way.
    for summary in (full, colour):
        assert summary["precision_20px"] == 1.0 and summary["success_auc"] > 0.6
        assert summary["mean_centre_error_px"] < 5.0

    # A parameter set from the command line, and said in the output.
    fixed = _run(capsys, "--sequence", str(folder), "--frames", "10", "--param", "scale_gain=0")
    assert fixed["params"] == {"scale_gain": "0.0"}
    assert all(t["frames"] == 10 for t in fixed["targets"])

    # OTB's spatial robustness: 12 more starts, shifted and scaled; a lone walker is held from all.
    robust = _run(capsys, "--sequence", str(folder), "--frames", "15", "--sre")
    assert robust["sre_precision_20px"] >= 0.9 and 0.0 < robust["sre_success_auc"] <= 1.0

    # Two sequences: one row each, and the means.
    assert (
        main(["eval", "track", "--sequence", str(folder), "--sequence", str(folder), "--frames", "10"]) == 0
    )
    table = capsys.readouterr().out
    assert table.count("Crossing ") == 2 and "mean (seq.)" in table


def test_eval_track_refuses_what_is_not_a_sequence(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["eval", "track", "--sequence", str(tmp_path / "nothing")]) == 1
    assert "not a folder" in capsys.readouterr().err
    (tmp_path / "bad" / "img").mkdir(parents=True)
    cv2.imwrite(str(tmp_path / "bad" / "img" / "0001.jpg"), np.zeros((20, 20, 3), np.uint8))
    (tmp_path / "bad" / "groundtruth_rect.txt").write_text("1,2,3\n")
    assert main(["eval", "track", "--sequence", str(tmp_path / "bad")]) == 1
    assert "groundtruth_rect.txt:1: expected 4 numbers" in capsys.readouterr().err
    good = _otb_folder(tmp_path / "good", CrossingScene(frames=3, passer=False))
    for param, message in (
        ("no_such=1", "want NAME=VALUE"),
        ("scale_gain=fast", "not a float"),
        ("adaptive_weights=maybe", "not a bool"),
        ("occlusion_ratio=0.99", "reacquire_ratio"),
    ):
        assert main(["eval", "track", "--sequence", str(good), "--param", param]) == 1
        assert message in capsys.readouterr().err


@pytest.mark.parametrize("tracker", ["full", "colour"])
def test_eval_track_on_the_first_frames_of_real_woman(
    shared_data: Path, tracker: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # OTB Woman, frames 1-60: the woman walks past parked cars before they hide her legs (about 121).
    summary = _run(
        capsys, "--sequence", str(shared_data / "person/Woman"), "--frames", "60", "--tracker", tracker
    )
    assert summary["frames"] == 60
    assert summary["precision_20px"] >= 0.9
    assert summary["success_auc"] >= 0.5


def test_sre_starts_are_otbs() -> None:
    starts = sre_boxes(np.array([10.0, 20.0, 40.0, 100.0]))
    assert len(starts) == 12
    shifts = {(round(b[0] - 10.0, 6), round(b[1] - 20.0, 6)) for b in starts[:8]}
    assert shifts == {(dx * 4.0, dy * 10.0) for dx in (-1, 0, 1) for dy in (-1, 0, 1)} - {(0.0, 0.0)}
    for box, s in zip(starts[8:], (0.8, 0.9, 1.1, 1.2), strict=True):
        np.testing.assert_allclose(box[2:], [40.0 * s, 100.0 * s])
        np.testing.assert_allclose(box[:2] + box[2:] / 2, [30.0, 70.0])  # about the same centre
