"""The side-by-side benchmark's quick pieces: GMapping's input format written from our logs and read back,
and the clean skip where GMapping cannot be built or a log is absent (benchmarks/slam_vs_gmapping.py)."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from agent.slam.logs import LogFormat, LogRecord, SlamLog
from agent.slam.scan import LaserGeometry

_SPEC = importlib.util.spec_from_file_location(
    "slam_vs_gmapping", Path(__file__).resolve().parents[2] / "benchmarks" / "slam_vs_gmapping.py"
)
assert _SPEC is not None and _SPEC.loader is not None
bench = importlib.util.module_from_spec(_SPEC)
sys.modules[_SPEC.name] = bench  # dataclasses look their module up there
_SPEC.loader.exec_module(bench)


def _log(geometry: LaserGeometry, fmt: LogFormat, records: int = 4) -> SlamLog:
    rng = np.random.default_rng(3)
    rows = []
    for i in range(records):
        ranges = rng.uniform(0.5, geometry.no_return_m * 0.9, geometry.beams)
        ranges[1] = 0.0  # no return, ours
        ranges[2] = geometry.no_return_m  # saturation: no return too
        odom = np.array([0.1 * i, -0.05 * i, 0.3 - 0.2 * i])
        rows.append(LogRecord(i + 1, 10.0 + 0.1 * i, ranges, odom))
    return SlamLog("<test>", fmt, geometry, tuple(rows))


@pytest.mark.parametrize(
    ("geometry", "fmt"),
    [
        (LaserGeometry(-math.pi / 2 + np.arange(180) * math.pi / 180, 0.0, 81.83), LogFormat.RADISH),
        (LaserGeometry.urg04lx((0.145, 0.0, 0.0)), LogFormat.BREEZYSLAM),
    ],
)
def test_the_gmapping_input_reads_back_as_the_log(
    tmp_path: Path, geometry: LaserGeometry, fmt: LogFormat
) -> None:
    log = _log(geometry, fmt)
    back = bench.read_gmapping_input(bench.write_gmapping_input(log, tmp_path / "x.gmlog"))
    assert back.beams == geometry.beams
    angles = back.angle0_rad + np.arange(back.beams) * back.dangle_rad
    np.testing.assert_allclose(angles, geometry.angles_rad, atol=1e-9)
    assert back.mount == pytest.approx(geometry.mount)
    assert (back.range_min_m, back.range_max_m) == pytest.approx((geometry.min_range_m, geometry.no_return_m))
    np.testing.assert_allclose(back.times_s, log.times_s(), atol=1e-6)
    np.testing.assert_allclose(back.odometry, log.odometry_poses(), atol=1e-8)
    ours = np.array([r.ranges_m for r in log.records])
    expected = np.where(ours >= geometry.no_return_m, 0.0, ours)  # no return is 0 for the driver
    np.testing.assert_allclose(back.ranges_m, expected, rtol=1e-5)
    assert np.all(back.ranges_m[:, 1:3] == 0.0)


def test_gmapping_is_skipped_with_a_reason_without_its_sources_or_a_compiler(tmp_path: Path) -> None:
    driver, reason = bench.build_gmapping(tmp_path / "absent", tmp_path / "build")
    assert driver is None and "not found" in reason
    peer = tmp_path / "peer"
    peer.mkdir()
    (peer / "build.sh").write_text("exit 1\n")
    driver, reason = bench.build_gmapping(peer, tmp_path / "build", compiler="no-such-compiler-x")
    assert driver is None and "no C++ compiler" in reason
    driver, reason = bench.build_gmapping(peer, tmp_path / "build", compiler="sh")
    assert driver is None and "build failed" in reason


def test_the_benchmark_reports_skips_in_its_json(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(bench, "SHARED", tmp_path)
    out = tmp_path / "out.json"
    assert bench.main(["--logs", "intel", "--peer", str(tmp_path / "none"), "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert "not found" in result["gmapping"]["skipped"]
    assert "log not found" in result["logs"]["intel"]["skipped"]
    assert json.loads(capsys.readouterr().out) == result
    # What the ratios were measured on: the CPU, the interpreter and the libraries, named.
    machine = result["machine"]
    assert machine["python"].split()[1] == ".".join(str(v) for v in sys.version_info[:3])
    assert machine["numpy"] == np.__version__
    assert machine["cpu"] and machine["cores"] >= 1 and machine["opencv"] and machine["scipy"]


def _figures(cpu_s: float, wall_s: float, update_ms: float | None) -> dict[str, object]:
    return {
        "cpu_s": cpu_s,
        "wall_s": wall_s,
        "update_ms_median": update_ms,
        "updates": 7,
        "peak_rss_mb": 80.0,
    }


def test_repeated_runs_report_the_median_times_and_each_run() -> None:
    poses = np.arange(12.0).reshape(4, 3)
    runs = [
        (poses, _figures(2.4, 2.5, 11.0)),
        (poses.copy(), _figures(2.1, 2.2, 10.0)),
        (poses, _figures(2.2, 2.9, 12.0)),
    ]
    out = bench.combine_runs(runs)
    assert out["cpu_s"] == 2.2 and out["cpu_s_runs"] == [2.4, 2.1, 2.2]
    assert out["wall_s"] == 2.5 and out["wall_s_runs"] == [2.5, 2.2, 2.9]
    assert out["update_ms_median"] == 11.0
    assert out["updates"] == 7 and out["peak_rss_mb"] == 80.0  # the first run's
    assert out["repeats_differ"] is False
    moved = poses.copy()
    moved[2, 0] += 1e-9
    assert bench.combine_runs([runs[0], (moved, _figures(2.0, 2.0, None))])["repeats_differ"] is True
    # One run: its own figures, nothing added; a missing time is left as it was.
    assert bench.combine_runs(runs[:1]) == runs[0][1]
    assert bench.combine_runs([runs[0], (poses, _figures(2.0, 2.0, None))])["update_ms_median"] == 11.0
    with pytest.raises(ValueError, match="no runs"):
        bench.combine_runs([])


def test_repeat_must_be_at_least_one(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        bench.main(["--logs", "intel", "--repeat", "0"])
    assert "--repeat must be at least 1" in capsys.readouterr().err


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="Linux /proc only")
def test_resident_memory_splits_into_own_data_and_mapped_files() -> None:
    held = np.ones(8 * 1024 * 1024 // 8)  # 8 MB of this process's own data, touched
    parts = bench.rss_parts_kb()
    assert set(parts) == {"rss_anon", "rss_file"}
    assert parts["rss_anon"] >= held.nbytes / 1024  # the array alone is that much
    assert parts["rss_file"] > 0  # the interpreter's own mapped pages at least
    # Both within the peak so far (a shared-memory part aside, which this process has none of).
    assert parts["rss_anon"] + parts["rss_file"] <= bench.peak_rss_kb() + 1024
