"""Re-run SLAM on a flight recording: a fresh mapper, built as the recorded one was, takes the recorded scans
with the odometry they went with, in the order the live SLAM loop gave them, as fast as the CPU allows; every
filter update's pose is compared with the one the live run recorded (``/slam/pose``).

What the live SLAM loop did is on ``/slam/input`` (``agent.recording.messages``): each scan it took (the
queue in front of it drops scans while it is busy: which ones depends on thread timing, so the replay
follows the recorded decisions rather than taking every scan), the odometry pose it gave with it (the
odometry track's interpolation at the scan's time, itself dependent on which wheel reads had arrived), each
VLP fix it passed on, and the fused pose the map was started at. The scans themselves come from
``/laser/scan_raw``. ``/slam/setup`` says how the mapper was built ([slam] config, the laser mount). Given
these, the filter (numpy, seeded) is deterministic: the replay reproduces the recorded poses bit for bit
on the same machine and library versions.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agent.config import MountConfig, SlamConfig, SlamMode
from agent.recording.reader import RecordedMessage, Recording
from agent.runtime.mapper import Pose, ScanMapper, make_local_mapper
from agent.runtime.types import AbsoluteFix
from drivers.samples import Scan

__all__ = [
    "SlamReplayResult",
    "replay_slam",
    "scan_from_message",
    "slam_config_from_json",
    "slam_setup",
]

log = logging.getLogger(__name__)


def _json_value(value: Any) -> Any:
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, Path):
        return str(value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _json_value(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, tuple):
        return [_json_value(v) for v in value]
    return value


def slam_setup(config: SlamConfig, mount: MountConfig, mapper_name: str) -> dict[str, Any]:
    """The ``/slam/setup`` message: every [slam] key, the laser mount and the mapper's name."""
    return {"config": _json_value(config), "mount": _json_value(mount), "mapper": mapper_name}


def slam_config_from_json(data: dict[str, Any]) -> SlamConfig:
    """The [slam] config a ``/slam/setup`` message holds. Keys this version does not know (a newer agent's)
    are left out, and logged."""
    kwargs: dict[str, Any] = {}
    known = {f.name: str(f.type) for f in dataclasses.fields(SlamConfig)}
    for key, value in data.items():
        kind = known.get(key)
        if kind is None:
            log.warning("/slam/setup: [slam] %s is not known to this version: left out of the replay", key)
            continue
        if value is None:
            kwargs[key] = None
        elif "SlamMode" in kind:
            kwargs[key] = SlamMode(value)
        elif "MountConfig" in kind:
            kwargs[key] = MountConfig(**value)
        elif "Path" in kind:
            kwargs[key] = Path(value)
        elif isinstance(value, list):
            kwargs[key] = tuple(value)
        else:
            kwargs[key] = value
    return SlamConfig(**kwargs)


def scan_from_message(data: dict[str, Any]) -> Scan:
    """A ``/laser/scan_raw`` message as the driver's ``Scan``."""
    return Scan(
        np.asarray(data["ranges_mm"], dtype=np.int32),
        float(data["angle_min_rad"]),
        float(data["angle_increment_rad"]),
        int(data["min_range_mm"]),
        int(data["max_range_mm"]),
        int(data["sequence"]),
        int(data["host_time_ns"]),
        None if data["device_time_ms"] is None else int(data["device_time_ms"]),
    )


@dataclass(frozen=True)
class SlamReplayResult:
    """``poses``: filter updates the replay gave a pose for; ``poses_compared``: of those, the ones the live
    run recorded at the same scan time; ``poses_unmatched``: recorded poses with no replayed one at their
    time, and replayed ones with no recorded one (0 when the replay followed the live run);
    ``steps_differing``: scans the replayed mapper treated otherwise than the live one (``updated`` against
    ``gated``, ...); ``scans_missing``: scans SLAM took whose raw scan is not in the recording (dropped, or
    in a file that was not read), not replayed; ``restarts``: SLAM process restarts followed (each a new
    map, as in the live run). ``max_diff_m`` / ``max_yaw_diff_rad``: over the compared
    poses (None: none compared)."""

    mapper: str
    restarts: int
    scans: int
    fixes: int
    scans_missing: int
    poses: int
    poses_compared: int
    poses_unmatched: int
    steps_differing: int
    max_diff_m: float | None
    max_yaw_diff_rad: float | None


def _messages(recordings: Iterable[Recording]) -> Iterable[RecordedMessage]:
    for recording in recordings:
        yield from recording.messages


def replay_slam(recordings: list[Recording]) -> SlamReplayResult | str:
    """Re-run SLAM over what :func:`agent.recording.reader.read_recordings` read. A string instead of a
    result says why SLAM cannot be replayed from these files (no ``/slam/setup``: SLAM was off, or the file
    was recorded before the SLAM inputs were)."""
    setup: dict[str, Any] | None = None
    inputs: list[dict[str, Any]] = []
    scans: dict[int, dict[str, Any]] = {}
    recorded: dict[int, dict[str, Any]] = {}
    for m in _messages(recordings):
        if m.topic == "/laser/scan_raw":
            scans[int(m.data["host_time_ns"])] = m.data
        elif m.topic == "/slam/input":
            inputs.append(m.data)
        elif m.topic == "/slam/pose":
            recorded[int(m.data["t_ns"])] = m.data
        elif m.topic == "/slam/setup" and setup is None:
            setup = m.data
    if setup is None:
        return "no /slam/setup in the recording (SLAM off, or recorded before SLAM inputs were)"
    config = dataclasses.replace(slam_config_from_json(setup["config"]), process=False, enabled=True)
    mount = MountConfig(**setup["mount"])
    starts: dict[int, Pose | None] = {}

    def start_pose(t_ns: int) -> Pose | None:
        return starts.get(t_ns)

    built, why = make_local_mapper(config, mount, start_pose)
    if built is None:
        return f"the recorded SLAM cannot be built here: {why}"
    mapper: ScanMapper = built
    n_scans = n_fixes = missing = differing = poses = restarts = 0
    compared: set[int] = set()
    worst_xy = worst_yaw = 0.0
    try:
        for r in inputs:
            kind = r["k"]
            if int(r.get("restarts", 0)) > restarts:
                # The live SLAM process died and a new one started a new map at this input: so does the
                # replay (the scan the old one lost was answered "rejected", and gave no pose either way).
                restarts = int(r["restarts"])
                mapper.close()
                built, why = make_local_mapper(config, mount, start_pose)
                if built is None:
                    return f"the recorded SLAM cannot be built here: {why}"
                mapper = built
            if kind == "start":
                pose = r["pose"]
                starts[int(r["t"])] = None if pose is None else (pose[0], pose[1], pose[2])
            elif kind == "fix":
                _add_fix(mapper, r)
                n_fixes += 1
            elif kind == "scan":
                raw = scans.get(int(r["t"]))
                if raw is None:
                    missing += 1
                    continue
                o = r["odom"]
                step = mapper.update(scan_from_message(raw), (o[0], o[1], o[2]))
                n_scans += 1
                differing += step.kind != r["step"]
                if step.fix is None:
                    continue
                poses += 1
                live = recorded.get(step.fix.t_ns)
                if live is None:
                    continue
                compared.add(step.fix.t_ns)
                worst_xy = max(worst_xy, math.hypot(step.fix.x_m - live["x_m"], step.fix.y_m - live["y_m"]))
                yaw = step.fix.yaw_rad if step.fix.yaw_rad is not None else live["yaw_rad"]
                worst_yaw = max(worst_yaw, abs(math.remainder(yaw - live["yaw_rad"], math.tau)))
    finally:
        mapper.close()
    unmatched = (len(recorded) - len(compared)) + (poses - len(compared))
    return SlamReplayResult(
        mapper=mapper.name,
        restarts=restarts,
        scans=n_scans,
        fixes=n_fixes,
        scans_missing=missing,
        poses=poses,
        poses_compared=len(compared),
        poses_unmatched=unmatched,
        steps_differing=differing,
        max_diff_m=worst_xy if compared else None,
        max_yaw_diff_rad=worst_yaw if compared else None,
    )


def _add_fix(mapper: ScanMapper, r: dict[str, Any]) -> None:
    cov = np.asarray(r["cov"], dtype=np.float64)
    side = math.isqrt(cov.size)
    o = r["odom"]
    fix = AbsoluteFix(int(r["t"]), float(r["x"]), float(r["y"]), r["yaw"], cov.reshape(side, side))
    mapper.add_fix(fix, (o[0], o[1], o[2]))
