"""The interactive wizard driven end to end on the simulated robot through a terminal (pexpect): the menu,
a step's questions, live progress, the verdict with its thresholds, the saved files, the menu's record of
what was done, and Ctrl-C in the middle of a step."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from calibration.camera_info import parse_camera_info
from tests.integration.terminal import press_ctrl_c, press_ctrl_c_at_prompt, signal_state, terminal_signals

pexpect = pytest.importorskip("pexpect")

REPO = Path(__file__).resolve().parents[2]
MENU = r"step \(1-10, a name, or q\) \[\w+\]: "


def wizard(folder: Path) -> pexpect.spawn:
    return pexpect.spawn(
        sys.executable,
        ["-m", "agent.cli", "calibrate", "--sim", "--dir", str(folder)],
        cwd=str(REPO),
        encoding="utf-8",
        timeout=90,
        preexec_fn=terminal_signals,
        dimensions=(50, 220),
        env={**os.environ, "COLUMNS": "220", "LINES": "50"},
    )


def test_wizard_runs_steps_and_saves_their_files(tmp_path: Path) -> None:
    child = wizard(tmp_path)
    try:
        child.expect("vlp-agent calibration wizard")
        child.expect("the simulated robot")
        child.expect(MENU)
        assert "status: not done" in child.before

        child.sendline("servos")
        child.expect(r"start \(yes/no\) \[yes\]: ")
        child.sendline("")
        child.expect("found id 1 at 57600 bps")
        child.expect("servos: GOOD: every check passed")
        child.expect(r"wheel servos answering at 1000000 bps: 2 of 2 \(needs >= 2 of 2\) ok")
        child.expect(MENU)

        child.sendline("2")
        child.expect(r"board \(chessboard/charuco\) \[chessboard\]: |views to collect")
        if "board" in child.after:
            child.sendline("")
            child.expect("views to collect")
        child.expect(r"\[40\]: ")
        child.sendline("many")  # not a number: asked again
        child.expect("'many' is not a whole number")
        child.sendline("20")
        child.expect(r"start \(yes/no\) \[yes\]: ")
        child.sendline("yes")
        child.expect(r"views \d+/20  cells \d/9", timeout=60)  # live progress
        child.expect("next: hold the board at the")  # coverage guidance, on the live line
        child.expect("intrinsics: GOOD: every check passed", timeout=180)
        child.expect(r"reprojection rms: [0-9.]+ px \(needs <= 0.5 px\) ok")
        child.expect("next: `vlp-agent calibrate mount`")
        child.expect(MENU)
        assert "status: done: GOOD (servos.toml, servos.png)" in child.before
        assert "status: done: GOOD (camera_info.yaml, camera_info.png)" in child.before

        child.sendline("q")
        child.expect("calibration wizard: bye")
        child.expect(pexpect.EOF)
    finally:
        child.close()
    assert child.exitstatus == 0
    info = parse_camera_info((tmp_path / "camera_info.yaml").read_text())
    assert (info.width, info.height) == (800, 600)
    assert abs(info.fx - 488.28) < 0.02 * 488.28
    assert (tmp_path / "servos.toml").is_file()


def test_ctrl_c_in_a_step_writes_nothing_and_returns_to_the_menu(tmp_path: Path) -> None:
    previous = "# a calibration that works\n"
    (tmp_path / "camera_info.yaml").write_text(previous)
    child = wizard(tmp_path)
    try:
        child.expect(MENU)
        assert "status: file from before: camera_info.yaml" in child.before
        child.sendline("intrinsics")
        child.expect("views to collect|board")
        if "board" in child.after:
            child.sendline("")
            child.expect("views to collect")
        child.sendline("")
        child.expect(r"start \(yes/no\)")
        child.sendline("")
        child.expect(r"views [1-9]\d*/40", timeout=60)
        press_ctrl_c(child)
        state = signal_state(child)
        assert child.expect(["intrinsics: interrupted; no calibration file was written", MENU]) == 0, state
        child.expect(MENU)
        assert "status: interrupted" in child.before
        press_ctrl_c_at_prompt(child)  # at the menu, Ctrl-C leaves
        answered = child.expect(["interrupted at the menu", pexpect.TIMEOUT])
        assert answered == 0, f"no answer to Ctrl-C at the menu: {signal_state(child)}"
        child.expect(pexpect.EOF)
    finally:
        child.close()
    assert child.exitstatus == 130
    assert (tmp_path / "camera_info.yaml").read_text() == previous
    assert sorted(p.name for p in tmp_path.iterdir()) == ["camera_info.yaml"]
