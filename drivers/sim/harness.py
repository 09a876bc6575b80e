"""The simulated robot as hardware: every fake device served where a real one would be.

``SimulatedRobot`` starts a :class:`~drivers.sim.simulation.Simulation` of a world and serves the fake
laser, servos and RFID reader on pseudo-terminals (with stable symlinks in a private folder, like the udev
names ``/dev/urg`` and ``/dev/dynamixel``), the fake IMU behind ``smbus2`` and the simulated camera. The agent
then opens them through the same drivers and the same config keys it uses on the robot. Fault injection
(pull a device, stall it) is here too, for tests and demonstrations.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import Any, Self

from drivers.fakes.dynamixel import FakeDynamixelBus
from drivers.fakes.pty import PtyServer
from drivers.fakes.rfid import FakeRfidReader
from drivers.fakes.urg import FakeUrg
from drivers.sim.simulation import Simulation
from drivers.sim.world import World

log = logging.getLogger(__name__)

# Each simulated robot's pty links and I2C bus live in a temporary folder named after the process that
# made it, so that a folder left by a killed run can be told from one in use and removed at the next start.
FOLDER_PREFIX = "vlp-sim-"
_FOLDER = re.compile(rf"{FOLDER_PREFIX}(\d+)-[^/]+")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process: alive
        return True
    return True


def remove_stale_folders(temp_dir: Path | None = None) -> list[Path]:
    """Remove this user's simulated-robot folders whose process has ended (killed before it could clean
    up). A reused pid only delays a removal; a folder without a pid in its name (older releases) is left."""
    root = Path(temp_dir) if temp_dir is not None else Path(tempfile.gettempdir())
    removed: list[Path] = []
    try:
        entries = list(root.glob(f"{FOLDER_PREFIX}*"))
    except OSError:
        return removed
    for entry in entries:
        match = _FOLDER.fullmatch(entry.name)
        try:
            ours = entry.is_dir() and not entry.is_symlink() and entry.stat().st_uid == os.getuid()
            if match is None or not ours:
                continue
        except OSError:
            continue
        if _alive(int(match.group(1))):
            continue
        shutil.rmtree(entry, ignore_errors=True)
        if not entry.exists():
            log.info("removed %s, left by a simulated robot that did not stop", entry)
            removed.append(entry)
    return removed


class SimulatedRobot:
    """Fake devices for one world, up while the context is open."""

    def __init__(
        self,
        world: World,
        simulation: Simulation | None = None,
        seed: int = 0,
        realtime: Callable[[], str | None] | None = None,
    ) -> None:
        """``realtime``: called first in each fake's serving thread to put it under real-time scheduling
        (``agent.runtime.priority.realtime_thread``: None when it took, else why not). The fakes stand in
        for hardware, which keeps its time whatever the computer's load; on a loaded machine time-shared
        fakes went quiet for tenths of a second at a time (no scan, no servo reply), which a real sensor
        never does. Where the system does not permit it they stay time-shared (logged once)."""
        self.world = world
        self.realtime = realtime
        self.device_realtime: dict[str, str | None] = {}
        self.simulation = simulation or Simulation(world, seed=seed)
        self.urg = FakeUrg(self.simulation, seed=seed)
        self.servos = FakeDynamixelBus(self.simulation)
        self.rfid = FakeRfidReader(self.simulation, seed=seed)
        self._dir: Path | None = None
        self.servers: dict[str, PtyServer] = {}
        self._imu: Any = None
        self.imu: Any = None
        self.seed = seed
        self._stack = contextlib.ExitStack()

    # -- where the agent finds the devices ---------------------------------------------------------
    @property
    def laser_url(self) -> str:
        return self.servers["laser"].path

    @property
    def servo_port(self) -> str:
        return self.servers["servos"].path

    @property
    def rfid_url(self) -> str:
        return self.servers["rfid"].path

    @property
    def imu_bus(self) -> str:
        return str(self._imu.path)

    def device_config(self) -> dict[str, dict[str, Any]]:
        """The devices as config tables, the same keys a robot's config file uses."""
        return {
            "laser": {"backend": "urg", "url": self.laser_url},
            "servos": {
                "backend": "dynamixel",
                "port": self.servo_port,
                "left_id": self.world.robot.left_id,
                "right_id": self.world.robot.right_id,
                "wheel_radius_m": self.world.robot.wheel_radius_m,
                "track_m": self.world.robot.track_m,
                # Fakes share a busy 2-core machine with the agent: allow more than the SDK's 16 ms
                # latency timer before a reply counts as missing.
                "latency_timer_ms": 50,
            },
            "rfid": self._rfid_table(),
            "imu": {"backend": "mpu6050", "bus": self.imu_bus},
            "camera": {"backend": "sim"},
        }

    def _rfid_table(self) -> dict[str, Any]:
        table: dict[str, Any] = {"backend": self.world.rfid.protocol, "url": self.rfid_url}
        if self.world.rfid.antenna_yaws_rad:  # a multi-antenna Mercury: read every port
            table["antenna_ports"] = tuple(range(1, len(self.world.rfid.antenna_yaws_rad) + 1))
        return table

    # -- lifecycle ---------------------------------------------------------------------------------
    def start(self) -> None:
        from drivers.fakes.imu import FakeI2cBus, FakeMpu6050

        remove_stale_folders()
        self._dir = Path(tempfile.mkdtemp(prefix=f"{FOLDER_PREFIX}{os.getpid()}-"))
        # How often each fake is polled for output of its own: the URG says when its next scan or reply
        # falls due and its server sleeps until then (at most the interval given), a tag reader reports
        # every few tens of milliseconds, the servos only ever answer (a reply goes out as soon as a
        # request arrives, whatever the interval). The simulated hardware shares the agent's process and
        # interpreter lock: every wake-up of a fake's thread takes the lock, so it wakes no more than it
        # must (a 2 ms poll of the URG was 500 wake-ups a second, one or two inside every camera frame).
        for name, device, poll_s in (
            ("laser", self.urg, 0.05),
            ("servos", self.servos, 0.05),
            ("rfid", self.rfid, 0.02),
        ):
            server = PtyServer(device, link=self._dir / name, poll_interval_s=poll_s)
            if self.realtime is not None:
                server.on_thread_start = self._realtime(name, self.realtime)
            server.start()
            self.servers[name] = server
        self._imu = FakeI2cBus(directory=self._dir)
        self._stack.callback(self._imu.close)
        self.imu = FakeMpu6050(self.simulation, seed=self.seed)
        self._imu.attach(0x68, self.imu)
        log.info("simulated robot up in %s", self._dir)

    def _realtime(self, name: str, realtime: Callable[[], str | None]) -> Callable[[], None]:
        def start() -> None:
            refused = realtime()
            self.device_realtime[name] = refused
            if refused is not None and len([r for r in self.device_realtime.values() if r]) == 1:
                log.warning("simulated devices time-shared: real-time scheduling %s", refused)

        return start

    def give_way_to(self, hot_path: Callable[[], None]) -> None:
        """Make every fake wait while ``hot_path`` says the program under test is busy (see
        ``PtyServer.give_way``): the simulated hardware must not take the agent's interpreter lock from
        its latency-critical path, as real hardware could not."""
        for server in self.servers.values():
            server.give_way = hot_path

    def lateness(self) -> dict[str, dict[str, float | int | bool]]:
        """Per served device: how late its thread woke at worst (s) and how often by more than its
        warning threshold (``PtyServer.late_max_s``, ``late_count``): starved by the machine's load."""
        return {
            name: {
                "late_max_s": round(server.late_max_s, 3),
                "late_count": server.late_count,
                "realtime": name in self.device_realtime and self.device_realtime[name] is None,
            }
            for name, server in self.servers.items()
        }

    def close(self) -> None:
        for server in self.servers.values():
            server.close()
        self._stack.close()
        if self._dir is not None:
            shutil.rmtree(self._dir, ignore_errors=True)
            self._dir = None

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- faults ------------------------------------------------------------------------------------
    def unplug(self, device: str) -> None:
        """Pull a serial device ("laser", "servos" or "rfid") as a USB cable would be pulled."""
        self.servers[device].unplug()

    def replug(self, device: str) -> None:
        self.servers[device].replug()
