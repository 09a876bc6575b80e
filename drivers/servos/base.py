"""The interface every wheel-servo backend implements: two drive wheels of a differential-drive base.

Units and signs are the robot's, not the servos': wheel angles in radians and speeds in rad/s, positive
when that wheel rolls the robot **forward**, whatever way its servo is mounted. A backend hides mirrored
mounting, servo units and bus addressing.

Errors (``drivers.errors``): :class:`~drivers.errors.DeviceTimeout` when a servo does not answer in time,
:class:`~drivers.errors.DeviceDisconnected` when the port went away (the backend reopens it on a later
call, or on :meth:`WheelServos.reconnect`), :class:`~drivers.errors.DeviceStatusError` when a servo
refused an instruction (``status`` is its ERR byte). A hardware error (overload, overheating, ...) is
not an exception: it is reported in every :class:`~drivers.samples.WheelState` and by
:meth:`WheelServos.hardware_errors`, because the servo still answers and the caller decides what to do.
"""

from __future__ import annotations

import abc

from drivers.device import Device
from drivers.samples import WheelState


class WheelServos(Device):
    """Two wheel servos (left, right).

    Health counters: ``reads`` and ``commands`` done; what went wrong: ``timeouts``, ``retries``,
    ``corrupt_replies``, ``comm_errors``, ``status_errors``, ``disconnects``, ``reconnects``,
    ``hardware_alerts`` (a new hardware error seen), ``clamped_commands`` (a speed beyond the limit),
    ``bus_watchdog_stops`` (a servo found stopped by its Bus Watchdog and started again).
    """

    def __init__(self, name: str, left_id: int, right_id: int) -> None:
        super().__init__(name)
        self.left_id = left_id
        self.right_id = right_id

    @property
    def ids(self) -> tuple[int, int]:
        return self.left_id, self.right_id

    @abc.abstractmethod
    def ping(self) -> dict[int, int]:
        """Model number of each wheel servo, by ID. Raises DeviceTimeout naming a servo that is silent."""

    @abc.abstractmethod
    def set_velocity(self, left_radps: float, right_radps: float) -> None:
        """Command wheel speeds (rad/s, forward positive). Values beyond the servos' limit are clamped."""

    def stop(self) -> None:
        """Command zero speed on both wheels (torque stays on, so the wheels hold)."""
        self.set_velocity(0.0, 0.0)

    @abc.abstractmethod
    def read(self) -> WheelState:
        """Present wheel angles (continuous, not wrapped), speeds, and each servo's hardware error bits."""

    @abc.abstractmethod
    def torque(self, on: bool) -> None:
        """Enable or disable both motors. With torque off the wheels turn freely and commands do nothing."""

    @abc.abstractmethod
    def hardware_errors(self) -> tuple[int, int]:
        """Hardware error bits (left, right) read from the servos now; 0 when healthy."""

    @abc.abstractmethod
    def reconnect(self) -> None:
        """Close and reopen the port and configure the servos again (after an unplug, a power cycle)."""
