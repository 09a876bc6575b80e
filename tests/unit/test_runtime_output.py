"""The pose stream writer on a real pseudo-terminal: the bytes a controller receives, in both formats."""

from __future__ import annotations

import math
import os
import select
import tty
from collections.abc import Iterator

import numpy as np
import pytest

from agent.config import OutputConfig, OutputFormat
from agent.fusion import Estimate
from agent.runtime.output import PoseOutput, Written, quality_for
from drivers.errors import DeviceNotFound
from firmware_protocol.pose_frame import WIRE_LENGTH, PoseFlags, PoseFrameDecoder

LIVE = PoseFlags.VLP | PoseFlags.ODOMETRY | PoseFlags.IMU


@pytest.fixture
def pty() -> Iterator[tuple[int, str]]:
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    try:
        yield master, os.ttyname(slave)
    finally:
        os.close(master)
        os.close(slave)


def read_all(fd: int) -> bytes:
    data = b""
    while select.select([fd], [], [], 0.05)[0]:
        data += os.read(fd, 65536)
    return data


def estimate(k: int) -> Estimate:
    cov = np.diag([0.003**2, 0.002**2, 0.01**2, 0.0, 0.0])
    return Estimate(1_000_000_000 + k * 33_000_000, 1.0 + 0.01 * k, -2.0, 0.5, 0.0, 0.0, cov, 0)


def test_frames_decode_in_order_after_the_leading_zero(pty: tuple[int, str]) -> None:
    master, path = pty
    written: list[Written] = []
    out = PoseOutput(OutputConfig(url=path), path, observer=written.append)
    out.open()
    for k in range(5):
        out.publish(estimate(k), LIVE, trigger_ns=estimate(k).t_ns - 20_000_000, arrival_ns=estimate(k).t_ns)
    out.close()
    data = read_all(master)
    assert data[0] == 0 and len(data) == 1 + 5 * WIRE_LENGTH
    frames = PoseFrameDecoder().feed(data)
    assert [f.sequence for f in frames] == [0, 1, 2, 3, 4]
    assert [f.t_us for f in frames] == [estimate(k).t_ns // 1000 for k in range(5)]
    assert frames[3].x_m == pytest.approx(1.03, abs=1e-4) and frames[3].y_m == pytest.approx(-2.0, abs=1e-4)
    assert frames[0].flags == LIVE
    assert frames[0].sigma_xy_m == pytest.approx(0.003, abs=1e-4)
    assert [w.frame.sequence for w in written] == [0, 1, 2, 3, 4]
    assert len(out.latency) == 5 and len(out.exposure_age) == 5
    assert out.counts["frames"] == 5


@pytest.mark.parametrize("message", ["vision_position_estimate", "odometry"])
def test_mavlink_is_decoded_by_pymavlink(pty: tuple[int, str], message: str) -> None:
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink.dialects.v20 import common

    master, path = pty
    config = OutputConfig(format=OutputFormat.MAVLINK, url=path, mavlink_message=message, mavlink_sysid=7)
    out = PoseOutput(config, path)
    out.open()
    for k in range(3):
        out.publish(estimate(k), LIVE)
    out.close()
    parser = common.MAVLink(None)
    messages = [m for m in parser.parse_buffer(read_all(master)[1:]) or []]
    assert [m.get_type() for m in messages] == [message.upper()] * 3
    assert all(m.get_srcSystem() == 7 for m in messages)
    first = messages[0]
    assert (first.x, first.y) == pytest.approx((1.0, 2.0), abs=1e-5)  # FRD: y flipped
    if message == "odometry":
        assert first.quality == quality_for(LIVE) == 100


def test_a_receiver_that_stops_reading_costs_frames_not_the_hot_path(pty: tuple[int, str]) -> None:
    master, path = pty
    out = PoseOutput(OutputConfig(url=path, write_timeout_s=0.002), path)
    out.open()
    k = 0
    while out.counts["write_timeouts"] == 0 and k < 10_000:
        out.publish(estimate(k), LIVE)
        k += 1
    assert out.counts["write_timeouts"] >= 1  # the pty filled: a frame was cut, counted
    data = read_all(master)
    for j in range(3):  # the receiver reads again: the next frames arrive whole
        assert out.publish(estimate(k + j), LIVE) is not None
    data += read_all(master)
    decoder = PoseFrameDecoder()
    frames = decoder.feed(data)
    assert [f.sequence for f in frames[-3:]] == [k, k + 1, k + 2]
    assert frames[-1].x_m == pytest.approx(estimate(k + 2).x_m, abs=1e-4)
    assert decoder.bad_frames <= 1  # only the cut frame, ended by the 0x00 sent ahead of the next
    out.close()


def test_a_missing_port_is_reported_and_retried() -> None:
    out = PoseOutput(OutputConfig(url="/nonexistent/tty"), "/nonexistent/tty", reopen_interval_s=0.0)
    with pytest.raises(DeviceNotFound, match="/nonexistent/tty"):
        out.open()
    assert out.publish(estimate(0), LIVE) is None
    assert out.counts["skipped_port_down"] == 1


def test_quality_follows_the_sources() -> None:
    assert quality_for(PoseFlags.SLAM | PoseFlags.ODOMETRY) == 70
    assert quality_for(PoseFlags.ODOMETRY) == 30
    assert quality_for(PoseFlags.LASER_LOST) == -1
    assert math.isfinite(estimate(0).sigma_yaw_rad)
