"""A fake MPU-6050 as a register file behind the real ``smbus2``.

smbus2 (0.6.1) does all its I/O with ``ioctl`` calls, imported into ``smbus2.smbus2``, on a file it opens by
path (``SMBus("/dev/i2c-1")``, or ``SMBus(1)``). :class:`FakeI2cBus` creates a temporary file to stand for
the bus device node and registers it with a scoped ioctl dispatcher. While any fake bus exists, the
dispatcher sits in place of ``smbus2.smbus2.ioctl``: calls on file descriptors open on a fake bus's file are
served by the fake, every other call goes to the ioctl that was there before (normally
``fcntl.ioctl``), so real buses keep working in the same process. smbus2 itself is not changed: its ctypes
structures are packed as for the kernel, and the fake unpacks them with its own copies of the kernel's
``i2c-dev.h`` layouts, so a packing bug on either side shows up.

The bus implements the kernel's ioctls: ``I2C_SLAVE``/``I2C_SLAVE_FORCE`` (per open file, as the kernel
keeps it), ``I2C_FUNCS``, ``I2C_RDWR`` (combined transfers) and ``I2C_SMBUS`` with QUICK, BYTE, BYTE_DATA,
WORD_DATA (SMBus words are little-endian on the wire: low byte first) and I2C_BLOCK_DATA, each turned into the
I2C write/read transactions the kernel's SMBus emulation would put on the wire. An address with no target, or
whose target has vanished, fails with ``OSError(ENXIO)`` like ``i2c-dev`` on many adapters (pass
``nak_errno=errno.EREMOTEIO`` for the Raspberry Pi's behaviour).

:class:`FakeMpu6050` is the target: the MPU-6050 register map (WHO_AM_I 0x75, PWR_MGMT_1 0x6B resetting to
0x40 = asleep, SMPLRT_DIV 0x19, CONFIG 0x1A, GYRO_CONFIG 0x1B, ACCEL_CONFIG 0x1C, ACCEL_CONFIG2 0x1D on the
MPU-6500 family, data 0x3B..0x48 big-endian) with an auto-incrementing register pointer. While awake it
refreshes the data registers at the configured sample rate from ``Simulation.imu_truth()`` (specific force
and angular rate in the robot base frame), rotated into the sensor frame by ``world.robot.imu_mount``
(roll/pitch/yaw), scaled by the configured full-scale range, with noise and bias, clipped to int16. Asleep,
the data registers hold their last values (zero after a reset).
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import logging
import math
import os
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import TracebackType
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
import smbus2.smbus2 as smbus2_module

from drivers.sim.simulation import Simulation

__all__ = [
    "FakeI2cBus",
    "FakeMpu6050",
    "I2cTarget",
    "install_ioctl_dispatcher",
    "ioctl_dispatcher",
    "uninstall_ioctl_dispatcher",
]

log = logging.getLogger(__name__)

# uapi/linux/i2c-dev.h and i2c.h
I2C_SLAVE = 0x0703
I2C_SLAVE_FORCE = 0x0706
I2C_FUNCS = 0x0705
I2C_RDWR = 0x0707
I2C_PEC = 0x0708
I2C_SMBUS = 0x0720
I2C_SMBUS_READ = 1
I2C_SMBUS_QUICK = 0
I2C_SMBUS_BYTE = 1
I2C_SMBUS_BYTE_DATA = 2
I2C_SMBUS_WORD_DATA = 3
I2C_SMBUS_I2C_BLOCK_DATA = 8
I2C_SMBUS_BLOCK_MAX = 32
I2C_M_RD = 0x0001
I2C_RDWR_IOCTL_MAX_MSGS = 42

# I2C_FUNC_* bits: plain I2C plus the SMBus transfers emulated above.
FUNC_I2C = 0x00000001
FUNC_SMBUS_QUICK = 0x00010000
FUNC_SMBUS_BYTE = 0x00060000
FUNC_SMBUS_BYTE_DATA = 0x00180000
FUNC_SMBUS_WORD_DATA = 0x00600000
FUNC_SMBUS_I2C_BLOCK = 0x0C000000
DEFAULT_FUNCS = (
    FUNC_I2C
    | FUNC_SMBUS_QUICK
    | FUNC_SMBUS_BYTE
    | FUNC_SMBUS_BYTE_DATA
    | FUNC_SMBUS_WORD_DATA
    | FUNC_SMBUS_I2C_BLOCK
)
# (SMBus transfer size, is a read) -> the I2C_FUNC bit an adapter needs for it.
_SMBUS_FUNC = {
    (I2C_SMBUS_QUICK, False): FUNC_SMBUS_QUICK,
    (I2C_SMBUS_QUICK, True): FUNC_SMBUS_QUICK,
    (I2C_SMBUS_BYTE, True): 0x00020000,  # READ_BYTE
    (I2C_SMBUS_BYTE, False): 0x00040000,  # WRITE_BYTE
    (I2C_SMBUS_BYTE_DATA, True): 0x00080000,  # READ_BYTE_DATA
    (I2C_SMBUS_BYTE_DATA, False): 0x00100000,  # WRITE_BYTE_DATA
    (I2C_SMBUS_WORD_DATA, True): 0x00200000,  # READ_WORD_DATA
    (I2C_SMBUS_WORD_DATA, False): 0x00400000,  # WRITE_WORD_DATA
    (I2C_SMBUS_I2C_BLOCK_DATA, True): 0x04000000,  # READ_I2C_BLOCK
    (I2C_SMBUS_I2C_BLOCK_DATA, False): 0x08000000,  # WRITE_I2C_BLOCK
}


# The kernel's structures, declared here rather than borrowed from smbus2, so each packing checks the other.
class _SmbusIoctlData(ctypes.Structure):
    _fields_ = [
        ("read_write", ctypes.c_uint8),
        ("command", ctypes.c_uint8),
        ("size", ctypes.c_uint32),
        ("data", ctypes.c_void_p),  # union i2c_smbus_data *: byte, word, or block[0] = length + 32 bytes
    ]


class _I2cMsg(ctypes.Structure):
    _fields_ = [
        ("addr", ctypes.c_uint16),
        ("flags", ctypes.c_uint16),
        ("len", ctypes.c_uint16),
        ("buf", ctypes.c_void_p),
    ]


class _RdwrIoctlData(ctypes.Structure):
    _fields_ = [("msgs", ctypes.c_void_p), ("nmsgs", ctypes.c_uint32)]


_SmbusBlock = ctypes.c_uint8 * (I2C_SMBUS_BLOCK_MAX + 2)


def _os_error(code: int) -> OSError:
    return OSError(code, os.strerror(code))


class I2cTarget(Protocol):
    """A device on a fake bus, at the level of I2C transactions."""

    @property
    def present(self) -> bool:
        """False: the device does not acknowledge its address (unpowered, unplugged)."""
        ...

    def i2c_write(self, data: bytes) -> None:
        """One write transaction (for register devices: the register pointer, then data)."""
        ...

    def i2c_read(self, length: int) -> bytes:
        """One read transaction of ``length`` bytes."""
        ...


# ================================================================================================
# the ioctl dispatcher
# ================================================================================================


class _Dispatcher:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._refcount = 0
        self._previous: Callable[..., Any] | None = None
        self._buses: dict[tuple[int, int], FakeI2cBus] = {}
        # One bound-method object, so "is it still ours?" can be asked with `is` at uninstall.
        self._entry: Callable[..., Any] = self.ioctl

    def install(self) -> None:
        with self._lock:
            if self._refcount == 0:
                # smbus2's .pyi leaves out the module-level ioctl it imports from fcntl, hence the ignores.
                self._previous = smbus2_module.ioctl  # type: ignore[attr-defined]
                smbus2_module.ioctl = self._entry  # type: ignore[attr-defined]
            self._refcount += 1

    def uninstall(self) -> None:
        with self._lock:
            if self._refcount == 0:
                raise RuntimeError("ioctl dispatcher uninstalled more often than installed")
            self._refcount -= 1
            if self._refcount == 0:
                if smbus2_module.ioctl is self._entry:  # type: ignore[attr-defined]
                    smbus2_module.ioctl = self._previous  # type: ignore[attr-defined]
                else:
                    # Someone patched over us since; putting ours back would break them.
                    log.warning("smbus2.smbus2.ioctl was replaced while the fake dispatcher was installed")

    @property
    def installed(self) -> bool:
        return self._refcount > 0

    def register(self, key: tuple[int, int], bus: FakeI2cBus) -> None:
        with self._lock:
            self._buses[key] = bus

    def unregister(self, key: tuple[int, int]) -> None:
        with self._lock:
            self._buses.pop(key, None)

    def ioctl(self, fd: int, request: int, arg: Any = 0, *rest: Any) -> Any:
        bus = None
        with contextlib.suppress(OSError, TypeError):
            st = os.fstat(fd)
            bus = self._buses.get((st.st_dev, st.st_ino))
        if bus is None:
            previous = self._previous
            assert previous is not None
            return previous(fd, request, arg, *rest)
        return bus.ioctl(fd, request, arg)


_DISPATCHER = _Dispatcher()


def install_ioctl_dispatcher() -> None:
    """Route smbus2's ioctls through the fake-bus dispatcher (refcounted; pair with uninstall)."""
    _DISPATCHER.install()


def uninstall_ioctl_dispatcher() -> None:
    _DISPATCHER.uninstall()


@contextlib.contextmanager
def ioctl_dispatcher() -> Iterator[None]:
    install_ioctl_dispatcher()
    try:
        yield
    finally:
        uninstall_ioctl_dispatcher()


# ================================================================================================
# the bus
# ================================================================================================


class FakeI2cBus:
    """A fake I2C adapter: open it with ``SMBus(bus.path)`` (or ``Mpu6050(bus=bus.path)``).

    ``funcs`` is what the adapter can do as Linux reports it (``I2C_FUNCS``, the kernel's SMBus emulation
    included); a transfer it does not list fails with ``EOPNOTSUPP``, as on a real SMBus-only controller.
    """

    def __init__(
        self,
        directory: str | os.PathLike[str] | None = None,
        nak_errno: int = errno.ENXIO,
        funcs: int = DEFAULT_FUNCS,
    ) -> None:
        fd, path = tempfile.mkstemp(prefix="fake-i2c-", dir=directory)
        os.close(fd)
        self.path = path
        self.nak_errno = nak_errno
        self.funcs = funcs
        self._targets: dict[int, I2cTarget] = {}
        self._fd_address: dict[tuple[int, int], int] = {}
        self._lock = threading.RLock()
        st = os.stat(path)
        self._key = (st.st_dev, st.st_ino)
        self.transfers = 0
        _DISPATCHER.register(self._key, self)
        _DISPATCHER.install()
        self._closed = False

    def attach(self, address: int, target: I2cTarget) -> None:
        if not 0x03 <= address <= 0x77:
            raise ValueError(f"7-bit I2C device addresses are 0x03..0x77, got {address:#x}")
        with self._lock:
            self._targets[address] = target

    def detach(self, address: int) -> None:
        with self._lock:
            self._targets.pop(address, None)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        _DISPATCHER.unregister(self._key)
        _DISPATCHER.uninstall()
        with contextlib.suppress(FileNotFoundError):
            Path(self.path).unlink()

    def __enter__(self) -> FakeI2cBus:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- transactions ----------------------------------------------------------------------------
    def _target(self, address: int) -> I2cTarget:
        target = self._targets.get(address)
        if target is None or not target.present:
            raise _os_error(self.nak_errno)
        return target

    def write(self, address: int, data: bytes) -> None:
        self._target(address).i2c_write(data)

    def read(self, address: int, length: int) -> bytes:
        data = self._target(address).i2c_read(length)
        if len(data) != length:
            raise AssertionError(f"fake target returned {len(data)} bytes for a {length}-byte read")
        return data

    # -- the kernel interface --------------------------------------------------------------------------
    def ioctl(self, fd: int, request: int, arg: Any) -> int:
        st = os.fstat(fd)
        fd_key = (fd, st.st_ino)
        with self._lock:
            self.transfers += 1
            if request in (I2C_SLAVE, I2C_SLAVE_FORCE):
                address = int(arg)
                if not 0 <= address <= 0x7F:
                    raise _os_error(errno.EINVAL)
                self._fd_address[fd_key] = address
                return 0
            if request == I2C_FUNCS:
                ctypes.c_ulong.from_buffer(arg).value = self.funcs
                return 0
            if request == I2C_PEC:
                if int(arg):
                    raise _os_error(errno.EOPNOTSUPP)  # we report no SMBUS_PEC support
                return 0
            if request == I2C_SMBUS:
                return self._smbus(self._fd_address.get(fd_key, 0), _SmbusIoctlData.from_buffer(arg))
            if request == I2C_RDWR:
                return self._rdwr(_RdwrIoctlData.from_buffer(arg))
        raise _os_error(errno.ENOTTY)

    def _smbus(self, address: int, req: _SmbusIoctlData) -> int:
        reading = req.read_write == I2C_SMBUS_READ
        size = req.size
        needed = _SMBUS_FUNC.get((size, reading))
        if needed is None or not self.funcs & needed:
            raise _os_error(errno.EOPNOTSUPP)
        block = _SmbusBlock.from_address(req.data) if req.data else None
        # The kernel's i2c_smbus_xfer_emulated(): which transactions each SMBus transfer is made of.
        if size == I2C_SMBUS_QUICK:
            self._target(address)
            return 0
        if block is None:
            raise _os_error(errno.EINVAL)
        if size == I2C_SMBUS_BYTE:
            if reading:
                block[0] = self.read(address, 1)[0]
            else:
                self.write(address, bytes([req.command]))
            return 0
        if size == I2C_SMBUS_BYTE_DATA:
            if reading:
                self.write(address, bytes([req.command]))
                block[0] = self.read(address, 1)[0]
            else:
                self.write(address, bytes([req.command, block[0]]))
            return 0
        if size == I2C_SMBUS_WORD_DATA:
            if reading:
                self.write(address, bytes([req.command]))
                lo, hi = self.read(address, 2)
                block[0], block[1] = lo, hi  # the union's word, little-endian in memory as on the wire
            else:
                self.write(address, bytes([req.command, block[0], block[1]]))
            return 0
        if size == I2C_SMBUS_I2C_BLOCK_DATA:
            length = block[0]
            if not 1 <= length <= I2C_SMBUS_BLOCK_MAX:
                raise _os_error(errno.EINVAL)
            if reading:
                self.write(address, bytes([req.command]))
                data = self.read(address, length)
                for k, value in enumerate(data, start=1):
                    block[k] = value
            else:
                self.write(address, bytes([req.command]) + bytes(block[1 : length + 1]))
            return 0
        raise _os_error(errno.EOPNOTSUPP)

    def _rdwr(self, req: _RdwrIoctlData) -> int:
        if not self.funcs & FUNC_I2C:
            raise _os_error(errno.EOPNOTSUPP)
        if not 1 <= req.nmsgs <= I2C_RDWR_IOCTL_MAX_MSGS or not req.msgs:
            raise _os_error(errno.EINVAL)
        msgs = (_I2cMsg * req.nmsgs).from_address(req.msgs)
        for msg in msgs:
            if msg.flags & I2C_M_RD:
                data = self.read(msg.addr, msg.len)
                ctypes.memmove(msg.buf, data, msg.len)
            else:
                self.write(msg.addr, ctypes.string_at(msg.buf, msg.len))
        return int(req.nmsgs)


# ================================================================================================
# the MPU-6050
# ================================================================================================

# Register map (InvenSense RM-MPU-6000A; Adafruit CircuitPython adafruit_mpu6050.py). Kept apart from the
# driver's copy on purpose: the fake checks the driver, so it must not share its tables.
SMPLRT_DIV = 0x19
CONFIG = 0x1A
GYRO_CONFIG = 0x1B
ACCEL_CONFIG = 0x1C
ACCEL_CONFIG2 = 0x1D
ACCEL_XOUT_H = 0x3B
GYRO_ZOUT_L = 0x48
PWR_MGMT_1 = 0x6B
WHO_AM_I = 0x75
PWR_MGMT_1_RESET = 0x40  # SLEEP set
_ACCEL_LSB_PER_G = (16384.0, 8192.0, 4096.0, 2048.0)  # AFS_SEL 0..3: +-2, 4, 8, 16 g
_GYRO_LSB_PER_DPS = (131.0, 65.5, 32.8, 16.4)  # FS_SEL 0..3: +-250, 500, 1000, 2000 deg/s
_STANDARD_GRAVITY = 9.80665


def _rotation_base_from_sensor(roll: float, pitch: float, yaw: float) -> npt.NDArray[np.float64]:
    """R such that v_base = R @ v_sensor, for a sensor mounted with yaw, then pitch, then roll (z-y-x)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    rotation: npt.NDArray[np.float64] = rz @ ry @ rx
    return rotation


class FakeMpu6050:
    """An MPU-6050 register file over a :class:`Simulation` (or, with ``sim=None``, a sensor at rest, level).

    ``who_am_i``: 0x68 (MPU-6050), or 0x70/0x71/0x73 to stand in for an MPU-6500/9250/9255 (their
    temperature scale, raw/333.87 + 21, is used), or anything else to play a wrong part.
    ``accel_bias_mps2`` / ``gyro_bias_radps`` are added in the sensor frame; noise is white, per sample.
    """

    def __init__(
        self,
        sim: Simulation | None = None,
        *,
        who_am_i: int = 0x68,
        accel_noise_mps2: float = 0.03,
        gyro_noise_radps: float = 0.001,
        accel_bias_mps2: tuple[float, float, float] = (0.0, 0.0, 0.0),
        gyro_bias_radps: tuple[float, float, float] = (0.0, 0.0, 0.0),
        temperature_c: float = 30.0,
        seed: int = 0,
        clock: Callable[[], float] | None = None,
    ) -> None:
        self.sim = sim
        self.who_am_i = who_am_i
        self.accel_noise_mps2 = accel_noise_mps2
        self.gyro_noise_radps = gyro_noise_radps
        self.accel_bias_mps2 = np.asarray(accel_bias_mps2, dtype=float)
        self.gyro_bias_radps = np.asarray(gyro_bias_radps, dtype=float)
        self.temperature_c = temperature_c
        self._clock = clock if clock is not None else (sim.now if sim is not None else time.monotonic)
        self._rng = np.random.default_rng(seed)
        mount = sim.world.robot.imu_mount if sim is not None else None
        self._r_base_sensor = _rotation_base_from_sensor(
            mount.roll_rad if mount else 0.0,
            mount.pitch_rad if mount else 0.0,
            mount.yaw_rad if mount else 0.0,
        )
        self._lock = threading.Lock()
        self._present = True
        self.samples = 0
        self.reset()

    # -- switches ------------------------------------------------------------------------------------
    @property
    def present(self) -> bool:
        return self._present

    @present.setter
    def present(self, value: bool) -> None:
        """False: the part stops acknowledging (wire pulled, power lost)."""
        self._present = value

    def reset(self) -> None:
        """Power-on reset: every register 0 except PWR_MGMT_1 = 0x40 (asleep) and WHO_AM_I."""
        with self._lock:
            self.regs = bytearray(128)
            self.regs[PWR_MGMT_1] = PWR_MGMT_1_RESET
            self.regs[WHO_AM_I] = self.who_am_i
            self._pointer = 0
            self._next_sample_t = -math.inf

    @property
    def asleep(self) -> bool:
        return bool(self.regs[PWR_MGMT_1] & 0x40)

    # -- I2cTarget -------------------------------------------------------------------------------------
    def i2c_write(self, data: bytes) -> None:
        if not data:
            return
        with self._lock:
            self._pointer = data[0] & 0x7F
            for value in data[1:]:
                self._write_register(self._pointer, value)
                self._pointer = (self._pointer + 1) & 0x7F

    def i2c_read(self, length: int) -> bytes:
        with self._lock:
            # The data registers are shadowed for the length of a burst read, so a 14-byte read from 0x3B
            # is one consistent sample: refresh them once, when the transaction starts.
            if ACCEL_XOUT_H <= self._pointer <= GYRO_ZOUT_L:
                self._update_data()
            out = bytearray()
            for _ in range(length):
                out.append(self.regs[self._pointer])
                self._pointer = (self._pointer + 1) & 0x7F
            return bytes(out)

    def _write_register(self, reg: int, value: int) -> None:
        if reg == PWR_MGMT_1 and value & 0x80:  # DEVICE_RESET: all registers to defaults, bit clears itself
            self.regs = bytearray(128)
            self.regs[PWR_MGMT_1] = PWR_MGMT_1_RESET
            self.regs[WHO_AM_I] = self.who_am_i
            self._next_sample_t = -math.inf
            return
        if reg == WHO_AM_I or ACCEL_XOUT_H <= reg <= GYRO_ZOUT_L:
            return  # read-only
        was_asleep = self.asleep
        self.regs[reg] = value
        if was_asleep and not self.asleep:
            self._next_sample_t = -math.inf  # the first sample comes right after waking

    # -- the measurement -----------------------------------------------------------------------------------
    def _sample_period_s(self) -> float:
        dlpf = self.regs[CONFIG] & 0x07
        gyro_rate_hz = 8000.0 if dlpf in (0, 7) else 1000.0  # register map, SMPLRT_DIV description
        return (1 + self.regs[SMPLRT_DIV]) / gyro_rate_hz

    def _update_data(self) -> None:
        if self.asleep:
            return  # frozen
        now = self._clock()
        if now < self._next_sample_t:
            return
        self._next_sample_t = now + self._sample_period_s()
        if self.sim is not None:
            f_base, w_base = self.sim.imu_truth()
        else:
            f_base, w_base = (0.0, 0.0, _STANDARD_GRAVITY), (0.0, 0.0, 0.0)
        # v_sensor = R^T v_base
        f_s = self._r_base_sensor.T @ np.asarray(f_base) + self.accel_bias_mps2
        w_s = self._r_base_sensor.T @ np.asarray(w_base) + self.gyro_bias_radps
        f_s = f_s + self._rng.normal(0.0, self.accel_noise_mps2, 3)
        w_s = w_s + self._rng.normal(0.0, self.gyro_noise_radps, 3)
        accel_lsb = _ACCEL_LSB_PER_G[(self.regs[ACCEL_CONFIG] >> 3) & 0x03]
        gyro_lsb = _GYRO_LSB_PER_DPS[(self.regs[GYRO_CONFIG] >> 3) & 0x03]
        if self.who_am_i in (0x70, 0x71, 0x73):
            temp_raw = (self.temperature_c - 21.0) * 333.87  # MPU-6500 family
        else:
            temp_raw = (self.temperature_c - 36.53) * 340.0  # MPU-6050
        values = [*(f_s / _STANDARD_GRAVITY * accel_lsb), temp_raw, *(np.degrees(w_s) * gyro_lsb)]
        raw = np.clip(np.round(values), -32768, 32767).astype(">i2").tobytes()
        self.regs[ACCEL_XOUT_H : GYRO_ZOUT_L + 1] = raw
        self.samples += 1
