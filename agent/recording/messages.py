"""Samples -> channel messages: what each recorded sample becomes in the recording, pure.

The agent's loops hand the recorder a *kind* and the sample they already hold (a frozen dataclass, or one
of the small records below); the writer thread turns it into one or more ``(topic, message dict)`` here,
so the loops pay one queue append and nothing of this. Times are the agent's clock
(``time.monotonic_ns()``, the drivers' host time); a Foxglove ``timestamp`` is the same time as sec/nsec.
"""

from __future__ import annotations

import base64
import dataclasses
import enum
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "CHANNELS",
    "KINDS",
    "CommandSample",
    "FusedSample",
    "GoalSample",
    "HealthSample",
    "SlamFixSample",
    "SlamScanSample",
    "SlamStartSample",
    "TruthSample",
    "WheelCommandSample",
    "fusion_record_time",
    "messages_for",
]

Message = dict[str, Any]

# topic -> schema name. The topics a config may name in ``recorder.channels``; no image topic exists.
CHANNELS: dict[str, str] = {
    "/laser/scan": "foxglove.LaserScan",
    "/laser/scan_raw": "vlp_agent.Scan",
    "/wheels/state": "vlp_agent.WheelState",
    "/wheels/command": "vlp_agent.WheelCommand",
    "/imu": "vlp_agent.ImuSample",
    "/rfid/tags": "vlp_agent.TagRead",
    "/vlp/fix": "vlp_agent.VlpFix",
    "/vlp/no_fix": "vlp_agent.NoFix",
    "/pose": "foxglove.PoseInFrame",
    "/pose/fused": "vlp_agent.FusedPose",
    "/tf": "foxglove.FrameTransforms",
    "/slam/pose": "vlp_agent.SlamPose",
    "/map": "foxglove.Grid",
    "/commands/received": "vlp_agent.Command",
    "/goals/status": "vlp_agent.GoalState",
    "/health": "vlp_agent.HealthEvent",
    "/fusion/setup": "vlp_agent.FusionSetup",
    "/fusion/input": "vlp_agent.FusionInput",
    "/slam/setup": "vlp_agent.SlamSetup",
    "/slam/input": "vlp_agent.SlamInput",
    "/sim/truth": "vlp_agent.SimTruth",
}

MAP_FRAME = "map"
BASE_FRAME = "base_link"
LASER_FRAME = "laser"


@dataclass(frozen=True, slots=True)
class WheelCommandSample:
    """The wheel speeds sent, and the base velocity they were made from (after the dead-man: 0 when it
    stopped the robot)."""

    host_time_ns: int
    left_radps: float
    right_radps: float
    v_mps: float = 0.0
    omega_radps: float = 0.0


@dataclass(frozen=True, slots=True)
class FusedSample:
    """A pose written on the pose output: the estimate (``agent.fusion.Estimate``) and the flags."""

    estimate: Any
    flags: int


@dataclass(frozen=True, slots=True)
class CommandSample:
    host_time_ns: int
    command: Any  # a firmware_protocol.command_frame command


@dataclass(frozen=True, slots=True)
class GoalSample:
    host_time_ns: int
    status: Any  # firmware_protocol.command_frame.GoalStatus


@dataclass(frozen=True, slots=True)
class HealthSample:
    host_time_ns: int
    device: str
    ok: bool
    reason: str


@dataclass(frozen=True, slots=True)
class SlamScanSample:
    """A scan the SLAM loop gave its mapper: the odometry pose it went with and what the mapper did."""

    scan: Any  # drivers.samples.Scan
    odom_pose: tuple[float, float, float]
    step: str
    restarts: int = 0  # the mapper's SLAM process restarts so far (each one started a new map)


@dataclass(frozen=True, slots=True)
class SlamFixSample:
    """An absolute fix (VLP) the SLAM loop gave its mapper, with the odometry pose at its time."""

    fix: Any  # agent.runtime.types.AbsoluteFix
    odom_pose: tuple[float, float, float]
    restarts: int = 0


@dataclass(frozen=True, slots=True)
class SlamStartSample:
    """What the mapper was told when it asked where its map starts (the fused pose, None: not yet)."""

    t_ns: int
    pose: tuple[float, float, float] | None


@dataclass(frozen=True, slots=True)
class TruthSample:
    """The simulated robot's true base pose at ``t_ns`` (``vlp-agent sim`` only)."""

    t_ns: int
    x_m: float
    y_m: float
    yaw_rad: float


def _time(t_ns: int) -> Message:
    t_ns = max(int(t_ns), 0)
    return {"sec": t_ns // 1_000_000_000, "nsec": t_ns % 1_000_000_000}


def _yaw_quaternion(yaw_rad: float) -> Message:
    return {"x": 0.0, "y": 0.0, "z": math.sin(0.5 * yaw_rad), "w": math.cos(0.5 * yaw_rad)}


def _pose(x_m: float, y_m: float, yaw_rad: float) -> Message:
    return {"position": {"x": x_m, "y": y_m, "z": 0.0}, "orientation": _yaw_quaternion(yaw_rad)}


_IDENTITY = _pose(0.0, 0.0, 0.0)


def _finite_or_none(value: Any) -> float | None:
    if value is None:
        return None
    v = float(value)
    return v if math.isfinite(v) else None


def _plain(value: Any) -> Any:
    """A command's or status's field as JSON: enums by name, None kept."""
    if isinstance(value, enum.Enum):
        return value.name
    if isinstance(value, float):
        return _finite_or_none(value)
    return value


def _fields(obj: Any) -> Message:
    return {f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}


def _scan(scan: Any) -> Iterable[tuple[str, Message]]:
    ranges = scan.ranges_mm
    n = int(ranges.size)
    # The device's error codes (below min_range_mm) and the out-of-range values become 0: JSON has no NaN,
    # and Foxglove skips nothing; /laser/scan_raw keeps the codes.
    metres = np.where(scan.valid_mask(), ranges * 1e-3, 0.0)
    yield (
        "/laser/scan",
        {
            "timestamp": _time(scan.host_time_ns),
            "frame_id": LASER_FRAME,
            "pose": _IDENTITY,
            "start_angle": float(scan.angle_min_rad),
            "end_angle": float(scan.angle_min_rad + scan.angle_increment_rad * max(n - 1, 0)),
            "ranges": metres.tolist(),
            "intensities": [],
        },
    )
    yield (
        "/laser/scan_raw",
        {
            "host_time_ns": int(scan.host_time_ns),
            "device_time_ms": None if scan.device_time_ms is None else int(scan.device_time_ms),
            "sequence": int(scan.sequence),
            "angle_min_rad": float(scan.angle_min_rad),
            "angle_increment_rad": float(scan.angle_increment_rad),
            "min_range_mm": int(scan.min_range_mm),
            "max_range_mm": int(scan.max_range_mm),
            "ranges_mm": ranges.tolist(),
        },
    )


def _wheels(w: Any) -> Iterable[tuple[str, Message]]:
    yield (
        "/wheels/state",
        {
            "host_time_ns": int(w.host_time_ns),
            "position_rad": [float(v) for v in w.position_rad],
            "velocity_radps": [float(v) for v in w.velocity_radps],
            "hardware_error": [int(v) for v in w.hardware_error],
        },
    )


def _wheel_command(c: WheelCommandSample) -> Iterable[tuple[str, Message]]:
    yield (
        "/wheels/command",
        {
            "host_time_ns": c.host_time_ns,
            "left_radps": c.left_radps,
            "right_radps": c.right_radps,
            "v_mps": c.v_mps,
            "omega_radps": c.omega_radps,
        },
    )


def _imu(s: Any) -> Iterable[tuple[str, Message]]:
    yield (
        "/imu",
        {
            "host_time_ns": int(s.host_time_ns),
            "accel_mps2": [float(v) for v in s.accel_mps2],
            "gyro_radps": [float(v) for v in s.gyro_radps],
            "temperature_c": float(s.temperature_c),
        },
    )


def _tag(t: Any) -> Iterable[tuple[str, Message]]:
    yield (
        "/rfid/tags",
        {
            "host_time_ns": int(t.host_time_ns),
            "tag_id": str(t.tag_id),
            "reader": str(t.reader),
            "rssi_dbm": _finite_or_none(t.rssi_dbm),
            "antenna": t.antenna,
            "frequency_khz": t.frequency_khz,
            "phase_deg": _finite_or_none(t.phase_deg),
            "device_time_ms": t.device_time_ms,
        },
    )


def _led(o: Any) -> Message:
    return {
        "track_id": int(o.track_id),
        "id": o.id,
        "id_confidence": float(o.id_confidence),
        "frame_id": o.frame_id,
        "u_px": float(o.centre_px[0]),
        "v_px": float(o.centre_px[1]),
        "radius_px": float(o.radius_px),
        "visibility": str(o.visibility),
        "map_index": None if o.map_index is None else int(o.map_index),
        "used": bool(o.used),
    }


def _vlp_fix(fix: Any) -> Iterable[tuple[str, Message]]:
    detail = fix.detail
    yield (
        "/vlp/fix",
        {
            "t_ns": int(fix.t_ns),
            "x_m": float(fix.x_m),
            "y_m": float(fix.y_m),
            "yaw_rad": _finite_or_none(fix.yaw_rad),
            "covariance": np.asarray(fix.covariance, dtype=np.float64).ravel().tolist(),
            "degraded": bool(fix.degraded),
            "ids": [str(i) for i in detail.get("ids", ())],
            "residual_rms": _finite_or_none(detail.get("residual_rms")),
            "flags": [str(f) for f in detail.get("flags", ())],
            "leds": [_led(o) for o in detail.get("leds", ())],
        },
    )


def _no_fix(n: Any) -> Iterable[tuple[str, Message]]:
    yield ("/vlp/no_fix", {"t_ns": int(n.t_ns), "reason": str(n.reason)})


def _fused(s: FusedSample) -> Iterable[tuple[str, Message]]:
    e = s.estimate
    x, y, yaw = float(e.x_m), float(e.y_m), float(e.yaw_rad)
    pose = _pose(x, y, yaw)
    yield ("/pose", {"timestamp": _time(e.t_ns), "frame_id": MAP_FRAME, "pose": pose})
    yield (
        "/pose/fused",
        {
            "t_ns": int(e.t_ns),
            "version": int(e.version),
            "x_m": x,
            "y_m": y,
            "yaw_rad": yaw,
            "covariance": np.asarray(e.covariance, dtype=np.float64)[:3, :3].ravel().tolist(),
            "flags": int(s.flags),
        },
    )
    yield (
        "/tf",
        {
            "transforms": [
                {
                    "timestamp": _time(e.t_ns),
                    "parent_frame_id": MAP_FRAME,
                    "child_frame_id": BASE_FRAME,
                    "translation": pose["position"],
                    "rotation": pose["orientation"],
                }
            ]
        },
    )


def _slam_pose(fix: Any) -> Iterable[tuple[str, Message]]:
    yield (
        "/slam/pose",
        {
            "t_ns": int(fix.t_ns),
            "x_m": float(fix.x_m),
            "y_m": float(fix.y_m),
            "yaw_rad": float(fix.yaw_rad),
            "covariance": np.asarray(fix.covariance, dtype=np.float64).ravel().tolist(),
        },
    )


def occupancy_cells(pixels: np.ndarray) -> np.ndarray:
    """map_server pixels (row 0 = top) -> int8 occupancy 0..100, -1 unknown, row 0 = the lowest y (as
    ``foxglove.Grid`` and nav_msgs/OccupancyGrid lay rows out). map_saver's unknown grey (205) is -1."""
    p = (255.0 - pixels.astype(np.float64)) / 255.0
    cells = np.rint(100.0 * p).astype(np.int8)
    cells[pixels == 205] = -1
    out: np.ndarray = np.ascontiguousarray(np.flipud(cells))
    return out


def _map(item: tuple[int, Any]) -> Iterable[tuple[str, Message]]:
    t_ns, image = item
    cells = occupancy_cells(image.pixels)
    cols = cells.shape[1]
    ox, oy, oyaw = image.origin
    yield (
        "/map",
        {
            "timestamp": _time(t_ns),
            "frame_id": MAP_FRAME,
            "pose": _pose(float(ox), float(oy), float(oyaw)),
            "column_count": int(cols),
            "cell_size": {"x": float(image.resolution_m), "y": float(image.resolution_m)},
            "row_stride": int(cols),
            "cell_stride": 1,
            "fields": [{"name": "occupancy", "offset": 0, "type": 2}],  # 2: INT8
            "data": base64.b64encode(cells.tobytes()).decode("ascii"),
        },
    )


def _command(c: CommandSample) -> Iterable[tuple[str, Message]]:
    kind = type(c.command).__name__.removesuffix("Command").lower()
    yield ("/commands/received", {"host_time_ns": c.host_time_ns, "kind": kind, "fields": _fields(c.command)})


def _goal(g: GoalSample) -> Iterable[tuple[str, Message]]:
    yield (
        "/goals/status",
        {"host_time_ns": g.host_time_ns, "state": g.status.state.name, "fields": _fields(g.status)},
    )


def _health(h: HealthSample) -> Iterable[tuple[str, Message]]:
    yield ("/health", {"host_time_ns": h.host_time_ns, "device": h.device, "ok": h.ok, "reason": h.reason})


def _fusion_setup(parameters: dict[str, Any]) -> Iterable[tuple[str, Message]]:
    yield ("/fusion/setup", {"parameters": parameters})


def _fusion_input(record: dict[str, Any]) -> Iterable[tuple[str, Message]]:
    # The filter's own record, as it is: its floats survive JSON exactly (repr round-trips), which is what
    # lets a replay reproduce the poses bit for bit.
    yield ("/fusion/input", record)


def _slam_setup(setup: dict[str, Any]) -> Iterable[tuple[str, Message]]:
    yield ("/slam/setup", setup)


def _floats(values: Iterable[Any]) -> list[float]:
    return [float(v) for v in values]


# The SLAM loop's calls into its mapper, in the order it made them (one thread): what a replay feeds a fresh
# mapper. Odometry and fixes are the floats the mapper got (JSON round-trips them exactly); the scan itself
# is on /laser/scan_raw (matched by host_time_ns), not written twice.
def _slam_scan(s: SlamScanSample) -> Iterable[tuple[str, Message]]:
    scan = s.scan
    yield (
        "/slam/input",
        {
            "k": "scan",
            "t": int(scan.host_time_ns),
            "seq": int(scan.sequence),
            "odom": _floats(s.odom_pose),
            "step": s.step,
            "restarts": s.restarts,
        },
    )


def _slam_fix(s: SlamFixSample) -> Iterable[tuple[str, Message]]:
    fix = s.fix
    yield (
        "/slam/input",
        {
            "k": "fix",
            "t": int(fix.t_ns),
            "x": float(fix.x_m),
            "y": float(fix.y_m),
            "yaw": None if fix.yaw_rad is None else float(fix.yaw_rad),
            "cov": np.asarray(fix.covariance, dtype=np.float64).ravel().tolist(),
            "odom": _floats(s.odom_pose),
            "restarts": s.restarts,
        },
    )


def _slam_start(s: SlamStartSample) -> Iterable[tuple[str, Message]]:
    yield (
        "/slam/input",
        {"k": "start", "t": int(s.t_ns), "pose": None if s.pose is None else _floats(s.pose)},
    )


def _truth(s: TruthSample) -> Iterable[tuple[str, Message]]:
    yield ("/sim/truth", {"t_ns": int(s.t_ns), "x_m": s.x_m, "y_m": s.y_m, "yaw_rad": s.yaw_rad})


def fusion_record_time(record: dict[str, Any]) -> int:
    """A fusion input's log time: when it arrived, else when it was measured."""
    for key in ("a", "t", "t1"):
        value = record.get(key)
        if value is not None:
            return int(value)
    return 0


# kind -> converter. The loops name the kind; one kind may give several channels (a scan: the Foxglove
# view and the raw one; a written pose: the pose, its detail and the transform).
KINDS: dict[str, Callable[[Any], Iterable[tuple[str, Message]]]] = {
    "scan": _scan,
    "wheels": _wheels,
    "wheel_command": _wheel_command,
    "imu": _imu,
    "tag": _tag,
    "vlp_fix": _vlp_fix,
    "no_fix": _no_fix,
    "pose": _fused,
    "slam_pose": _slam_pose,
    "map": _map,
    "command": _command,
    "goal_status": _goal,
    "health": _health,
    "fusion_setup": _fusion_setup,
    "fusion_input": _fusion_input,
    "slam_setup": _slam_setup,
    "slam_scan": _slam_scan,
    "slam_fix": _slam_fix,
    "slam_start": _slam_start,
    "sim_truth": _truth,
}


def messages_for(kind: str, sample: Any) -> list[tuple[str, Message]]:
    """The channel messages of one sample of ``kind`` (KeyError: not a kind the recording knows)."""
    return list(KINDS[kind](sample))
