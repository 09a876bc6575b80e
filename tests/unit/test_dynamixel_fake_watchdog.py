"""The fake XL430's Bus Watchdog (98) on a clock the test sets: when it fires, what counts as hearing.

The same behaviour through the real dynamixel-sdk on a pty is in ``test_dynamixel_sdk_fake.py``; here the
instants are exact, so the boundary ("an interval larger than the set value") is checked to the tick.
"""

from __future__ import annotations

import pytest

from drivers.fakes.dynamixel import FakeDynamixelBus
from drivers.servos.control_table import XL430_W250
from firmware_protocol.dynamixel import (
    DynamixelDecoder,
    ErrorNumber,
    StatusPacket,
    encode_ping,
    encode_sync_write,
    encode_write,
)

_GOAL = XL430_W250["Goal Velocity"]


def write(bus: FakeDynamixelBus, servo_id: int, name: str, value: int, now: float) -> int:
    """The error number of a WRITE's status."""
    item = XL430_W250[name]
    reply = bus.receive(encode_write(servo_id, item.address, item.encode(value)), now)
    (status,) = [p for p in DynamixelDecoder().feed(reply) if isinstance(p, StatusPacket)]
    return status.error


def armed_bus(period_units: int) -> FakeDynamixelBus:
    bus = FakeDynamixelBus(ids=(1, 2))
    for servo_id in (1, 2):
        assert write(bus, servo_id, "Operating Mode", 1, 0.0) == 0
        assert write(bus, servo_id, "Torque Enable", 1, 0.0) == 0
    assert write(bus, 1, "Bus Watchdog", period_units, 1.0) == 0
    assert write(bus, 1, "Goal Velocity", 100, 1.0) == 0
    return bus


def test_it_fires_once_the_interval_is_larger_than_the_period_not_before() -> None:
    bus = armed_bus(5)  # 100 ms from the last instruction, heard at t = 1.0
    assert bus.next_output_in(1.04) == pytest.approx(0.06)
    bus.poll(1.0999)
    assert bus.register(1, "Bus Watchdog") == 5
    assert bus.servo(1).motor.shaft(1.0999)[1] > 0  # still turning
    bus.poll(1.1001)
    assert bus.register(1, "Bus Watchdog") == -1
    assert bus.servo(1).motor.shaft(1.2)[1] == 0.0  # stopped
    assert bus.next_output_in(1.2) is None  # nothing left to watch
    assert bus.register(1, "Goal Velocity") == 100  # the e-Manual says it stops, not that the goal changes


def test_a_late_instruction_finds_it_fired_rather_than_resetting_it() -> None:
    bus = armed_bus(5)
    # The first byte heard after 150 ms of silence: the servo had stopped before it came.
    assert write(bus, 1, "Goal Velocity", 50, 1.15) == ErrorNumber.DATA_RANGE
    assert bus.register(1, "Goal Velocity") == 100


def test_instructions_to_it_or_to_all_keep_it_quiet_but_not_those_to_another_servo() -> None:
    bus = armed_bus(5)
    t = 1.0
    for _ in range(10):
        t += 0.09
        bus.receive(encode_ping(1), t)
    for _ in range(10):
        t += 0.09
        bus.receive(encode_sync_write(_GOAL.address, _GOAL.size, {2: _GOAL.encode(0)}), t)
    assert bus.register(1, "Bus Watchdog") == 5
    bus.receive(encode_ping(2), t + 0.09)
    bus.receive(encode_ping(2), t + 0.18)
    assert bus.register(1, "Bus Watchdog") == -1


def test_a_muted_servo_hears_nothing_and_fires() -> None:
    bus = armed_bus(5)
    bus.mute(1)
    bus.receive(encode_ping(1), 1.05)
    bus.receive(encode_ping(1), 1.10)
    bus.poll(1.11)
    assert bus.register(1, "Bus Watchdog") == -1
    bus.mute(1, False)
    assert write(bus, 1, "Goal Velocity", 0, 1.2) == ErrorNumber.DATA_RANGE


def test_only_zero_clears_it_then_goals_are_taken_and_followed_again() -> None:
    bus = armed_bus(1)
    bus.poll(1.05)
    assert write(bus, 1, "Bus Watchdog", 1, 1.06) == ErrorNumber.DATA_RANGE
    assert write(bus, 1, "Goal Velocity", 0, 1.06) == ErrorNumber.DATA_RANGE
    assert bus.register(1, "Bus Watchdog") == -1
    assert write(bus, 1, "Bus Watchdog", 0, 1.07) == 0
    # Cleared, the servo follows the goal it still holds: a host must write a new one.
    assert bus.servo(1).motor.shaft(1.08)[1] > 0
    assert write(bus, 1, "Goal Velocity", 0, 1.08) == 0
    assert bus.servo(1).motor.shaft(1.09)[1] == 0.0
    # Off (0) means off: no firing however long the silence.
    bus.poll(100.0)
    assert bus.register(1, "Bus Watchdog") == 0


def test_torque_off_pauses_the_watch() -> None:
    bus = armed_bus(5)
    assert write(bus, 1, "Torque Enable", 0, 1.05) == 0
    assert bus.next_output_in(1.06) is None
    bus.poll(10.0)
    assert bus.register(1, "Bus Watchdog") == 5
    assert write(bus, 1, "Torque Enable", 1, 10.0) == 0  # counts from this instruction
    bus.poll(10.09)
    assert bus.register(1, "Bus Watchdog") == 5
    bus.poll(10.11)
    assert bus.register(1, "Bus Watchdog") == -1
