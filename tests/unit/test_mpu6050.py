"""The fake MPU-6050 behind the real smbus2, and the Mpu6050 driver against it.

The fake is checked first with smbus2 alone (register file, SMBus word order, burst reads, the ioctl
dispatcher leaving other file descriptors to the kernel), so that the driver tests below rest on a fake
that is itself tested.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import math
import os
import struct
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import smbus2.smbus2 as smbus2_module
from smbus2 import SMBus, i2c_msg

from drivers.errors import ConfigError, DeviceError, DeviceNotFound
from drivers.fakes.imu import (
    FUNC_SMBUS_BYTE_DATA,
    FUNC_SMBUS_WORD_DATA,
    FakeI2cBus,
    FakeMpu6050,
    ioctl_dispatcher,
)
from drivers.imu.mpu6050 import ACCEL_RANGES_G, GYRO_RANGES_DPS, Mpu6050
from drivers.registry import backend_class
from drivers.sim.simulation import Simulation
from drivers.sim.world import Mount, RobotSpec, World

G = 9.80665


class ManualClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def bus(tmp_path: Path) -> Iterator[FakeI2cBus]:
    with FakeI2cBus(tmp_path) as fake_bus:
        yield fake_bus


def quiet_fake(sim: Simulation | None = None, **options: object) -> FakeMpu6050:
    """A fake without noise, so values can be compared to the LSB."""
    return FakeMpu6050(sim, accel_noise_mps2=0.0, gyro_noise_radps=0.0, **options)  # type: ignore[arg-type]


def open_imu(bus: FakeI2cBus, **options: object) -> Mpu6050:
    # The default start-up wait stays: after a configuration change the part (and the fake) needs a
    # sample period before the data registers use the new scale.
    imu = Mpu6050(bus=bus.path, **options)  # type: ignore[arg-type]
    imu.open()
    return imu


# ---------------------------------------------------------------------------------------------------
# the fake, through smbus2
# ---------------------------------------------------------------------------------------------------


def test_power_on_state_is_asleep_with_frozen_zero_data(bus: FakeI2cBus) -> None:
    bus.attach(0x68, quiet_fake())
    with SMBus(bus.path) as smbus:
        assert smbus.read_byte_data(0x68, 0x75) == 0x68
        assert smbus.read_byte_data(0x68, 0x6B) == 0x40
        assert smbus.read_i2c_block_data(0x68, 0x3B, 14) == [0] * 14
        smbus.write_byte_data(0x68, 0x6B, 0x01)  # wake, PLL clock
        ax, ay, az, _, gx, gy, gz = struct.unpack(">7h", bytes(smbus.read_i2c_block_data(0x68, 0x3B, 14)))
    assert (ax, ay, az) == (0, 0, 16384)  # +1 g on z at +-2 g full scale
    assert (gx, gy, gz) == (0, 0, 0)


def test_word_reads_are_little_endian_block_reads_big_endian(bus: FakeI2cBus) -> None:
    """The pitfall the driver avoids: SMBus words put the *first* byte low; the MPU's registers are H, L."""
    bus.attach(0x68, quiet_fake())
    with SMBus(bus.path) as smbus:
        smbus.write_byte_data(0x68, 0x6B, 0x00)
        block = bytes(smbus.read_i2c_block_data(0x68, 0x3F, 2))  # ACCEL_ZOUT_H, _L
        word = smbus.read_word_data(0x68, 0x3F)
    assert block == (16384).to_bytes(2, "big")
    assert word == 0x0040  # bytes 40 00 read as a little-endian word
    assert struct.unpack(">h", block)[0] == 16384


def test_i2c_rdwr_combined_transfer_and_pointer_auto_increment(bus: FakeI2cBus) -> None:
    bus.attach(0x68, quiet_fake())
    with SMBus(bus.path) as smbus:
        smbus.i2c_rdwr(i2c_msg.write(0x68, [0x19, 7, 3, 0x18, 0x08]))  # SMPLRT_DIV, CONFIG, GYRO, ACCEL
        write, read = i2c_msg.write(0x68, [0x19]), i2c_msg.read(0x68, 4)
        smbus.i2c_rdwr(write, read)
        assert ctypes.string_at(read.buf, read.len) == bytes([7, 3, 0x18, 0x08])
        assert smbus.read_i2c_block_data(0x68, 0x19, 4) == [7, 3, 0x18, 0x08]


def test_read_only_registers_and_device_reset(bus: FakeI2cBus) -> None:
    fake = quiet_fake()
    bus.attach(0x68, fake)
    with SMBus(bus.path) as smbus:
        smbus.write_byte_data(0x68, 0x75, 0x12)
        assert smbus.read_byte_data(0x68, 0x75) == 0x68
        smbus.write_byte_data(0x68, 0x1C, 0x18)
        smbus.write_byte_data(0x68, 0x6B, 0x80)  # DEVICE_RESET
        assert smbus.read_byte_data(0x68, 0x1C) == 0x00
        assert smbus.read_byte_data(0x68, 0x6B) == 0x40
    assert fake.asleep


def test_absent_or_vanished_address_naks_with_the_bus_errno(tmp_path: Path) -> None:
    with FakeI2cBus(tmp_path, nak_errno=errno.EREMOTEIO) as fake_bus, SMBus(fake_bus.path) as smbus:
        fake = quiet_fake()
        fake_bus.attach(0x68, fake)
        with pytest.raises(OSError) as absent:
            smbus.read_byte_data(0x69, 0x75)
        assert absent.value.errno == errno.EREMOTEIO
        fake.present = False
        with pytest.raises(OSError) as vanished:
            smbus.read_byte_data(0x68, 0x75)
        assert vanished.value.errno == errno.EREMOTEIO
        fake.present = True
        assert smbus.read_byte_data(0x68, 0x75) == 0x68


def test_dispatcher_passes_other_fds_to_the_kernel(bus: FakeI2cBus, tmp_path: Path) -> None:
    other = tmp_path / "not-a-bus"
    other.write_bytes(b"")
    fd = os.open(other, os.O_RDWR)
    try:
        with pytest.raises(OSError) as direct:
            fcntl.ioctl(fd, 0x0705, bytearray(8))
        with pytest.raises(OSError) as routed:
            smbus2_module.ioctl(fd, 0x0705, bytearray(8))  # type: ignore[attr-defined]
        assert routed.value.errno == direct.value.errno == errno.ENOTTY
    finally:
        os.close(fd)


def test_dispatcher_is_refcounted_and_restores_the_real_ioctl(tmp_path: Path) -> None:
    original = smbus2_module.ioctl  # type: ignore[attr-defined]
    first = FakeI2cBus(tmp_path)
    with ioctl_dispatcher():
        second = FakeI2cBus(tmp_path)
        first.close()
        assert smbus2_module.ioctl is not original  # type: ignore[attr-defined]
        second.close()
        second.close()  # idempotent: must not unbalance the count
        assert smbus2_module.ioctl is not original  # type: ignore[attr-defined]
    assert smbus2_module.ioctl is original  # type: ignore[attr-defined]
    assert not Path(first.path).exists()


def test_two_buses_from_many_threads(tmp_path: Path) -> None:
    with FakeI2cBus(tmp_path) as bus_a, FakeI2cBus(tmp_path) as bus_b:
        bus_a.attach(0x68, quiet_fake(who_am_i=0x68))
        bus_b.attach(0x68, quiet_fake(who_am_i=0x71))
        errors: list[BaseException] = []

        def hammer(path: str, expected: int) -> None:
            try:
                with SMBus(path) as smbus:
                    for _ in range(300):
                        assert smbus.read_byte_data(0x68, 0x75) == expected
            except BaseException as exc:  # collected for the main thread
                errors.append(exc)

        threads = [
            threading.Thread(target=hammer, args=(b.path, w)) for b, w in [(bus_a, 0x68), (bus_b, 0x71)] * 3
        ]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    assert errors == []


# ---------------------------------------------------------------------------------------------------
# the driver
# ---------------------------------------------------------------------------------------------------


def test_bring_up_writes_the_configuration(bus: FakeI2cBus) -> None:
    fake = quiet_fake()
    bus.attach(0x68, fake)
    with open_imu(bus, accel_range_g=8, gyro_range_dps=1000, dlpf=5, sample_rate_hz=50.0) as imu:
        assert fake.regs[0x6B] == 0x01  # awake, PLL
        assert fake.regs[0x19] == 19  # 1 kHz / (1 + 19) = 50 Hz
        assert fake.regs[0x1A] == 5
        assert fake.regs[0x1B] == 2 << 3
        assert fake.regs[0x1C] == 2 << 3
        assert fake.regs[0x1D] == 0  # not written on an MPU-6050
        assert imu.sample_rate_hz == 50.0
        assert imu.chip is not None and imu.chip.name == "MPU-6050"


def test_sample_rate_is_rounded_to_what_the_divider_allows(bus: FakeI2cBus) -> None:
    bus.attach(0x68, quiet_fake())
    with open_imu(bus, sample_rate_hz=300.0) as imu:
        assert imu.smplrt_div == 2
        assert imu.sample_rate_hz == pytest.approx(1000.0 / 3)
    with open_imu(bus, dlpf=0, sample_rate_hz=8000.0) as imu:
        assert imu.smplrt_div == 0


@pytest.mark.parametrize("accel_range_g", sorted(ACCEL_RANGES_G))
def test_accel_scaling_for_every_range(bus: FakeI2cBus, accel_range_g: int) -> None:
    fake = quiet_fake(accel_bias_mps2=(1.5, -0.5, 0.0))
    bus.attach(0x68, fake)
    with open_imu(bus, accel_range_g=accel_range_g) as imu:
        sample = imu.read()
        raw_z = struct.unpack(">h", bytes(fake.regs[0x3F:0x41]))[0]
    lsb_per_g = ACCEL_RANGES_G[accel_range_g][1]
    assert raw_z == round(lsb_per_g)  # 1 g at this full scale, straight from the register file
    quantum = G / lsb_per_g
    assert sample.accel_mps2 == pytest.approx((1.5, -0.5, G), abs=quantum)


@pytest.mark.parametrize("gyro_range_dps", sorted(GYRO_RANGES_DPS))
def test_gyro_scaling_for_every_range(bus: FakeI2cBus, gyro_range_dps: int) -> None:
    rate = (0.2, -0.4, 1.0)  # rad/s, inside the +-250 deg/s (4.36 rad/s) range
    bus.attach(0x68, quiet_fake(gyro_bias_radps=rate))
    with open_imu(bus, gyro_range_dps=gyro_range_dps) as imu:
        sample = imu.read()
    quantum = math.radians(1.0) / GYRO_RANGES_DPS[gyro_range_dps][1]
    assert sample.gyro_radps == pytest.approx(rate, abs=quantum)


def test_full_scale_saturates_rather_than_wraps(bus: FakeI2cBus) -> None:
    bus.attach(0x68, quiet_fake(accel_bias_mps2=(0.0, 0.0, 3 * G)))  # 4 g on z
    with open_imu(bus, accel_range_g=2) as imu:
        assert imu.read().accel_mps2[2] == pytest.approx(32767 / 16384 * G)
    with open_imu(bus, accel_range_g=8) as imu:
        assert imu.read().accel_mps2[2] == pytest.approx(4 * G, abs=G / 4096)


@pytest.mark.parametrize(
    ("who_am_i", "name"), [(0x68, "MPU-6050"), (0x70, "MPU-6500"), (0x71, "MPU-9250"), (0x73, "MPU-9255")]
)
def test_accepted_parts_and_their_temperature_scales(bus: FakeI2cBus, who_am_i: int, name: str) -> None:
    fake = quiet_fake(who_am_i=who_am_i, temperature_c=27.5)
    bus.attach(0x68, fake)
    with open_imu(bus, dlpf=2) as imu:
        assert imu.chip is not None and imu.chip.name == name
        assert imu.read().temperature_c == pytest.approx(27.5, abs=0.01)
    assert fake.regs[0x1D] == (2 if who_am_i != 0x68 else 0)  # accel DLPF register on the 6500 family


def test_wrong_who_am_i_is_refused_naming_the_value(bus: FakeI2cBus) -> None:
    bus.attach(0x68, quiet_fake(who_am_i=0x12))
    imu = Mpu6050(bus=bus.path, startup_s=0.0)
    with pytest.raises(DeviceError, match="WHO_AM_I is 0x12") as info:
        imu.open()
    assert not isinstance(info.value, DeviceNotFound)
    assert not imu.is_open


def test_absent_part_and_missing_bus_are_not_found(bus: FakeI2cBus, tmp_path: Path) -> None:
    with pytest.raises(DeviceNotFound, match="acknowledges"):
        Mpu6050(bus=bus.path, address=0x69, startup_s=0.0).open()
    with pytest.raises(DeviceNotFound, match="cannot open the I2C bus"):
        Mpu6050(bus=str(tmp_path / "i2c-99"), startup_s=0.0).open()


def test_adapter_without_block_reads_is_refused(tmp_path: Path) -> None:
    smbus_only = FUNC_SMBUS_BYTE_DATA | FUNC_SMBUS_WORD_DATA  # an SMBus controller without I2C-block reads
    with FakeI2cBus(tmp_path, funcs=smbus_only) as fake_bus:
        fake_bus.attach(0x68, quiet_fake())
        with SMBus(fake_bus.path) as smbus:
            assert smbus.read_byte_data(0x68, 0x75) == 0x68
            with pytest.raises(OSError) as refused:
                smbus.read_i2c_block_data(0x68, 0x3B, 14)
            assert refused.value.errno == errno.EOPNOTSUPP
            with pytest.raises(OSError):
                smbus.i2c_rdwr(i2c_msg.write(0x68, [0x3B]), i2c_msg.read(0x68, 14))
        with pytest.raises(DeviceError, match="SMBUS_READ_I2C_BLOCK"):
            Mpu6050(bus=fake_bus.path).open()


def test_bad_settings_are_config_errors() -> None:
    for options, key in [
        ({"accel_range_g": 3}, "imu.accel_range_g"),
        ({"gyro_range_dps": 300}, "imu.gyro_range_dps"),
        ({"dlpf": 7}, "imu.dlpf"),
        ({"sample_rate_hz": 2000.0}, "imu.sample_rate_hz"),
        ({"address": 0x80}, "imu.address"),
    ]:
        with pytest.raises(ConfigError) as info:
            Mpu6050(**options)  # type: ignore[arg-type]
        assert info.value.key == key


def test_registry_names_the_driver() -> None:
    assert backend_class("imu", "mpu6050") is Mpu6050


# ---------------------------------------------------------------------------------------------------
# the mount
# ---------------------------------------------------------------------------------------------------


def sim_with_mount(mount: Mount) -> tuple[Simulation, ManualClock]:
    clock = ManualClock()
    return Simulation(World("imu", robot=RobotSpec(imu_mount=mount)), clock=clock), clock


def test_upside_down_mount_flips_gravity_and_yaw_rate(bus: FakeI2cBus) -> None:
    sim, clock = sim_with_mount(Mount(roll_rad=math.pi))
    bus.attach(0x68, quiet_fake(sim))
    with open_imu(bus) as imu:
        sim.set_body_velocity(0.0, 0.8)
        clock.t += 1.0
        sample = imu.read()
    assert sample.accel_mps2 == pytest.approx((0.0, 0.0, -G), abs=0.002)
    assert sample.gyro_radps[2] == pytest.approx(-0.8, abs=0.002)


def test_pitched_mount_shows_as_tilt_of_gravity(bus: FakeI2cBus) -> None:
    pitch = math.radians(10.0)
    sim, _ = sim_with_mount(Mount(pitch_rad=pitch))
    bus.attach(0x68, quiet_fake(sim))
    with open_imu(bus) as imu:
        ax, _, az = imu.read().accel_mps2
    # Positive pitch turns the sensor's x axis down, so the upward specific force shows on -x.
    assert math.atan2(-ax, az) == pytest.approx(pitch, abs=math.radians(0.05))


def test_yawed_mount_moves_forward_acceleration_to_the_sensor_y_axis(bus: FakeI2cBus) -> None:
    sim, clock = sim_with_mount(Mount(yaw_rad=math.pi / 2))  # sensor x points to the robot's left
    bus.attach(0x68, quiet_fake(sim))
    with open_imu(bus) as imu:
        sim.set_body_velocity(0.3, 0.0)
        clock.t += 0.005  # still accelerating: wheels ramp at 20 rad/s^2 -> 0.66 m/s^2
        ax, ay, _ = imu.read().accel_mps2
    wheel_accel = sim.world.robot.wheel_radius_m * sim.world.robot.max_wheel_accel_radps2
    assert ax == pytest.approx(0.0, abs=0.002)
    assert ay == pytest.approx(-wheel_accel, abs=0.01)
