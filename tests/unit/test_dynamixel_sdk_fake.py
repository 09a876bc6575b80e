"""The fake XL430 servos checked by an independent client: the real dynamixel-sdk over a pty.

Nothing of ours sits on the client side here: PortHandler opens the pty path like a USB adapter,
PacketHandler(2.0) and the Group* helpers build and parse every byte, so what passes here is what the
ROBOTIS tools would see.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import dynamixel_sdk.port_handler
import numpy as np
import pytest
from dynamixel_sdk import (
    BROADCAST_ID,
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    GroupBulkRead,
    GroupSyncRead,
    GroupSyncWrite,
    PacketHandler,
    PortHandler,
)

from drivers.fakes.dynamixel import FakeDynamixelBus
from drivers.fakes.pty import PtyServer
from drivers.servos.control_table import RADPS_PER_VELOCITY_UNIT, HardwareError
from drivers.sim.simulation import Simulation
from drivers.sim.world import World
from firmware_protocol.dynamixel import ErrorNumber, encode_read

ADDR_OPERATING_MODE = 11
ADDR_TORQUE = 64
ADDR_LED = 65
ADDR_STATUS_RETURN_LEVEL = 68
ADDR_REGISTERED = 69
ADDR_HARDWARE_ERROR = 70
ADDR_BUS_WATCHDOG = 98
ADDR_GOAL_VELOCITY = 104
ADDR_PRESENT_VELOCITY = 128
ADDR_PRESENT_POSITION = 132
ADDR_INDIRECT_DATA_1 = 224

# The SDK waits 2 x LATENCY_TIMER + 2 ms (+ the bytes' time) for a reply, measured on the wall clock while
# it spins; a reply ends the wait at once. For instructions that must be answered the deadline is long
# (about 1 s): with a CPU hog and other jobs on 2 cores the fake's thread or this one can be off the CPU for
# over 100 ms, and 50 (102 ms) timed out (-3001). Silence awaited keeps the SDK's own 16 (34 ms), so the
# tests that expect no answer stay fast; only deadlines change, not a byte on the wire.
ANSWER_LATENCY_TIMER = 500
SILENCE_LATENCY_TIMER = 16


@dataclass
class Rig:
    sim: Simulation
    bus: FakeDynamixelBus
    server: PtyServer
    port: PortHandler
    ph: PacketHandler


@pytest.fixture
def rig(monkeypatch: pytest.MonkeyPatch) -> Iterator[Rig]:
    monkeypatch.setattr(dynamixel_sdk.port_handler, "LATENCY_TIMER", ANSWER_LATENCY_TIMER)
    sim = Simulation(World("sdk-fake"))
    bus = FakeDynamixelBus(sim)
    with PtyServer(bus) as server:
        port = PortHandler(server.path)
        assert port.setBaudRate(57600)
        try:
            yield Rig(sim, bus, server, port, PacketHandler(2.0))
        finally:
            port.closePort()


def wait_for(condition: Callable[[], bool], timeout_s: float = 5.0) -> bool:
    """Poll until ``condition`` holds; the deadline only stops a broken test from hanging."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.01)
    return condition()


@contextlib.contextmanager
def silence_expected() -> Iterator[None]:
    """Within: the SDK's short deadline, for an instruction that no servo should answer."""
    saved = dynamixel_sdk.port_handler.LATENCY_TIMER
    dynamixel_sdk.port_handler.LATENCY_TIMER = SILENCE_LATENCY_TIMER
    try:
        yield
    finally:
        dynamixel_sdk.port_handler.LATENCY_TIMER = saved


def signed32(value: int) -> int:
    return value - (1 << 32) if value & 0x80000000 else value


def ok(result: int, error: int = 0) -> None:
    assert (result, error) == (COMM_SUCCESS, 0)


def velocity_mode_torque_on(rig: Rig) -> None:
    for servo_id in (1, 2):
        ok(*rig.ph.write1ByteTxRx(rig.port, servo_id, ADDR_OPERATING_MODE, 1))
        ok(*rig.ph.write1ByteTxRx(rig.port, servo_id, ADDR_TORQUE, 1))


def sync_write_goal_velocity(rig: Rig, units: dict[int, int]) -> None:
    group = GroupSyncWrite(rig.port, rig.ph, ADDR_GOAL_VELOCITY, 4)
    for servo_id, value in units.items():
        assert group.addParam(servo_id, list(value.to_bytes(4, "little", signed=True)))
    assert group.txPacket() == COMM_SUCCESS


def test_ping_finds_two_xl430(rig: Rig) -> None:
    for servo_id in (1, 2):
        model, result, error = rig.ph.ping(rig.port, servo_id)
        ok(result, error)
        assert model == 1060
    with silence_expected():
        _, result, _ = rig.ph.ping(rig.port, 3)
    assert result == COMM_RX_TIMEOUT


def test_an_id_written_takes_effect_at_once(rig: Rig) -> None:
    # ID (7) is EEPROM: writable with the torque off (as after power-on). The servo answers that very
    # write from its new id already (which the SDK, waiting for id 2, does not take: sent without waiting
    # here, its status then received on its own), and from then on it answers to the new id only.
    assert rig.ph.write1ByteTxOnly(rig.port, 2, 7, 9) == COMM_SUCCESS
    # That status must be read before the next instruction: the SDK flushes its input only when it sends,
    # and a status still on its way then (the fake's thread off the CPU beside a CPU hog) would be taken
    # as the ping's answer (id 9, no parameters: the model read from its checksum).
    rig.port.setPacketTimeout(11)  # a status without parameters: 11 bytes
    status, result = rig.ph.rxPacket(rig.port, False)
    assert result == COMM_SUCCESS
    assert (status[4], status[7], status[8]) == (9, 0x55, 0)  # from id 9, a status, no error
    assert wait_for(lambda: rig.bus.ids == (1, 9))
    model, result, error = rig.ph.ping(rig.port, 9)
    ok(result, error)
    assert model == 1060
    with silence_expected():
        assert rig.ph.ping(rig.port, 2)[1] == COMM_RX_TIMEOUT


def test_broadcast_ping_lists_both_servos(rig: Rig) -> None:
    found, result = rig.ph.broadcastPing(rig.port)
    assert result == COMM_SUCCESS
    assert found == {1: [1060, 46], 2: [1060, 46]}


def test_reads_of_one_two_and_four_bytes_show_power_on_values(rig: Rig) -> None:
    ph, port = rig.ph, rig.port
    assert ph.read1ByteTxRx(port, 2, 7) == (2, COMM_SUCCESS, 0)  # ID
    assert ph.read1ByteTxRx(port, 1, 8) == (1, COMM_SUCCESS, 0)  # Baud Rate index 1 = 57600
    assert ph.read1ByteTxRx(port, 1, 9) == (250, COMM_SUCCESS, 0)  # Return Delay Time
    assert ph.read1ByteTxRx(port, 1, ADDR_OPERATING_MODE) == (3, COMM_SUCCESS, 0)  # position mode
    assert ph.read1ByteTxRx(port, 1, ADDR_STATUS_RETURN_LEVEL) == (2, COMM_SUCCESS, 0)
    assert ph.read1ByteTxRx(port, 1, ADDR_TORQUE) == (0, COMM_SUCCESS, 0)
    assert ph.read2ByteTxRx(port, 1, 0) == (1060, COMM_SUCCESS, 0)  # Model Number
    assert ph.read2ByteTxRx(port, 2, 32) == (140, COMM_SUCCESS, 0)  # Max Voltage Limit
    assert ph.read4ByteTxRx(port, 1, 44) == (265, COMM_SUCCESS, 0)  # Velocity Limit
    assert ph.read4ByteTxRx(port, 1, ADDR_PRESENT_POSITION) == (1024, COMM_SUCCESS, 0)
    assert ph.read4ByteTxRx(port, 2, ADDR_PRESENT_POSITION) == (3072, COMM_SUCCESS, 0)
    # Past the end of the table: an Access Error status without data. The SDK hands back what follows ERR
    # (here the CRC) as "data", and read4ByteTxRx would raise IndexError, so look at the error only.
    _, result, error = ph.readTxRx(port, 1, 660, 4)
    assert (result, error) == (COMM_SUCCESS, ErrorNumber.ACCESS)


def test_writes_are_checked_like_a_servo_does(rig: Rig) -> None:
    ph, port = rig.ph, rig.port
    ok(*ph.write1ByteTxRx(port, 1, ADDR_LED, 1))
    assert ph.read1ByteTxRx(port, 1, ADDR_LED) == (1, COMM_SUCCESS, 0)
    ok(*ph.write4ByteTxRx(port, 2, 108, 40))  # Profile Acceleration
    assert ph.read4ByteTxRx(port, 2, 108) == (40, COMM_SUCCESS, 0)
    assert ph.write4ByteTxRx(port, 1, ADDR_PRESENT_POSITION, 0) == (COMM_SUCCESS, ErrorNumber.ACCESS)
    assert ph.write1ByteTxRx(port, 1, 40, 0) == (COMM_SUCCESS, ErrorNumber.ACCESS)  # undefined address
    assert ph.write1ByteTxRx(port, 1, ADDR_GOAL_VELOCITY, 5) == (COMM_SUCCESS, ErrorNumber.DATA_LENGTH)
    assert ph.write1ByteTxRx(port, 1, ADDR_STATUS_RETURN_LEVEL, 3) == (COMM_SUCCESS, ErrorNumber.DATA_RANGE)
    assert ph.write1ByteTxRx(port, 1, ADDR_OPERATING_MODE, 2) == (COMM_SUCCESS, ErrorNumber.DATA_RANGE)
    # Goal Velocity beyond Velocity Limit (265) is a data limit error, and the old goal stays.
    assert ph.write4ByteTxRx(port, 1, ADDR_GOAL_VELOCITY, 300) == (COMM_SUCCESS, ErrorNumber.DATA_LIMIT)
    assert ph.read4ByteTxRx(port, 1, ADDR_GOAL_VELOCITY) == (0, COMM_SUCCESS, 0)


def test_access_error_for_an_eeprom_write_with_torque_on(rig: Rig) -> None:
    ph, port = rig.ph, rig.port
    ok(*ph.write1ByteTxRx(port, 1, ADDR_TORQUE, 1))
    assert ph.write1ByteTxRx(port, 1, ADDR_OPERATING_MODE, 1) == (COMM_SUCCESS, ErrorNumber.ACCESS)
    assert ph.read1ByteTxRx(port, 1, ADDR_OPERATING_MODE) == (3, COMM_SUCCESS, 0)
    ok(*ph.write1ByteTxRx(port, 1, ADDR_TORQUE, 0))
    ok(*ph.write1ByteTxRx(port, 1, ADDR_OPERATING_MODE, 1))
    assert ph.read1ByteTxRx(port, 1, ADDR_OPERATING_MODE) == (1, COMM_SUCCESS, 0)


def test_read_of_a_value_holding_ff_ff_fd_is_stuffed_on_the_wire(rig: Rig) -> None:
    ph, port = rig.ph, rig.port
    # One WRITE across Indirect Data 1..3: the SDK stuffs this instruction, the fake has to unstuff it.
    ok(*ph.writeTxRx(port, 1, ADDR_INDIRECT_DATA_1, 3, [0xFF, 0xFF, 0xFD]))
    assert wait_for(lambda: rig.server.bytes_out == 11)  # the WRITE's status, counted
    before = rig.server.bytes_out
    value, result, error = ph.read4ByteTxRx(port, 1, ADDR_INDIRECT_DATA_1)
    ok(result, error)
    assert value == 0x00FDFFFF
    # A 4-byte READ reply is 15 bytes; the stuffed FD makes it 16. (The server thread counts a write after
    # it returns, which can be after the SDK already has the reply: wait for the count, then check it.)
    assert wait_for(lambda: rig.server.bytes_out - before >= 15)
    assert rig.server.bytes_out - before == 16


def test_sync_write_then_sync_read_velocity_and_position(rig: Rig) -> None:
    velocity_mode_torque_on(rig)
    # The right servo is mirrored: -120 on it turns the right wheel forward, like +120 on the left.
    sync_write_goal_velocity(rig, {1: 120, 2: -120})
    assert rig.ph.read4ByteTxRx(rig.port, 2, ADDR_GOAL_VELOCITY) == ((-120) & 0xFFFFFFFF, COMM_SUCCESS, 0)

    group = GroupSyncRead(rig.port, rig.ph, ADDR_PRESENT_VELOCITY, 8)
    assert group.addParam(1) and group.addParam(2)

    def settled() -> bool:
        assert group.txRxPacket() == COMM_SUCCESS
        return [signed32(group.getData(i, ADDR_PRESENT_VELOCITY, 4)) for i in (1, 2)] == [120, -120]

    assert wait_for(settled)
    first = [signed32(group.getData(i, ADDR_PRESENT_POSITION, 4)) for i in (1, 2)]
    time.sleep(0.1)
    assert group.txRxPacket() == COMM_SUCCESS
    second = [signed32(group.getData(i, ADDR_PRESENT_POSITION, 4)) for i in (1, 2)]
    assert second[0] > first[0] and second[1] < first[1]
    truth = rig.sim.wheels()
    assert truth.velocity_radps == pytest.approx((120 * RADPS_PER_VELOCITY_UNIT,) * 2)


def test_fast_sync_read_and_bulk_read(rig: Rig) -> None:
    group = GroupSyncRead(rig.port, rig.ph, ADDR_PRESENT_POSITION, 4)
    assert group.addParam(1) and group.addParam(2)
    assert group.fastSyncRead() == COMM_SUCCESS
    assert [group.getData(i, ADDR_PRESENT_POSITION, 4) for i in (1, 2)] == [1024, 3072]

    bulk = GroupBulkRead(rig.port, rig.ph)
    assert bulk.addParam(1, 144, 2) and bulk.addParam(2, 146, 1)  # input voltage, temperature
    assert bulk.txRxPacket() == COMM_SUCCESS
    assert bulk.getData(1, 144, 2) == 120 and bulk.getData(2, 146, 1) == 32
    assert bulk.fastBulkRead() == COMM_SUCCESS
    assert bulk.getData(1, 144, 2) == 120 and bulk.getData(2, 146, 1) == 32


def test_goal_velocity_moves_the_simulated_robot_forward(rig: Rig) -> None:
    velocity_mode_torque_on(rig)
    sync_write_goal_velocity(rig, {1: 100, 2: -100})
    assert wait_for(lambda: rig.sim.pose().x_m > 0.02)
    pose = rig.sim.pose()
    assert abs(pose.y_m) < 1e-3 and abs(pose.yaw_rad) < 1e-2
    # Same sign on both servos turns the robot on the spot (counter-clockwise: right wheel forward).
    sync_write_goal_velocity(rig, {1: -100, 2: -100})
    yaw0 = rig.sim.pose().yaw_rad
    assert wait_for(lambda: rig.sim.pose().yaw_rad > yaw0 + 0.2)
    sync_write_goal_velocity(rig, {1: 0, 2: 0})
    assert wait_for(lambda: rig.sim.wheels().velocity_radps == (0.0, 0.0))


def test_torque_off_stops_the_wheels(rig: Rig) -> None:
    velocity_mode_torque_on(rig)
    sync_write_goal_velocity(rig, {1: 100, 2: -100})
    assert wait_for(lambda: rig.sim.wheels().velocity_radps[0] > 2.0)
    ok(*rig.ph.write1ByteTxRx(rig.port, 1, ADDR_TORQUE, 0))
    assert wait_for(lambda: rig.sim.wheels().velocity_radps[0] == 0.0)
    assert rig.sim.wheels().velocity_radps[1] > 2.0


def test_reg_write_waits_for_action(rig: Rig) -> None:
    ph, port = rig.ph, rig.port
    ok(*ph.regWriteTxRx(port, 1, ADDR_LED, 1, [1]))
    assert ph.read1ByteTxRx(port, 1, ADDR_LED) == (0, COMM_SUCCESS, 0)
    assert ph.read1ByteTxRx(port, 1, ADDR_REGISTERED) == (1, COMM_SUCCESS, 0)
    assert ph.action(port, BROADCAST_ID) == COMM_SUCCESS  # broadcast: no status comes back
    assert wait_for(lambda: ph.read1ByteTxRx(port, 1, ADDR_LED) == (1, COMM_SUCCESS, 0))
    assert ph.read1ByteTxRx(port, 1, ADDR_REGISTERED) == (0, COMM_SUCCESS, 0)


def test_reboot_and_factory_reset(rig: Rig) -> None:
    ph, port = rig.ph, rig.port
    ok(*ph.write1ByteTxRx(port, 2, ADDR_OPERATING_MODE, 1))
    ok(*ph.write1ByteTxRx(port, 2, ADDR_TORQUE, 1))
    rig.bus.set_hardware_error(2, HardwareError.OVERLOAD)
    assert ph.reboot(port, 2) == (COMM_SUCCESS, 0x80)  # answered before rebooting, so still alerting
    assert ph.read1ByteTxRx(port, 2, ADDR_TORQUE) == (0, COMM_SUCCESS, 0)  # RAM back to power-on values
    assert ph.read1ByteTxRx(port, 2, ADDR_HARDWARE_ERROR) == (0, COMM_SUCCESS, 0)
    assert ph.read1ByteTxRx(port, 2, ADDR_OPERATING_MODE) == (1, COMM_SUCCESS, 0)  # EEPROM kept
    ok(*ph.factoryReset(port, 2, 0x01))  # all but the ID
    assert ph.read1ByteTxRx(port, 2, ADDR_OPERATING_MODE) == (3, COMM_SUCCESS, 0)
    assert ph.read1ByteTxRx(port, 2, 7) == (2, COMM_SUCCESS, 0)


def test_hardware_error_sets_the_alert_bit_and_turns_torque_off(rig: Rig) -> None:
    ph, port = rig.ph, rig.port
    ok(*ph.write1ByteTxRx(port, 1, ADDR_TORQUE, 1))
    rig.bus.set_hardware_error(1, HardwareError.OVERHEATING)
    # The instruction still succeeds; only the alert bit (0x80) is set, on every status of that servo.
    assert ph.read1ByteTxRx(port, 1, ADDR_HARDWARE_ERROR) == (HardwareError.OVERHEATING, COMM_SUCCESS, 0x80)
    assert ph.read1ByteTxRx(port, 1, ADDR_TORQUE) == (0, COMM_SUCCESS, 0x80)  # Shutdown covers overheating
    assert ph.read1ByteTxRx(port, 2, ADDR_TORQUE) == (0, COMM_SUCCESS, 0)


def test_status_return_level_one_answers_reads_only(rig: Rig) -> None:
    ph, port = rig.ph, rig.port
    assert ph.write1ByteTxOnly(port, 1, ADDR_STATUS_RETURN_LEVEL, 1) == COMM_SUCCESS
    assert wait_for(lambda: ph.read1ByteTxRx(port, 1, ADDR_STATUS_RETURN_LEVEL) == (1, COMM_SUCCESS, 0))
    with silence_expected():
        assert ph.write1ByteTxRx(port, 1, ADDR_LED, 1)[0] == COMM_RX_TIMEOUT  # carried out, not answered
    assert ph.read1ByteTxRx(port, 1, ADDR_LED) == (1, COMM_SUCCESS, 0)
    assert ph.ping(port, 1)[1] == COMM_SUCCESS


def test_bus_watchdog_stops_a_servo_that_hears_nothing_and_latches_until_cleared(rig: Rig) -> None:
    # The e-Manual's own example (XL430-W250, "Bus Watchdog (98) Example"), with a 100 ms period.
    ph, port = rig.ph, rig.port
    velocity_mode_torque_on(rig)
    assert ph.read1ByteTxRx(port, 1, ADDR_BUS_WATCHDOG) == (0, COMM_SUCCESS, 0)  # off at power-on
    ok(*ph.write1ByteTxRx(port, 1, ADDR_BUS_WATCHDOG, 5))  # 5 x 20 ms
    ok(*ph.write4ByteTxRx(port, 1, ADDR_GOAL_VELOCITY, 50))
    assert wait_for(lambda: rig.sim.wheels().velocity_radps[0] > 0.5)
    # Silence on the bus: the servo stops by itself and Bus Watchdog reads -1 (0xFF).
    assert wait_for(lambda: rig.sim.wheels().velocity_radps[0] == 0.0)
    assert ph.read1ByteTxRx(port, 1, ADDR_BUS_WATCHDOG) == (0xFF, COMM_SUCCESS, 0)
    assert ph.read4ByteTxRx(port, 1, ADDR_PRESENT_VELOCITY) == (0, COMM_SUCCESS, 0)
    assert ph.read1ByteTxRx(port, 2, ADDR_BUS_WATCHDOG) == (0, COMM_SUCCESS, 0)  # the other was not armed
    # Goal Velocity is read-only now: a new goal gets a Data Range Error and changes nothing; so does
    # re-arming without clearing, and a sync write's goal (no status) is dropped.
    assert ph.write4ByteTxRx(port, 1, ADDR_GOAL_VELOCITY, 150) == (COMM_SUCCESS, ErrorNumber.DATA_RANGE)
    assert ph.write1ByteTxRx(port, 1, ADDR_BUS_WATCHDOG, 5) == (COMM_SUCCESS, ErrorNumber.DATA_RANGE)
    sync_write_goal_velocity(rig, {1: 150, 2: 0})
    assert ph.read4ByteTxRx(port, 1, ADDR_GOAL_VELOCITY) == (50, COMM_SUCCESS, 0)
    assert rig.sim.wheels().velocity_radps[0] == 0.0
    # Writing 0 clears it; then a goal is taken again.
    ok(*ph.write1ByteTxRx(port, 1, ADDR_BUS_WATCHDOG, 0))
    ok(*ph.write4ByteTxRx(port, 1, ADDR_GOAL_VELOCITY, 150))
    assert wait_for(lambda: rig.sim.wheels().velocity_radps[0] > 150 * RADPS_PER_VELOCITY_UNIT * 0.99)
    assert ph.write1ByteTxRx(port, 1, ADDR_BUS_WATCHDOG, 128) == (COMM_SUCCESS, ErrorNumber.DATA_RANGE)
    assert ph.write1ByteTxRx(port, 1, ADDR_BUS_WATCHDOG, 0xFF) == (COMM_SUCCESS, ErrorNumber.DATA_RANGE)


def test_bus_watchdog_is_kept_quiet_by_instructions_and_only_watches_with_torque_on(rig: Rig) -> None:
    ph, port = rig.ph, rig.port
    velocity_mode_torque_on(rig)
    ok(*ph.write1ByteTxRx(port, 1, ADDR_BUS_WATCHDOG, 25))  # 500 ms
    sync_write_goal_velocity(rig, {1: 50, 2: 0})
    end = time.monotonic() + 1.2
    while time.monotonic() < end:  # any instruction counts: pings, reads, broadcast sync writes
        ok(*ph.ping(port, 1)[1:])
        sync_write_goal_velocity(rig, {1: 50, 2: 0})
        time.sleep(0.05)
    assert ph.read1ByteTxRx(port, 1, ADDR_BUS_WATCHDOG) == (25, COMM_SUCCESS, 0)
    assert rig.sim.wheels().velocity_radps[0] > 0.5
    # Torque off: nothing to watch, however long the silence.
    ok(*ph.write1ByteTxRx(port, 1, ADDR_TORQUE, 0))
    time.sleep(0.7)
    assert ph.read1ByteTxRx(port, 1, ADDR_BUS_WATCHDOG) == (25, COMM_SUCCESS, 0)
    # A reboot puts RAM, Bus Watchdog included, back to power-on values (0: off).
    ok(*ph.write1ByteTxRx(port, 1, ADDR_TORQUE, 1))
    time.sleep(0.7)  # (polling would keep it quiet)
    assert ph.read1ByteTxRx(port, 1, ADDR_BUS_WATCHDOG) == (0xFF, COMM_SUCCESS, 0)
    ok(*ph.reboot(port, 1))
    assert ph.read1ByteTxRx(port, 1, ADDR_BUS_WATCHDOG) == (0, COMM_SUCCESS, 0)


def test_muted_servo_does_not_answer(rig: Rig) -> None:
    rig.bus.mute(2)
    group = GroupSyncRead(rig.port, rig.ph, ADDR_PRESENT_VELOCITY, 8)
    assert group.addParam(1) and group.addParam(2)
    with silence_expected():
        assert rig.ph.ping(rig.port, 2)[1] == COMM_RX_TIMEOUT
        assert group.txRxPacket() == COMM_RX_TIMEOUT
    rig.bus.mute(2, False)
    assert rig.ph.ping(rig.port, 2)[1] == COMM_SUCCESS


def test_junk_before_an_instruction_and_a_damaged_instruction(rig: Rig) -> None:
    ph, port = rig.ph, rig.port
    discarded = rig.bus.discarded_bytes
    junk = b"\x00\x42\xff\xff\xfd\xfd\xff"
    assert port.writePort(junk) == len(junk)
    assert ph.ping(port, 1) == (1060, COMM_SUCCESS, 0)
    assert rig.bus.discarded_bytes == discarded + len(junk)

    damaged = bytearray(encode_read(1, ADDR_PRESENT_POSITION, 4))
    damaged[-1] ^= 0x55
    port.clearPort()
    assert port.writePort(bytes(damaged)) == len(damaged)
    port.setPacketTimeout(11)
    reply, result = ph.rxPacket(port, False)
    assert result == COMM_SUCCESS
    assert reply[4] == 1 and reply[8] == ErrorNumber.CRC  # the e-Manual's CRC Error status
    assert ph.ping(port, 1) == (1060, COMM_SUCCESS, 0)


def test_a_sync_read_samples_both_wheels_at_the_same_instant(monkeypatch: pytest.MonkeyPatch) -> None:
    """Servos that hear one Sync Read answer with their positions of that moment, however long the fake
    takes between the two replies (here the simulation's clock moves 1-9 ms whenever it is read). Sampled
    one after the other, a robot driving straight would show turns in its odometry."""
    monkeypatch.setattr(dynamixel_sdk.port_handler, "LATENCY_TIMER", ANSWER_LATENCY_TIMER)
    rng = np.random.default_rng(0)
    t = [0.0]

    def clock() -> float:
        t[0] += float(rng.uniform(0.001, 0.009))
        return t[0]

    sim = Simulation(World("sdk-fake"), clock=clock)
    bus = FakeDynamixelBus(sim)
    with PtyServer(bus) as server:
        port = PortHandler(server.path)
        assert port.setBaudRate(57600)
        try:
            rig = Rig(sim, bus, server, port, PacketHandler(2.0))
            velocity_mode_torque_on(rig)
            sync_write_goal_velocity(rig, {1: 120, 2: -120})  # straight ahead (the right servo mirrored)
            group = GroupSyncRead(port, rig.ph, ADDR_PRESENT_VELOCITY, 8)
            assert group.addParam(1) and group.addParam(2)

            def read() -> tuple[list[int], list[int]]:
                assert group.txRxPacket() == COMM_SUCCESS
                return (
                    [signed32(group.getData(i, ADDR_PRESENT_VELOCITY, 4)) for i in (1, 2)],
                    [signed32(group.getData(i, ADDR_PRESENT_POSITION, 4)) for i in (1, 2)],
                )

            assert wait_for(lambda: read()[0] == [120, -120])
            # At one speed both wheels roll alike: left minus right (mirrored) is the same at every read.
            differences = []
            for _ in range(10):
                position = read()[1]
                differences.append(position[0] + position[1])
            assert max(differences) - min(differences) <= 1, differences
        finally:
            port.closePort()
