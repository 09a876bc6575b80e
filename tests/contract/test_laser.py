"""The laser scanner contract: what any ``LaserScanner`` backend must do, checked on the fake URG and, when
``VLP_TEST_URG_PORT`` names a port (e.g. ``/dev/ttyACM0``), on a real URG.

Only facts that hold for every URG are checked: device information, a one-shot scan of 682 beams over
about 240 degrees, ~10 Hz streaming with a rising device clock, stop/start, an idempotent close.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from drivers.errors import DeviceDisconnected, DeviceError
from drivers.fakes.pty import PtyServer
from drivers.fakes.urg import FakeUrg
from drivers.laser.base import LaserScanner
from drivers.registry import DeviceKind, backend_class
from drivers.sim.simulation import Simulation
from drivers.sim.world import Pose2D, RobotSpec, Wall, World

HARDWARE_PORT = os.environ.get("VLP_TEST_URG_PORT")


def _world() -> World:
    walls = (Wall(-3.0, -2.0, 4.0, -2.0), Wall(4.0, -2.0, 4.0, 2.5), Wall(4.0, 2.5, -3.0, 2.5),
             Wall(-3.0, 2.5, -3.0, -2.0))  # fmt: skip
    return World("contract room", walls=walls, robot=RobotSpec(start=Pose2D(0.0, 0.0, 0.0)))


@pytest.fixture(params=["fake", pytest.param("hardware", marks=pytest.mark.hardware)])
def laser(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[LaserScanner]:
    """An open laser: the fake URG on a pty, or the real one at ``VLP_TEST_URG_PORT``."""
    urg = backend_class(DeviceKind.LASER, "urg")  # through the registry, as the agent picks it
    if request.param == "hardware":
        if not HARDWARE_PORT:
            pytest.skip("set VLP_TEST_URG_PORT to the URG's port to run the contract on hardware")
        dev: LaserScanner = urg(HARDWARE_PORT)
        dev.open()
        try:
            yield dev
        finally:
            dev.close()
        return
    with PtyServer(FakeUrg(Simulation(_world())), link=tmp_path / "urg") as server:
        dev = urg(server.path)
        dev.open()
        try:
            yield dev
        finally:
            dev.close()


def test_info_is_sane(laser: LaserScanner) -> None:
    info = laser.info()
    assert info.model and info.serial and info.firmware
    assert 0 < info.min_range_mm < info.max_range_mm
    assert info.steps_per_rev > 0 and info.scan_rpm > 0
    assert 0 <= info.first_step <= info.front_step <= info.last_step < info.steps_per_rev
    assert 0.01 < info.scan_period_s < 1.0
    assert laser.health().connected


def test_scan_once_covers_240_degrees(laser: LaserScanner) -> None:
    info = laser.info()
    scan = laser.scan_once(timeout_s=2.0)
    assert scan.ranges_mm.dtype == np.int32 and scan.ranges_mm.shape == (682,)
    span_deg = math.degrees(scan.angles_rad()[-1] - scan.angles_rad()[0])
    assert span_deg == pytest.approx(240.0, abs=1.0)
    assert scan.angle_min_rad < 0.0 < scan.angle_min_rad + scan.angle_increment_rad * 681
    assert (scan.min_range_mm, scan.max_range_mm) == (info.min_range_mm, info.max_range_mm)
    assert np.all(scan.ranges_mm >= 0) and np.all(scan.ranges_mm <= 262143)
    assert scan.valid_mask().sum() > 100  # a sensor indoors sees walls
    assert scan.device_time_ms is not None and scan.host_time_ns > 0


def test_streaming_at_about_10_hz(laser: LaserScanner) -> None:
    laser.start()
    assert laser.streaming
    scans = [laser.read(timeout_s=2.0) for _ in range(12)]
    device = np.asarray([s.device_time_ms for s in scans], dtype=np.int64)
    period_ms = np.diff(device)
    assert np.all(period_ms > 0)
    assert np.median(period_ms) == pytest.approx(1000.0 * laser.info().scan_period_s, rel=0.1)
    assert np.all(np.diff([s.host_time_ns for s in scans]) > 0)
    assert np.all(np.diff([s.sequence for s in scans]) > 0)
    assert all(s.ranges_mm.shape == (682,) for s in scans)
    laser.stop()
    assert not laser.streaming


def test_stop_then_start_again(laser: LaserScanner) -> None:
    laser.start()
    first = laser.read(timeout_s=2.0)
    laser.stop()
    with pytest.raises(DeviceError, match="not streaming"):
        for _ in range(10):  # what was already queued may still be read
            laser.read(timeout_s=0.5)
    assert laser.scan_once(timeout_s=2.0).ranges_mm.shape == (682,)  # one-shot works between streams
    laser.start()
    again = laser.read(timeout_s=2.0)
    assert again.sequence > first.sequence
    assert again.device_time_ms is not None and first.device_time_ms is not None
    assert again.device_time_ms > first.device_time_ms
    laser.stop()


def test_close_is_idempotent(laser: LaserScanner) -> None:
    laser.start()
    laser.read(timeout_s=2.0)
    laser.close()
    laser.close()
    assert not laser.is_open and not laser.health().connected
    with pytest.raises(DeviceDisconnected):
        laser.read(timeout_s=0.1)
