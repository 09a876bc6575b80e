"""Contract for wheel servos (``drivers.servos.WheelServos``), run against the Dynamixel backend.

By default the backend talks to fake XL430s on a pty that drive a simulated robot. With
``VLP_TEST_DYNAMIXEL_PORT=/dev/ttyUSB0`` (and optionally ``VLP_TEST_DYNAMIXEL_BAUD``, default 57600) the
same checks run on real servos, IDs 1 (left) and 2 (right): **lift the robot's wheels off the ground**;
only small speeds are commanded and the wheels are stopped in ``finally``. Fault injection (pulled cable,
junk on the wire, a silent servo, hardware errors) runs on the fake only.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import pytest
from dynamixel_sdk import COMM_RX_TIMEOUT

from drivers.errors import (
    ConfigError,
    DeviceDisconnected,
    DeviceError,
    DeviceNotFound,
    DeviceStatusError,
    DeviceTimeout,
)
from drivers.fakes.dynamixel import FakeDynamixelBus
from drivers.fakes.pty import PtyServer
from drivers.samples import WheelState
from drivers.servos import WheelOdometry, WheelServos
from drivers.servos.control_table import (
    MODEL_XL430_W250,
    RADPS_PER_VELOCITY_UNIT,
    XL430_W250,
    ControlTable,
    HardwareError,
)
from drivers.servos.dynamixel import DynamixelWheels
from drivers.sim.simulation import Simulation
from drivers.sim.world import World

HARDWARE_PORT = os.environ.get("VLP_TEST_DYNAMIXEL_PORT")
HARDWARE_BAUD = int(os.environ.get("VLP_TEST_DYNAMIXEL_BAUD", "57600"))
SPEED_RADPS = 0.5  # about 1.7 cm/s on a TurtleBot3 wheel: safe on a bench
# The SDK's reply deadline is 2 x latency timer + 2 ms; its 16 ms default is tight for a fake on a pty
# on a loaded, shared machine, so the fake runs get about 100 ms.
FAKE_LATENCY_TIMER_MS = 50.0
ONE_UNIT = RADPS_PER_VELOCITY_UNIT  # Present Velocity resolution


@dataclass
class Backend:
    servos: DynamixelWheels
    sim: Simulation | None = None
    bus: FakeDynamixelBus | None = None
    server: PtyServer | None = None


@contextlib.contextmanager
def fake_backend(
    link: Path, position_ticks: dict[int, int] | None = None, **driver_options: object
) -> Iterator[Backend]:
    sim = Simulation(World("servo-contract"))
    bus = FakeDynamixelBus(sim, position_ticks=position_ticks)
    server = PtyServer(bus, link=link)
    server.start()
    options: dict[str, object] = {"latency_timer_ms": FAKE_LATENCY_TIMER_MS, **driver_options}
    servos = DynamixelWheels(str(link), **options)  # type: ignore[arg-type]
    try:
        with servos:
            yield Backend(servos, sim, bus, server)
    finally:
        server.close()


@pytest.fixture(params=["fake", pytest.param("hardware", marks=pytest.mark.hardware)])
def backend(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Backend]:
    if request.param == "fake":
        with fake_backend(tmp_path / "dxl") as fake:
            yield fake
        return
    if not HARDWARE_PORT:
        pytest.skip("set VLP_TEST_DYNAMIXEL_PORT to run the servo contract on real servos")
    servos = DynamixelWheels(HARDWARE_PORT, baudrate=HARDWARE_BAUD)
    with servos:
        try:
            yield Backend(servos)
        finally:
            with contextlib.suppress(DeviceError):
                servos.stop()


@pytest.fixture
def fake(tmp_path: Path) -> Iterator[Backend]:
    with fake_backend(tmp_path / "dxl") as backend:
        yield backend


def fake_parts(backend: Backend) -> tuple[Simulation, FakeDynamixelBus, PtyServer]:
    assert backend.sim is not None and backend.bus is not None and backend.server is not None
    return backend.sim, backend.bus, backend.server


def read_until(
    servos: WheelServos, condition: Callable[[WheelState], bool], timeout_s: float = 5.0
) -> WheelState:
    """Read until ``condition`` holds; the deadline only keeps a broken backend from hanging the run."""
    deadline = time.monotonic() + timeout_s
    state = servos.read()
    while not condition(state) and time.monotonic() < deadline:
        time.sleep(0.01)
        state = servos.read()
    return state


def near(value: float, target: float, tolerance: float = 2 * ONE_UNIT) -> bool:
    return abs(value - target) <= tolerance


def all_near(values: Sequence[float], targets: Sequence[float], tolerance: float = 2 * ONE_UNIT) -> bool:
    return all(near(v, t, tolerance) for v, t in zip(values, targets, strict=True))


def settled_wheels(
    sim: Simulation, target: tuple[float, float], timeout_s: float = 5.0
) -> tuple[float, float]:
    """The simulated wheels' speeds once both are within half a velocity unit of ``target`` (the goal
    the servos got is ``target`` rounded to whole units); the deadline only stops a hang."""
    deadline = time.monotonic() + timeout_s
    speeds = sim.wheels().velocity_radps
    while not all_near(speeds, target, ONE_UNIT / 2):
        if time.monotonic() > deadline:
            break
        time.sleep(0.005)
        speeds = sim.wheels().velocity_radps
    return speeds


# -- every backend -----------------------------------------------------------------------------------


def test_ping_finds_both_servos(backend: Backend) -> None:
    assert backend.servos.ping() == {1: 1060, 2: 1060}


def test_servos_are_in_velocity_mode_with_torque_on(backend: Backend) -> None:
    for servo_id in backend.servos.ids:
        assert backend.servos.read_item(servo_id, "Operating Mode") == 1
        assert backend.servos.read_item(servo_id, "Torque Enable") == 1
        assert backend.servos.read_item(servo_id, "Drive Mode") & 0x01 == 0
    assert backend.servos.connected


def test_set_velocity_shows_in_read_with_sign_and_magnitude(backend: Backend) -> None:
    servos = backend.servos
    try:
        for left, right in (
            (SPEED_RADPS, -SPEED_RADPS),
            (-SPEED_RADPS, SPEED_RADPS),
            (SPEED_RADPS, SPEED_RADPS),
        ):
            servos.set_velocity(left, right)
            target = (left, right)

            def reached(s: WheelState, target: tuple[float, float] = target) -> bool:
                return all_near(s.velocity_radps, target)

            state = read_until(servos, reached)
            assert state.velocity_radps == pytest.approx((left, right), abs=2 * ONE_UNIT)
            if backend.sim is not None:
                # Forward-positive in the driver is forward-positive on the simulated robot's wheels.
                truth = settled_wheels(backend.sim, (left, right))
                assert truth == pytest.approx((left, right), abs=ONE_UNIT / 2)
    finally:
        servos.stop()


def test_stop_gives_zero_velocity(backend: Backend) -> None:
    servos = backend.servos
    servos.set_velocity(SPEED_RADPS, SPEED_RADPS)
    read_until(servos, lambda s: near(s.velocity_radps[0], SPEED_RADPS))
    servos.stop()
    state = read_until(servos, lambda s: s.velocity_radps == (0.0, 0.0))
    assert state.velocity_radps == pytest.approx((0.0, 0.0), abs=ONE_UNIT)
    assert state.hardware_error == (0, 0)


def test_odometry_advances_when_driving_forward(backend: Backend) -> None:
    servos = backend.servos
    odometry = WheelOdometry(servos.wheel_radius_m, servos.track_m)
    first = odometry.update(servos.read())
    start = backend.sim.pose() if backend.sim is not None else None
    try:
        servos.set_velocity(SPEED_RADPS, SPEED_RADPS)
        deadline = time.monotonic() + 0.6
        while time.monotonic() < deadline:
            odometry.update(servos.read())
            time.sleep(0.02)
    finally:
        servos.stop()
    end = odometry.update(read_until(servos, lambda s: s.velocity_radps == (0.0, 0.0)))
    assert end.x_m - first.x_m > 0.005  # 0.5 rad/s * 0.033 m for ~0.6 s is ~1 cm
    assert abs(end.y_m) < 0.1 * end.x_m and abs(end.yaw_rad) < 0.1
    assert end.distance_m == pytest.approx(end.x_m - first.x_m, rel=0.05)
    if backend.sim is not None and start is not None:
        # The simulated robot went where the odometry says (encoder ticks are 1.5 mrad: 0.05 mm of wheel).
        truth = backend.sim.pose()
        assert (end.x_m, end.y_m) == pytest.approx((truth.x_m - start.x_m, truth.y_m - start.y_m), abs=5e-4)
        assert end.yaw_rad == pytest.approx(truth.yaw_rad - start.yaw_rad, abs=5e-3)


def test_wheel_angles_stay_continuous_across_int32_overflow_and_long_gaps(tmp_path: Path) -> None:
    # Present Position is a signed 32-bit turn counter in velocity mode. Start both servos near its ends,
    # drive at full speed and read only after more than half a wheel turn: the driver has to unwrap
    # across the overflow and must not alias the long gap into a short step backwards.
    ticks = {1: 2**31 - 1000, 2: -(2**31) + 1000}
    # The 0.6 s without a word to the servos is the point here, so their Bus Watchdog stays off.
    with fake_backend(tmp_path / "dxl", position_ticks=ticks, bus_watchdog_ms=0) as backend:
        sim, _, _ = fake_parts(backend)
        servos = backend.servos
        before, truth_before = servos.read(), sim.wheels()
        servos.set_velocity(6.0, 6.0)
        time.sleep(0.6)
        servos.stop()
        # Compare at rest (a reading and the truth taken a few ms apart differ while turning at 6 rad/s);
        # wait on the simulation, not by reading, so the driver sees one long gap.
        deadline = time.monotonic() + 5.0
        while sim.wheels().velocity_radps != (0.0, 0.0) and time.monotonic() < deadline:
            time.sleep(0.01)
        after, truth_after = servos.read(), sim.wheels()
        for i in (0, 1):
            moved = after.position_rad[i] - before.position_rad[i]
            truth = truth_after.position_rad[i] - truth_before.position_rad[i]
            assert truth > math.pi  # the gap really is longer than half a turn
            assert moved == pytest.approx(truth, abs=0.01)


def test_a_refused_write_raises_device_status_error(backend: Backend) -> None:
    # Operating Mode is EEPROM; with torque on the servo refuses it with an Access Error (7).
    with pytest.raises(DeviceStatusError) as info:
        backend.servos.write_item(1, "Operating Mode", 1)
    assert isinstance(info.value.status, int) and info.value.status & 0x7F == 7
    assert backend.servos.health().counters["status_errors"] == 1
    assert backend.servos.read_item(1, "Operating Mode") == 1


def test_torque_off_and_on(backend: Backend) -> None:
    servos = backend.servos
    servos.torque(False)
    assert [servos.read_item(i, "Torque Enable") for i in servos.ids] == [0, 0]
    servos.torque(True)
    assert [servos.read_item(i, "Torque Enable") for i in servos.ids] == [1, 1]
    assert [servos.read_item(i, "Goal Velocity") for i in servos.ids] == [0, 0]
    units = servos.bus_watchdog_units
    assert [servos.read_item(i, "Bus Watchdog") for i in servos.ids] == [units, units]


def test_the_bus_watchdog_is_armed(backend: Backend) -> None:
    units = backend.servos.bus_watchdog_units
    assert units > 0
    assert [backend.servos.read_item(i, "Bus Watchdog") for i in backend.servos.ids] == [units, units]


# -- fake only: limits and faults --------------------------------------------------------------------


def test_commands_beyond_the_velocity_limit_are_clamped(fake: Backend) -> None:
    sim, _, _ = fake_parts(fake)
    limit_radps = 265 * RADPS_PER_VELOCITY_UNIT  # Velocity Limit (44) power-on value
    fake.servos.set_velocity(100.0, -100.0)
    target = (limit_radps, -limit_radps)
    state = read_until(fake.servos, lambda s: all_near(s.velocity_radps, target, ONE_UNIT / 2))
    # A sync-written goal beyond the limit would be dropped by the servo; the driver clamps instead.
    assert state.velocity_radps == pytest.approx(target, abs=ONE_UNIT / 2)
    assert fake.servos.health().counters["clamped_commands"] == 2
    assert settled_wheels(sim, target) == pytest.approx(target, abs=ONE_UNIT / 2)


def test_unplugged_port_is_reported_and_reconnected(fake: Backend) -> None:
    sim, bus, server = fake_parts(fake)
    servos = fake.servos
    servos.set_velocity(SPEED_RADPS, SPEED_RADPS)
    before = read_until(servos, lambda s: near(s.velocity_radps[0], SPEED_RADPS))
    server.unplug()
    with pytest.raises(DeviceDisconnected):
        for _ in range(3):  # the first call may have its reply in flight already
            servos.read()
    assert not servos.connected
    with pytest.raises(DeviceDisconnected):
        servos.read()  # still gone: the reopen fails, reported the same way
    with pytest.raises(DeviceDisconnected):
        servos.set_velocity(0.0, 0.0)
    server.replug()
    after = servos.read()  # reopened and configured again on the next call
    assert servos.connected
    counters = servos.health().counters
    assert counters["disconnects"] == 1 and counters["reconnects"] == 1
    # Bring-up after the reconnect left the servos in velocity mode, torque on, commanded to stand still.
    assert [bus.register(i, "Torque Enable") for i in (1, 2)] == [1, 1]
    assert [bus.register(i, "Goal Velocity") for i in (1, 2)] == [0, 0]
    # Wheel angles carry on from where they were: no jump from re-seeding the unwrapping.
    for b, a in zip(before.position_rad, after.position_rad, strict=True):
        assert a >= b - 1e-9
    assert read_until(servos, lambda s: s.velocity_radps == (0.0, 0.0)).velocity_radps == (0.0, 0.0)
    # reconnect() on request does the same.
    server.unplug()
    server.replug()
    servos.reconnect()
    assert servos.read().velocity_radps == (0.0, 0.0)
    assert servos.health().counters["reconnects"] == 2
    assert sim.wheels().velocity_radps == (0.0, 0.0)


def test_junk_between_frames_is_skipped(fake: Backend) -> None:
    _, bus, server = fake_parts(fake)
    servos = fake.servos
    # Junk on the wire before a reply: the host side resyncs on the next header.
    bus.inject_junk(b"\x00\x55\xff\xff\xfd\xfd\x13\xff")
    servos.read()
    # Junk before an instruction: the fake servos resync too (another writer on the same pty).
    discarded = bus.discarded_bytes
    junk = b"\x42\xff\xff\xfd\xfd\x00\xfe"
    fd = os.open(server.path, os.O_WRONLY | os.O_NOCTTY)
    try:
        os.write(fd, junk)
    finally:
        os.close(fd)
    state = servos.read()
    assert state.hardware_error == (0, 0)
    assert bus.discarded_bytes == discarded + len(junk)
    assert servos.ping() == {1: 1060, 2: 1060}
    assert "timeouts" not in servos.health().counters


def test_a_silent_servo_times_out_instead_of_hanging(fake: Backend) -> None:
    _, bus, _ = fake_parts(fake)
    servos = fake.servos
    bus.mute(2)
    with pytest.raises(DeviceTimeout) as info:
        servos.read()
    assert "servo 2" in str(info.value)
    with pytest.raises(DeviceTimeout):
        servos.ping()
    counters = servos.health().counters
    assert counters["timeouts"] == 2 * (servos.retries + 1) and counters["retries"] == 2 * servos.retries
    bus.mute(2, False)
    assert servos.read().hardware_error == (0, 0)
    assert servos.connected


def drive_like_the_agent(servos: DynamixelWheels, seconds: float, radps: float) -> None:
    """The agent's servo loop for ``seconds``: read, then command; after a failed read, command zero
    (what still listens stops)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            servos.read()
            servos.set_velocity(radps, radps)
        except DeviceError:
            with contextlib.suppress(DeviceError):
                servos.set_velocity(0.0, 0.0)
        time.sleep(0.02)


def drive_until(servos: DynamixelWheels, sim: Simulation, radps: float, timeout_s: float = 3.0) -> None:
    """Drive like the agent until the simulated wheels turn at ``radps`` (or ``timeout_s`` passed): the
    wheels take 0.1 s of simulated time to get there, which a loaded machine stretches."""
    end = time.monotonic() + timeout_s
    while True:
        drive_like_the_agent(servos, 0.1, radps)
        if sim.wheels().velocity_radps == pytest.approx((radps, radps), abs=ONE_UNIT):
            return
        if time.monotonic() > end:
            return


def test_a_servo_cut_off_stops_by_its_bus_watchdog_and_drives_again_when_it_hears(fake: Backend) -> None:
    sim, bus, _ = fake_parts(fake)
    servos = fake.servos
    # (The simulated wheels take 0.1 s to reach 2 rad/s, as long as the watchdog's period: keep talking.)
    drive_like_the_agent(servos, 0.3, 2.0)
    assert sim.wheels().velocity_radps == pytest.approx((2.0, 2.0), abs=ONE_UNIT)
    bus.mute(1)  # the left servo's cable pulled
    cut = time.monotonic()
    stopped_after = math.inf
    while time.monotonic() - cut < 1.0:
        drive_like_the_agent(servos, 0.02, 2.0)
        if sim.wheels().velocity_radps[0] == 0.0:
            stopped_after = min(stopped_after, time.monotonic() - cut)
    # Without the watchdog the left wheel keeps 2 rad/s for as long as the cable is out. With it, its
    # servo stops 220 ms (this latency timer's default) after the last instruction it heard (exact in
    # test_dynamixel_fake_watchdog.py), and the simulated wheel takes 0.1 s more to spin down; a loaded
    # machine may add its delays.
    assert sim.wheels().velocity_radps == (0.0, 0.0)
    assert stopped_after < 0.6
    assert bus.register(1, "Bus Watchdog") == -1
    bus.mute(1, False)
    # Answering again, the servo is found fired and started again; commands turn its wheel once more.
    drive_like_the_agent(servos, 0.4, 2.0)
    assert bus.register(1, "Bus Watchdog") == servos.bus_watchdog_units
    assert sim.wheels().velocity_radps == pytest.approx((2.0, 2.0), abs=ONE_UNIT)
    assert servos.health().counters["bus_watchdog_stops"] == 1


def test_after_a_stall_longer_than_the_watchdog_the_next_command_still_drives(fake: Backend) -> None:
    sim, bus, _ = fake_parts(fake)
    servos = fake.servos
    drive_like_the_agent(servos, 0.3, 2.0)
    time.sleep(0.5)  # the caller stalls: both servos hear nothing for 500 ms and stop
    assert sim.wheels().velocity_radps == (0.0, 0.0)
    assert [bus.register(i, "Bus Watchdog") for i in (1, 2)] == [-1, -1]
    # Their Goal Velocity is read-only now; the driver sees the gap, starts them again, then commands.
    servos.set_velocity(1.0, 1.0)
    units = servos.bus_watchdog_units
    assert [bus.register(i, "Bus Watchdog") for i in (1, 2)] == [units, units]
    assert servos.health().counters["bus_watchdog_stops"] == 2
    drive_until(servos, sim, 1.0)
    assert sim.wheels().velocity_radps == pytest.approx((1.0, 1.0), abs=ONE_UNIT)


def test_the_bus_watchdog_period_outlasts_a_lost_reply() -> None:
    # 20 ms units; by default 100 ms, or twice the reply deadline (2 x latency timer + 2 ms) if longer.
    assert DynamixelWheels("/dev/null").bus_watchdog_units == 5  # SDK's 16 ms: deadline 34 ms
    assert DynamixelWheels("/dev/null", latency_timer_ms=2).bus_watchdog_units == 5
    assert DynamixelWheels("/dev/null", latency_timer_ms=50).bus_watchdog_units == 11  # 2 x 102 -> 220 ms
    assert DynamixelWheels("/dev/null", latency_timer_ms=100).bus_watchdog_units == 21  # 2 x 202 -> 420 ms
    assert DynamixelWheels("/dev/null", bus_watchdog_ms=0).bus_watchdog_units == 0  # off
    assert DynamixelWheels("/dev/null", bus_watchdog_ms=2540).bus_watchdog_units == 127


@pytest.mark.parametrize(("value", "latency_ms"), [(30, 16.0), (-20, 16.0), (2560, 16.0), (200, 50.0)])
def test_a_bus_watchdog_period_the_servo_cannot_hold_is_a_config_error(value: int, latency_ms: float) -> None:
    with pytest.raises(ConfigError) as info:
        DynamixelWheels("/dev/null", bus_watchdog_ms=value, latency_timer_ms=latency_ms)
    assert info.value.key == "servos.bus_watchdog_ms"


def test_servos_without_a_bus_watchdog_still_drive(tmp_path: Path) -> None:
    # Firmware before v38 has no Bus Watchdog: writing it is an Access Error. The driver says so and drives.
    old = ControlTable(
        MODEL_XL430_W250,
        "XL430-W250 (old firmware)",
        tuple(i for i in XL430_W250 if i.name != "Bus Watchdog"),
    )
    sim = Simulation(World("servo-contract"))
    with (
        PtyServer(FakeDynamixelBus(sim, table=old)) as server,
        DynamixelWheels(server.path, latency_timer_ms=FAKE_LATENCY_TIMER_MS) as servos,
    ):
        servos.set_velocity(1.0, 1.0)
        time.sleep(0.3)  # silence: nothing to stop them
        assert sim.wheels().velocity_radps == pytest.approx((1.0, 1.0), abs=ONE_UNIT)
        servos.read()
        servos.set_velocity(0.5, 0.5)
        assert settled_wheels(sim, (0.5, 0.5)) == pytest.approx((0.5, 0.5), abs=ONE_UNIT)


def test_a_corrupt_reply_is_a_device_error(fake: Backend) -> None:
    _, bus, _ = fake_parts(fake)
    bus.corrupt_next_reply()
    with pytest.raises(DeviceError) as info:
        fake.servos.read()
    assert not isinstance(info.value, DeviceTimeout | DeviceDisconnected)
    assert fake.servos.health().counters["corrupt_replies"] == 1
    fake.servos.read()


def test_hardware_error_bits_are_reported(fake: Backend) -> None:
    _, bus, _ = fake_parts(fake)
    servos = fake.servos
    bits = HardwareError.OVERLOAD | HardwareError.OVERHEATING
    bus.set_hardware_error(2, bits)
    state = servos.read()
    assert state.hardware_error == (0, bits)
    assert servos.hardware_errors() == (0, bits)
    health = servos.health()
    assert health.counters["hardware_alerts"] == 1
    assert health.last_error is not None and "OVERLOAD" in health.last_error
    # Overload is in Shutdown (63): the servo dropped its torque, so the right wheel no longer follows.
    servos.set_velocity(SPEED_RADPS, SPEED_RADPS)
    state = read_until(servos, lambda s: near(s.velocity_radps[0], SPEED_RADPS))
    assert state.velocity_radps[1] == 0.0 and state.hardware_error == (0, bits)
    servos.stop()


def test_open_reports_a_missing_port_or_silent_servos(tmp_path: Path) -> None:
    with pytest.raises(DeviceNotFound):
        DynamixelWheels(str(tmp_path / "no-such-port")).open()
    bus = FakeDynamixelBus(ids=(1, 2))
    bus.mute(1)
    bus.mute(2)
    with PtyServer(bus) as server, pytest.raises(DeviceNotFound) as info:
        DynamixelWheels(server.path, retries=0).open()
    assert "no answer" in str(info.value)


def test_close_is_idempotent_and_stops_the_robot(tmp_path: Path) -> None:
    with fake_backend(tmp_path / "dxl") as backend:
        sim, bus, _ = fake_parts(backend)
        backend.servos.set_velocity(SPEED_RADPS, SPEED_RADPS)
        read_until(backend.servos, lambda s: near(s.velocity_radps[0], SPEED_RADPS))
        backend.servos.close()
        backend.servos.close()
        assert [bus.register(i, "Torque Enable") for i in (1, 2)] == [0, 0]
        with pytest.raises(DeviceError):
            backend.servos.read()
        deadline = time.monotonic() + 5.0
        while sim.wheels().velocity_radps != (0.0, 0.0) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert sim.wheels().velocity_radps == (0.0, 0.0)
        assert math.isfinite(sim.pose().x_m)


# -- odometry: pure, on the samples this interface produces --------------------------------------------

R_M, TRACK_M = 0.033, 0.160


def sample(t_s: float, left_rad: float, right_rad: float, wl: float = 0.0, wr: float = 0.0) -> WheelState:
    return WheelState((left_rad, right_rad), (wl, wr), round(t_s * 1e9))


@pytest.mark.parametrize("steps", [1, 7, 300])
def test_odometry_is_exact_on_an_arc_whatever_the_sampling(steps: int) -> None:
    # Constant wheel speeds drive the base on a circle: v = r (wl + wr) / 2, omega = r (wr - wl) / track,
    # yaw(T) = omega T, x = v / omega sin(yaw), y = v / omega (1 - cos(yaw)). Arc integration hits it
    # exactly even in one step, where an Euler step would be centimetres off.
    wl, wr, duration_s = 2.0, 4.0, 3.0
    v, omega = R_M * (wl + wr) / 2, R_M * (wr - wl) / TRACK_M
    odometry = WheelOdometry(R_M, TRACK_M)
    for k in range(steps + 1):
        t = duration_s * k / steps
        odom = odometry.update(sample(t, wl * t, wr * t, wl, wr))
    yaw = omega * duration_s
    assert (odom.x_m, odom.y_m) == pytest.approx(
        (v / omega * math.sin(yaw), v / omega * (1 - math.cos(yaw))), abs=1e-9
    )
    assert odom.yaw_rad == pytest.approx(yaw, abs=1e-12)
    assert (odom.v_mps, odom.omega_radps) == pytest.approx((v, omega), rel=1e-6)  # ns timestamps
    assert odom.distance_m == pytest.approx(v * duration_s, rel=1e-12)


def test_odometry_first_sample_and_time_going_backwards() -> None:
    odometry = WheelOdometry(R_M, TRACK_M, x_m=1.0, y_m=2.0, yaw_rad=math.pi / 2)
    assert odometry.odom is None
    first = odometry.update(sample(10.0, 5.0, -3.0, 1.0, 1.0))  # arbitrary absolute angles: reference only
    assert (first.x_m, first.y_m, first.yaw_rad) == pytest.approx((1.0, 2.0, math.pi / 2))
    assert first.v_mps == pytest.approx(R_M)  # from the servos' own speed readings
    moved = odometry.update(sample(11.0, 6.0, -2.0, 1.0, 1.0))  # both wheels 1 rad forward, heading +y
    assert (moved.x_m, moved.y_m) == pytest.approx((1.0, 2.0 + R_M), abs=1e-12)
    assert moved.v_mps == pytest.approx(R_M)
    # A sample stamped earlier than the last one: the angles still count, the velocity does not divide by
    # a negative interval.
    back = odometry.update(sample(10.5, 7.0, -1.0, 0.5, 0.5))
    assert (back.x_m, back.y_m) == pytest.approx((1.0, 2.0 + 2 * R_M), abs=1e-12)
    assert back.v_mps == pytest.approx(0.5 * R_M) and odometry.time_reversals == 1
    later = odometry.update(sample(11.5, 8.0, 0.0))
    assert later.v_mps == pytest.approx(R_M) and later.y_m == pytest.approx(2.0 + 3 * R_M)
    odometry.reset()
    assert odometry.odom is None and odometry.update(sample(12.0, 0.0, 0.0)).x_m == 0.0


def test_odometry_turning_on_the_spot() -> None:
    odometry = WheelOdometry(R_M, TRACK_M)
    odometry.update(sample(0.0, 0.0, 0.0))
    quarter_turn_rad = (math.pi / 2) * (TRACK_M / 2) / R_M  # wheel angle for a 90 degree turn
    odom = odometry.update(sample(1.0, -quarter_turn_rad, quarter_turn_rad))
    assert (odom.x_m, odom.y_m) == pytest.approx((0.0, 0.0), abs=1e-12)
    assert odom.yaw_rad == pytest.approx(math.pi / 2) and odom.omega_radps == pytest.approx(math.pi / 2)
    assert odom.v_mps == pytest.approx(0.0, abs=1e-12)


def test_one_servo_found_stopped_gets_the_other_checked_so_the_robot_does_not_pivot(fake: Backend) -> None:
    # The bus cut off from both servos (a cable between the adapter and the first servo): both watchdogs
    # fire, but the sync reads that time out name only the first servo that did not answer. Found
    # stopped, it makes the other a suspect in the same check: both are started again together, and the
    # next goal turns both wheels (the other, still latched, would refuse it and the robot would pivot).
    sim, bus, _ = fake_parts(fake)
    servos = fake.servos
    drive_like_the_agent(servos, 0.3, 2.0)
    servos._next_watchdog_check = time.monotonic() + 60.0  # no once-a-second check of both in this test
    bus.mute(1)
    bus.mute(2)
    cut = time.monotonic()
    while time.monotonic() - cut < 0.6:
        drive_like_the_agent(servos, 0.02, 2.0)
    assert [bus.register(i, "Bus Watchdog") for i in (1, 2)] == [-1, -1]
    bus.mute(1, False)
    bus.mute(2, False)
    servos.read()
    units = servos.bus_watchdog_units
    assert [bus.register(i, "Bus Watchdog") for i in (1, 2)] == [units, units]
    assert servos.health().counters["bus_watchdog_stops"] == 2
    drive_until(servos, sim, 2.0)
    assert sim.wheels().velocity_radps == pytest.approx((2.0, 2.0), abs=ONE_UNIT)


def _lose_bus_watchdog_replies(
    servos: DynamixelWheels, monkeypatch: pytest.MonkeyPatch, count: int
) -> list[int]:
    """The next ``count`` Bus Watchdog reads time out as a reply lost to a loaded host would; every other
    read goes to the real SDK's packet handler. Returns the servos whose replies were lost."""
    real = servos._ph.readTxRx
    address = next(item.address for item in XL430_W250 if item.name == "Bus Watchdog")
    lost: list[int] = []

    def read(port: object, servo_id: int, at: int, length: int) -> tuple[list[int], int, int]:
        if at == address and len(lost) < count:
            lost.append(servo_id)
            return [], COMM_RX_TIMEOUT, 0
        return real(port, servo_id, at, length)  # type: ignore[no-any-return]

    monkeypatch.setattr(servos._ph, "readTxRx", read)
    return lost


def test_a_lost_bus_watchdog_reply_is_read_again(fake: Backend, monkeypatch: pytest.MonkeyPatch) -> None:
    servos = fake.servos
    assert isinstance(servos, DynamixelWheels)
    lost = _lose_bus_watchdog_replies(servos, monkeypatch, 1)
    retries = servos.health().counters.get("retries", 0)
    servos._next_watchdog_check = 0.0  # the once-a-second check of both servos, now
    servos.read()
    assert lost == [1]
    assert servos.health().counters["retries"] == retries + 1
    assert servos._watchdog_suspects == set()  # read again and found armed


def test_a_bus_watchdog_check_that_times_out_keeps_the_state_read_and_its_suspect(
    fake: Backend, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Every try of the check's read lost: read() still returns the state both servos just sent, the
    # silent one stays a suspect, and the next read checks it again.
    servos = fake.servos
    assert isinstance(servos, DynamixelWheels)
    lost = _lose_bus_watchdog_replies(servos, monkeypatch, servos.retries + 1)
    timeouts = servos.health().counters.get("timeouts", 0)
    servos._next_watchdog_check = 0.0
    state = servos.read()
    assert isinstance(state, WheelState)
    assert lost == [1] * (servos.retries + 1)
    assert servos.health().counters["timeouts"] == timeouts + servos.retries + 1
    assert 1 in servos._watchdog_suspects
    servos.read()
    assert servos._watchdog_suspects == set()


def test_a_command_whose_bus_watchdog_check_times_out_says_so(
    fake: Backend, monkeypatch: pytest.MonkeyPatch
) -> None:
    # After a stall a command checks the watchdogs before it returns; a servo that does not answer that
    # check is an error of the command (the wheel may still be latched), not silence.
    servos = fake.servos
    assert isinstance(servos, DynamixelWheels)
    _lose_bus_watchdog_replies(servos, monkeypatch, servos.retries + 1)
    servos._watchdog_suspects.update(servos.ids)
    servos._last_transaction = time.monotonic() - 10.0  # the caller stalled
    with pytest.raises(DeviceTimeout, match="READ Bus Watchdog"):
        servos.set_velocity(0.0, 0.0)
