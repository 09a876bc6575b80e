"""InvenSense MPU-6050 (and register-compatible parts) on Linux I2C, through ``smbus2``.

Accepted parts, by WHO_AM_I (register 0x75) — they share the accel/gyro/temperature register map and the
full-scale bits used here:

====  ===========================  ======================================================================
0x68  MPU-6050 / MPU-6000          temperature raw / 340 + 36.53 deg C (MPU-6000/6050 register map)
0x70  MPU-6500                     temperature raw / 333.87 + 21 deg C; accel DLPF in ACCEL_CONFIG2 0x1D
0x71  MPU-9250 (MPU-6500 + AK8963) as MPU-6500; the magnetometer is not used
0x73  MPU-9255                     as MPU-9250
====  ===========================  ======================================================================

(WHO_AM_I values as in InvenSense's register maps; e.g. ``MPU6500_WHOAMI_DEFAULT_VALUE 0x70``,
``MPU9250 0x71``, ``MPU9255 0x73`` in public MPU-925x drivers. The MPU-6050 answers 0x68 whichever address
AD0 selects.) Any other value is refused with a :class:`~drivers.errors.DeviceError` naming it, rather than
misreading a different part.

Bring-up: WHO_AM_I check; PWR_MGMT_1 = 0x01 (out of sleep, clock from the X-gyro PLL, which the datasheet
recommends over the internal oscillator); SMPLRT_DIV, CONFIG (DLPF), GYRO_CONFIG, ACCEL_CONFIG (and
ACCEL_CONFIG2 on the 6500 family); then the configuration is read back. A sample is one 14-byte burst
from ACCEL_XOUT_H (0x3B): accel x/y/z, temperature, gyro x/y/z, each a *big-endian* int16. (SMBus
``read_word_data`` assumes little-endian and would swap every byte pair, so it is not used.)

Faults: no acknowledge (``ENXIO``, or ``EREMOTEIO`` on the Raspberry Pi) at bring-up is
:class:`DeviceNotFound`, during reads :class:`DeviceDisconnected`; the next ``read()`` reopens the bus and
repeats the bring-up, because a part that lost power comes back asleep with its configuration reset. A part
found asleep by the periodic PWR_MGMT_1 check (a brown-out reset leaves the data registers frozen) is
re-initialised the same way and counted as ``rewakes``.
"""

from __future__ import annotations

import errno
import logging
import math
import os
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

from smbus2 import I2cFunc, SMBus

from drivers.errors import ConfigError, DeviceDisconnected, DeviceError, DeviceNotFound, DeviceTimeout
from drivers.imu.base import Imu
from drivers.samples import ImuSample

__all__ = ["Mpu6050"]

log = logging.getLogger(__name__)

_T = TypeVar("_T")

# Register map (InvenSense RM-MPU-6000A-00; Adafruit CircuitPython adafruit_mpu6050.py).
SMPLRT_DIV = 0x19
CONFIG = 0x1A
GYRO_CONFIG = 0x1B
ACCEL_CONFIG = 0x1C
ACCEL_CONFIG2 = 0x1D  # MPU-6500 family only
ACCEL_XOUT_H = 0x3B
PWR_MGMT_1 = 0x6B
WHO_AM_I = 0x75
PWR_SLEEP = 0x40
CLKSEL_PLL_XGYRO = 0x01
BURST_LENGTH = 14

STANDARD_GRAVITY_MPS2 = 9.80665

# full scale -> (FS_SEL bits, LSB per unit)
ACCEL_RANGES_G = {2: (0, 16384.0), 4: (1, 8192.0), 8: (2, 4096.0), 16: (3, 2048.0)}
GYRO_RANGES_DPS = {250: (0, 131.0), 500: (1, 65.5), 1000: (2, 32.8), 2000: (3, 16.4)}

# DLPF_CFG -> (accel bandwidth Hz, gyro bandwidth Hz) of the MPU-6050; with 0 the gyro samples at 8 kHz.
DLPF_BANDWIDTH_HZ = {
    0: (260, 256),
    1: (184, 188),
    2: (94, 98),
    3: (44, 42),
    4: (21, 20),
    5: (10, 10),
    6: (5, 5),
}

# Errno values that mean "nobody acknowledged": ENXIO (i2c-dev default), EREMOTEIO (i2c-bcm2835), EIO
# (older adapters).
_NO_ACK = {errno.ENXIO, errno.EREMOTEIO, errno.EIO}
# The adapter itself went away (USB-I2C bridge unplugged).
_NO_BUS = {errno.ENODEV, errno.ENOENT, errno.EBADF}


@dataclass(frozen=True, slots=True)
class Chip:
    name: str
    temp_lsb_per_c: float
    temp_offset_c: float
    accel_config2: bool


CHIPS = {
    0x68: Chip("MPU-6050", 340.0, 36.53, False),
    0x70: Chip("MPU-6500", 333.87, 21.0, True),
    0x71: Chip("MPU-9250", 333.87, 21.0, True),
    0x73: Chip("MPU-9255", 333.87, 21.0, True),
}


class Mpu6050(Imu):
    """An MPU-6050-family IMU on I2C bus ``bus`` (a number for ``/dev/i2c-N`` or a device path).

    ``dlpf``: DLPF_CFG 0..6 (3: 44 Hz accel / 42 Hz gyro, a good match for 100 Hz sampling);
    ``sample_rate_hz``: the output rate, set through SMPLRT_DIV (gyro rate / (1 + div)), rounded to what the
    divider allows (see :attr:`sample_rate_hz`); ``sleep_check_interval_s``: how often a read also checks
    PWR_MGMT_1 for a part that fell asleep (0: every read); ``startup_s``: wait after waking the part
    (default: the 30 ms gyro start-up time plus one sample period).
    """

    def __init__(
        self,
        bus: int | str = 1,
        address: int = 0x68,
        accel_range_g: int = 2,
        gyro_range_dps: int = 250,
        dlpf: int = 3,
        sample_rate_hz: float = 100.0,
        name: str = "imu",
        *,
        sleep_check_interval_s: float = 1.0,
        startup_s: float | None = None,
    ) -> None:
        super().__init__(name)
        if not 0x03 <= address <= 0x77:
            raise ConfigError("imu.address", f"must be a 7-bit I2C address, got {address:#x}")
        if accel_range_g not in ACCEL_RANGES_G:
            raise ConfigError(
                "imu.accel_range_g", f"must be one of {sorted(ACCEL_RANGES_G)}, got {accel_range_g}"
            )
        if gyro_range_dps not in GYRO_RANGES_DPS:
            raise ConfigError(
                "imu.gyro_range_dps", f"must be one of {sorted(GYRO_RANGES_DPS)}, got {gyro_range_dps}"
            )
        if dlpf not in DLPF_BANDWIDTH_HZ:
            raise ConfigError("imu.dlpf", f"must be a DLPF_CFG value 0..6, got {dlpf}")
        gyro_rate_hz = 8000.0 if dlpf == 0 else 1000.0
        low_hz = gyro_rate_hz / 256
        if not low_hz <= sample_rate_hz <= gyro_rate_hz:
            raise ConfigError(
                "imu.sample_rate_hz",
                f"must be {low_hz:.3g}..{gyro_rate_hz:.0f} Hz with DLPF {dlpf}, not {sample_rate_hz}",
            )
        if sleep_check_interval_s < 0:
            raise ConfigError("imu.sleep_check_interval_s", "must not be negative")
        self.bus = bus
        self.address = address
        self.accel_range_g = accel_range_g
        self.gyro_range_dps = gyro_range_dps
        self.dlpf = dlpf
        self.smplrt_div = max(0, min(255, round(gyro_rate_hz / sample_rate_hz) - 1))
        self.sample_rate_hz = gyro_rate_hz / (1 + self.smplrt_div)
        self.sleep_check_interval_s = sleep_check_interval_s
        self.startup_s = 0.03 + 1.0 / self.sample_rate_hz if startup_s is None else startup_s
        self.chip: Chip | None = None
        self.who_am_i: int | None = None
        self._accel_scale = STANDARD_GRAVITY_MPS2 / ACCEL_RANGES_G[accel_range_g][1]
        self._gyro_scale = math.radians(1.0) / GYRO_RANGES_DPS[gyro_range_dps][1]
        self._smbus: SMBus | None = None
        self._needs_init = False
        self._next_sleep_check = 0.0

    @property
    def device(self) -> str:
        bus = f"/dev/i2c-{self.bus}" if isinstance(self.bus, int) else self.bus
        return f"{bus}@{self.address:#04x}"

    # -- lifecycle ---------------------------------------------------------------------------------
    def _open(self) -> None:
        self._bring_up(first=True)

    def _close(self) -> None:
        self._close_bus()

    @property
    def connected(self) -> bool:
        return self.is_open and not self._needs_init

    def _close_bus(self) -> None:
        smbus, self._smbus = self._smbus, None
        if smbus is not None:
            try:
                smbus.close()
            except OSError as exc:
                log.debug("%s: closing the bus: %s", self.name, exc)

    def _open_bus(self, first: bool) -> SMBus:
        smbus = SMBus()
        try:
            smbus.open(self.bus)
        except OSError as exc:
            smbus.close()  # SMBus.open() leaves its fd open when the I2C_FUNCS ioctl fails
            if exc.errno == errno.EACCES:
                raise DeviceError(
                    f"permission denied opening the I2C bus (add the user to the 'i2c' group): {exc}",
                    self.device,
                ) from exc
            if first:
                raise DeviceNotFound(f"cannot open the I2C bus: {exc}", self.device) from exc
            raise DeviceDisconnected(f"cannot reopen the I2C bus: {exc}", self.device) from exc
        # Linux reports what an adapter can do, the kernel's SMBus emulation included; every adapter with
        # plain I2C has these, a few SMBus-only controllers do not.
        needed = I2cFunc.SMBUS_READ_BYTE_DATA | I2cFunc.SMBUS_WRITE_BYTE_DATA | I2cFunc.SMBUS_READ_I2C_BLOCK
        missing = needed & ~I2cFunc(smbus.funcs)
        if missing:
            smbus.close()
            raise DeviceError(f"the I2C adapter cannot do {missing.name} transfers", self.device)
        return smbus

    def _bring_up(self, first: bool) -> None:
        """Open the bus, check the part, wake and configure it. ``first``: at open() (no ack = not found)."""
        self._close_bus()
        try:
            self._smbus = self._open_bus(first)
        except DeviceError as exc:
            self._needs_init = True
            self.note_error(f"{type(exc).__name__}: {exc}")
            raise
        try:
            who = self._read_register(WHO_AM_I, first)
            chip = CHIPS.get(who)
            if chip is None:
                known = ", ".join(f"{k:#04x} {c.name}" for k, c in CHIPS.items())
                raise DeviceError(
                    f"WHO_AM_I is {who:#04x}, not an MPU-6050-family part (accepted: {known})", self.device
                )
            self.who_am_i, self.chip = who, chip
            accel_bits = ACCEL_RANGES_G[self.accel_range_g][0] << 3
            gyro_bits = GYRO_RANGES_DPS[self.gyro_range_dps][0] << 3
            config = [
                (PWR_MGMT_1, CLKSEL_PLL_XGYRO),  # wake first: the part starts asleep after power-on
                (SMPLRT_DIV, self.smplrt_div),
                (CONFIG, self.dlpf),
                (GYRO_CONFIG, gyro_bits),
                (ACCEL_CONFIG, accel_bits),
            ]
            if chip.accel_config2:
                config.append((ACCEL_CONFIG2, self.dlpf))  # ACCEL_FCHOICE_B = 0, A_DLPF_CFG = dlpf
            for reg, value in config:
                self._write_register(reg, value, first)
            for reg, value in config:
                got = self._read_register(reg, first)
                if got != value:
                    raise DeviceError(
                        f"register {reg:#04x} reads back {got:#04x} after writing {value:#04x}", self.device
                    )
        except BaseException:
            self._close_bus()
            self._needs_init = True
            raise
        # The gyros need ~30 ms from sleep to run (datasheet start-up time) and the first sample lands one
        # sample period after that; reading sooner returns the reset values (zeros).
        if self.startup_s > 0:
            time.sleep(self.startup_s)
        self._needs_init = False
        self._next_sleep_check = time.monotonic() + self.sleep_check_interval_s
        log.info(
            "%s: %s at %s, +-%d g, +-%d deg/s, DLPF %d, %.1f Hz",
            self.name,
            chip.name,
            self.device,
            self.accel_range_g,
            self.gyro_range_dps,
            self.dlpf,
            self.sample_rate_hz,
        )

    # -- reading ---------------------------------------------------------------------------------------
    def read(self) -> ImuSample:
        if not self.is_open:
            raise DeviceError("IMU is closed", self.device)
        if self._needs_init:
            self._bring_up(first=False)
            self.count("reconnects")
        if time.monotonic() >= self._next_sleep_check:
            self._check_awake()
        t0 = time.monotonic_ns()
        raw = self._xfer(self._burst, first=False)
        t1 = time.monotonic_ns()
        ax, ay, az, temp, gx, gy, gz = struct.unpack(">7h", raw)
        chip = self.chip
        assert chip is not None
        self.count("reads")
        return ImuSample(
            accel_mps2=(ax * self._accel_scale, ay * self._accel_scale, az * self._accel_scale),
            gyro_radps=(gx * self._gyro_scale, gy * self._gyro_scale, gz * self._gyro_scale),
            temperature_c=temp / chip.temp_lsb_per_c + chip.temp_offset_c,
            host_time_ns=(t0 + t1) // 2,
        )

    def _burst(self, smbus: SMBus) -> bytes:
        return bytes(smbus.read_i2c_block_data(self.address, ACCEL_XOUT_H, BURST_LENGTH))

    def _check_awake(self) -> None:
        power = self._read_register(PWR_MGMT_1, first=False)
        self._next_sleep_check = time.monotonic() + self.sleep_check_interval_s
        if power & PWR_SLEEP:
            # Only a reset (brown-out, another process) puts it back to sleep; its configuration is gone too.
            log.warning("%s: found asleep (PWR_MGMT_1 %#04x); re-initialising", self.name, power)
            self.count("rewakes")
            self.note_error(f"part found asleep (PWR_MGMT_1 {power:#04x}), re-initialised")
            self._bring_up(first=False)

    def _read_register(self, reg: int, first: bool) -> int:
        return self._xfer(lambda smbus: smbus.read_byte_data(self.address, reg), first)

    def _write_register(self, reg: int, value: int, first: bool) -> None:
        self._xfer(lambda smbus: smbus.write_byte_data(self.address, reg, value), first)

    def _xfer(self, op: Callable[[SMBus], _T], first: bool) -> _T:
        """Run one bus operation; an OSError becomes the matching DeviceError and schedules a bring-up."""
        smbus = self._smbus
        if smbus is None:
            self._needs_init = True
            raise DeviceDisconnected("the I2C bus is not open", self.device)
        try:
            return op(smbus)
        except OSError as exc:
            self.count("errors")
            self._needs_init = True
            error = self._device_error(exc, first)
            self.note_error(f"{type(error).__name__}: {error}")
            raise error from exc

    def _device_error(self, exc: OSError, first: bool) -> DeviceError:
        code = exc.errno or 0
        reason = os.strerror(code) if code else str(exc)
        if code in _NO_ACK:
            if first:
                return DeviceNotFound(f"no device acknowledges the address ({reason})", self.device)
            return DeviceDisconnected(f"the device stopped acknowledging ({reason})", self.device)
        if code in _NO_BUS:
            if first:
                return DeviceNotFound(f"the I2C bus is not there ({reason})", self.device)
            return DeviceDisconnected(f"the I2C bus went away ({reason})", self.device)
        if code == errno.ETIMEDOUT:
            return DeviceTimeout(f"I2C transfer timed out ({reason})", self.device)
        return DeviceError(f"I2C transfer failed ({reason})", self.device)
