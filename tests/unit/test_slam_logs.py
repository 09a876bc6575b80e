"""Log readers: the real recordings whole, and synthetic lines cut short, garbled or inconsistent."""

from __future__ import annotations

import contextlib
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.slam.logs import LogFormat, LogFormatError, parse_breezyslam, parse_radish, read_log
from drivers.errors import ConfigError


def breezy_line(t_us: int = 1_000_000, left: int = 0, right: int = 0, ranges: list[int] | None = None) -> str:
    values = ranges if ranges is not None else [1000] * 682
    header = [str(t_us), "14000", str(left), str(right)] + ["0"] * 20
    return " ".join(header + [str(v) for v in values] + ["0"])


def radish_line(t: float = 1.0, n: int = 180, ranges: list[float] | None = None) -> str:
    values = ranges if ranges is not None else [2.0] * n
    return " ".join([f"{t}", "0.1", "0.2", "0.3", "1.0", "2.0", "0.5", str(n)] + [f"{v}" for v in values])


# -- the real logs -------------------------------------------------------------------------------------


def test_exp1_whole(shared_data: Path) -> None:
    log = read_log(shared_data / "slam/breezyslam/exp1.dat", "breezyslam")
    assert log.format is LogFormat.BREEZYSLAM
    assert len(log) == 756
    assert log.geometry.beams == 682
    # 682 URG-04LX steps 44..725 at 360/1024 deg: -119.53 .. +119.88 deg, front (step 384) at 0.
    assert math.degrees(log.geometry.angles_rad[0]) == pytest.approx(-119.53, abs=0.01)
    assert math.degrees(log.geometry.angles_rad[-1]) == pytest.approx(119.88, abs=0.01)
    assert log.records[0].t_s == pytest.approx(212.387282)
    assert log.duration_s == pytest.approx(287.007421 - 212.387282)
    ranges = np.stack([r.ranges_m for r in log.records])
    assert np.mean(ranges == 0.0) == pytest.approx(0.525, abs=0.005)  # reference/slam.md §1.1
    assert ranges.max() == pytest.approx(5.562)
    # The odometry integrates to the end pose and totals reference/slam.md §1.1 reports.
    odometry = log.odometry_poses()
    assert odometry[-1, 0] == pytest.approx(-5.78, abs=0.005)
    assert odometry[-1, 1] == pytest.approx(-2.98, abs=0.005)
    assert math.degrees(odometry[-1, 2]) == pytest.approx(106.9, abs=0.05)
    steps = np.diff(odometry[:, :2], axis=0)
    assert np.hypot(steps[:, 0], steps[:, 1]).sum() == pytest.approx(46.0, abs=0.05)
    assert log.reference_poses() is None


def test_intel_whole(shared_data: Path) -> None:
    log = read_log(shared_data / "slam/radish/intel_scans.txt", "radish")
    assert log.format is LogFormat.RADISH
    assert len(log) == 910
    assert log.geometry.beams == 180
    assert math.degrees(log.geometry.angles_rad[0]) == pytest.approx(-90.0)
    assert math.degrees(log.geometry.angles_rad[1] - log.geometry.angles_rad[0]) == pytest.approx(1.0)
    assert log.geometry.no_return_m == pytest.approx(81.83)  # the SICK saturation value
    first = log.records[0]
    assert first.line == 2  # after the header line
    assert first.t_s == pytest.approx(32.9068)
    assert first.reference_pose is not None
    np.testing.assert_allclose(first.reference_pose, [0.600266, -0.032033, -0.354665])
    np.testing.assert_allclose(first.odom_pose, [0.698035, -0.013284, -0.460915])
    reference = log.reference_poses()
    assert reference is not None and reference.shape == (910, 3)
    # Raw odometry drifts by tens of metres over the run (data/README.md), GMapping's path closes.
    assert np.hypot(*(log.odometry_poses()[-1, :2] - log.odometry_poses()[0, :2])) > 20.0
    # Four scans carry timestamps earlier than the one before: the filter will reject those.
    assert int(np.sum(np.diff(log.times_s()) <= 0.0)) == 4


def test_aces_saturation(shared_data: Path) -> None:
    log = read_log(shared_data / "slam/radish/aces_scans.txt", "radish")
    assert len(log) == 440
    assert log.geometry.no_return_m == pytest.approx(50.0)


def test_missing_file_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read the log"):
        read_log(tmp_path / "nope.dat", "breezyslam")


def test_unknown_format() -> None:
    with pytest.raises(ValueError):
        read_log("x", "carmen")


# -- BreezySLAM, synthetic -----------------------------------------------------------------------------


def test_breezyslam_odometry_model() -> None:
    # 2000 ticks = one wheel turn = 2 pi 0.077 m; both wheels one turn: straight ahead.
    log = parse_breezyslam([breezy_line(0, 0, 0), breezy_line(100_000, 2000, 2000)])
    np.testing.assert_allclose(log.records[1].odom_pose, [2 * math.pi * 0.077, 0.0, 0.0], atol=1e-12)
    # Right wheel forward, left back by the same: turn on the spot by r (phi_r - phi_l) / (2 b).
    log = parse_breezyslam([breezy_line(0, 0, 0), breezy_line(100_000, -100, 100)])
    phi = 100 * 2 * math.pi / 2000
    assert log.records[1].odom_pose[2] == pytest.approx(0.077 * 2 * phi / (2 * 0.165))
    assert log.records[1].odom_pose[0] == pytest.approx(0.0, abs=1e-12)
    assert log.records[1].t_s == pytest.approx(0.1)


def test_breezyslam_ranges_in_metres_zero_kept() -> None:
    ranges = [0] * 682
    ranges[10] = 1234
    log = parse_breezyslam([breezy_line(ranges=ranges)])
    assert log.records[0].ranges_m[10] == pytest.approx(1.234)
    assert np.count_nonzero(log.records[0].ranges_m) == 1


def test_breezyslam_truncated_line_names_file_and_line() -> None:
    good = breezy_line()
    cut = good[: len(good) // 2]
    with pytest.raises(LogFormatError) as err:
        parse_breezyslam([good, good, cut], source="exp.dat")
    assert err.value.file == "exp.dat"
    assert err.value.line_number == 3
    assert "exp.dat:3: truncated line" in str(err.value)
    assert err.value.data == cut.encode()


def test_breezyslam_extra_tokens() -> None:
    with pytest.raises(LogFormatError, match="too many tokens"):
        parse_breezyslam([breezy_line() + " 7"])


def test_breezyslam_not_a_number() -> None:
    bad = breezy_line().split()
    bad[30] = "12x4"
    with pytest.raises(LogFormatError, match=r"<lines>:1: not an integer"):
        parse_breezyslam([" ".join(bad)])


def test_breezyslam_blank_lines_skipped() -> None:
    log = parse_breezyslam(["", breezy_line(), "   ", breezy_line(2_000_000)])
    assert [r.line for r in log.records] == [2, 4]


# -- radish, synthetic ---------------------------------------------------------------------------------


def test_radish_fields() -> None:
    log = parse_radish(["# header", radish_line(3.5, 4, [1.0, 2.0, 50.0, 3.0])])
    record = log.records[0]
    assert record.t_s == 3.5
    np.testing.assert_allclose(record.reference_pose, [0.1, 0.2, 0.3])
    np.testing.assert_allclose(record.odom_pose, [1.0, 2.0, 0.5])
    np.testing.assert_allclose(record.ranges_m, [1.0, 2.0, 50.0, 3.0])
    assert log.geometry.no_return_m == 50.0
    np.testing.assert_allclose(np.degrees(log.geometry.angles_rad), [-90.0, -45.0, 0.0, 45.0])


@pytest.mark.parametrize(
    ("line", "message"),
    [
        (radish_line(n=180, ranges=[1.0] * 179), "truncated line: the line announces 180 ranges and has 179"),
        (radish_line(n=3, ranges=[1.0] * 4), "too many tokens"),
        ("1.0 2.0 3.0", "truncated line: 3 tokens"),
        (radish_line().replace("0.2", "zero", 1), "not a number"),
        (radish_line(n=1, ranges=[1.0]), "beam count 1 is not a scan"),
        (radish_line().replace("1.0", "nan", 1), "non-finite time or pose"),
    ],
)
def test_radish_malformed(line: str, message: str) -> None:
    with pytest.raises(LogFormatError, match=message) as err:
        parse_radish(["# header", radish_line(), line], source="intel.txt")
    assert err.value.line_number == 3
    assert str(err.value).startswith("intel.txt:3: ")


def test_radish_beam_count_must_not_change() -> None:
    with pytest.raises(LogFormatError, match="360 beams where the log's first scan has 180"):
        parse_radish([radish_line(), radish_line(n=360)])


def test_radish_empty_log() -> None:
    with pytest.raises(LogFormatError, match="no scans"):
        parse_radish(["# only a header\n"])


# -- any garbage parses or raises LogFormatError, nothing else --------------------------------------------

_TOKENS = st.sampled_from(["0", "1", "-3", "2.5", "nan", "inf", "x", "1e999", "", "#", "180", "682"])


@settings(max_examples=150, deadline=None)
@given(
    st.lists(st.lists(_TOKENS, max_size=12).map(" ".join), max_size=4),
    st.integers(0, 706),
    st.binary(max_size=8),
)
def test_garbage_raises_only_log_format_error(extra: list[str], cut: int, junk: bytes) -> None:
    mangled_breezy = breezy_line()[:cut] + junk.decode("latin-1")
    mangled_radish = radish_line(n=5, ranges=[1.0] * 5)[: cut % 40] + junk.decode("latin-1")
    for parse, line in ((parse_breezyslam, mangled_breezy), (parse_radish, mangled_radish)):
        with contextlib.suppress(LogFormatError):
            parse([line, *extra])


def test_odometry_shifted_interpolates_between_records_and_holds_at_the_ends() -> None:
    from agent.slam.logs import LogRecord, SlamLog
    from agent.slam.scan import LaserGeometry

    geometry = LaserGeometry(np.radians(np.linspace(-90.0, 90.0, 5)), 0.02, 5.6, (0.0, 0.0, 0.0))
    yaws = [3.0, -3.0, -2.8]  # across the +-pi seam: unwrapped before interpolating
    records = tuple(
        LogRecord(k, 0.1 * k, np.ones(5), np.array([float(k), 2.0 * k, yaws[k]])) for k in range(3)
    )
    log = SlamLog("test", LogFormat.BREEZYSLAM, geometry, records)
    shifted = log.odometry_shifted(-0.5).odometry_poses()
    assert shifted[0] == pytest.approx([0.0, 0.0, 3.0])  # held at the start
    assert shifted[1][:2] == pytest.approx([0.5, 1.0])
    unwrapped = 3.0 + 0.5 * (2.0 * math.pi - 6.0)
    assert shifted[1][2] == pytest.approx(unwrapped)
    assert log.odometry_shifted(0.0) is log
