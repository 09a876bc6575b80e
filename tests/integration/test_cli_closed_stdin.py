"""Every command as a script runs it: stdin closed, ``--json`` where the command has it. None ends in a
traceback; each JSON answer parses with a strict parser (no ``NaN`` or ``Infinity`` tokens); the calibration
steps on the simulated robot need no answer from anyone (the LED survey takes the world's LED coordinates);
the wizard with no one to answer says so and exits non-zero; an unwritable ``--dir`` is refused before the
robot moves."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from agent import cli
from tests.strict_json import strict_loads

REPO = Path(__file__).resolve().parents[2]
ENV1 = REPO / "examples" / "worlds" / "env1.toml"


def closed_stdin(*args: str, cwd: Path, timeout: float = 240) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "agent.cli", *args],
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=cwd,
        check=False,
    )


# Every calibration step's own integration test (tests/integration/test_calibration_*.py) runs it on the
# simulated robot with stdin closed and --json, and checks for no traceback and strict JSON. Here: the LED
# survey, the one step that asked (for the LED coordinates) before it took them from the world file.
def test_the_led_survey_on_the_simulated_robot_asks_for_nothing(tmp_path: Path) -> None:
    out_dir = tmp_path / "cal"
    out = closed_stdin(
        "calibrate",
        "leds",
        "--world",
        str(ENV1),
        "--dir",
        str(out_dir),
        "--json",
        "--frames",
        "6",
        cwd=tmp_path,
    )
    assert "Traceback" not in out.stderr, out.stderr[-3000:]
    assert out.returncode in (0, 3), out.stderr[-3000:]  # done (3: done, but the checks failed)
    result = strict_loads(out.stdout)
    # The simulated ceiling's LEDs are where the world file says: nothing was asked.
    assert "LED coordinates: 4 from the world file env1.toml" in out.stderr
    assert "id [L1]" not in out.stderr
    assert sorted(led["id"] for led in result["leds"]) == ["L1", "L2", "L3", "L4"]
    assert any(out_dir.iterdir())  # its report at least (leds.toml only when the checks pass)


def test_the_wizard_with_stdin_closed_says_so_and_exits_non_zero(tmp_path: Path) -> None:
    out = closed_stdin("calibrate", "--sim", "--dir", str(tmp_path / "cal"), cwd=tmp_path, timeout=60)
    assert out.returncode == 1
    assert "Traceback" not in out.stderr
    assert "end of input (stdin is closed)" in out.stdout
    assert "vlp-agent calibrate STEP" in out.stdout


def test_a_question_with_no_answer_names_it() -> None:
    from calibration.leds import type_coordinates
    from calibration.report import CalibrationError

    class Closed:
        def say(self, text: str = "") -> None:
            pass

        def status(self, text: str) -> None:
            pass

        def ask(self, question: str) -> str:
            raise EOFError

    with pytest.raises(CalibrationError, match=r"no answer to 'LED 1 id \[L1\]': end of input"):
        type_coordinates(Closed(), 1)


@pytest.mark.parametrize("step", ["wheels", "leds"])
def test_an_unwritable_dir_is_refused_before_the_robot_moves(
    step: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # A file where a folder should be: unwritable for every user, root included.
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("")
    moved: list[str] = []
    import calibration.rig

    def no_robot(*args: Any, **kwargs: Any) -> Any:
        moved.append(step)
        raise AssertionError("the robot was brought up before the folder was checked")

    monkeypatch.setattr(calibration.rig.Rig, "__init__", no_robot)
    code = cli.main(["calibrate", step, "--sim", "--dir", str(blocker / "cal")])
    err = capsys.readouterr().err
    assert code == 1
    assert moved == []
    assert f"cannot write calibration files in {blocker / 'cal'}" in err
    assert "no calibration file was written" in err


def test_a_missing_dir_is_created_and_checked_first(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import calibration.rig

    def stop_here(*args: Any, **kwargs: Any) -> Any:
        raise KeyboardInterrupt  # as Ctrl-C at the first motion: nothing else to run

    monkeypatch.setattr(calibration.rig.Rig, "__init__", stop_here)
    folder = tmp_path / "new" / "cal"
    assert cli.main(["calibrate", "wheels", "--sim", "--dir", str(folder)]) == 130
    assert folder.is_dir() and list(folder.iterdir()) == []  # the probe file is gone


@pytest.mark.parametrize(
    "command",
    [
        ["devices", "--json"],
        ["sim", "--seconds", "3", "--json", "--out", "simout"],
        ["run", "--config", str(REPO / "examples" / "sim.toml"), "--seconds", "3", "--json"],
        ["eval", "vlp", "--points", "4", "--repeats", "2", "--json"],
        ["eval", "slam", "--world", str(ENV1), "--seconds", "6", "--json", "--out", "slamout"],
    ],
    ids=lambda c: " ".join(c[:2]),
)
def test_every_command_json_is_strict_with_stdin_closed(command: list[str], tmp_path: Path) -> None:
    out = closed_stdin(*command, cwd=tmp_path)
    assert "Traceback" not in out.stderr, out.stderr[-3000:]
    assert out.returncode == 0, out.stderr[-3000:]
    assert isinstance(strict_loads(out.stdout), dict)


def test_fake_with_stdin_closed_serves_and_names_its_protocol(tmp_path: Path) -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "agent.cli", "fake", "rfid", "--rfid-protocol", "rdm6300"],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    try:
        assert proc.stdout is not None and proc.stderr is not None
        assert proc.stdout.readline().startswith("/dev/pts/")
        line = proc.stderr.readline()
        assert "protocol rdm6300" in line, line
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0
        assert "Traceback" not in proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_sim_summary_reads_as_lines_and_the_status_line_has_the_exposure_age(tmp_path: Path) -> None:
    out = closed_stdin("sim", "--seconds", "4", "--fault", "laser@1+1", "--out", "simout", cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    # The fault, as it happened, in words; no Python dict or list reprs anywhere in the summary.
    assert re.search(r"^  injected {10}laser off at 1\.\d s, laser back at 2\.\d s$", out.stdout, re.M), (
        out.stdout
    )
    assert "{" not in out.stdout and "[" not in out.stdout, out.stdout
    # The README's status line: latency and, beside it, the frame's age since mid-exposure.
    status = [line for line in out.stderr.splitlines() if line.startswith("t=")]
    assert status and all("latency p50=" in line and "age p50=" in line for line in status)
