"""``vlp-agent run``, the service entry: what systemd hears from it, and that a hung critical loop stops the
watchdog pings (so systemd restarts the agent) while a device that is merely unplugged does not."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from agent.config import parse_config
from agent.runtime import create_agent
from agent.runtime.devices import build_devices
from drivers.camera.base import Camera, CameraSettings
from drivers.samples import Frame
from drivers.sim.harness import SimulatedRobot
from tests.integration.test_agent_accuracy import REPO, vlp_agent

OFFICE = REPO / "examples" / "worlds" / "office.toml"


def test_run_tells_systemd_ready_watchdog_status_and_stopping(tmp_path: Path) -> None:
    notify_path = tmp_path / "notify.sock"
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(notify_path))
    notify.settimeout(0.2)
    config = tmp_path / "robot.toml"
    config.write_text((REPO / "examples" / "sim.toml").read_text().replace('"worlds/', f'"{OFFICE.parent}/'))
    env = {**os.environ, "NOTIFY_SOCKET": str(notify_path), "WATCHDOG_USEC": "1000000"}
    proc = subprocess.Popen(
        vlp_agent("run", "--config", str(config), "--seconds", "6", "--json"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
        env=env,
    )
    messages: list[str] = []
    ping_times: list[float] = []
    try:
        while proc.poll() is None:
            try:
                message = notify.recv(4096).decode()
            except TimeoutError:
                continue
            messages.append(message)
            if "WATCHDOG=1" in message.split("\n"):
                ping_times.append(time.monotonic())
        stdout, stderr = proc.communicate(timeout=30)
        while True:
            try:
                messages.append(notify.recv(4096).decode())
            except (TimeoutError, BlockingIOError):
                break
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        notify.close()
    assert proc.returncode == 0, stderr[-2000:]
    fields = [line for m in messages for line in m.split("\n")]
    ready = [i for i, f in enumerate(fields) if f == "READY=1"]
    pings = [i for i, f in enumerate(fields) if f == "WATCHDOG=1"]
    assert len(ready) == 1
    assert len(pings) >= 3 and min(pings) > ready[0]  # every 0.5 s once ready, for the rest of the run
    # At the configured interval: half of WATCHDOG_USEC (1 s), as sd_watchdog_enabled(3) advises.
    intervals = np.diff(ping_times)
    assert 0.3 <= float(np.median(intervals)) <= 0.7, intervals
    assert float(intervals.max()) < 1.0, intervals  # never as late as the watchdog itself
    assert any(f.startswith("STATUS=pose (") for f in fields)
    stopping = [i for i, f in enumerate(fields) if f == "STOPPING=1"]
    assert len(stopping) == 1 and stopping[0] > max(pings)
    summary = json.loads(stdout)
    assert summary["frames_received"] > 0  # "pty": read back by the simulated controller


class HangingCamera(Camera):
    """A driver stuck in a call that never returns (a wedged USB transfer): the loop cannot beat."""

    def __init__(self) -> None:
        super().__init__("hanging-camera", CameraSettings())
        self.release = threading.Event()

    def _open(self) -> None:
        pass

    def _close(self) -> None:
        self.release.set()

    def settings(self) -> CameraSettings:
        return self.requested

    def _acquire(self, timeout_s: float) -> tuple[Frame, Callable[[], None]]:
        self.release.wait()
        return Frame(np.zeros((600, 800), np.uint8), 0, time.monotonic_ns()), lambda: None


@dataclass
class Notifier:
    watchdog_interval_s: float | None = 0.25
    sent: list[str] = field(default_factory=list)

    def ready(self, status: str | None = None) -> bool:
        self.sent.append("READY")
        return True

    def status(self, text: str) -> bool:
        return True

    def watchdog_ping_if(self, all_alive: bool) -> bool:
        self.sent.append("WATCHDOG" if all_alive else "WITHHELD")
        return all_alive

    def stopping(self, status: str | None = None) -> bool:
        self.sent.append("STOPPING")
        return True


def test_a_hung_critical_loop_withholds_the_watchdog_and_an_unplugged_device_does_not() -> None:
    config = parse_config(
        f'[sim]\nworld = "{OFFICE}"\n[rfid]\nenabled = false\n[health]\nloop_timeout_s = 1.0\n',
        str(OFFICE.parent / "c.toml"),
    )
    assert config.sim is not None
    with SimulatedRobot(config.sim.world) as robot:
        devices = build_devices(config, robot)
        notifier = Notifier()
        agent = create_agent(config, robot=robot, notifier=notifier, output_url=None, devices=devices)
        agent.start()
        try:
            deadline = time.monotonic() + 20
            while "READY" not in notifier.sent or notifier.sent.count("WATCHDOG") < 2:
                assert time.monotonic() < deadline
                time.sleep(0.05)
            # The laser unplugged: a device fault, reported; its loop keeps beating, the pings go on.
            robot.unplug("laser")
            time.sleep(1.5)
            assert not agent.status().devices["laser"].ok
            assert agent.health.check().all_critical_alive
            pings = notifier.sent.count("WATCHDOG")
            time.sleep(0.6)
            assert notifier.sent.count("WATCHDOG") > pings
            robot.replug("laser")
        finally:
            agent.stop()

    # A camera driver that hangs: its loop stops beating and the watchdog is withheld.
    config = parse_config(
        f'[sim]\nworld = "{OFFICE}"\n[rfid]\nenabled = false\n[laser]\nenabled = false\n'
        "[health]\nloop_timeout_s = 1.0\n",
        str(OFFICE.parent / "c.toml"),
    )
    assert config.sim is not None
    with SimulatedRobot(config.sim.world) as robot:
        devices = build_devices(config, robot)
        devices.camera = HangingCamera()
        notifier = Notifier()
        agent = create_agent(config, robot=robot, notifier=notifier, output_url=None, devices=devices)
        agent.start()
        try:
            deadline = time.monotonic() + 20
            while "WITHHELD" not in notifier.sent:
                assert time.monotonic() < deadline, notifier.sent
                time.sleep(0.05)
            report = agent.health.check()
            assert "camera" in report.stalled and not report.all_critical_alive
        finally:
            agent.stop()
    assert notifier.sent[-1] == "STOPPING"


def test_run_without_its_devices_says_it_is_not_localizing_and_keeps_the_watchdog(tmp_path: Path) -> None:
    """The robot's own config with every device and the output port absent: READY names them all, and
    while no position source is live the journal and STATUS= say so, again and again. The watchdog is still
    fed (a restart plugs in no camera; docs/operations.md)."""
    gone = tmp_path / "gone"
    text = (REPO / "examples" / "turtlebot3.toml").read_text()
    for old, new in (
        ('"/opt/MVS/lib/64/MvProducerU3V.cti"', f'"{gone}/producer.cti"'),
        ('"/dev/urg"', f'"{gone}/urg"'),
        ('"/dev/dynamixel"', f'"{gone}/dynamixel"'),
        ('"/dev/ttyS0"', f'"{gone}/rfid"'),
        ('"/dev/opencr"', f'"{gone}/opencr"'),
        ("\nbus = 1\n", "\nbus = 97\n"),  # /dev/i2c-97: no such bus
        ("\nwatchdog = true\n", "\nwatchdog = true\nready_grace_s = 1.0\nnot_localizing_log_s = 1.0\n"),
    ):
        assert old in text, old
        text = text.replace(old, new)
    config = tmp_path / "robot.toml"
    config.write_text(text)
    notify_path = tmp_path / "notify.sock"
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(notify_path))
    notify.settimeout(0.2)
    env = {**os.environ, "NOTIFY_SOCKET": str(notify_path), "WATCHDOG_USEC": "1000000"}
    proc = subprocess.Popen(
        vlp_agent("run", "--config", str(config), "--seconds", "10"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
        env=env,
    )
    fields: list[str] = []
    try:
        while proc.poll() is None:
            try:
                fields += notify.recv(4096).decode().split("\n")
            except TimeoutError:
                continue
        _, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        notify.close()
    assert proc.returncode == 0, stderr[-2000:]
    lines = stderr.splitlines()
    output = f"output {gone}/opencr"
    ready = [line for line in lines if "ready without" in line]
    assert len(ready) == 1, stderr[-3000:]
    assert all(name in ready[0] for name in ("camera", "laser", "servos", "imu", "rfid", output)), ready
    # In the journal, repeatedly (every not_localizing_log_s once it has lasted 5 s), with what is missing.
    warnings = [line for line in lines if "not localizing for" in line]
    assert len(warnings) >= 2, stderr[-3000:]
    names = ("camera", "laser", "servos", "imu", output)
    assert all(all(name in w for name in names) for w in warnings), warnings
    # In STATUS= (systemctl status), refreshed every status_interval_s.
    status = [f for f in fields if f.startswith("STATUS=")]
    not_localizing = [f for f in status if f.startswith("STATUS=NOT LOCALIZING: ")]
    assert len(not_localizing) >= 2, status
    assert all("missing: camera, laser, servos, imu, rfid" in f for f in not_localizing), not_localizing
    assert fields.count("READY=1") == 1
    pings = [i for i, f in enumerate(fields) if f == "WATCHDOG=1"]
    assert len(pings) >= 5 and max(pings) > fields.index(not_localizing[-1])
