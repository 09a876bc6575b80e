"""`vlp-agent sim` and `vlp-agent fake` end to end, as a user runs them (separate processes)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
ENV1 = REPO / "examples" / "worlds" / "env1.toml"


def vlp_agent(*args: str) -> list[str]:
    return [sys.executable, "-m", "agent.cli", *args]


def test_sim_drives_the_route_through_every_device() -> None:
    out = subprocess.run(
        vlp_agent("sim", "--seconds", "4", "--json"),
        capture_output=True,
        text=True,
        timeout=60,
        cwd=REPO,
        check=False,
    )
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout)
    assert summary["world"] == "office"
    # The laser streams at its real 10 Hz, the camera at the world's 30 fps, the drive loop at 20 Hz.
    assert summary["scans"] >= 30
    assert summary["frames"] >= 80
    assert summary["imu_samples"] >= 50
    # The office ceiling is laid out so that at least two LEDs are always in view.
    assert summary["leds_in_view_mean"] >= 2.0
    # The robot moved only because the fake servos received Dynamixel velocity commands.
    assert summary["distance_m"] > 0.4
    assert summary["odometry_error_m_max"] < 0.05
    assert summary["device_errors"] == {}
    assert "not built yet" in summary["stage"]


def test_sim_on_env1_writes_a_trajectory(tmp_path: Path) -> None:
    png = tmp_path / "traj.png"
    out = subprocess.run(
        vlp_agent("sim", "--world", str(ENV1), "--seconds", "2", "--trajectory", str(png)),
        capture_output=True,
        text=True,
        timeout=60,
        cwd=REPO,
        check=False,
    )
    assert out.returncode == 0, out.stderr
    assert "vlp-agent sim on world" in out.stdout
    assert png.stat().st_size > 1000


def test_sim_with_a_missing_world_says_so() -> None:
    out = subprocess.run(
        vlp_agent("sim", "--world", "/nonexistent/world.toml"),
        capture_output=True,
        text=True,
        timeout=30,
        cwd=REPO,
        check=False,
    )
    assert out.returncode == 1
    assert "no such world file" in out.stderr
    assert "Traceback" not in out.stderr


@pytest.mark.parametrize("device", ["urg", "dynamixel", "rfid"])
def test_fake_prints_its_path_first_and_serves_until_interrupted(device: str) -> None:
    proc = subprocess.Popen(
        vlp_agent("fake", device), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO
    )
    try:
        assert proc.stdout is not None
        path = proc.stdout.readline().strip()
        assert path.startswith("/dev/pts/"), path
        assert os.path.exists(path)
        if device == "urg":
            from drivers.laser.urg import UrgLaser

            with UrgLaser(path) as laser:
                assert laser.info().model.startswith("URG-04LX")
                scan = laser.scan_once(timeout_s=2.0)
                assert scan.ranges_mm.size == 682
        elif device == "dynamixel":
            from dynamixel_sdk import COMM_SUCCESS, PacketHandler, PortHandler

            port = PortHandler(path)
            assert port.openPort()
            try:
                model, result, error = PacketHandler(2.0).ping(port, 1)
                assert (result, error, model) == (COMM_SUCCESS, 0, 1060)
            finally:
                port.closePort()
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=5) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
