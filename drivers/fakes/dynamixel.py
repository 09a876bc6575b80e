"""Fake XL430-W250 servos on one Dynamixel Protocol 2.0 bus, as a :class:`~drivers.fakes.pty.ByteDevice`.

Serve it with ``PtyServer(FakeDynamixelBus(sim))`` and point dynamixel-sdk (or our driver) at the path.
Each servo has a register file built from :data:`drivers.servos.control_table.XL430_W250` (power-on
values: Operating Mode 3, Baud Rate index 1, Return Delay 250, Status Return Level 2, torque off) and
follows the e-Manual's rules: no status for broadcast instructions except PING and the sync/bulk reads,
Status Return Level, Access Error (7) for read-only or undefined addresses and for EEPROM writes while
torque is on, Data Range (4), Data Length (5) and Data Limit (6) errors, the alert bit (0x80) while
Hardware Error Status is non-zero, a CRC Error (3) status for a damaged instruction addressed to a servo.

Motion: in velocity mode with torque on, Goal Velocity turns the shaft. With a
:class:`~drivers.sim.simulation.Simulation` the two wheel servos (``world.robot.left_id``/``right_id``)
drive its wheels and report its wheel angles and speeds; without one each servo integrates its own shaft.

Mounting, as on a TurtleBot3: both servos face outwards, so a shaft turning counter-clockwise (the
servo's positive direction in Normal mode) rolls the left wheel forward and the right wheel backward.
The right servo's ``mount_sign`` is therefore -1: positive Goal Velocity on the right servo drives the
robot backward, exactly as on the real robot. Drive Mode (10) bit 0 (Reverse mode) inverts velocity and
position on a servo, as the e-Manual describes.

Bus Watchdog (98), as the e-Manual's XL430-W250 page describes it (ROBOTIS-GIT/emanual @ 01a2df191e6a,
``_includes/en/dxl/control_table_buswatchdog.md``, its example included): 0 deactivates it and clears its
error, 1..127 arms it in 20 ms units, and it watches "the communication interval" only while Torque Enable
is 1, counting "all the Instruction Packet[s]". When the interval grows larger than the set value the servo
stops, Bus Watchdog reads -1 (0xFF) and the Goal items (Goal PWM, Goal Velocity, Goal Position; the XL430
has no Goal Current) turn read-only: a write to one gets a Data Range Error (4) in its status. Writing 0 to
Bus Watchdog clears the error. Where the e-Manual is silent the fake takes the strict reading: an
instruction counts for a servo when it is addressed to its ID or broadcast (a packet for another ID does
not); a non-zero write to Bus Watchdog while it reads -1 is refused (Data Range), so only 0 clears; the Goal
registers keep the values they had (the e-Manual says the servo stops, not that they change), and once the
error is cleared the servo follows them again, so a host must write a new goal. The servo checks the
interval whenever time passes for it: on every instruction and whenever the pty server polls it
(:meth:`FakeDynamixelBus.next_output_in` wakes the server when a watchdog falls due).

Not modelled: position and PWM control (Goal Position/PWM are stored and range-checked, the shaft does
not follow them), Return Delay Time (replies go out at once, well inside the SDK's ~34 ms timeout),
Indirect Address mapping (indirect data are plain RAM), baud rate changes.

Fault switches for tests: :meth:`FakeDynamixelBus.mute` (a servo stops hearing and answering),
:meth:`~FakeDynamixelBus.set_hardware_error`, :meth:`~FakeDynamixelBus.inject_junk` (bytes before the next
reply) and :meth:`~FakeDynamixelBus.corrupt_next_reply`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import termios
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Protocol

from drivers.servos.control_table import (
    BAUD_RATES,
    BUS_WATCHDOG_EXPIRED,
    BUS_WATCHDOG_GOALS,
    BUS_WATCHDOG_UNIT_S,
    RAD_PER_TICK,
    RADPS_PER_VELOCITY_UNIT,
    TICKS_PER_REV,
    XL430_W250,
    Area,
    ControlItem,
    ControlTable,
    OperatingMode,
)
from drivers.sim.simulation import Simulation, WheelTruth
from firmware_protocol.dynamixel import (
    BROADCAST_ID,
    CLEAR_MULTI_TURN_KEY,
    Action,
    BulkRead,
    BulkWrite,
    Clear,
    DynamixelDecoder,
    DynamixelError,
    ErrorNumber,
    FactoryReset,
    FactoryResetOption,
    FastBulkRead,
    FastReadItem,
    FastSyncRead,
    Instruction,
    InstructionPacket,
    Ping,
    Read,
    Reboot,
    RegWrite,
    SyncRead,
    SyncWrite,
    Write,
    encode_fast_read_status,
    encode_status,
    parse_command,
)

__all__ = [
    "BaudAwareDynamixelBus",
    "FakeDynamixelBus",
    "FakeXl430",
    "FreeMotor",
    "Motor",
    "SimulatedWheelMotor",
    "SimulatedWheels",
]

log = logging.getLogger(__name__)

_READS = {
    Instruction.READ,
    Instruction.SYNC_READ,
    Instruction.FAST_SYNC_READ,
    Instruction.BULK_READ,
    Instruction.FAST_BULK_READ,
}
_INSTRUCTIONS = frozenset(int(i) for i in Instruction) - {Instruction.STATUS}
_MODES = frozenset(int(m) for m in OperatingMode)
_RESET_OPTIONS = frozenset(int(o) for o in FactoryResetOption)
_INT32 = 1 << 32


def _wrap_int32(value: int) -> int:
    return (value + (1 << 31)) % _INT32 - (1 << 31)


class Motor(Protocol):
    """A servo's shaft, in the servo's own frame (positive = counter-clockwise seen from the horn)."""

    def shaft(self, now: float) -> tuple[float, float]:
        """(angle rad, speed rad/s) at monotonic time ``now``."""
        ...

    def drive(self, velocity_radps: float, now: float) -> None:
        """Set the shaft speed the servo's controller aims for."""
        ...


class FreeMotor:
    """A shaft with no load: it turns at the commanded speed at once and integrates its angle."""

    def __init__(self, angle_rad: float = 0.0) -> None:
        self._angle = angle_rad
        self._speed = 0.0
        self._t: float | None = None

    def shaft(self, now: float) -> tuple[float, float]:
        if self._t is not None and now > self._t:
            self._angle += self._speed * (now - self._t)
        self._t = now if self._t is None else max(self._t, now)
        return self._angle, self._speed

    def drive(self, velocity_radps: float, now: float) -> None:
        self.shaft(now)
        self._speed = velocity_radps


class SimulatedWheels:
    """Both drive wheels of a :class:`Simulation`; the simulation takes both goals at once.

    The wheels are sampled once per instruction (:meth:`at`): every servo a Sync Read asks answers with
    its position at the same instant, as servos that all hear the instruction at once do (on the real
    bus the replies follow each other within a packet's time). Sampling each servo when its reply is
    built would let another thread of the process run between the two replies, and the left wheel's
    position would then be milliseconds older than the right's: a turn the robot never made, in
    odometry made from them."""

    def __init__(self, simulation: Simulation) -> None:
        self.simulation = simulation
        self._goal = [0.0, 0.0]
        self._sampled: tuple[float, WheelTruth] | None = None

    def at(self, now: float) -> WheelTruth:
        """The wheels as they were when the instruction received at ``now`` arrived (sampled on the first
        call for that instruction)."""
        if self._sampled is None or self._sampled[0] != now:
            self._sampled = (now, self.simulation.wheels())
        return self._sampled[1]

    def set_goal(self, index: int, wheel_radps: float) -> None:
        self._goal[index] = wheel_radps
        self.simulation.set_wheel_velocity(self._goal[0], self._goal[1])


class SimulatedWheelMotor:
    """One wheel of a :class:`Simulation` seen from its servo: ``mount_sign`` turns wheel-forward into the
    servo's shaft direction (+1 left, -1 right for outward-facing servos)."""

    def __init__(self, wheels: SimulatedWheels, index: int, mount_sign: int) -> None:
        self.wheels = wheels
        self.index = index
        self.mount_sign = mount_sign

    def shaft(self, now: float) -> tuple[float, float]:
        truth = self.wheels.at(now)
        return (
            self.mount_sign * truth.position_rad[self.index],
            self.mount_sign * truth.velocity_radps[self.index],
        )

    def drive(self, velocity_radps: float, now: float) -> None:
        self.wheels.set_goal(self.index, self.mount_sign * velocity_radps)


class FakeXl430:
    """One servo: its register file and what it does with each instruction. Not thread-safe by itself;
    :class:`FakeDynamixelBus` serialises access."""

    def __init__(
        self,
        servo_id: int,
        motor: Motor,
        table: ControlTable = XL430_W250,
        position_ticks: int = 0,
        input_voltage_dv: int = 120,
        temperature_c: int = 32,
    ) -> None:
        self.table = table
        self.motor = motor
        self.regs = table.default_image()
        self.regs[table["ID"].address] = servo_id
        self.muted = False
        # Monotonic time of the last instruction packet this servo heard (Bus Watchdog counts from it).
        self.heard_at: float | None = None
        self._has_watchdog = "Bus Watchdog" in table  # firmware v38 and later
        self.input_voltage_dv = input_voltage_dv
        self.temperature_c = temperature_c
        self._registered: tuple[int, bytes] | None = None
        # The span a read refreshes from the motor first: Realtime Tick (120) to Present Temperature (146).
        self._live_from = table["Realtime Tick"].address
        self._live_to = table["Present Temperature"].end
        # Present Position = direction * shaft ticks + offset; the offset puts the power-on reading at
        # ``position_ticks`` (a real XL430 starts inside one turn, from its absolute encoder).
        self._offset_ticks = 0
        angle, _ = motor.shaft(0.0)
        self._offset_ticks = position_ticks - self._shaft_ticks(angle)

    # -- registers -----------------------------------------------------------------------------------
    def get(self, name: str) -> int:
        item = self.table[name]
        return item.decode(self.regs[item.address : item.end])

    def _set(self, name: str, value: int) -> None:
        item = self.table[name]
        self.regs[item.address : item.end] = item.encode(value)

    @property
    def id(self) -> int:
        return self.get("ID")

    @property
    def torque_on(self) -> bool:
        return self.get("Torque Enable") == 1

    def _direction(self) -> int:
        return -1 if self.get("Drive Mode") & 0x01 else 1

    def _shaft_ticks(self, angle_rad: float) -> int:
        return round(angle_rad / RAD_PER_TICK)

    def status_error(self, number: int = ErrorNumber.NONE) -> int:
        return number | (0x80 if self.get("Hardware Error Status") else 0)

    def answers(self, instruction: int) -> bool:
        """Status Return Level: 0 PING only, 1 PING and reads, 2 everything."""
        level = self.get("Status Return Level")
        return instruction == Instruction.PING or level == 2 or (level == 1 and instruction in _READS)

    # -- Bus Watchdog ----------------------------------------------------------------------------------
    @property
    def watchdog_expired(self) -> bool:
        return self._has_watchdog and self.get("Bus Watchdog") == BUS_WATCHDOG_EXPIRED

    def watchdog_left(self, now: float) -> float | None:
        """Seconds until the Bus Watchdog fires if nothing is heard (None: it is not watching)."""
        period = self.get("Bus Watchdog") if self._has_watchdog else 0
        if period <= 0 or not self.torque_on or self.heard_at is None:
            return None
        return self.heard_at + period * BUS_WATCHDOG_UNIT_S - now

    def check_watchdog(self, now: float) -> None:
        """Fire the Bus Watchdog if the interval since the last instruction is larger than its period."""
        left = self.watchdog_left(now)
        if left is not None and left < 0:
            self._set("Bus Watchdog", BUS_WATCHDOG_EXPIRED)
            self.update_drive(now)
            log.debug("fake servo %d: Bus Watchdog fired", self.id)

    def hear(self, now: float) -> None:
        """An instruction packet for this servo arrived at ``now`` (before it is carried out)."""
        self.check_watchdog(now)
        self.heard_at = now

    # -- motion --------------------------------------------------------------------------------------
    def _driving(self) -> bool:
        velocity_mode = self.get("Operating Mode") == OperatingMode.VELOCITY
        return self.torque_on and velocity_mode and not self.watchdog_expired

    def update_drive(self, now: float) -> None:
        goal = self.get("Goal Velocity") if self._driving() else 0
        self.motor.drive(self._direction() * goal * RADPS_PER_VELOCITY_UNIT, now)

    def _refresh(self, now: float) -> None:
        angle, speed = self.motor.shaft(now)
        d = self._direction()
        velocity = round(d * speed / RADPS_PER_VELOCITY_UNIT)
        self._set("Present Velocity", velocity)
        self._set("Present Position", _wrap_int32(d * self._shaft_ticks(angle) + self._offset_ticks))
        self._set("Velocity Trajectory", self.get("Goal Velocity") if self._driving() else 0)
        self._set("Moving", int(abs(velocity) > self.get("Moving Threshold")))
        self._set("Realtime Tick", int(now * 1000) % 32768)
        self._set("Present Input Voltage", self.input_voltage_dv)
        self._set("Present Temperature", self.temperature_c)

    def _rebase_position(self, now: float) -> None:
        """Present Position back inside one turn, as after a reboot or CLEAR (multi-turn count dropped)."""
        self._refresh(now)
        present = self.get("Present Position")
        self._offset_ticks -= present - present % TICKS_PER_REV

    # -- reading and writing -------------------------------------------------------------------------
    def read(self, address: int, length: int, now: float) -> tuple[int, bytes]:
        """(error number, data); reads may span gaps, which read as 0, but not run past the table."""
        if length == 0 or address + length > len(self.regs):
            return ErrorNumber.ACCESS, b""
        if address < self._live_to and address + length > self._live_from:
            self._refresh(now)
        return ErrorNumber.NONE, bytes(self.regs[address : address + length])

    def check_write(self, address: int, data: bytes) -> int:
        """The error number a WRITE of ``data`` at ``address`` would get (0: it would be accepted)."""
        end = address + len(data)
        if not data:
            return ErrorNumber.DATA_LENGTH
        if end > len(self.regs):
            return ErrorNumber.ACCESS
        items: list[ControlItem] = []
        for a in range(address, end):
            item = self.table.item_at(a)
            if item is None:
                return ErrorNumber.ACCESS
            if not items or items[-1] is not item:
                items.append(item)
        if items[0].address != address or items[-1].end != end:
            return ErrorNumber.DATA_LENGTH  # only part of an item
        if any(not item.writable for item in items):
            return ErrorNumber.ACCESS
        if self.torque_on and any(item.area is Area.EEPROM for item in items):
            return ErrorNumber.ACCESS
        new = bytearray(self.regs)
        new[address:end] = data
        for item in items:
            value = item.decode(new[item.address : item.end])
            if not item.in_range(value):
                return ErrorNumber.DATA_RANGE
            if item.name == "Operating Mode" and value not in _MODES:
                return ErrorNumber.DATA_RANGE
            if self.watchdog_expired and (
                item.name in BUS_WATCHDOG_GOALS or (item.name == "Bus Watchdog" and value != 0)
            ):
                return ErrorNumber.DATA_RANGE  # read-only until Bus Watchdog is cleared with 0
        return self._check_limits(new, items)

    def _check_limits(self, new: bytearray, items: Sequence[ControlItem]) -> int:
        """Data Limit: goals checked against the limit items, with the values this write would leave."""

        def value(name: str) -> int:
            item = self.table[name]
            return item.decode(new[item.address : item.end])

        names = {item.name for item in items}
        if "Goal Velocity" in names and abs(value("Goal Velocity")) > value("Velocity Limit"):
            return ErrorNumber.DATA_LIMIT
        if "Goal PWM" in names and abs(value("Goal PWM")) > value("PWM Limit"):
            return ErrorNumber.DATA_LIMIT
        if (
            "Goal Position" in names
            and value("Operating Mode") == OperatingMode.POSITION
            and not value("Min Position Limit") <= value("Goal Position") <= value("Max Position Limit")
        ):
            return ErrorNumber.DATA_LIMIT
        return ErrorNumber.NONE

    def write(self, address: int, data: bytes, now: float) -> int:
        error = self.check_write(address, data)
        if error:
            return error
        torque_item = self.table["Torque Enable"]
        shutdown = self.get("Hardware Error Status") & self.get("Shutdown")
        self.regs[address : address + len(data)] = data
        if shutdown and self.torque_on:
            # After a shutdown only a REBOOT lets torque back on.
            self.regs[torque_item.address] = 0
        self.update_drive(now)
        return ErrorNumber.NONE

    def reg_write(self, address: int, data: bytes) -> int:
        error = self.check_write(address, data)
        if not error:
            self._registered = (address, bytes(data))
            self._set("Registered Instruction", 1)
        return error

    def action(self, now: float) -> int:
        if self._registered is None:
            return ErrorNumber.INSTRUCTION
        address, data = self._registered
        self._registered = None
        self._set("Registered Instruction", 0)
        return self.write(address, data, now)

    def reboot(self, now: float) -> None:
        """RAM back to power-on values (torque off, errors cleared), EEPROM kept, position within one turn."""
        default = self.table.default_image()
        ram_from = min(item.address for item in self.table if item.area is Area.RAM)
        self.regs[ram_from:] = default[ram_from:]
        self._registered = None
        self.update_drive(now)
        self._rebase_position(now)

    def factory_reset(self, option: int, now: float) -> None:
        keep = (
            {"ID"}
            if option == FactoryResetOption.ALL_EXCEPT_ID
            else ({"ID", "Baud Rate"} if option == FactoryResetOption.ALL_EXCEPT_ID_AND_BAUD else set())
        )
        kept = {name: self.get(name) for name in keep}
        self.regs[:] = self.table.default_image()
        for name, value in kept.items():
            self._set(name, value)
        self._registered = None
        self.update_drive(now)
        self._rebase_position(now)

    def clear_multi_turn(self, now: float) -> int:
        self._refresh(now)
        if self.get("Moving"):
            return ErrorNumber.RESULT_FAIL  # e-Manual: CLEAR only while stopped
        self._rebase_position(now)
        return ErrorNumber.NONE

    def raise_hardware_error(self, bits: int, now: float) -> None:
        self._set("Hardware Error Status", bits)
        if bits & self.get("Shutdown"):
            self._set("Torque Enable", 0)
        self.update_drive(now)


class FakeDynamixelBus:
    """XL430-W250 servos on one bus, speaking Protocol 2.0 bytes (a ``ByteDevice`` for ``PtyServer``).

    With ``simulation``, servos ``world.robot.left_id`` and ``right_id`` drive its wheels (the right one
    mounted mirrored). ``ids`` adds free-running servos, or lists all servos when there is no simulation.
    """

    #: A real servo drops a partial packet after 1.5 ms of silence; a pty adds scheduling jitter, so wait
    #: longer before deciding the rest of a packet is never coming.
    inter_byte_timeout_s = 0.05

    def __init__(
        self,
        simulation: Simulation | None = None,
        ids: Iterable[int] = (),
        table: ControlTable = XL430_W250,
        position_ticks: dict[int, int] | None = None,
    ) -> None:
        self.simulation = simulation
        self.table = table
        self.decoder = DynamixelDecoder()
        self._lock = threading.Lock()
        self._servos: dict[int, FakeXl430] = {}
        self._junk = b""
        self._corrupt = 0
        self._last_rx: float | None = None
        self.instructions = 0
        self.crc_errors = 0
        self.timeouts = 0
        start_ticks = position_ticks or {}
        if simulation is not None:
            robot = simulation.world.robot
            wheels = SimulatedWheels(simulation)
            for index, (servo_id, sign) in enumerate(((robot.left_id, 1), (robot.right_id, -1))):
                motor = SimulatedWheelMotor(wheels, index, sign)
                self._add(FakeXl430(servo_id, motor, table, start_ticks.get(servo_id, 1024 + 2048 * index)))
        for servo_id in ids:
            if servo_id not in self._servos:
                self._add(FakeXl430(servo_id, FreeMotor(), table, start_ticks.get(servo_id, 0)))
        if not self._servos:
            raise ValueError("a fake bus needs a simulation or at least one servo ID")

    def _add(self, servo: FakeXl430) -> None:
        self._servos[servo.id] = servo

    # -- test switches -------------------------------------------------------------------------------
    def servo(self, servo_id: int) -> FakeXl430:
        return self._servos[servo_id]

    @property
    def ids(self) -> tuple[int, ...]:
        return tuple(sorted(self._servos))

    def register(self, servo_id: int, name: str) -> int:
        """A register's value as the servo holds it (live values as of the last read)."""
        with self._lock:
            return self._servos[servo_id].get(name)

    def mute(self, servo_id: int, muted: bool = True) -> None:
        """A muted servo neither hears nor answers (a loose cable, a brown-out)."""
        with self._lock:
            self._servos[servo_id].muted = muted

    def set_hardware_error(self, servo_id: int, bits: int, now: float | None = None) -> None:
        """Latch Hardware Error Status bits; bits covered by Shutdown (63) turn the torque off."""
        with self._lock:
            servo = self._servos[servo_id]
            servo.raise_hardware_error(bits, self._now(now))

    def inject_junk(self, data: bytes) -> None:
        """Send ``data`` on the wire just before the next reply."""
        with self._lock:
            self._junk += bytes(data)

    def corrupt_next_reply(self, count: int = 1) -> None:
        """Flip a CRC bit in the next ``count`` replies."""
        with self._lock:
            self._corrupt += count

    @property
    def discarded_bytes(self) -> int:
        return self.decoder.discarded_bytes

    def _now(self, now: float | None) -> float:
        if now is not None:
            return now
        # PtyServer passes time.monotonic() to receive(); a simulation may run on its own clock.
        return self.simulation.now() if self.simulation is not None else time.monotonic()

    # -- ByteDevice ----------------------------------------------------------------------------------
    def poll(self, now: float) -> bytes:
        with self._lock:
            self._check_watchdogs(now)
        return b""

    def next_output_in(self, now: float) -> float | None:
        """When the next Bus Watchdog falls due: the server polls then, so a servo stops on time. (It has
        nothing to send then; a servo never speaks unasked.)"""
        with self._lock:
            due = [left for s in self._servos.values() if (left := s.watchdog_left(now)) is not None]
        return max(0.0, min(due)) if due else None

    def _check_watchdogs(self, now: float) -> None:
        for servo in self._servos.values():
            servo.check_watchdog(now)

    def receive(self, data: bytes, now: float) -> bytes:
        with self._lock:
            self._check_watchdogs(now)
            if (
                self._last_rx is not None
                and self.decoder.buffered
                and (now - self._last_rx > self.inter_byte_timeout_s)
            ):
                self.timeouts += 1
                self.decoder.reset()
            self._last_rx = now
            replies: list[bytes] = []
            packets = self.decoder.feed(data)
            for error in self.decoder.take_errors():
                self._answer_crc_error(error, replies)
            for packet in packets:
                if isinstance(packet, InstructionPacket):
                    self.instructions += 1
                    self._handle(packet, now, replies)
                    # An ID written takes effect at once: the servo answers to its new ID from the next
                    # packet on (EEPROM, so only with the torque off, which the servo itself checks).
                    self._rekey()
            return self._wire(replies)

    def _rekey(self) -> None:
        servos = self._servos
        for key, servo in list(servos.items()):
            if servo.id != key:
                del servos[key]
                servos[servo.id] = servo

    def _wire(self, replies: list[bytes]) -> bytes:
        if not replies:
            return b""
        out = bytearray()
        for reply in replies:
            if self._corrupt:
                self._corrupt -= 1
                reply = reply[:-1] + bytes((reply[-1] ^ 0x01,))
            out += reply
        if self._junk:
            out[:0] = self._junk
            self._junk = b""
        return bytes(out)

    def _answer_crc_error(self, error: DynamixelError, replies: list[bytes]) -> None:
        if not error.crc_mismatch:
            return
        self.crc_errors += 1
        servo = self._servos.get(error.packet_id) if error.packet_id is not None else None
        # The instruction byte of a damaged packet is still the best guess at what was asked.
        instruction = error.data[7] if len(error.data) > 7 else Instruction.PING
        if servo is not None and not servo.muted and servo.answers(instruction):
            replies.append(encode_status(servo.id, servo.status_error(ErrorNumber.CRC)))

    def _targets(self, packet_id: int) -> list[FakeXl430]:
        if packet_id == BROADCAST_ID:
            return [s for _, s in sorted(self._servos.items()) if not s.muted]
        servo = self._servos.get(packet_id)
        return [servo] if servo is not None and not servo.muted else []

    def _handle(self, packet: InstructionPacket, now: float, replies: list[bytes]) -> None:
        targets = self._targets(packet.id)
        if not targets:
            return
        for servo in targets:
            servo.hear(now)
        unicast = packet.id != BROADCAST_ID

        def reply(
            servo: FakeXl430,
            number: int = ErrorNumber.NONE,
            params: bytes = b"",
            instruction: int = packet.instruction,
        ) -> None:
            if servo.answers(instruction):
                replies.append(encode_status(servo.id, servo.status_error(number), params))

        if packet.instruction not in _INSTRUCTIONS:
            if unicast:
                reply(targets[0], ErrorNumber.INSTRUCTION)
            return
        try:
            command = parse_command(packet)
        except DynamixelError as exc:
            log.debug("fake servo: malformed instruction: %s", exc)
            if unicast:
                reply(targets[0], ErrorNumber.INSTRUCTION)
            return

        match command:
            case Ping():
                for servo in targets:
                    # Model Number (LSB, MSB) and Firmware Version.
                    reply(
                        servo,
                        params=servo.get("Model Number").to_bytes(2, "little")
                        + bytes((servo.get("Firmware Version"),)),
                    )
            case Read(address, length) if unicast:
                number, data = targets[0].read(address, length, now)
                reply(targets[0], number, data)
            case Write(address, data):
                for servo in targets:
                    number = servo.write(address, data, now)
                    if unicast:
                        reply(servo, number)
            case RegWrite(address, data):
                for servo in targets:
                    number = servo.reg_write(address, data)
                    if unicast:
                        reply(servo, number)
            case Action():
                for servo in targets:
                    number = servo.action(now)
                    if unicast:
                        reply(servo, number)
            case Reboot():
                for servo in targets:
                    if unicast:
                        reply(servo)
                    servo.reboot(now)
            case FactoryReset(option):
                if option not in _RESET_OPTIONS:
                    if unicast:
                        reply(targets[0], ErrorNumber.DATA_RANGE)
                    return
                if not unicast and option == FactoryResetOption.ALL:
                    return  # e-Manual: a broadcast "reset all" is ignored (firmware 42+)
                for servo in targets:
                    if unicast:
                        reply(servo)
                    servo.factory_reset(option, now)
            case Clear(option, data):
                for servo in targets:
                    ok = option == 0x01 and data == CLEAR_MULTI_TURN_KEY
                    number = servo.clear_multi_turn(now) if ok else ErrorNumber.INSTRUCTION
                    if unicast:
                        reply(servo, number)
            case SyncRead(address, length, ids) if not unicast:
                # Each servo answers in the order of the request (the SDK expects exactly that).
                self._read_each([(i, address, length) for i in ids], now, reply)
            case BulkRead(entries) if not unicast:
                self._read_each([(e.id, e.address, e.length) for e in entries], now, reply)
            case FastSyncRead(address, length, ids) if not unicast:
                self._fast_read([(i, address, length) for i in ids], now, replies)
            case FastBulkRead(entries) if not unicast:
                self._fast_read([(e.id, e.address, e.length) for e in entries], now, replies)
            case SyncWrite(address, _, data) if not unicast:
                # No status: a value a servo refuses (say beyond Velocity Limit) is dropped silently.
                self._write_each([(i, address, chunk) for i, chunk in data.items()], now)
            case BulkWrite(entries) if not unicast:
                self._write_each([(e.id, e.address, e.data) for e in entries], now)
            case _:
                # Sync/bulk instructions must be broadcast; READ cannot be.
                if unicast:
                    reply(targets[0], ErrorNumber.INSTRUCTION)

    def _live(self, servo_id: int) -> FakeXl430 | None:
        servo = self._servos.get(servo_id)
        return servo if servo is not None and not servo.muted else None

    def _read_each(
        self, requests: list[tuple[int, int, int]], now: float, reply: Callable[[FakeXl430, int, bytes], None]
    ) -> None:
        for servo_id, address, length in requests:
            servo = self._live(servo_id)
            if servo is not None:
                number, data = servo.read(address, length, now)
                reply(servo, number, data)

    def _write_each(self, requests: list[tuple[int, int, bytes]], now: float) -> None:
        for servo_id, address, data in requests:
            servo = self._live(servo_id)
            if servo is not None:
                servo.write(address, data, now)

    def _fast_read(self, requests: list[tuple[int, int, int]], now: float, replies: list[bytes]) -> None:
        items = []
        for servo_id, address, length in requests:
            servo = self._live(servo_id)
            if servo is None or not servo.answers(Instruction.FAST_SYNC_READ):
                continue  # the chain has a hole; the host sees a short packet
            number, data = servo.read(address, length, now)
            items.append(FastReadItem(servo.id, servo.status_error(number), data.ljust(length, b"\x00")))
        if items:
            replies.append(encode_fast_read_status(items))


# -- a bus with baud rates -----------------------------------------------------------------------------------
_TERMIOS_BAUD = {
    getattr(termios, f"B{rate}"): rate for rate in BAUD_RATES.values() if hasattr(termios, f"B{rate}")
}


class BaudAwareDynamixelBus(FakeDynamixelBus):
    """The fake bus with baud rates: a servo hears (and answers) only when the port runs at the rate its Baud
    Rate register (8) selects, as on the real thing, so a bus scan finds servos at the rates they are set
    to and writing Baud Rate moves a servo to another rate. The port's rate is read from the pty's
    terminal settings, which the client sets; call :meth:`attach` with the pty path once it is served.
    (Muting, the fault switch of :class:`FakeDynamixelBus`, is taken over by the baud rates here.)"""

    def __init__(self, simulation: Simulation | None = None, ids: tuple[int, ...] = ()) -> None:
        super().__init__(simulation, ids)
        self._fd: int | None = None
        self._path: str | None = None

    def attach(self, path: str) -> None:
        self._path = path

    def close(self) -> None:
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = None

    def set_servo(
        self,
        servo_id: int,
        *,
        new_id: int | None = None,
        baud_index: int | None = None,
        mode: int | None = None,
    ) -> None:
        """Put a servo in a state (as it came from the factory, or from another robot)."""
        servo = self.servo(servo_id)
        table = servo.table
        for name, value in (("Baud Rate", baud_index), ("Operating Mode", mode), ("ID", new_id)):
            if value is not None:
                item = table[name]
                servo.regs[item.address : item.end] = item.encode(value)
        with self._lock:
            self._rekey()

    def line_rate(self) -> int | None:
        """The rate the client set on the port (None when unknown)."""
        if self._path is None:
            return None
        try:
            if self._fd is None:
                self._fd = os.open(self._path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
            speed = termios.tcgetattr(self._fd)[5]
        except (OSError, termios.error):
            self.close()
            return None
        return _TERMIOS_BAUD.get(speed)

    def receive(self, data: bytes, now: float) -> bytes:
        rate = self.line_rate()
        if rate is not None:
            for servo_id in self.ids:
                servo = self.servo(servo_id)
                servo.muted = BAUD_RATES.get(servo.get("Baud Rate")) != rate
        return super().receive(data, now)
