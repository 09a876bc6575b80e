"""The benchmarks' reading of /proc/stat: the shares of an interval stolen, busy and idle."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

_SPEC = importlib.util.spec_from_file_location(
    "cpu_share", Path(__file__).resolve().parents[2] / "benchmarks" / "cpu_share.py"
)
assert _SPEC is not None and _SPEC.loader is not None
cpu_share = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(cpu_share)


def _stat(path: Path, user: int, idle: int, steal: int) -> None:
    # user nice system idle iowait irq softirq steal guest guest_nice
    path.write_text(f"cpu  {user} 0 10 {idle} 0 0 0 {steal} 0 0\ncpu0 1 2 3 4 5 6 7 8 9 10\n")


def test_shares_of_an_interval(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    stat = tmp_path / "stat"
    real = cpu_share.cpu_times
    monkeypatch.setattr(cpu_share, "cpu_times", lambda: real(stat))
    _stat(stat, 100, 1000, 50)
    share = cpu_share.CpuShare().start()
    _stat(stat, 160, 1100, 90)  # +60 user, +100 idle, +40 steal: 200 ticks
    share.stop()
    assert share.result() == {"steal": 0.2, "busy": 0.3, "idle": 0.5}


def test_missing_or_odd_stat_gives_nothing(tmp_path: Path) -> None:
    assert cpu_share.cpu_times(tmp_path / "absent") is None
    odd = tmp_path / "stat"
    odd.write_text("intr 1 2 3\n")
    assert cpu_share.cpu_times(odd) is None
    assert cpu_share.CpuShare().result() == {}
