"""The XL430-W250 control table as data, shared by the driver and the fake servo.

Sources: ROBOTIS e-Manual ``docs/en/dxl/x/xl430-w250.md`` (addresses, sizes, access, initial values,
ranges, units) and the SDK's ``control_table/xl430_w250.model`` (same addresses; it lacks Startup
Configuration (60) and Backup Ready (147), which newer firmware (v45+) has). Hardware error bits from the
e-Manual "Shutdown" item, baud indices from its X-series baud table.

The XL430 has **Present Load** at 126 (0.1 % units); Present Current at 126 exists only on XM/XH models.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cached_property

MODEL_XL430_W250 = 1060
FIRMWARE_VERSION = 46  # a current XL430 firmware; Fast Sync/Bulk Read need v45 or later

#: Goal/Present Velocity unit: 0.229 rev/min per LSB (e-Manual; TurtleBot3 uses the same constant).
VELOCITY_UNIT_RPM = 0.229
RADPS_PER_VELOCITY_UNIT = VELOCITY_UNIT_RPM * 2.0 * math.pi / 60.0
#: Present Position: 4096 pulses per revolution.
TICKS_PER_REV = 4096
RAD_PER_TICK = 2.0 * math.pi / TICKS_PER_REV
#: Return Delay Time unit, seconds.
RETURN_DELAY_UNIT_S = 2e-6
#: Bus Watchdog unit, seconds.
BUS_WATCHDOG_UNIT_S = 0.020
#: What Bus Watchdog (98) reads once it has fired (e-Manual: "-1", i.e. 0xFF on the wire).
BUS_WATCHDOG_EXPIRED = -1
#: The items a fired Bus Watchdog makes read-only until it is cleared (the XL430 has no Goal Current).
BUS_WATCHDOG_GOALS = ("Goal PWM", "Goal Velocity", "Goal Position")

#: Baud Rate (8) index -> bits per second.
BAUD_RATES = {
    0: 9600,
    1: 57600,
    2: 115200,
    3: 1_000_000,
    4: 2_000_000,
    5: 3_000_000,
    6: 4_000_000,
    7: 4_500_000,
}


class OperatingMode(enum.IntEnum):
    """Operating Mode (11) values the XL430 supports (it has no current control)."""

    VELOCITY = 1
    POSITION = 3
    EXTENDED_POSITION = 4
    PWM = 16


class HardwareError(enum.IntFlag):
    """Hardware Error Status (70) bits; the same bits select what Shutdown (63) turns torque off for."""

    INPUT_VOLTAGE = 0x01
    OVERHEATING = 0x04
    MOTOR_ENCODER = 0x08
    ELECTRICAL_SHOCK = 0x10
    OVERLOAD = 0x20


#: Shutdown (63) initial value: torque goes off on overload, electrical shock and overheating.
SHUTDOWN_DEFAULT = HardwareError.OVERLOAD | HardwareError.ELECTRICAL_SHOCK | HardwareError.OVERHEATING


def describe_hardware_error(bits: int) -> str:
    """``"OVERLOAD|OVERHEATING"`` style text for a Hardware Error Status value; ``"none"`` for 0."""
    if not bits:
        return "none"
    names = [flag.name or "" for flag in HardwareError if bits & flag]
    unknown = bits & ~sum(HardwareError)
    if unknown:
        names.append(f"0x{unknown:02X}")
    return "|".join(names)


class Access(enum.StrEnum):
    R = "R"
    RW = "RW"


class Area(enum.StrEnum):
    EEPROM = "EEPROM"  # writable only while Torque Enable (64) is 0, kept over power cycles
    RAM = "RAM"


@dataclass(frozen=True, slots=True)
class ControlItem:
    """One control table item. ``minimum``/``maximum`` are the e-Manual's static range (None: no range
    given); ``scale`` converts raw values to ``unit``."""

    address: int
    size: int
    name: str
    access: Access
    area: Area
    default: int | None = None
    minimum: int | None = None
    maximum: int | None = None
    signed: bool = False
    unit: str = ""
    scale: float = 1.0

    @property
    def end(self) -> int:
        return self.address + self.size

    @property
    def writable(self) -> bool:
        return self.access is Access.RW

    def decode(self, raw: bytes | bytearray) -> int:
        if len(raw) != self.size:
            raise ValueError(f"{self.name} is {self.size} bytes, got {len(raw)}")
        return int.from_bytes(raw, "little", signed=self.signed)

    def encode(self, value: int) -> bytes:
        """Little-endian bytes; negative values of signed items in two's complement."""
        return int(value).to_bytes(self.size, "little", signed=self.signed and value < 0)

    def in_range(self, value: int) -> bool:
        return (self.minimum is None or value >= self.minimum) and (
            self.maximum is None or value <= self.maximum
        )


_R, _RW = Access.R, Access.RW
_E, _M = Area.EEPROM, Area.RAM

# address, size, name, access, area, default, minimum, maximum, signed, unit, scale
_XL430_ITEMS: tuple[ControlItem, ...] = (
    ControlItem(0, 2, "Model Number", _R, _E, MODEL_XL430_W250),
    ControlItem(2, 4, "Model Information", _R, _E, 0),
    ControlItem(6, 1, "Firmware Version", _R, _E, FIRMWARE_VERSION),
    ControlItem(7, 1, "ID", _RW, _E, 1, 0, 252),
    ControlItem(8, 1, "Baud Rate", _RW, _E, 1, 0, 7),
    ControlItem(9, 1, "Return Delay Time", _RW, _E, 250, 0, 254, unit="s", scale=RETURN_DELAY_UNIT_S),
    ControlItem(10, 1, "Drive Mode", _RW, _E, 0, 0, 13),
    ControlItem(11, 1, "Operating Mode", _RW, _E, OperatingMode.POSITION, 0, 16),
    # The e-Manual range is 0..252, but its initial value 255 means "no secondary ID".
    ControlItem(12, 1, "Secondary(Shadow) ID", _RW, _E, 255, 0, 255),
    ControlItem(13, 1, "Protocol Type", _RW, _E, 2, 1, 2),
    ControlItem(20, 4, "Homing Offset", _RW, _E, 0, -1_044_479, 1_044_479, True, "tick"),
    ControlItem(24, 4, "Moving Threshold", _RW, _E, 10, 0, 1023, unit="rad/s", scale=RADPS_PER_VELOCITY_UNIT),
    ControlItem(31, 1, "Temperature Limit", _RW, _E, 72, 0, 100, unit="degC"),
    ControlItem(32, 2, "Max Voltage Limit", _RW, _E, 140, 60, 140, unit="V", scale=0.1),
    ControlItem(34, 2, "Min Voltage Limit", _RW, _E, 60, 60, 140, unit="V", scale=0.1),
    ControlItem(36, 2, "PWM Limit", _RW, _E, 885, 0, 885, unit="%", scale=0.113),
    ControlItem(44, 4, "Velocity Limit", _RW, _E, 265, 0, 1023, unit="rad/s", scale=RADPS_PER_VELOCITY_UNIT),
    ControlItem(48, 4, "Max Position Limit", _RW, _E, 4095, 0, 4095, unit="tick"),
    ControlItem(52, 4, "Min Position Limit", _RW, _E, 0, 0, 4095, unit="tick"),
    ControlItem(60, 1, "Startup Configuration", _RW, _E, 0, 0, 3),
    ControlItem(63, 1, "Shutdown", _RW, _E, SHUTDOWN_DEFAULT, 0, 255),
    ControlItem(64, 1, "Torque Enable", _RW, _M, 0, 0, 1),
    ControlItem(65, 1, "LED", _RW, _M, 0, 0, 1),
    ControlItem(68, 1, "Status Return Level", _RW, _M, 2, 0, 2),
    ControlItem(69, 1, "Registered Instruction", _R, _M, 0),
    ControlItem(70, 1, "Hardware Error Status", _R, _M, 0),
    ControlItem(76, 2, "Velocity I Gain", _RW, _M, 1000, 0, 16383),
    ControlItem(78, 2, "Velocity P Gain", _RW, _M, 100, 0, 16383),
    ControlItem(80, 2, "Position D Gain", _RW, _M, 4000, 0, 16383),
    ControlItem(82, 2, "Position I Gain", _RW, _M, 0, 0, 16383),
    ControlItem(84, 2, "Position P Gain", _RW, _M, 640, 0, 16383),
    ControlItem(88, 2, "Feedforward 2nd Gain", _RW, _M, 0, 0, 16383),
    ControlItem(90, 2, "Feedforward 1st Gain", _RW, _M, 0, 0, 16383),
    # 0 disables (and clears) the watchdog, 1..127 arms it; the servo sets it to -1 (0xFF) itself when it
    # fires, so it is read signed. -1 is not a value a host may write.
    ControlItem(98, 1, "Bus Watchdog", _RW, _M, 0, 0, 127, True, "s", BUS_WATCHDOG_UNIT_S),
    # Goal PWM/Velocity/Position: their real bound is another item (PWM/Velocity/Position Limit), a
    # "data limit" checked by the servo against the current limit value.
    ControlItem(100, 2, "Goal PWM", _RW, _M, 0, -885, 885, True, "%", 0.113),
    ControlItem(104, 4, "Goal Velocity", _RW, _M, 0, -1023, 1023, True, "rad/s", RADPS_PER_VELOCITY_UNIT),
    ControlItem(108, 4, "Profile Acceleration", _RW, _M, 0, 0, 32767),
    ControlItem(112, 4, "Profile Velocity", _RW, _M, 0, 0, 32767),
    ControlItem(116, 4, "Goal Position", _RW, _M, 0, -1_048_575, 1_048_575, True, "tick"),
    ControlItem(120, 2, "Realtime Tick", _R, _M, 0, unit="s", scale=0.001),
    ControlItem(122, 1, "Moving", _R, _M, 0),
    ControlItem(123, 1, "Moving Status", _R, _M, 0),
    ControlItem(124, 2, "Present PWM", _R, _M, 0, signed=True, unit="%", scale=0.113),
    ControlItem(126, 2, "Present Load", _R, _M, 0, signed=True, unit="%", scale=0.1),
    ControlItem(
        128, 4, "Present Velocity", _R, _M, 0, signed=True, unit="rad/s", scale=RADPS_PER_VELOCITY_UNIT
    ),
    ControlItem(132, 4, "Present Position", _R, _M, 0, signed=True, unit="rad", scale=RAD_PER_TICK),
    ControlItem(
        136, 4, "Velocity Trajectory", _R, _M, 0, signed=True, unit="rad/s", scale=RADPS_PER_VELOCITY_UNIT
    ),
    ControlItem(140, 4, "Position Trajectory", _R, _M, 0, signed=True, unit="rad", scale=RAD_PER_TICK),
    ControlItem(144, 2, "Present Input Voltage", _R, _M, 0, unit="V", scale=0.1),
    ControlItem(146, 1, "Present Temperature", _R, _M, 0, unit="degC"),
    ControlItem(147, 1, "Backup Ready", _R, _M, 0),
    *(ControlItem(168 + 2 * n, 2, f"Indirect Address {n + 1}", _RW, _M, 224 + n, 64, 661) for n in range(28)),
    *(ControlItem(224 + n, 1, f"Indirect Data {n + 1}", _RW, _M, 0, 0, 255) for n in range(28)),
    *(
        ControlItem(578 + 2 * n, 2, f"Indirect Address {n + 29}", _RW, _M, 634 + n, 64, 661)
        for n in range(28)
    ),
    *(ControlItem(634 + n, 1, f"Indirect Data {n + 29}", _RW, _M, 0, 0, 255) for n in range(28)),
)


@dataclass(frozen=True)
class ControlTable:
    """A model's control table: look items up by name or by address, build the power-on register image."""

    model_number: int
    model_name: str
    items: tuple[ControlItem, ...]

    def __post_init__(self) -> None:
        taken: dict[int, str] = {}
        for item in self.items:
            for a in range(item.address, item.end):
                if a in taken:
                    raise ValueError(f"{item.name} overlaps {taken[a]} at address {a}")
                taken[a] = item.name

    def __iter__(self) -> Iterator[ControlItem]:
        return iter(self.items)

    def __getitem__(self, name: str) -> ControlItem:
        try:
            return self._by_name[name]
        except KeyError:
            raise KeyError(f"{self.model_name} has no control table item {name!r}") from None

    def __contains__(self, name: object) -> bool:
        return name in self._by_name

    @cached_property
    def _by_name(self) -> dict[str, ControlItem]:
        return {item.name: item for item in self.items}

    @cached_property
    def _by_address(self) -> dict[int, ControlItem]:
        return {a: item for item in self.items for a in range(item.address, item.end)}

    @property
    def size(self) -> int:
        """One past the highest address."""
        return max(item.end for item in self.items)

    def item_at(self, address: int) -> ControlItem | None:
        """The item that covers ``address`` (not only starts there), or None in a gap."""
        return self._by_address.get(address)

    def default_image(self) -> bytearray:
        """The register file as the servo powers up (gaps and items without an initial value read 0)."""
        image = bytearray(self.size)
        for item in self.items:
            if item.default is not None:
                image[item.address : item.end] = item.encode(item.default)
        return image


XL430_W250 = ControlTable(MODEL_XL430_W250, "XL430-W250", _XL430_ITEMS)
