"""The IMU interface: one synchronous read gives one :class:`~drivers.samples.ImuSample`.

An I2C IMU is read on demand (a burst read takes well under a millisecond), so there is no thread and no
queue here: the caller's loop sets the rate. ``read()`` raises the :mod:`drivers.errors` family when the
part misbehaves; a backend recovers on a later ``read()`` once the part answers again.
"""

from __future__ import annotations

import abc

from drivers.device import Device
from drivers.samples import ImuSample

__all__ = ["Imu"]


class Imu(Device, abc.ABC):
    """Base of every IMU backend. Samples are in the sensor frame: accel in m/s^2 (specific force, so a
    sensor at rest reads +9.81 m/s^2 up), gyro in rad/s (right-handed), temperature of the die in deg C."""

    @abc.abstractmethod
    def read(self) -> ImuSample:
        """Read the latest sample. Raises ``DeviceError`` (or a subclass) if the part cannot be read."""
