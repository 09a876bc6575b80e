"""Readers for recorded laser logs: BreezySLAM ``.dat`` and the radish scans format (``../shared/data/slam``).

Both give a :class:`SlamLog`: the laser geometry plus one :class:`LogRecord` per scan with its time, its
ranges (metres, this package's convention: 0 = no return) and the robot's odometry pose. A line that does
not follow the format raises :class:`LogFormatError` naming the file and the line; nothing is skipped
silently (bad *scans* in a well-formed line are the filter's business, see ``agent.slam.scan``).

Formats (``reference/slam.md`` §1.1, ``data/README.md``):

* BreezySLAM: one scan per line, 707 tokens: [0] timestamp in microseconds, [2] and [3] cumulative left
  and right wheel encoder ticks, [24..705] 682 URG-04LX ranges in millimetres (0 = no return), the last
  token ignored (as BreezySLAM's own readers do). The robot is BreezySLAM's ``mines.Rover``: wheel radius
  77 mm, half axle 165 mm, 2000 ticks per wheel turn, laser 145 mm ahead of the axle.
* radish: a ``#`` header, then per scan ``t gm_x gm_y gm_th odo_x odo_y odo_th n r_0 .. r_{n-1}`` (s, m,
  rad); ``gm_*`` is GMapping's corrected pose (a reference, not ground truth), ``odo_*`` raw odometry.
  Beams follow GMapping's CARMEN convention: -90 deg + i * 180/n deg. The largest reading in the file is
  the sensor's saturation code (81.83 m Intel, 50 m ACES, 81.91 m FR079) and means no return.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from agent.slam.scan import LaserGeometry
from drivers.errors import ConfigError
from firmware_protocol.errors import ProtocolError

FloatArray = npt.NDArray[np.float64]


class LogFormat(enum.StrEnum):
    BREEZYSLAM = "breezyslam"
    RADISH = "radish"
    SIMULATED = "simulated"  # made in memory by ``agent.slam.simlog``; no file format
    MCAP = "mcap"  # a flight recording, read by ``agent.recording.slam_log`` (not by read_log)


class LogFormatError(ProtocolError):
    """A log line that does not follow its format. ``file`` and ``line_number`` (1-based) say where."""

    def __init__(self, reason: str, file: str, line_number: int, line: bytes = b"") -> None:
        super().__init__(reason, line)
        self.file = file
        self.line_number = line_number
        shown = line[:48].decode("ascii", "replace")
        more = "..." if len(line) > 48 else ""
        self.args = (f"{file}:{line_number}: {reason} (line: {shown!r}{more})",)


@dataclass(frozen=True, slots=True)
class LogRecord:
    """One scan of a log. ``odom_pose`` is the robot base's odometry pose (x_m, y_m, yaw_rad);
    ``reference_pose`` the log's reference (GMapping's corrected pose in radish logs), if it has one."""

    line: int
    t_s: float
    ranges_m: FloatArray
    odom_pose: FloatArray
    reference_pose: FloatArray | None = None


@dataclass(frozen=True)
class SlamLog:
    source: str
    format: LogFormat
    geometry: LaserGeometry
    records: tuple[LogRecord, ...]

    def __len__(self) -> int:
        return len(self.records)

    @property
    def duration_s(self) -> float:
        return self.records[-1].t_s - self.records[0].t_s if self.records else 0.0

    def times_s(self) -> FloatArray:
        return np.array([r.t_s for r in self.records], dtype=np.float64)

    def odometry_poses(self) -> FloatArray:
        return np.array([r.odom_pose for r in self.records], dtype=np.float64).reshape(-1, 3)

    def reference_poses(self) -> FloatArray | None:
        if not self.records or any(r.reference_pose is None for r in self.records):
            return None
        return np.array([r.reference_pose for r in self.records], dtype=np.float64).reshape(-1, 3)

    def sliced(self, start: int = 0, stop: int | None = None) -> SlamLog:
        return SlamLog(self.source, self.format, self.geometry, self.records[start:stop])

    def odometry_shifted(self, records: float) -> SlamLog:
        """The log with each record's odometry read ``records`` records later (earlier when negative),
        interpolated linearly between neighbouring records (the heading unwrapped) and held at the ends:
        for checking whether a log's odometry was sampled at another moment than its scans (a record written
        once the scan has arrived holds odometry about half a sweep later than the sweep's middle)."""
        if len(self.records) < 2 or records == 0.0:
            return self
        poses = self.odometry_poses()
        index = np.arange(len(self.records), dtype=np.float64)
        at = index + records
        x = np.interp(at, index, poses[:, 0])
        y = np.interp(at, index, poses[:, 1])
        yaw = np.interp(at, index, np.unwrap(poses[:, 2]))
        shifted = tuple(
            dataclasses.replace(r, odom_pose=np.array([x[k], y[k], yaw[k]]))
            for k, r in enumerate(self.records)
        )
        return SlamLog(self.source, self.format, self.geometry, shifted)


# -- BreezySLAM ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class WheelOdometryModel:
    """Differential drive from cumulative encoder ticks. Defaults: BreezySLAM's ``mines.Rover``."""

    wheel_radius_m: float = 0.077
    half_axle_m: float = 0.165
    ticks_per_turn: int = 2000

    def step(self, d_left_ticks: float, d_right_ticks: float) -> tuple[float, float]:
        """(distance travelled by the axle centre, heading change) for one tick increment.

        phi = ticks * 2 pi / ticks_per_turn;  d = r (phi_l + phi_r) / 2;  dyaw = r (phi_r - phi_l) / (2 b)
        """
        k = 2.0 * math.pi / self.ticks_per_turn
        phi_l, phi_r = d_left_ticks * k, d_right_ticks * k
        return (
            self.wheel_radius_m * (phi_l + phi_r) / 2.0,
            self.wheel_radius_m * (phi_r - phi_l) / (2.0 * self.half_axle_m),
        )


BREEZYSLAM_HEADER_TOKENS = 24
BREEZYSLAM_LASER_MOUNT = (0.145, 0.0, 0.0)
# The log's timestamps mark the end of the sweep: de-skewing with the stamp on the last of the 682 beams
# (97.7 us apart) fits exp1 best (docs/slam.md, "Motion during a sweep").
BREEZYSLAM_SWEEP_START_S = -681 * 0.1 / 1024.0


def parse_breezyslam(
    lines: Iterable[str], source: str = "<lines>", beams: int = 682, wheels: WheelOdometryModel | None = None
) -> SlamLog:
    """Parse BreezySLAM log lines (see the module docstring). Odometry starts at (0, 0, 0) and is integrated
    with the midpoint rule: x += d cos(yaw + dyaw/2), y += d sin(yaw + dyaw/2), yaw += dyaw."""
    wheels = wheels or WheelOdometryModel()
    expected = BREEZYSLAM_HEADER_TOKENS + beams + 1
    records: list[LogRecord] = []
    x_m = y_m = yaw_rad = 0.0
    last_ticks: tuple[int, int] | None = None
    for number, text in enumerate(lines, start=1):
        if not text.strip():
            continue
        tokens = text.split()
        raw = text.encode("utf-8", "replace")
        if len(tokens) != expected:
            what = "truncated line" if len(tokens) < expected else "too many tokens"
            raise LogFormatError(
                f"{what}: {len(tokens)} tokens, a {beams}-beam BreezySLAM line has {expected}",
                source,
                number,
                raw,
            )
        try:
            t_us = int(tokens[0])
            ticks = (int(tokens[2]), int(tokens[3]))
            ranges_mm = np.array(
                tokens[BREEZYSLAM_HEADER_TOKENS : BREEZYSLAM_HEADER_TOKENS + beams], dtype=np.int64
            )
        except ValueError as exc:
            raise LogFormatError(
                f"not an integer where the format has one ({exc})", source, number, raw
            ) from exc
        if last_ticks is not None:
            dist_m, dyaw_rad = wheels.step(ticks[0] - last_ticks[0], ticks[1] - last_ticks[1])
            x_m += dist_m * math.cos(yaw_rad + dyaw_rad / 2.0)
            y_m += dist_m * math.sin(yaw_rad + dyaw_rad / 2.0)
            yaw_rad = math.atan2(math.sin(yaw_rad + dyaw_rad), math.cos(yaw_rad + dyaw_rad))
        last_ticks = ticks
        ranges_m = ranges_mm.astype(np.float64) / 1000.0
        records.append(LogRecord(number, t_us * 1e-6, ranges_m, np.array([x_m, y_m, yaw_rad])))
    geometry = (
        LaserGeometry.urg04lx(BREEZYSLAM_LASER_MOUNT, BREEZYSLAM_SWEEP_START_S)
        if beams == 682
        else LaserGeometry(
            np.linspace(-2.0 * math.pi / 3.0, 2.0 * math.pi / 3.0, beams), 0.02, 5.6, BREEZYSLAM_LASER_MOUNT
        )
    )
    return SlamLog(source, LogFormat.BREEZYSLAM, geometry, tuple(records))


# -- radish ------------------------------------------------------------------------------------------------


def parse_radish(lines: Iterable[str], source: str = "<lines>") -> SlamLog:
    """Parse radish scan lines (see the module docstring)."""
    records: list[LogRecord] = []
    beams: int | None = None
    for number, text in enumerate(lines, start=1):
        stripped = text.strip()
        if not stripped or stripped.startswith("#"):
            continue
        tokens = stripped.split()
        raw = text.encode("utf-8", "replace")
        if len(tokens) < 8:
            raise LogFormatError(
                f"truncated line: {len(tokens)} tokens, need at least 8 before the ranges",
                source,
                number,
                raw,
            )
        try:
            values = np.array(tokens[:7], dtype=np.float64)
            n = int(tokens[7])
            ranges_m = np.array(tokens[8:], dtype=np.float64)
        except ValueError as exc:
            raise LogFormatError(
                f"not a number where the format has one ({exc})", source, number, raw
            ) from exc
        if n <= 1:
            raise LogFormatError(f"beam count {n} is not a scan", source, number, raw)
        if ranges_m.size != n:
            what = "truncated line" if ranges_m.size < n else "too many tokens"
            raise LogFormatError(
                f"{what}: the line announces {n} ranges and has {ranges_m.size}", source, number, raw
            )
        if beams is None:
            beams = n
        elif n != beams:
            raise LogFormatError(f"{n} beams where the log's first scan has {beams}", source, number, raw)
        if not np.all(np.isfinite(values)):
            raise LogFormatError("non-finite time or pose", source, number, raw)
        records.append(LogRecord(number, float(values[0]), ranges_m, values[4:7].copy(), values[1:4].copy()))
    if beams is None:
        raise LogFormatError("no scans in the log", source, 0)
    all_ranges = np.concatenate([r.ranges_m for r in records])
    finite = all_ranges[np.isfinite(all_ranges)]
    saturation_m = float(finite.max()) if finite.size else 1.0
    angles_rad = -math.pi / 2.0 + np.arange(beams, dtype=np.float64) * (math.pi / beams)
    geometry = LaserGeometry(angles_rad, 0.0, max(saturation_m, 1e-3))
    return SlamLog(source, LogFormat.RADISH, geometry, tuple(records))


# -- files ------------------------------------------------------------------------------------------------


def read_log(path: str | Path, log_format: LogFormat | str) -> SlamLog:
    """Read a whole log file in the given format."""
    chosen = LogFormat(log_format)
    file = Path(path)
    if chosen is LogFormat.SIMULATED:
        raise ConfigError(
            "format", "simulated logs are made by agent.slam.simlog, not read from files", str(file)
        )
    if chosen is LogFormat.MCAP:
        raise ConfigError("format", "flight recordings are read by agent.recording.slam_log", str(file))
    try:
        with file.open("r", encoding="ascii", errors="replace") as handle:
            lines = handle.readlines()
    except OSError as exc:
        raise ConfigError("log", f"cannot read the log: {exc.strerror or exc}", str(file)) from exc
    if chosen is LogFormat.BREEZYSLAM:
        return parse_breezyslam(lines, str(file))
    return parse_radish(lines, str(file))
