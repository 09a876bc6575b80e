"""Wheel servos: the interface (:class:`WheelServos`), wheel odometry, and the Dynamixel backend.

The Dynamixel backend (``drivers.servos.dynamixel``) imports ``dynamixel_sdk``; it is not imported here,
so that choosing another backend never needs that library (see ``drivers/registry.py``).
"""

from drivers.servos.base import WheelServos
from drivers.servos.odometry import Odom, WheelOdometry

__all__ = ["Odom", "WheelOdometry", "WheelServos"]
