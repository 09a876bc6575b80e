"""What device threads hand to consumers: small frozen dataclasses with both clocks.

Every sample carries ``host_time_ns`` (``time.monotonic_ns()`` on this computer, aligned to when the device
took the measurement where the driver can tell) and, where the device has one, its own timestamp, kept
apart and unmodified so that clock alignment can be checked and redone offline.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt


@dataclass(frozen=True, slots=True)
class Frame:
    """One camera image, 8-bit: shape (height, width) for Mono8, (height, width, 3) in BGR order for BGR8."""

    image: npt.NDArray[np.uint8]
    sequence: int
    host_time_ns: int
    device_time_ns: int | None = None
    exposure_s: float | None = None


@dataclass(frozen=True, slots=True)
class Scan:
    """One laser scan.

    ``ranges_mm`` holds the raw values for each reported step (after clustering); values below
    ``min_range_mm`` are the device's error codes, not distances. The angle of element ``i`` is
    ``angle_min_rad + i * angle_increment_rad``, counter-clockwise, zero straight ahead.
    """

    ranges_mm: npt.NDArray[np.int32]
    angle_min_rad: float
    angle_increment_rad: float
    min_range_mm: int
    max_range_mm: int
    sequence: int
    host_time_ns: int
    device_time_ms: int | None = None

    def valid_mask(self) -> npt.NDArray[np.bool_]:
        return (self.ranges_mm >= self.min_range_mm) & (self.ranges_mm <= self.max_range_mm)

    def angles_rad(self) -> npt.NDArray[np.float64]:
        steps = np.arange(self.ranges_mm.size, dtype=np.float64)
        angles: npt.NDArray[np.float64] = self.angle_min_rad + self.angle_increment_rad * steps
        return angles


@dataclass(frozen=True, slots=True)
class WheelState:
    """Present state of the two drive wheels (left, right), in SI units, plus raw servo error bits."""

    position_rad: tuple[float, float]
    velocity_radps: tuple[float, float]
    host_time_ns: int
    hardware_error: tuple[int, int] = (0, 0)


@dataclass(frozen=True, slots=True)
class ImuSample:
    """Accelerometer (m/s^2), gyroscope (rad/s), both in the sensor frame, and die temperature."""

    accel_mps2: tuple[float, float, float]
    gyro_radps: tuple[float, float, float]
    temperature_c: float
    host_time_ns: int


@dataclass(frozen=True, slots=True)
class TagRead:
    """One RFID tag detection. ``rssi_dbm``, ``antenna``, ``frequency_khz``, ``phase_deg`` and the reader's
    own ``device_time_ms`` only from readers that report them (UHF)."""

    tag_id: str
    host_time_ns: int
    reader: str
    rssi_dbm: float | None = None
    antenna: int | None = None
    frequency_khz: int | None = None
    phase_deg: float | None = None
    device_time_ms: int | None = None
