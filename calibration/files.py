"""Saving calibration files: atomically, keeping the previous version.

A file is written to a temporary file in the same folder, flushed to disk, and renamed over the target, so a
reader sees the old file or the new one, never half of either, and a crash or Ctrl-C leaves the old file in
place. Before the rename the previous version is kept as ``NAME.bak`` (itself written atomically, so an
interrupted save never loses the only good copy). Several files of one step are saved together: every
temporary file is written first, and only then are they renamed, so a failure while writing changes nothing.
"""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from agent.slam.mapio import fsync_dir, new_file_mode
from calibration.report import CalibrationError, StepResult

__all__ = ["SavedFile", "backup_path", "check_writable", "commit", "save_all", "save_atomic"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class SavedFile:
    path: Path
    backup: Path | None


def backup_path(path: Path) -> Path:
    """Where the previous version of ``path`` is kept."""
    return path.with_name(path.name + ".bak")


def _mode_for(path: Path) -> int:
    """The permissions a new version gets: the old file's, or what ``open()`` would give (0666 - umask)."""
    try:
        return path.stat().st_mode & 0o777
    except OSError:
        return new_file_mode()


def check_writable(folder: Path) -> None:
    """Make sure files can be saved in ``folder`` (created if missing) before a step moves the robot: a
    folder found unwritable only at the end would cost the whole procedure. A temporary file is written
    and removed, which catches what a permission check misses (read-only file systems, full disks, root
    squash, a file where the folder should be)."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".vlp-agent-probe.", suffix=".tmp", dir=folder)
        try:
            os.write(fd, b"probe")
        finally:
            os.close(fd)
            os.unlink(tmp)
    except OSError as exc:
        raise CalibrationError(
            f"cannot write calibration files in {folder}: {exc.strerror or exc} (choose another with --dir)"
        ) from exc


def _write_temp(folder: Path, name: str, data: bytes, mode: int) -> Path:
    fd, tmp = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp", dir=folder)
    try:
        os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as fp:
            fp.write(data)
            fp.flush()
            os.fsync(fp.fileno())
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return Path(tmp)


def save_all(files: Sequence[tuple[Path, bytes | str]], *, backup: bool = True) -> list[SavedFile]:
    """Save each (path, content) atomically; the previous version of each is kept as ``NAME.bak``.

    Raises CalibrationError (nothing changed) when a folder cannot be created or a file cannot be written.
    """
    staged: list[tuple[Path, Path]] = []
    try:
        for path, content in files:
            data = content.encode("utf-8") if isinstance(content, str) else bytes(content)
            folder = path.parent
            try:
                folder.mkdir(parents=True, exist_ok=True)
                staged.append((path, _write_temp(folder, path.name, data, _mode_for(path))))
            except OSError as exc:
                raise CalibrationError(f"cannot write {path}: {exc.strerror or exc}") from exc
        saved: list[SavedFile] = []
        for path, tmp in staged:
            kept: Path | None = None
            if backup and path.exists():
                kept = backup_path(path)
                try:
                    old = _write_temp(path.parent, kept.name, path.read_bytes(), _mode_for(path))
                    os.replace(old, kept)
                except OSError as exc:
                    raise CalibrationError(
                        f"cannot keep the previous {path} as {kept}: {exc.strerror or exc}"
                    ) from exc
            try:
                os.replace(tmp, path)
            except OSError as exc:
                raise CalibrationError(f"cannot replace {path}: {exc.strerror or exc}") from exc
            fsync_dir(path.parent)
            log.info("saved %s%s", path, f" (previous version: {kept})" if kept else "")
            saved.append(SavedFile(path, kept))
        return saved
    finally:
        for _, tmp in staged:
            with contextlib.suppress(OSError):
                if tmp.exists():
                    tmp.unlink()


def save_atomic(path: Path, content: bytes | str, *, backup: bool = True) -> SavedFile:
    """Save one file atomically, keeping its previous version as ``NAME.bak``."""
    return save_all([(path, content)], backup=backup)[0]


def commit(result: StepResult, *, force: bool = False) -> StepResult:
    """Write a step's outputs: all of them when its checks pass (or ``force``), else only its report files,
    so a result that failed its checks never replaces a working calibration. Records what was written in
    ``result.files`` and what was held back in ``result.withheld``."""
    keep = result.ok or force
    chosen = [o for o in result.outputs if keep or o.report]
    result.withheld = [o.path for o in result.outputs if o not in chosen]
    saved = save_all([(o.path, o.content) for o in chosen])
    result.files = [s.path for s in saved]
    return result
