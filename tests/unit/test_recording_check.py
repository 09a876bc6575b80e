"""``agent.recording.check``: a recording's counts against the agent's and its rates against the devices',
each rate over the time its device was up by the recording's ``/health`` stamps."""

from __future__ import annotations

from typing import Any

import pytest

from agent.recording.check import FRAMES, Tolerance, check_channels, device_up_s, expected_rates
from agent.recording.messages import CHANNELS
from agent.recording.reader import RecordedMessage

S = 1_000_000_000
RATES = expected_rates(laser_hz=10.0, camera_hz=30.0, imu_hz=100.0, servo_hz=50.0)


def health(t_s: float, device: str, ok: bool) -> RecordedMessage:
    data = {"host_time_ns": round(t_s * S), "device": device, "ok": ok, "reason": "" if ok else "lost"}
    return RecordedMessage("/health", CHANNELS["/health"], round(t_s * S), data)


def periodic(topic: str, hz: float, start_s: float, end_s: float, skip: tuple[float, float] = (0, 0)) -> list:
    out = []
    k = 0
    while (t := start_s + k / hz) < end_s:
        if not skip[0] <= t < skip[1]:
            out.append(RecordedMessage(topic, CHANNELS[topic], round(t * S), {}))
        k += 1
    return out


def run(laser_hz: float = 10.0, imu_gap: tuple[float, float] = (0, 0)) -> tuple[list, dict[str, Any]]:
    """20 s: every device up at 1 s, the laser down from 8 to 10 s; one message of each other channel."""
    messages = [health(1.0, d, True) for d in ("laser", "imu", "servos", "camera")]
    messages += [health(8.0, "laser", False), health(10.0, "laser", True)]
    messages += periodic("/laser/scan", laser_hz, 1.0, 21.0, skip=(8.0, 10.0))
    messages += periodic("/laser/scan_raw", laser_hz, 1.0, 21.0, skip=(8.0, 10.0))
    messages += periodic("/imu", 100.0, 1.0, 21.0, skip=imu_gap)
    messages += periodic("/wheels/state", 50.0, 1.0, 21.0) + periodic("/wheels/command", 50.0, 1.0, 21.0)
    messages += periodic("/vlp/fix", 30.0, 1.0, 21.0)
    for topic in set(CHANNELS) - {m.topic for m in messages} - {"/vlp/no_fix", "/rfid/tags"}:
        messages.append(RecordedMessage(topic, CHANNELS[topic], 2 * S, {}))
    n = {t: sum(m.topic == t for m in messages) for t in CHANNELS}
    summary = {
        "counts": {"scans": n["/laser/scan"], "wheel_reads": n["/wheels/state"], "imu_samples": n["/imu"]},
        "fixes": n["/vlp/fix"],
        "no_fix": 0,
        "frames_out": 1,
        "camera_frames": n["/vlp/fix"],
        "goals": {"statuses_decoded": 1},
        "slam": {"filter_updates": 1},
    }
    summary["counts"]["slam_fused"] = 1
    return sorted(messages, key=lambda m: m.log_time_ns), summary


def test_up_time_is_from_the_first_up_to_the_end_less_the_bad_spells() -> None:
    messages, _ = run()
    up = device_up_s(messages, 21 * S)
    assert up["laser"] == pytest.approx(18.0) and up["imu"] == pytest.approx(20.0)


def test_a_run_at_its_rates_passes_with_every_channel_counted() -> None:
    messages, summary = run()
    checked = check_channels(messages, summary, RATES, Tolerance())
    assert checked["failures"] == []
    scans = checked["channels"]["/laser/scan"]
    assert scans["up_s"] == pytest.approx(18.0, abs=0.02) and scans["ratio"] == pytest.approx(1.0, abs=0.01)
    assert checked["channels"][FRAMES]["results_per_frame"] == 1.0


def test_a_slow_loop_a_gap_a_lost_sample_and_a_missing_channel_each_fail() -> None:
    messages, summary = run(laser_hz=8.0)  # the laser's loop at 8 Hz: 20 % short
    failures = check_channels(messages, summary, RATES, Tolerance())["failures"]
    assert [f.split(":")[0] for f in failures] == ["/laser/scan", "/laser/scan_raw"]
    # Three seconds without IMU samples while the IMU was said to be up: 15 % short.
    messages, summary = run(imu_gap=(5.0, 8.0))
    assert [f.split(":")[0] for f in check_channels(messages, summary, RATES)["failures"]] == ["/imu"]
    # One sample the agent counted is not in the file; a channel is missing altogether.
    messages, summary = run()
    messages = [m for m in messages if m.topic != "/map"]
    summary["counts"]["imu_samples"] += 1
    failures = check_channels(messages, summary, RATES)["failures"]
    assert any(f.startswith("/imu: 2000 recorded, the agent counted 2001") for f in failures), failures
    assert "/map: missing" in failures
    # Fewer VLP results than camera frames.
    messages, summary = run()
    summary["camera_frames"] = 700
    failures = check_channels(messages, summary, RATES)["failures"]
    assert [f.split(":")[0] for f in failures] == [FRAMES]
