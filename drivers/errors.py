"""Device and configuration branches of the project's exception tree (root: ``VlpAgentError``)."""

from __future__ import annotations

from firmware_protocol.errors import ProtocolError, VlpAgentError

__all__ = [
    "BackendUnavailable",
    "ConfigError",
    "DeviceDisconnected",
    "DeviceError",
    "DeviceNotFound",
    "DeviceStatusError",
    "DeviceTimeout",
    "ProtocolError",
    "VlpAgentError",
]


class DeviceError(VlpAgentError):
    """A device misbehaved. ``device`` names it (a port path, a bus address, a camera id)."""

    def __init__(self, message: str, device: str = "") -> None:
        self.device = device
        super().__init__(f"{device}: {message}" if device else message)


class DeviceNotFound(DeviceError):
    """Nothing answers at the configured place (no such port, no such camera, no I2C ack)."""


class DeviceTimeout(DeviceError):
    """The device did not answer before the deadline."""


class DeviceDisconnected(DeviceError):
    """The device went away mid-stream (unplugged, port closed under us)."""


class DeviceStatusError(DeviceError):
    """The device answered, but with an error status. ``status`` is the device's own code."""

    def __init__(self, message: str, device: str = "", status: int | str | None = None) -> None:
        self.status = status
        super().__init__(message, device)


class BackendUnavailable(DeviceError):
    """The chosen backend needs a library or file that is not installed; the message says what to install."""


class ConfigError(VlpAgentError):
    """A file a person wrote is wrong. Names the file and the key so it can be fixed."""

    def __init__(self, key: str, reason: str, file: str | None = None) -> None:
        self.key = key
        self.reason = reason
        self.file = file
        where = f"{file}: " if file else ""
        super().__init__(f"{where}{key}: {reason}" if key else f"{where}{reason}")
