"""Bad input to the calibration steps: a clear message, a non-zero exit, and the previous files untouched.
No board in the images, too few views, a coordinate that is not a number, Ctrl-C in the middle of a step."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from agent.cli import main
from drivers.sim.targets import Chessboard, TargetRenderer
from drivers.sim.world import CameraModel
from tests.integration.terminal import press_ctrl_c, signal_state, terminal_signals

REPO = Path(__file__).resolve().parents[2]
PREVIOUS = "# the calibration that works\n"


def folder_with(tmp_path: Path, images: list[np.ndarray]) -> Path:
    folder = tmp_path / "images"
    folder.mkdir()
    for n, image in enumerate(images):
        cv2.imwrite(str(folder / f"view{n:02d}.png"), image)
    return folder


def previous_file(tmp_path: Path, name: str = "camera_info.yaml") -> Path:
    out = tmp_path / "out"
    out.mkdir()
    (out / name).write_text(PREVIOUS)
    return out


def untouched(out: Path, name: str = "camera_info.yaml") -> None:
    assert (out / name).read_text() == PREVIOUS
    assert sorted(p.name for p in out.iterdir()) == [name]


def test_no_board_in_the_images(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 255, (600, 800), dtype=np.uint8) for _ in range(5)]
    folder = folder_with(tmp_path, images)
    out = previous_file(tmp_path)
    code = main(["calibrate", "intrinsics", "--images", str(folder), "--dir", str(out)])
    err = capsys.readouterr().err
    assert code == 1
    assert "no board found in any of the 5 images" in err
    assert "9 x 6 chessboard" in err and "--cols/--rows" in err
    assert "no calibration file was written" in err
    untouched(out)


def test_too_few_views(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    board = Chessboard()
    renderer = TargetRenderer(CameraModel(), board, seed=1)
    images = []
    w, h = board.size_m
    # Four clearly different views: tilted each way, in different parts of the picture.
    for rvec, centre in [
        ((0.5, 0.0, 0.0), (-0.12, -0.08, 0.5)),
        ((-0.5, 0.0, 0.3), (0.12, -0.08, 0.5)),
        ((0.0, 0.5, -0.3), (-0.12, 0.08, 0.5)),
        ((0.0, -0.5, 0.0), (0.12, 0.08, 0.5)),
    ]:
        rot, _ = cv2.Rodrigues(np.array(rvec))
        t = np.array(centre) - rot @ np.array([w / 2, h / 2, 0.0])
        images.append(renderer.render(rot, t).image)
    images.append(np.full((600, 800), 30, dtype=np.uint8))
    folder = folder_with(tmp_path, images)
    out = previous_file(tmp_path)
    code = main(["calibrate", "intrinsics", "--images", str(folder), "--dir", str(out), "--json"])
    captured = capsys.readouterr()
    assert code == 1
    assert captured.out == ""  # no JSON for a step that did not run
    assert "too few views: 4 usable, at least 10 needed" in captured.err
    assert "found in 4 of 5 images" in captured.err and "1 no board" in captured.err
    untouched(out)


def test_a_folder_without_images(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "empty").mkdir()
    out = previous_file(tmp_path)
    assert main(["calibrate", "intrinsics", "--images", str(tmp_path / "empty"), "--dir", str(out)]) == 1
    assert "no images in" in capsys.readouterr().err
    untouched(out)


def test_non_numeric_coordinate_in_the_led_csv(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    csv = tmp_path / "leds.csv"
    csv.write_text("id,x_m,y_m,z_m\nL1,-0.465,0.495,1.5\nL2,-0.46,abc,1.5\n")
    out = previous_file(tmp_path, "leds.toml")
    code = main(["calibrate", "leds", "--sim", "--coordinates", str(csv), "--dir", str(out)])
    err = capsys.readouterr().err
    assert code == 1
    assert "leds.csv line 3: y_m 'abc' is not a number" in err
    untouched(out, "leds.toml")


class _TypedAnswers:
    """A console fed with typed answers, as a person at the robot would give them."""

    def __init__(self, answers: list[str]) -> None:
        self.answers = answers
        self.said: list[str] = []

    def say(self, text: str = "") -> None:
        self.said.append(text)

    def status(self, text: str) -> None:
        pass

    def ask(self, question: str) -> str:
        if not self.answers:
            raise EOFError
        return self.answers.pop(0)


def test_non_numeric_coordinate_typed_is_asked_again() -> None:
    # On a robot (no world file to read them from) the survey asks for the LED coordinates; the first x is
    # given as "west" before the number. (Under --sim they come from the world file and nothing is asked.)
    from calibration.leds import LedEntry, type_coordinates

    console = _TypedAnswers(["", "west", "-0.465", "0.495", "1.5", "", "-0.46", "-0.42", ""])
    entries = type_coordinates(console, 2)  # type: ignore[arg-type]
    assert any("'west' is not a number; try again" in line for line in console.said)
    assert entries == [LedEntry("L1", -0.465, 0.495, 1.5), LedEntry("L2", -0.46, -0.42, 1.5)]


def test_ctrl_c_in_the_middle_of_a_step(tmp_path: Path) -> None:
    pexpect = pytest.importorskip("pexpect")
    out = previous_file(tmp_path)
    child = pexpect.spawn(
        sys.executable,
        ["-m", "agent.cli", "calibrate", "intrinsics", "--sim", "--dir", str(out)],
        cwd=str(REPO),
        encoding="utf-8",
        timeout=90,
        preexec_fn=terminal_signals,
        env={**os.environ, "COLUMNS": "200"},
    )
    try:
        child.expect(r"views [1-9]\d*/40")
        press_ctrl_c(child)
        state = signal_state(child)
        pattern = "interrupted; no calibration file was written \\(previous files kept\\)"
        assert child.expect([pattern, pexpect.EOF]) == 0, state
        child.expect(pexpect.EOF)
    finally:
        child.close()
    assert child.exitstatus == 130
    untouched(out)
