"""With MAVLink selected, pymavlink decodes the pose stream the agent writes on a pty, and the poses are
the same as the simulation's truth (in MAVLink's z-down frame)."""

from __future__ import annotations

import math
import os
from pathlib import Path

import pytest

from tests.integration.test_agent_accuracy import PtyReader, read_truth, run_sim


@pytest.mark.parametrize("message", ["vision_position_estimate", "odometry"])
def test_pymavlink_decodes_the_stream(tmp_path: Path, message: str) -> None:
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink.dialects.v20 import common

    config = tmp_path / "mavlink.toml"
    examples = Path(__file__).resolve().parents[2] / "examples"
    config.write_text(
        (examples / "sim.toml")
        .read_text()
        .replace('"worlds/office.toml"', f'"{examples}/worlds/office.toml"')
        .replace('format = "frame"', f'format = "mavlink"\nmavlink_message = "{message}"\nmavlink_sysid = 42')
    )
    reader = PtyReader()
    try:
        summary = run_sim(tmp_path, reader, "--config", str(config), "--seconds", "5")
    finally:
        data = reader.close()
    assert summary["output_format"] == "mavlink"
    parser = common.MAVLink(None)
    messages = [m for m in parser.parse_buffer(data[1:]) or [] if m.get_type() != "BAD_DATA"]
    assert len(messages) == summary["frames_out"] and len(messages) >= 5 * 20 * 0.8
    assert {m.get_type() for m in messages} == {message.upper()}
    assert all(m.get_srcSystem() == 42 and m.get_srcComponent() == 197 for m in messages)
    truth = read_truth(tmp_path / "truth.csv")
    errors = []
    yaw_errors = []
    times = []
    # MAVLink's 8-bit header sequence wraps: match the messages to the truth by their time stamps.
    by_time = {t_us: (x, y, yaw) for t_us, x, y, yaw in truth.values()}
    for m in messages:
        t_us = m.usec if message == "vision_position_estimate" else m.time_usec
        x, y, yaw = by_time[t_us]
        # Map (z up, yaw counter-clockwise) -> MAVLink local FRD (z down): (x, -y, -yaw).
        errors.append(math.hypot(m.x - x, m.y + y))
        times.append(t_us)
        mav_yaw = m.yaw if message == "vision_position_estimate" else 2.0 * math.atan2(m.q[3], m.q[0])
        yaw_errors.append(abs(math.remainder(mav_yaw + yaw, math.tau)))
    off = [
        (round((t - times[0]) * 1e-6, 2), round(100 * e, 1))
        for t, e in zip(times, errors, strict=True)
        if e > 0.02
    ]
    # On failure, also what the agent fused and dropped: a stall of the machine (late odometry and frames)
    # and a SLAM pose fused off the VLP track look alike in the error alone.
    keys = ("fixes", "fixes_fused", "fixes_rejected", "no_fix_reasons", "counts")
    diagnosis = {k: summary.get(k) for k in keys}
    assert sum(e <= 0.02 for e in errors) / len(errors) >= 0.95, (
        f"(s after the first, cm) over 2 cm: {off}; {diagnosis}"
    )
    yaw_off = [
        (round((t - times[0]) * 1e-6, 2), round(math.degrees(e), 2))
        for t, e in zip(times, yaw_errors, strict=True)
        if e >= math.radians(2.0)
    ]
    assert not yaw_off, f"(s after the first, deg) yaw 2 deg or more off: {yaw_off}; {diagnosis}"
