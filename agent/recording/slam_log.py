"""A flight recording as a laser log for ``vlp-agent eval slam --log``: scans with the odometry pose of each.

Which scans, and which odometry:

* when the recording holds ``/slam/input`` (the agent ran SLAM), the scans the live SLAM loop took, each
  with the odometry pose it was given, and the VLP fixes it passed on: the live filter's own inputs;
* otherwise (SLAM was off), every scan of ``/laser/scan_raw``, with the wheel odometry integrated from the
  fusion's odometry records (``/fusion/input``, ``k = odometry``: distance and heading change over each
  wheel interval) and interpolated to the scan's time; scans outside the odometry are left out.

The map starts where the live one did (the recorded start pose), else at the first fused pose, else at
the origin. A ``vlp-agent sim`` recording holds the simulation's truth (``/sim/truth``, at each pose
written): the truth at each scan is interpolated from it, for the trajectory error; a robot's recording
has none.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from agent.recording.reader import Recording
from agent.recording.slam_replay import scan_from_message
from agent.slam.fix import PoseFix, TimedFix
from agent.slam.logs import LogFormat, LogRecord, SlamLog
from agent.slam.scan import LaserGeometry, ranges_from_scan

__all__ = ["RecordedSlamLog", "integrate_odometry", "slam_log_from_recording"]

FloatArray = npt.NDArray[np.float64]
Pose = tuple[float, float, float]


@dataclass(frozen=True)
class RecordedSlamLog:
    """``odometry``: where the odometry came from (``slam_input`` or ``fusion_input``); ``skipped``: raw
    scans left out (not taken by the live SLAM loop, or outside the odometry)."""

    log: SlamLog
    fixes: tuple[TimedFix, ...]
    start_pose: tuple[float, float, float] | None
    odometry: str
    skipped: int
    mount: tuple[float, float, float] = (0.0, 0.0, 0.0)
    truth: FloatArray | None = None  # (N, 3): the true base pose at each record's time (sim recordings)


def integrate_odometry(inputs: Iterable[dict[str, Any]]) -> Iterator[tuple[int, Pose, float, float]]:
    """The wheel odometry in the fusion's ``odometry`` records (``/fusion/input``: distance ``ds`` and
    heading change ``dyaw`` over each wheel interval ``t0``..``t1``), integrated from the origin:
    x += ds cos(yaw + dyaw / 2), y += ds sin(...), yaw += dyaw. Yields (t_ns, pose, v_mps, w_radps) at the
    first interval's start and at each interval's end (records that go back in time are skipped)."""
    x = y = yaw = 0.0
    last: int | None = None
    for r in inputs:
        if r.get("k") != "odometry":
            continue
        t0, t1 = int(r["t0"]), int(r["t1"])
        if last is None:
            last = t0
            yield t0, (x, y, yaw), 0.0, 0.0
        if t1 <= last:
            continue
        ds, dyaw = float(r["ds"]), float(r["dyaw"])
        mid = yaw + 0.5 * dyaw
        x, y, yaw = x + ds * math.cos(mid), y + ds * math.sin(mid), math.remainder(yaw + dyaw, math.tau)
        dt_s = (t1 - t0) * 1e-9 if t1 > t0 else math.inf
        last = t1
        yield t1, (x, y, yaw), ds / dt_s, dyaw / dt_s


def _odometry_track(inputs: list[dict[str, Any]]) -> tuple[list[int], list[Pose]]:
    times: list[int] = []
    poses: list[Pose] = []
    for t_ns, pose, _, _ in integrate_odometry(inputs):
        times.append(t_ns)
        poses.append(pose)
    return times, poses


def _at(times: list[int], poses: list[Pose], t_ns: int) -> FloatArray | None:
    if len(times) < 2 or not times[0] <= t_ns <= times[-1]:
        return None
    i = max(min(bisect.bisect_right(times, t_ns), len(times) - 1), 1)
    t0, t1 = times[i - 1], times[i]
    w = (t_ns - t0) / (t1 - t0) if t1 > t0 else 0.0
    (x0, y0, a0), (x1, y1, a1) = poses[i - 1], poses[i]
    a = a0 + w * math.remainder(a1 - a0, math.tau)
    return np.array([x0 + w * (x1 - x0), y0 + w * (y1 - y0), math.remainder(a, math.tau)])


def slam_log_from_recording(recordings: list[Recording], source: str) -> RecordedSlamLog:
    """The laser log in what :func:`agent.recording.reader.read_recordings` read (see the module doc)."""
    raw: dict[int, dict[str, Any]] = {}
    slam_inputs: list[dict[str, Any]] = []
    fusion_inputs: list[dict[str, Any]] = []
    fused: list[tuple[int, tuple[float, float, float]]] = []
    setup: dict[str, Any] | None = None
    truth: list[tuple[int, Pose]] = []
    for recording in recordings:
        for m in recording.messages:
            if m.topic == "/laser/scan_raw":
                raw[int(m.data["host_time_ns"])] = m.data
            elif m.topic == "/slam/input":
                slam_inputs.append(m.data)
            elif m.topic == "/fusion/input":
                fusion_inputs.append(m.data)
            elif m.topic == "/pose/fused":
                d = m.data
                fused.append((int(d["t_ns"]), (float(d["x_m"]), float(d["y_m"]), float(d["yaw_rad"]))))
            elif m.topic == "/slam/setup" and setup is None:
                setup = m.data
            elif m.topic == "/sim/truth":
                d = m.data
                truth.append((int(d["t_ns"]), (float(d["x_m"]), float(d["y_m"]), float(d["yaw_rad"]))))
    mount = (0.0, 0.0, 0.0)
    if setup is not None:
        mt = setup["mount"]
        mount = (float(mt.get("x_m", 0.0)), float(mt.get("y_m", 0.0)), float(mt.get("yaw_rad", 0.0)))
    records: list[LogRecord] = []
    fixes: list[TimedFix] = []
    start: tuple[float, float, float] | None = None
    geometry: LaserGeometry | None = None
    if slam_inputs:
        odometry = "slam_input"
        for r in slam_inputs:
            if r["k"] == "start" and start is None and r["pose"] is not None:
                p = r["pose"]
                start = (float(p[0]), float(p[1]), float(p[2]))
            elif r["k"] == "fix":
                cov = np.asarray(r["cov"], dtype=np.float64)
                side = math.isqrt(cov.size)
                fix = PoseFix(float(r["x"]), float(r["y"]), r["yaw"], cov.reshape(side, side))
                fixes.append(TimedFix(int(r["t"]) * 1e-9, fix, np.asarray(r["odom"], dtype=np.float64)))
            elif r["k"] == "scan" and int(r["t"]) in raw:
                scan = scan_from_message(raw[int(r["t"])])
                geometry = geometry or LaserGeometry.from_scan(scan, mount)
                odom = np.asarray(r["odom"], dtype=np.float64)
                records.append(
                    LogRecord(len(records) + 1, scan.host_time_ns * 1e-9, ranges_from_scan(scan), odom)
                )
    else:
        odometry = "fusion_input"
        times, poses = _odometry_track(fusion_inputs)
        for t_ns in sorted(raw):
            at = _at(times, poses, t_ns)
            if at is None:
                continue
            scan = scan_from_message(raw[t_ns])
            geometry = geometry or LaserGeometry.from_scan(scan, mount)
            records.append(LogRecord(len(records) + 1, scan.host_time_ns * 1e-9, ranges_from_scan(scan), at))
    if start is None and records and fused:
        first_ns = round(records[0].t_s * 1e9)
        after = [pose for t, pose in fused if t >= first_ns]
        start = after[0] if after else fused[-1][1]
    if geometry is None:
        geometry = LaserGeometry.urg04lx(mount)  # no scan: an empty log, refused by the caller
    log = SlamLog(source, LogFormat.MCAP, geometry, tuple(records))
    fixes.sort(key=lambda f: f.t_s)
    at_scans = _truth_at([round(r.t_s * 1e9) for r in records], truth) if records else None
    return RecordedSlamLog(log, tuple(fixes), start, odometry, len(raw) - len(records), mount, at_scans)


def _truth_at(times_ns: list[int], truth: list[tuple[int, Pose]]) -> FloatArray | None:
    """The truth interpolated at ``times_ns`` (held at its ends); None without truth samples."""
    truth = sorted(dict(truth).items())
    if len(truth) < 2:
        return None
    t = np.array([s for s, _ in truth], dtype=np.float64)
    poses = np.array([p for _, p in truth], dtype=np.float64)
    at = np.asarray(times_ns, dtype=np.float64)
    yaw = np.unwrap(poses[:, 2])
    out: FloatArray = np.stack(
        [np.interp(at, t, poses[:, 0]), np.interp(at, t, poses[:, 1]), np.interp(at, t, yaw)], axis=1
    )
    out[:, 2] = np.remainder(out[:, 2] + np.pi, 2.0 * np.pi) - np.pi
    return out
