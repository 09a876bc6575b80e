"""Device objects from the config: one per configured kind, built by backend name, not opened.

The loops open them (and reopen them after a failure), so a device that is not there at start-up does not
stop the agent. Under ``[sim]`` the simulated robot says where each device is (its ptys, its I2C bus) and
gives the world's robot geometry; the config's tables give the rest.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

from agent.config import AgentConfig, DeviceConfig
from drivers.camera.base import Camera
from drivers.device import Device
from drivers.errors import ConfigError
from drivers.imu.base import Imu
from drivers.laser.base import LaserScanner
from drivers.registry import DeviceKind, backend_class, forward_camera_class
from drivers.rfid.base import RfidReader
from drivers.servos.base import WheelServos

__all__ = ["Devices", "build_device", "build_devices", "build_forward_camera"]

log = logging.getLogger(__name__)


@dataclass
class Devices:
    """The robot's devices (None where the config has none)."""

    camera: Camera | None = None
    laser: LaserScanner | None = None
    servos: WheelServos | None = None
    imu: Imu | None = None
    rfid: RfidReader | None = None
    forward_camera: Camera | None = None  # [camera.forward], person following's colour camera

    def all(self) -> dict[str, Device]:
        out: dict[str, Device] = {}
        for kind in DeviceKind:
            device = getattr(self, kind.value)
            if device is not None:
                out[kind.value] = device
        if self.forward_camera is not None:
            out["forward_camera"] = self.forward_camera
        return out


def build_device(device: DeviceConfig, config_file: str, robot: Any | None = None) -> Device:
    """One device object. ``robot``: a started ``drivers.sim.harness.SimulatedRobot`` under ``[sim]``."""
    kind = device.kind
    cls = backend_class(kind, device.backend)
    kwargs: dict[str, Any] = dict(device.options)
    if robot is not None:
        simulated = dict(robot.device_config()[kind.value])
        simulated.pop("backend", None)
        for key, value in simulated.items():
            kwargs.setdefault(key, value)
        if kind is DeviceKind.CAMERA:
            kwargs["simulation"] = robot.simulation
            kwargs.setdefault("seed", robot.seed)
    if kind is DeviceKind.RFID:
        kwargs["protocol"] = device.backend
    try:
        built: Device = cls(**kwargs)
    except ConfigError as exc:
        raise ConfigError(exc.key, exc.reason, config_file) from exc
    return built


def build_forward_camera(device: DeviceConfig, config_file: str, robot: Any | None = None) -> Camera:
    """The forward camera of ``[camera.forward]``; under ``[sim]`` the simulated robot's."""
    cls = forward_camera_class(device.backend)
    kwargs: dict[str, Any] = dict(device.options)
    kwargs.setdefault("name", "forward-camera")
    if robot is not None:
        kwargs["simulation"] = robot.simulation
        kwargs.setdefault("seed", robot.seed)
    try:
        built: Camera = cls(**kwargs)
    except ConfigError as exc:
        raise ConfigError(exc.key, exc.reason, config_file) from exc
    return built


def build_devices(config: AgentConfig, robot: Any | None = None) -> Devices:
    devices = Devices()
    for kind, device in config.devices.items():
        setattr(devices, kind.value, build_device(device, config.file, robot))
    if config.forward_camera is not None:
        devices.forward_camera = build_forward_camera(config.forward_camera, config.file, robot)
    return devices
