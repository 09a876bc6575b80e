"""IMUs: the :class:`Imu` interface and its backends (chosen by name in the registry: "mpu6050")."""

from drivers.imu.base import Imu

__all__ = ["Imu"]
