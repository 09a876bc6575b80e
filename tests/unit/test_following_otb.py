"""OTB ground truth as OTB ships it (separators, line endings, 1-based boxes, several targets) and OTB's
two scores on boxes whose answers are known."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from agent.following.otb import (
    OtbFormatError,
    centre_errors,
    load_sequence,
    overlaps,
    parse_groundtruth,
    precision_at,
    success_auc,
)
from drivers.errors import ConfigError

EXPECTED = np.array([[50.0, 46.0, 25.0, 62.0], [46.0, 41.0, 24.0, 62.0]])  # 0-based


@pytest.mark.parametrize(
    "text",
    [
        b"51,47,25,62\n47,42,24,62\n",  # comma, LF (Jogging, Woman)
        b"51,47,25,62\r\n47,42,24,62\r\n",  # comma, CRLF (Woman)
        b"51\t47\t25\t62\r\n47\t42\t24\t62\r\n",  # TAB, CRLF (Couple, Subway)
        b"51 47 25 62\n47 42 24 62",  # spaces, no final newline (Jogging-1's file ends so)
        b"51, 47, 25, 62\n\n47 ,42\t24,62\n\r\n",  # mixed, blank lines
        b"\xef\xbb\xbf51,47,25,62\n47,42,24,62\n",  # a byte-order mark
        b"51.0,47.0,25.0,62.0\n47,42,24,62\n",  # decimals (some OTB files have them)
    ],
)
def test_groundtruth_separators_and_line_endings(text: bytes) -> None:
    np.testing.assert_array_equal(parse_groundtruth(text), EXPECTED)


@pytest.mark.parametrize(
    ("text", "line", "reason"),
    [
        (b"51,47,25\n", 1, "expected 4 numbers"),
        (b"51,47,25,62\n1,2,x,4\n", 2, "not a number"),
        (b"51,47,0,62\n", 1, "positive"),
        (b"51,47,-3,62\n", 1, "positive"),
        (b"51,47,nan,62\n", 1, "finite"),
        (b"", 0, "no boxes"),
        (b"\r\n\n", 0, "no boxes"),
    ],
)
def test_groundtruth_refuses_bad_lines(text: bytes, line: int, reason: str) -> None:
    with pytest.raises(OtbFormatError) as info:
        parse_groundtruth(text, "gt.txt")
    assert info.value.line_number == line
    assert reason in str(info.value) and "gt.txt" in str(info.value)


def _folder(root: Path, frames: int, files: dict[str, bytes]) -> Path:
    (root / "img").mkdir(parents=True)
    for i in range(1, frames + 1):
        (root / "img" / f"{i:04d}.jpg").write_bytes(b"")
    for name, data in files.items():
        (root / name).write_bytes(data)
    return root


def test_sequence_with_two_targets_like_jogging(tmp_path: Path) -> None:
    seq = _folder(
        tmp_path / "Jogging",
        3,
        {"groundtruth_rect.1.txt": b"1,1,5,5\n2,2,5,5\n3,3,5,5", "groundtruth_rect.2.txt": b"9,9,4,4\n" * 3},
    )
    (seq / "img" / ".DS_Store").write_bytes(b"junk")  # not a frame
    sequence = load_sequence(seq)
    assert [p.name for p in sequence.frames] == ["0001.jpg", "0002.jpg", "0003.jpg"]
    assert [t.name for t in sequence.targets] == ["Jogging-1", "Jogging-2"]
    np.testing.assert_array_equal(sequence.targets[0].boxes[2], [2.0, 2.0, 5.0, 5.0])


def test_sequence_with_fewer_boxes_scores_those_and_more_is_an_error(tmp_path: Path) -> None:
    seq = _folder(tmp_path / "A", 3, {"groundtruth_rect.txt": b"1,1,5,5\n2,2,5,5\n"})
    assert load_sequence(seq).targets[0].name == "A"
    assert len(load_sequence(seq).targets[0].boxes) == 2
    seq = _folder(tmp_path / "B", 1, {"groundtruth_rect.txt": b"1,1,5,5\n2,2,5,5\n"})
    with pytest.raises(OtbFormatError, match="2 boxes for 1 frames"):
        load_sequence(seq)


def test_sequence_folder_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not a folder"):
        load_sequence(tmp_path / "missing")
    with pytest.raises(ConfigError, match=r"no \.jpg"):
        load_sequence(_folder(tmp_path / "C", 0, {"groundtruth_rect.txt": b"1,1,5,5\n"}))
    with pytest.raises(ConfigError, match="groundtruth_rect"):
        load_sequence(_folder(tmp_path / "D", 2, {}))


def test_scores_on_known_boxes() -> None:
    truth = np.array([[0.0, 0.0, 10.0, 10.0]] * 4)
    pred = np.array(
        [
            [0.0, 0.0, 10.0, 10.0],  # exact: IoU 1, error 0
            [5.0, 0.0, 10.0, 10.0],  # half over: IoU 50/150, error 5
            [0.0, 0.0, 5.0, 10.0],  # inside, half the size: IoU 0.5, error 2.5
            [30.0, 40.0, 10.0, 10.0],  # far: IoU 0, error 50
        ]
    )
    np.testing.assert_allclose(centre_errors(pred, truth), [0.0, 5.0, 2.5, 50.0])
    np.testing.assert_allclose(overlaps(pred, truth), [1.0, 1.0 / 3.0, 0.5, 0.0])
    assert precision_at(centre_errors(pred, truth), 20.0) == 0.75
    assert precision_at(centre_errors(pred, truth), 4.0) == 0.5
    # Success curve at t = 0, 0.05, ..., 1: 3 frames above t up to 1/3, 2 up to 1/2, 1 until t = 1,
    # where IoU > 1 never holds. AUC = mean over the 21 thresholds.
    thresholds = np.linspace(0.0, 1.0, 21)
    ious = np.array([1.0, 1.0 / 3.0, 0.5, 0.0])
    expected = np.mean([np.mean(ious > t) for t in thresholds])
    assert success_auc(ious) == pytest.approx(expected)
    assert success_auc(np.ones(5)) == pytest.approx(20.0 / 21.0)
    with pytest.raises(ValueError):
        overlaps(pred[:2], truth)
