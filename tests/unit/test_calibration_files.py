"""Saving calibration files: atomic replacement, the previous version kept, nothing changed on failure, and a
result that fails its checks never replacing a working calibration."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from calibration import files
from calibration.files import backup_path, commit, save_all, save_atomic
from calibration.report import CalibrationError, Check, Output, StepResult


def test_first_save_writes_the_file_and_no_backup(tmp_path: Path) -> None:
    target = tmp_path / "sub" / "camera_info.yaml"
    saved = save_atomic(target, "one\n")
    assert target.read_text() == "one\n"
    assert saved.backup is None
    assert not backup_path(target).exists()


def test_second_save_keeps_the_previous_version(tmp_path: Path) -> None:
    target = tmp_path / "leds.toml"
    save_atomic(target, "one\n")
    saved = save_atomic(target, "two\n")
    assert target.read_text() == "two\n"
    assert saved.backup == tmp_path / "leds.toml.bak"
    assert saved.backup.read_text() == "one\n"
    save_atomic(target, b"three\n")
    assert backup_path(target).read_text() == "two\n"


def test_no_temporary_files_are_left(tmp_path: Path) -> None:
    target = tmp_path / "a.toml"
    for n in range(3):
        save_atomic(target, f"{n}\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.toml", "a.toml.bak"]


def test_permissions_follow_the_old_file_or_the_umask(tmp_path: Path) -> None:
    target = tmp_path / "a.toml"
    old = os.umask(0o022)
    try:
        save_atomic(target, "x")
        assert stat.S_IMODE(target.stat().st_mode) == 0o644
        target.chmod(0o600)
        save_atomic(target, "y")
        assert stat.S_IMODE(target.stat().st_mode) == 0o600
    finally:
        os.umask(old)


def test_a_failure_while_replacing_changes_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    target = tmp_path / "camera_info.yaml"
    save_atomic(target, "good\n")
    real_replace = os.replace
    calls: list[tuple[str, str]] = []

    def failing_replace(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> None:
        calls.append((str(src), str(dst)))
        if Path(dst) == target:
            raise OSError(28, "No space left on device")
        real_replace(src, dst)

    monkeypatch.setattr(files.os, "replace", failing_replace)
    with pytest.raises(CalibrationError, match="No space left"):
        save_atomic(target, "bad\n")
    assert target.read_text() == "good\n"
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_an_interrupt_while_writing_leaves_the_old_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    target = tmp_path / "camera_info.yaml"
    save_atomic(target, "good\n")
    real_fsync = os.fsync

    def interrupted(fd: int) -> None:
        real_fsync(fd)
        raise KeyboardInterrupt

    monkeypatch.setattr(files.os, "fsync", interrupted)
    with pytest.raises(KeyboardInterrupt):
        save_atomic(target, "half\n")
    assert target.read_text() == "good\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["camera_info.yaml"]


def test_several_files_are_staged_before_any_is_replaced(tmp_path: Path) -> None:
    a, b = tmp_path / "a.toml", tmp_path / "b.png"
    save_all([(a, "a1"), (b, b"b1")])
    blocked = tmp_path / "blocked"
    blocked.write_text("a file where a folder should be")
    with pytest.raises(CalibrationError, match="cannot write"):
        save_all([(a, "a2"), (blocked / "c.toml", "c")])
    assert a.read_text() == "a1"


def _result(ok: bool, folder: Path) -> StepResult:
    check = Check("rms", 0.1 if ok else 2.0, 0.5, "px")
    outputs = [
        Output(folder / "camera_info.yaml", "new\n"),
        Output(folder / "camera_info.png", b"png", report=True),
    ]
    return StepResult("intrinsics", {"rms_px": check.value}, [check], outputs=outputs)


def test_a_result_failing_its_checks_saves_only_its_report(tmp_path: Path) -> None:
    (tmp_path / "camera_info.yaml").write_text("working\n")
    result = commit(_result(False, tmp_path))
    assert (tmp_path / "camera_info.yaml").read_text() == "working\n"
    assert (tmp_path / "camera_info.png").read_bytes() == b"png"
    assert result.files == [tmp_path / "camera_info.png"]
    assert result.withheld == [tmp_path / "camera_info.yaml"]
    assert result.as_json()["not_saved"] == [str(tmp_path / "camera_info.yaml")]


def test_force_saves_a_failing_result_and_a_passing_one_saves_everything(tmp_path: Path) -> None:
    (tmp_path / "camera_info.yaml").write_text("working\n")
    commit(_result(False, tmp_path), force=True)
    assert (tmp_path / "camera_info.yaml").read_text() == "new\n"
    assert (tmp_path / "camera_info.yaml.bak").read_text() == "working\n"
    result = commit(_result(True, tmp_path))
    assert result.withheld == []
    assert len(result.files) == 2
