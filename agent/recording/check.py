"""A ``vlp-agent sim`` recording checked against the run that made it, pure (messages and the run's JSON
summary in, a verdict out): every channel there, each one's count equal to what the agent itself counted
(nothing lost between a loop and the file), and the periodic ones at their device's rate.

Rates are measured on the recording's own stamps, not on anyone's wall clock: a channel's count over the
time its device was up, from the device's first ``/health`` "up" to the recording's last message, less the
spells the device was bad (a fault injected, a reconnect). A run that started late or a device that came
up late beside a busy machine is then no slower for it; a loop that missed its period, or samples lost on
the way, are. The VLP result of each frame (``/vlp/fix`` or ``/vlp/no_fix``) is also counted against the
camera frames the agent took, and those against the camera's rate.

:func:`expected_rates` gives the rates of the simulated robot's devices (the world's laser and camera, the
IMU loop's period, ``control.loop_rate_hz`` for the servo loop); :func:`check_channels` compares. The
benchmark ``benchmarks/recording_check.py`` and the whole-agent test use both, with their own tolerances.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from agent.recording.messages import CHANNELS
from agent.recording.reader import RecordedMessage

__all__ = ["Rate", "Tolerance", "check_channels", "device_up_s", "expected_rates"]


@dataclass(frozen=True)
class Rate:
    """A periodic channel: the device whose up-time it is measured over and its rate."""

    device: str
    hz: float
    source: str  # where the figure comes from


@dataclass(frozen=True)
class Tolerance:
    """How far a measured rate may be from the expected one (as a ratio), and the least share of camera
    frames that must have a VLP result (a fix or a reason for none)."""

    rate_low: float = 0.9
    rate_high: float = 1.1
    results_per_frame_low: float = 0.95


# The camera's frames are not a channel of their own: the VLP results (one per frame handled) stand for them.
FRAMES = "/vlp/fix+/vlp/no_fix"


def expected_rates(*, laser_hz: float, camera_hz: float, imu_hz: float, servo_hz: float) -> dict[str, Rate]:
    """The periodic channels of a recording and the rates their devices run at."""
    return {
        "/laser/scan": Rate("laser", laser_hz, "the laser's scan rate"),
        "/laser/scan_raw": Rate("laser", laser_hz, "the laser's scan rate"),
        "/imu": Rate("imu", imu_hz, "the IMU loop's period"),
        "/wheels/state": Rate("servos", servo_hz, "control.loop_rate_hz"),
        "/wheels/command": Rate("servos", servo_hz, "control.loop_rate_hz"),
        FRAMES: Rate("camera", camera_hz, "the camera's frame rate"),
    }


def device_up_s(messages: Iterable[RecordedMessage], end_ns: int) -> dict[str, float]:
    """Seconds each device was up by the ``/health`` events: from its first "ok" to ``end_ns``, less the
    spells between an event that said it went bad and the next that said it was ok again."""
    up: dict[str, float] = {}
    since: dict[str, int | None] = {}
    for m in messages:
        if m.topic != "/health":
            continue
        device, ok, t = str(m.data["device"]), bool(m.data["ok"]), m.log_time_ns
        if ok and since.get(device) is None:
            since[device] = t
        elif not ok and since.get(device) is not None:
            start = since[device]
            assert start is not None
            up[device] = up.get(device, 0.0) + (t - start) / 1e9
            since[device] = None
        up.setdefault(device, 0.0)
    for device, start in since.items():
        if start is not None:
            up[device] += max(end_ns - start, 0) / 1e9
    return up


def _agent_counts(summary: Mapping[str, Any]) -> dict[str, int]:
    """What the agent counted itself (the run's JSON summary) for each channel it counts."""
    counts = summary.get("counts", {})
    goals = summary.get("goals") or {}
    slam = counts.get("slam_fused", 0) + counts.get("slam_rejected", 0)
    out = {
        "/laser/scan": counts.get("scans", 0),
        "/laser/scan_raw": counts.get("scans", 0),
        "/wheels/state": counts.get("wheel_reads", 0),
        "/imu": counts.get("imu_samples", 0),
        "/rfid/tags": counts.get("tag_reads", 0),
        "/vlp/fix": summary.get("fixes", 0),
        "/vlp/no_fix": summary.get("no_fix", 0),
        "/pose": summary.get("frames_out", 0),
        "/pose/fused": summary.get("frames_out", 0),
        "/tf": summary.get("frames_out", 0),
        "/slam/pose": slam,
        "/fusion/setup": 1,
        "/goals/status": goals.get("statuses_decoded", 0),
    }
    if summary.get("slam"):
        out["/slam/setup"] = 1
    return out


def _optional(summary: Mapping[str, Any]) -> set[str]:
    """Channels a run may rightly leave empty: no tag passed, every frame gave a fix, no goal sent, no
    SLAM."""
    counts = summary.get("counts", {})
    out = set()
    if not counts.get("tag_reads"):
        out.add("/rfid/tags")
    if not summary.get("no_fix"):
        out.add("/vlp/no_fix")
    if not summary.get("goals"):
        out |= {"/commands/received", "/goals/status"}
    if not summary.get("slam"):
        out |= {"/slam/setup", "/slam/input", "/slam/pose", "/map"}
    return out


def _fail(entry: dict[str, Any], why: str) -> None:
    entry["ok"] = False
    entry["why"] = f"{entry['why']}; {why}" if entry["why"] else why


def check_channels(
    messages: list[RecordedMessage],
    summary: Mapping[str, Any],
    rates: Mapping[str, Rate],
    tolerance: Tolerance = Tolerance(),
    map_period_s: float = 0.0,
) -> dict[str, Any]:
    """Per channel: ``count``, ``agent_count`` (None: the agent does not count it), and for the periodic
    ones ``expected_hz``, ``up_s``, ``rate_hz``, ``ratio``; ``ok`` and ``why`` (empty when ok). Returns
    ``{"channels": ..., "up_s": per device, "span_s": the recording's, "failures": [...]}``."""
    by_topic: dict[str, int] = {}
    for m in messages:
        by_topic[m.topic] = by_topic.get(m.topic, 0) + 1
    if not messages:
        return {"channels": {}, "up_s": {}, "span_s": 0.0, "failures": ["the recording holds no message"]}
    first_ns = min(m.log_time_ns for m in messages)
    end_ns = max(m.log_time_ns for m in messages)
    up = device_up_s(messages, end_ns)
    agent = _agent_counts(summary)
    optional = _optional(summary)
    channels: dict[str, dict[str, Any]] = {}
    for topic in sorted(CHANNELS):
        n = by_topic.get(topic, 0)
        problems: list[str] = []
        if n == 0 and topic not in optional:
            problems.append("missing")
        expected_n = agent.get(topic)
        if expected_n is not None and n != expected_n:
            problems.append(f"{n} recorded, the agent counted {expected_n}")
        channels[topic] = {"count": n, "agent_count": expected_n}
        if topic == "/map" and n and map_period_s > 0:
            most = int((end_ns - first_ns) / 1e9 / map_period_s) + 1
            channels[topic]["at_most"] = most
            if n > most:
                problems.append(f"{n} map snapshots, more than one per {map_period_s:g} s ({most})")
        channels[topic]["ok"], channels[topic]["why"] = not problems, "; ".join(problems)
    frames = by_topic.get("/vlp/fix", 0) + by_topic.get("/vlp/no_fix", 0)
    for topic, rate in rates.items():
        n = frames if topic == FRAMES else by_topic.get(topic, 0)
        up_s = up.get(rate.device, 0.0)
        measured = n / up_s if up_s > 0 else 0.0
        ratio = measured / rate.hz
        entry = channels.setdefault(topic, {"count": n, "agent_count": None, "ok": True, "why": ""})
        entry.update(
            expected_hz=rate.hz,
            source=rate.source,
            device=rate.device,
            up_s=round(up_s, 3),
            rate_hz=round(measured, 3),
            ratio=round(ratio, 4),
        )
        if not tolerance.rate_low <= ratio <= tolerance.rate_high:
            _fail(entry, f"{measured:.2f} Hz over {up_s:.1f} s up, expected {rate.hz:g} Hz ({rate.source})")
    camera_frames = int(summary.get("camera_frames", 0))
    per_frame = frames / camera_frames if camera_frames else 0.0
    entry = channels[FRAMES]
    entry.update(camera_frames=camera_frames, results_per_frame=round(per_frame, 4))
    if not tolerance.results_per_frame_low <= per_frame <= 1.0:
        _fail(entry, f"{frames} VLP results for {camera_frames} camera frames")
    failures = [f"{topic}: {c['why']}" for topic, c in channels.items() if not c["ok"]]
    return {
        "channels": channels,
        "up_s": {k: round(v, 3) for k, v in sorted(up.items())},
        "span_s": round((end_ns - first_ns) / 1e9, 3),
        "failures": failures,
    }
