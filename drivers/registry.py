"""Backends chosen by name: a table from (device kind, backend name) to "module:Class", imported lazily.

A vendor library (harvesters, dynamixel-sdk, smbus2, ...) is imported only when its backend is chosen, and a
missing one fails with :class:`~drivers.errors.BackendUnavailable` saying what to install.
"""

from __future__ import annotations

import enum
import importlib
from typing import Any

from drivers.errors import BackendUnavailable, ConfigError


class DeviceKind(enum.StrEnum):
    CAMERA = "camera"
    LASER = "laser"
    SERVOS = "servos"
    IMU = "imu"
    RFID = "rfid"


BACKENDS: dict[DeviceKind, dict[str, str]] = {
    DeviceKind.CAMERA: {
        "genicam": "drivers.camera.genicam:GenicamCamera",
        "v4l2": "drivers.camera.v4l2:V4l2Camera",
        "sim": "drivers.camera.sim:SimCamera",
    },
    DeviceKind.LASER: {
        "urg": "drivers.laser.urg:UrgLaser",
    },
    DeviceKind.SERVOS: {
        "dynamixel": "drivers.servos.dynamixel:DynamixelWheels",
    },
    DeviceKind.IMU: {
        "mpu6050": "drivers.imu.mpu6050:Mpu6050",
    },
    DeviceKind.RFID: {
        "id12la": "drivers.rfid.serial_reader:SerialRfidReader",
        "rdm6300": "drivers.rfid.serial_reader:SerialRfidReader",
        "mercury": "drivers.rfid.serial_reader:SerialRfidReader",
    },
}

# The forward camera of person following ([camera.forward]): the same real backends as the ceiling camera,
# and its own simulated one (a colour view of the world's walls and people).
FORWARD_CAMERA_BACKENDS: dict[str, str] = {
    "genicam": "drivers.camera.genicam:GenicamCamera",
    "v4l2": "drivers.camera.v4l2:V4l2Camera",
    "sim": "drivers.camera.sim_forward:SimForwardCamera",
    "fake": "drivers.camera.fake_forward:FakeForwardCamera",
}

INSTALL_HINTS = {
    "harvesters": "pip install harvesters genicam",
    "genicam": "pip install genicam",
    "dynamixel_sdk": "pip install dynamixel-sdk",
    "smbus2": "pip install smbus2",
    "cv2": "pip install 'opencv-python-headless>=4.10,<5'",
    "serial": "pip install pyserial",
    "usb": "pip install pyusb (and the libusb-1.0 system library)",
}


def backend_class(kind: DeviceKind | str, name: str) -> Any:
    """Import and return the class for backend ``name`` of device ``kind``."""
    kind = DeviceKind(kind)
    table = BACKENDS[kind]
    if name not in table:
        raise ConfigError(f"{kind.value}.backend", f"unknown backend {name!r}; choose one of {sorted(table)}")
    return _import(table[name], name, kind.value)


def forward_camera_class(name: str) -> Any:
    """Import and return the class of forward-camera backend ``name`` (``FORWARD_CAMERA_BACKENDS``)."""
    if name not in FORWARD_CAMERA_BACKENDS:
        raise ConfigError(
            "camera.forward.backend",
            f"unknown backend {name!r}; choose one of {sorted(FORWARD_CAMERA_BACKENDS)}",
        )
    return _import(FORWARD_CAMERA_BACKENDS[name], name, "camera.forward")


def _import(target: str, name: str, device: str) -> Any:
    module_name, _, class_name = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        missing = (exc.name or "").split(".")[0]
        hint = INSTALL_HINTS.get(missing, f"pip install {missing}")
        raise BackendUnavailable(
            f"backend {name!r} needs the Python module {missing!r}, which is not installed: {hint}",
            device=device,
        ) from exc
    return getattr(module, class_name)
