"""Contract suite for IMUs: what every backend must do, run on the fake MPU-6050 (a register file behind the
real smbus2, over the simulated robot) and, when ``VLP_TEST_IMU_BUS`` names an I2C bus (a number or a
``/dev/i2c-N`` path; ``VLP_TEST_IMU_ADDRESS`` defaults to 0x68), on a real part. On hardware, keep the
sensor still while the suite runs.

The tests that move the robot or pull the part need the simulation and the fake's switches, so they run on
the fake only.
"""

from __future__ import annotations

import contextlib
import math
import os
import statistics
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from smbus2 import SMBus

from drivers.errors import DeviceDisconnected, DeviceError, DeviceNotFound
from drivers.fakes.imu import FakeI2cBus, FakeMpu6050
from drivers.imu import Imu
from drivers.imu.mpu6050 import CHIPS, Mpu6050
from drivers.samples import ImuSample
from drivers.sim.simulation import Simulation
from drivers.sim.world import World

HW_BUS = os.environ.get("VLP_TEST_IMU_BUS")
HW_ADDRESS = int(os.environ.get("VLP_TEST_IMU_ADDRESS", "0x68"), 0)
G = 9.80665
# Datasheet tolerances an uncalibrated MPU-6050 must meet: zero-rate output +-20 deg/s, accel zero-g
# offset +-80 mg on x/y and +-150 mg on z, sensitivity +-3 %. The fake is far inside these.
GYRO_AT_REST_RADPS = math.radians(20.0)
ACCEL_NORM_TOLERANCE_MPS2 = 0.06 * G


class ManualClock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


@dataclass
class Rig:
    bus: int | str
    address: int
    sim: Simulation | None = None
    clock: ManualClock | None = None
    fake: FakeMpu6050 | None = None
    fake_bus: FakeI2cBus | None = None

    def imu(self, **options: object) -> Mpu6050:
        return Mpu6050(bus=self.bus, address=self.address, **options)  # type: ignore[arg-type]


def _hw_bus() -> int | str:
    assert HW_BUS is not None
    return int(HW_BUS) if HW_BUS.isdigit() else HW_BUS


@contextlib.contextmanager
def fake_rig_in(directory: Path) -> Iterator[Rig]:
    clock = ManualClock()
    sim = Simulation(World("imu-contract"), clock=clock)
    with FakeI2cBus(directory) as fake_bus:
        fake = FakeMpu6050(sim, seed=7)
        fake_bus.attach(0x68, fake)
        yield Rig(fake_bus.path, 0x68, sim, clock, fake, fake_bus)


@pytest.fixture
def fake_rig(tmp_path: Path) -> Iterator[Rig]:
    with fake_rig_in(tmp_path) as rig:
        yield rig


@pytest.fixture(params=["fake", "hardware"])
def rig(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Rig]:
    if request.param == "hardware":
        if not HW_BUS:
            pytest.skip("set VLP_TEST_IMU_BUS (and VLP_TEST_IMU_ADDRESS) to run on a real IMU")
        yield Rig(_hw_bus(), HW_ADDRESS)
        return
    with fake_rig_in(tmp_path) as fake:
        yield fake


def read_many(imu: Imu, rig: Rig, n: int = 30) -> list[ImuSample]:
    samples = []
    for _ in range(n):
        if rig.clock is not None:
            rig.clock.t += 0.01  # one sample period of the default 100 Hz
        samples.append(imu.read())
    return samples


def mean(values: list[float]) -> float:
    return statistics.fmean(values)


# ---------------------------------------------------------------------------------------------------
# the contract (fake and hardware)
# ---------------------------------------------------------------------------------------------------


def test_identifies_a_known_part(rig: Rig) -> None:
    with rig.imu() as imu:
        assert imu.who_am_i in CHIPS
        assert imu.chip is CHIPS[imu.who_am_i]
        assert imu.health().connected


def test_at_rest_reads_gravity_and_no_rotation(rig: Rig) -> None:
    with rig.imu() as imu:
        samples = read_many(imu, rig)
    accel = [mean([s.accel_mps2[k] for s in samples]) for k in range(3)]
    gyro = [mean([s.gyro_radps[k] for s in samples]) for k in range(3)]
    assert math.hypot(*accel) == pytest.approx(G, abs=ACCEL_NORM_TOLERANCE_MPS2)
    assert math.hypot(*gyro) < GYRO_AT_REST_RADPS
    assert all(-40.0 <= s.temperature_c <= 85.0 for s in samples)  # the part's operating range
    times = [s.host_time_ns for s in samples]
    assert times == sorted(times) and len(set(times)) == len(times)


@pytest.mark.parametrize(("accel_range_g", "gyro_range_dps"), [(2, 250), (4, 500), (8, 1000), (16, 2000)])
def test_every_range_setting_reads_the_same_physical_values(
    rig: Rig, accel_range_g: int, gyro_range_dps: int
) -> None:
    with rig.imu(accel_range_g=accel_range_g, gyro_range_dps=gyro_range_dps) as imu:
        samples = read_many(imu, rig, 20)
    accel = [mean([s.accel_mps2[k] for s in samples]) for k in range(3)]
    # A wrong LSB table is off by a factor of 2 or more between ranges; one LSB at 16 g is 0.0048 m/s^2.
    assert math.hypot(*accel) == pytest.approx(G, abs=ACCEL_NORM_TOLERANCE_MPS2)
    gyro = [mean([s.gyro_radps[k] for s in samples]) for k in range(3)]
    assert math.hypot(*gyro) < GYRO_AT_REST_RADPS


def test_close_is_idempotent_and_reading_a_closed_imu_raises(rig: Rig) -> None:
    imu = rig.imu()
    imu.open()
    imu.read()
    imu.close()
    imu.close()
    assert not imu.health().connected
    with pytest.raises(DeviceError):
        imu.read()
    with imu:  # and it opens again
        imu.read()


# ---------------------------------------------------------------------------------------------------
# the simulated robot (fake only)
# ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("yaw_rate_radps", [0.5, -1.2])
def test_a_turning_robot_reads_its_yaw_rate(fake_rig: Rig, yaw_rate_radps: float) -> None:
    assert fake_rig.sim is not None and fake_rig.clock is not None
    with fake_rig.imu() as imu:
        fake_rig.sim.set_body_velocity(0.0, yaw_rate_radps)  # counter-clockwise positive, seen from above
        fake_rig.clock.t += 1.0  # well past the wheels' ramp
        samples = read_many(imu, fake_rig, 20)
    gz = mean([s.gyro_radps[2] for s in samples])
    assert gz == pytest.approx(yaw_rate_radps, abs=0.005)
    assert abs(mean([s.gyro_radps[0] for s in samples])) < 0.005
    # Turning on the spot: no centripetal force on the base's centre, gravity still on z.
    assert mean([s.accel_mps2[2] for s in samples]) == pytest.approx(G, abs=0.05)


def test_driving_a_curve_shows_centripetal_acceleration(fake_rig: Rig) -> None:
    assert fake_rig.sim is not None and fake_rig.clock is not None
    with fake_rig.imu() as imu:
        fake_rig.sim.set_body_velocity(0.1, 0.5)
        fake_rig.clock.t += 1.0
        samples = read_many(imu, fake_rig, 20)
    v_mps, _, omega_radps = fake_rig.sim.body_motion()
    assert (v_mps, omega_radps) == pytest.approx((0.1, 0.5), abs=1e-6)  # within the wheels' limits
    # a_y = v * omega toward the centre of the turn, which is to the left (+y) for a left turn.
    assert mean([s.accel_mps2[1] for s in samples]) == pytest.approx(v_mps * omega_radps, abs=0.02)


def test_the_part_starts_asleep_and_the_driver_wakes_it(fake_rig: Rig) -> None:
    assert fake_rig.fake is not None
    with SMBus(fake_rig.bus) as smbus:
        assert smbus.read_byte_data(0x68, 0x6B) & 0x40
        assert smbus.read_i2c_block_data(0x68, 0x3B, 14) == [0] * 14  # frozen at reset
    with fake_rig.imu() as imu:
        assert not fake_rig.fake.asleep
        assert imu.read().accel_mps2[2] == pytest.approx(G, abs=0.2)


def test_a_part_that_falls_asleep_is_woken_and_reconfigured(fake_rig: Rig) -> None:
    assert fake_rig.fake is not None
    with fake_rig.imu(accel_range_g=16, gyro_range_dps=2000, sleep_check_interval_s=0.0) as imu:
        imu.read()
        fake_rig.fake.reset()  # brown-out: asleep, configuration back to defaults
        sample = imu.read()
        health = imu.health()
        assert fake_rig.fake.regs[0x1C] == 3 << 3  # +-16 g again: the driver re-wrote its configuration
    assert health.counters["rewakes"] == 1
    assert sample.accel_mps2[2] == pytest.approx(G, abs=0.2)  # and read at the right scale


def test_absent_part_is_device_not_found(fake_rig: Rig) -> None:
    imu = Mpu6050(bus=fake_rig.bus, address=0x69)
    with pytest.raises(DeviceNotFound, match="0x69"):
        imu.open()
    assert not imu.is_open


def test_a_vanishing_part_is_reported_and_recovered_when_back(fake_rig: Rig) -> None:
    assert fake_rig.fake is not None and fake_rig.clock is not None
    with fake_rig.imu(accel_range_g=4) as imu:
        imu.read()
        fake_rig.fake.present = False
        with pytest.raises(DeviceDisconnected, match="stopped acknowledging"):
            imu.read()
        with pytest.raises(DeviceDisconnected):  # still gone: the retry fails the same way
            imu.read()
        health = imu.health()
        assert not health.connected
        assert health.last_error is not None and "DeviceDisconnected" in health.last_error
        fake_rig.fake.reset()  # it comes back from a power cycle: asleep, default configuration
        fake_rig.fake.present = True
        fake_rig.clock.t += 0.01
        sample = imu.read()
        health = imu.health()
    assert health.connected
    assert health.counters["reconnects"] == 1
    assert health.counters["errors"] == 2
    assert fake_rig.fake.regs[0x1C] == 1 << 3  # +-4 g restored
    assert sample.accel_mps2[2] == pytest.approx(G, abs=0.2)
