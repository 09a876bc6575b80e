"""Two XL430-W250 wheel servos through the real ``dynamixel-sdk`` (Protocol 2.0), TurtleBot3 style.

Bring-up (``open()`` and every reconnect): ping both IDs, then per servo torque off, clear Drive Mode's
Reverse bit and set Operating Mode 1 (velocity) where they differ (EEPROM items, so only written when
needed, and only with torque off), read Velocity Limit, then start it: torque off, Bus Watchdog 0 (which
clears a watchdog that fired), Goal Velocity 0, torque on, Bus Watchdog armed.

**Bus Watchdog.** A servo cut off from the agent (cable pulled, adapter or agent dead) would otherwise keep
its last Goal Velocity: one wheel driving, the other stopped, the robot pivots. The XL430 stops by itself
when it hears no instruction for longer than Bus Watchdog (98, 20 ms units, firmware v38+; ROBOTIS
e-Manual, XL430-W250 control table, "Bus Watchdog"), so the driver arms it with ``bus_watchdog_ms``:
the wheel stops at most that long after the last instruction the servo heard, i.e. after it was cut off.
A fired watchdog latches: the item reads -1 and Goal Velocity is read-only (a write gets a Data Range
Error, and a sync write's goal is dropped without a word) until 0 is written to it. So when a servo may
have fired, the driver reads the item and, if it is not what was armed, starts that servo again (torque
off first, so the old goal is never followed): after a servo timed out and answers again, after the bus
was quiet for half a period (a stalled caller), and once a second in any case.

**Mirrored wheel.** Both servos face outwards, so for the robot to go forward the left shaft turns
counter-clockwise (the servo's positive direction) and the right one clockwise. This driver flips the
sign of the right wheel itself (``right_mirrored=True``) instead of setting Drive Mode's Reverse bit:
that leaves the servos' EEPROM as shipped (a spare servo works without setup), works on firmware older
than v38 (which has no Drive Mode), and keeps the convention in one place. To make it the only place,
bring-up clears a Reverse bit it finds set.

Units: Goal/Present Velocity 0.229 rev/min per LSB, Present Position 4096 ticks per revolution. In
velocity mode Present Position counts turns as a signed 32-bit value; it is unwrapped to a continuous
angle. After a reconnect the unwrapping restarts from the next reading (the servos may have rebooted,
which moves Present Position back inside one turn), so motion during the gap is lost, never invented.

Errors: no status in time -> :class:`DeviceTimeout`; port gone (EIO, unplugged) ->
:class:`DeviceDisconnected`, after which the next call (or :meth:`DynamixelWheels.reconnect`) reopens the
port and configures the servos again; an error number in a status packet -> :class:`DeviceStatusError`
with the ERR byte as ``status``. The alert bit (hardware error) is not an exception: when it appears the
driver reads Hardware Error Status (70), which latches until a reboot, and reports it in each
:class:`WheelState`.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import os
import select
import termios
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from dynamixel_sdk import (
    COMM_RX_CORRUPT,
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    GroupSyncRead,
    GroupSyncWrite,
    PacketHandler,
    PortHandler,
)

from drivers.errors import (
    ConfigError,
    DeviceDisconnected,
    DeviceError,
    DeviceNotFound,
    DeviceStatusError,
    DeviceTimeout,
)
from drivers.samples import WheelState
from drivers.servos.base import WheelServos
from drivers.servos.control_table import (
    BUS_WATCHDOG_EXPIRED,
    BUS_WATCHDOG_UNIT_S,
    MODEL_XL430_W250,
    RAD_PER_TICK,
    RADPS_PER_VELOCITY_UNIT,
    XL430_W250,
    ControlItem,
    OperatingMode,
    describe_hardware_error,
)
from drivers.servos.odometry import WheelOdometry
from firmware_protocol.dynamixel import MAX_ID, ErrorNumber, StatusError

__all__ = ["DynamixelWheels"]

_T = TypeVar("_T")

log = logging.getLogger(__name__)

#: Baud rates ``PortHandler.setBaudRate`` accepts (its ``getCFlagBaud`` list; note: no 4.5 Mbps).
SDK_BAUDRATES = frozenset(
    {
        9600,
        19200,
        38400,
        57600,
        115200,
        230400,
        460800,
        500000,
        576000,
        921600,
        1_000_000,
        1_152_000,
        2_000_000,
        2_500_000,
        3_000_000,
        3_500_000,
        4_000_000,
    }
)

_TABLE = XL430_W250
_TORQUE = _TABLE["Torque Enable"]
_DRIVE_MODE = _TABLE["Drive Mode"]
_OPERATING_MODE = _TABLE["Operating Mode"]
_VELOCITY_LIMIT = _TABLE["Velocity Limit"]
_HARDWARE_ERROR = _TABLE["Hardware Error Status"]
_BUS_WATCHDOG = _TABLE["Bus Watchdog"]
_BUS_WATCHDOG_UNIT_MS = round(BUS_WATCHDOG_UNIT_S * 1000)
# How often the driver reads Bus Watchdog back even when nothing suggests it fired (a servo that rebooted,
# or a gap in instructions the driver could not see).
_WATCHDOG_CHECK_S = 1.0
_DEFAULT_BUS_WATCHDOG_MS = 100
_GOAL_VELOCITY = _TABLE["Goal Velocity"]
_PRESENT_VELOCITY = _TABLE["Present Velocity"]
_PRESENT_POSITION = _TABLE["Present Position"]
# One SYNC_READ covers Present Velocity (128, 4) and Present Position (132, 4).
_READ_ADDRESS = _PRESENT_VELOCITY.address
_READ_LENGTH = _PRESENT_POSITION.end - _PRESENT_VELOCITY.address
_REVERSE_BIT = 0x01
# What the port raises when the device goes away: pyserial's SerialException (an OSError), plain OSError
# (EIO from a hung-up tty), termios.error from the SDK's tcflush before every packet.
_PORT_ERRORS: tuple[type[BaseException], ...] = (OSError, termios.error)
# Longest single wait for reply bytes in ``_PortHandler.readPort``.
_MAX_READ_WAIT_MS = 5.0


class _PortHandler(PortHandler):  # type: ignore[misc]  # the SDK is untyped
    """dynamixel-sdk's port with two changes to its reply deadline.

    The SDK waits ``tx time + 2 * LATENCY_TIMER + 2`` ms for a status, with LATENCY_TIMER a module
    constant of 16 ms (an FTDI adapter's default latency timer). Here it is per port, so it can match an
    adapter tuned to 1 ms (faster failure detection) or a loaded machine talking to a fake on a pty.
    And the deadline runs on ``time.monotonic()``, not the SDK's ``time.time()``, which jumps with NTP.
    """

    def __init__(self, port_name: str, latency_timer_ms: float) -> None:
        super().__init__(port_name)
        self.latency_timer_ms = latency_timer_ms

    def setPacketTimeout(self, packet_length: int) -> None:  # overrides the SDK (its naming)
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = self.tx_time_per_byte * packet_length + 2.0 * self.latency_timer_ms + 2.0

    def getCurrentTime(self) -> float:  # milliseconds, as the SDK expects
        return time.monotonic() * 1000.0

    def readPort(self, length: int) -> bytes:  # overrides the SDK (its naming)
        """Wait (GIL released, in ``select``) until the port has bytes or the reply deadline passes, then
        read what is there.

        The SDK opens the port with ``timeout=0`` and polls ``readPort`` in a loop until a status packet
        is complete or the deadline passes: a busy spin that holds a core and, in a Python process with
        other threads, the interpreter lock for the whole reply time. Each wait is capped at
        ``_MAX_READ_WAIT_MS`` so that the SDK's own deadline check keeps running.
        """
        ser = self.ser
        left_ms = self.packet_timeout - (self.getCurrentTime() - self.packet_start_time)
        if left_ms > 0.0:
            with contextlib.suppress(ValueError):  # a closed port: the read below says so
                select.select([ser.fileno()], [], [], min(left_ms, _MAX_READ_WAIT_MS) * 1e-3)
        data: bytes = ser.read(length)
        return data


class _Unwrapper:
    """Signed 32-bit Present Position -> continuous ticks, across int32 overflow."""

    def __init__(self) -> None:
        self.total: int | None = None
        self._raw: int | None = None

    def reseed(self) -> None:
        """Take the next reading as a new reference, keeping the total so far."""
        self._raw = None

    def update(self, raw: int) -> int:
        if self.total is None:
            self.total = raw
        elif self._raw is not None:
            self.total += (raw - self._raw + (1 << 31)) % (1 << 32) - (1 << 31)
        self._raw = raw
        return self.total


class DynamixelWheels(WheelServos):
    """Left and right wheel servos (XL430-W250, Protocol 2.0) on one serial port.

    Defaults are a TurtleBot3 burger's: IDs 1 (left) and 2 (right), wheel radius 0.033 m, track 0.160 m.
    The servos leave the factory at 57600 bps; TurtleBot3 runs them at 1 Mbps behind its OpenCR board.
    ``retries`` applies to reads and pings only (a lost read is harmless to repeat, a write is not
    re-sent blindly). ``max_wheel_radps`` caps commands below the servos' own Velocity Limit.
    ``latency_timer_ms`` sets the reply deadline the SDK's way (tx time + 2 x latency + 2 ms): 16 is the
    SDK's value for an untuned FTDI adapter; use 1-2 for a tuned one, more on a pty fake under load.
    ``bus_watchdog_ms`` arms each servo's Bus Watchdog (a multiple of 20 ms, up to 2540; 0 leaves it off):
    a servo that hears nothing for longer stops by itself. It must outlast the longest gap between two
    instructions to a servo that is fine, which is one reply deadline when the other servo's reply is
    lost; so it is at least twice the reply deadline, and by default 100 ms or that, whichever is longer
    (100 ms with the SDK's 16 ms latency timer). The caller must talk to the servos more often than that
    (the agent does every control period).
    """

    def __init__(
        self,
        port: str,
        baudrate: int = 57600,
        left_id: int = 1,
        right_id: int = 2,
        wheel_radius_m: float = 0.033,
        track_m: float = 0.160,
        name: str = "servos",
        right_mirrored: bool = True,
        left_mirrored: bool = False,
        retries: int = 1,
        max_wheel_radps: float | None = None,
        low_latency: bool = True,
        latency_timer_ms: float = 16.0,
        bus_watchdog_ms: int | None = None,
    ) -> None:
        for key, value in (("left_id", left_id), ("right_id", right_id)):
            if not 0 <= value <= MAX_ID:
                raise ConfigError(f"{name}.{key}", f"servo ID must be 0..{MAX_ID}, not {value}")
        if left_id == right_id:
            raise ConfigError(
                f"{name}.right_id", f"left and right servos need different IDs, both are {left_id}"
            )
        if baudrate not in SDK_BAUDRATES:
            raise ConfigError(
                f"{name}.baudrate",
                f"{baudrate} bps is not one dynamixel-sdk can set; choose one of {sorted(SDK_BAUDRATES)}",
            )
        if not (wheel_radius_m > 0 and track_m > 0):
            raise ConfigError(f"{name}.wheel_radius_m", "wheel radius and track must be positive")
        if retries < 0:
            raise ConfigError(f"{name}.retries", "must be 0 or more")
        if not latency_timer_ms > 0:
            raise ConfigError(f"{name}.latency_timer_ms", f"must be positive, not {latency_timer_ms}")
        # A healthy servo hears nothing for one reply deadline while the driver waits for a lost reply.
        shortest_ms = 2.0 * (2.0 * latency_timer_ms + 2.0)
        if bus_watchdog_ms is None:
            bus_watchdog_ms = max(
                _DEFAULT_BUS_WATCHDOG_MS,
                _BUS_WATCHDOG_UNIT_MS * math.ceil(shortest_ms / _BUS_WATCHDOG_UNIT_MS),
            )
        if bus_watchdog_ms % _BUS_WATCHDOG_UNIT_MS or not _BUS_WATCHDOG.in_range(
            bus_watchdog_ms // _BUS_WATCHDOG_UNIT_MS
        ):
            raise ConfigError(
                f"{name}.bus_watchdog_ms",
                f"must be 0 (off) or a multiple of {_BUS_WATCHDOG_UNIT_MS} up to "
                f"{_BUS_WATCHDOG_UNIT_MS * (_BUS_WATCHDOG.maximum or 0)}, not {bus_watchdog_ms}",
            )
        if 0 < bus_watchdog_ms < shortest_ms:
            raise ConfigError(
                f"{name}.bus_watchdog_ms",
                f"{bus_watchdog_ms} ms is shorter than twice the reply deadline (2 x latency_timer_ms + 2 = "
                f"{shortest_ms / 2:g} ms): one lost reply would stop both wheels",
            )
        super().__init__(name, left_id, right_id)
        self.port = port
        self.baudrate = baudrate
        self.wheel_radius_m = wheel_radius_m
        self.track_m = track_m
        self.retries = retries
        self.max_wheel_radps = max_wheel_radps
        self.low_latency = low_latency
        self.latency_timer_ms = latency_timer_ms
        self.bus_watchdog_units = bus_watchdog_ms // _BUS_WATCHDOG_UNIT_MS
        self.signs = (-1 if left_mirrored else 1, -1 if right_mirrored else 1)
        self.models: dict[int, int] = {}
        self._lock = threading.RLock()
        self._port: Any = None  # dynamixel_sdk.PortHandler
        self._ph: Any = PacketHandler(2.0)
        self._port_lost = False
        self._limit_units = {left_id: _VELOCITY_LIMIT.default or 0, right_id: _VELOCITY_LIMIT.default or 0}
        self._hardware_error = {left_id: 0, right_id: 0}
        self._alert_pending: set[int] = set()  # alert bit seen, Hardware Error Status not read yet
        self._unwrap = {left_id: _Unwrapper(), right_id: _Unwrapper()}
        # Bus Watchdog: servos whose watchdog may have fired, servos without one (firmware before v38),
        # when the last transaction ended and when the item is next read back anyway.
        self._watchdog_suspects: set[int] = set()
        self._no_watchdog: set[int] = set()
        self._last_transaction: float | None = None
        self._next_watchdog_check = 0.0
        self.commanded_radps = (0.0, 0.0)

    # -- lifecycle -------------------------------------------------------------------------------------
    @property
    def connected(self) -> bool:
        return self.is_open and not self._port_lost

    def _open(self) -> None:
        with self._lock:
            self._port_lost = False
            self._connect()
            try:
                self._configure()
            except BaseException:
                self._drop_port()
                raise

    def _close(self) -> None:
        with self._lock:
            if self._port is not None and not self._port_lost:
                # Leave the robot stopped and the motors free, as the TurtleBot3 node does on shutdown.
                try:
                    self._sync_write_velocity((0, 0))
                    for servo_id in self.ids:
                        self._write(servo_id, _TORQUE, 0)
                except DeviceError as exc:
                    log.warning("%s: could not stop the servos while closing: %s", self.name, exc)
            self._drop_port()

    def reconnect(self) -> None:
        with self._lock:
            if not self.is_open:
                self.open()
                return
            self._drop_port()
            # Until bring-up completes the port counts as lost, so the next call tries again.
            self._port_lost = True
            self._connect()
            self._port_lost = False
            try:
                self._configure()
            except BaseException:
                self._port_lost = True
                self._drop_port()
                raise
            self.count("reconnects")
            log.info("%s: reconnected on %s", self.name, self.port)

    def odometry(self) -> WheelOdometry:
        """A fresh odometry integrator with this robot's wheel radius and track."""
        return WheelOdometry(self.wheel_radius_m, self.track_m)

    def _connect(self) -> None:
        try:
            port = _PortHandler(self.port, self.latency_timer_ms)
            # setBaudRate opens the port (pyserial) at that rate; openPort() would open at 1 Mbps first.
            if not port.setBaudRate(self.baudrate):
                raise DeviceError(f"dynamixel-sdk refused {self.baudrate} bps", self.name)
        except _PORT_ERRORS as exc:
            raise DeviceNotFound(f"cannot open {self.port}: {exc}", self.name) from exc
        self._port = port
        if self.low_latency:
            self._set_low_latency(port)

    def _set_low_latency(self, port: Any) -> None:
        """Best effort: the SDK's reply timeout assumes a 16 ms USB latency timer; 1 ms makes every
        transaction faster. Not possible on a pty or without permission, which is fine."""
        try:
            port.ser.set_low_latency_mode(True)
        except (ValueError, OSError, AttributeError) as exc:
            log.debug("%s: low latency mode not set on %s: %s", self.name, self.port, exc)
        tty_name = Path(os.path.realpath(self.port)).name
        timer = Path("/sys/bus/usb-serial/devices") / tty_name / "latency_timer"
        if timer.exists():
            try:
                timer.write_text("1\n")
            except OSError as exc:
                log.debug("%s: could not set %s to 1 ms: %s", self.name, timer, exc)

    def _drop_port(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            try:
                port.closePort()
            except _PORT_ERRORS as exc:
                log.debug("%s: closing %s: %s", self.name, self.port, exc)

    def _configure(self) -> None:
        try:
            self.models = self._ping_once()
        except DeviceTimeout as exc:
            raise DeviceNotFound(
                f"no answer from servo IDs {self.ids} on {self.port} at {self.baudrate} bps ({exc})",
                self.name,
            ) from exc
        for servo_id in self.ids:
            self._write(servo_id, _TORQUE, 0)
            try:
                drive_mode = self._read(servo_id, _DRIVE_MODE)
            except DeviceStatusError as exc:
                log.debug(
                    "%s: servo %d has no Drive Mode (firmware before v38?): %s", self.name, servo_id, exc
                )
                drive_mode = 0
            if drive_mode & _REVERSE_BIT:
                log.warning(
                    "%s: servo %d had Reverse mode set in Drive Mode; clearing it (this driver does "
                    "the mirroring)",
                    self.name,
                    servo_id,
                )
                self._write(servo_id, _DRIVE_MODE, drive_mode & ~_REVERSE_BIT)
            if self._read(servo_id, _OPERATING_MODE) != OperatingMode.VELOCITY:
                self._write(servo_id, _OPERATING_MODE, OperatingMode.VELOCITY)
            self._limit_units[servo_id] = self._read(servo_id, _VELOCITY_LIMIT)
            self._hardware_error[servo_id] = self._read(servo_id, _HARDWARE_ERROR)
            if self._hardware_error[servo_id]:
                # A latched error in Shutdown keeps torque off until the servo is rebooted or power-cycled.
                log.warning(
                    "%s: servo %d reports hardware error %s at bring-up",
                    self.name,
                    servo_id,
                    describe_hardware_error(self._hardware_error[servo_id]),
                )
            self._start(servo_id)
            self._unwrap[servo_id].reseed()
        self._watchdog_suspects.clear()
        self._next_watchdog_check = time.monotonic() + _WATCHDOG_CHECK_S
        self.commanded_radps = (0.0, 0.0)
        log.info(
            "%s: servos %s (models %s) in velocity mode on %s at %d bps",
            self.name,
            self.ids,
            self.models,
            self.port,
            self.baudrate,
        )

    # -- Bus Watchdog ------------------------------------------------------------------------------------
    def _start(self, servo_id: int) -> None:
        """Torque on from standstill, Bus Watchdog armed. The watchdog is cleared (0) before Goal Velocity
        is written, which a fired watchdog makes read-only; with torque off meanwhile, a servo that follows
        its old goal again once cleared (the e-Manual does not say it will not) cannot move."""
        self._write(servo_id, _TORQUE, 0)
        watchdog = servo_id not in self._no_watchdog
        if watchdog:
            try:
                self._write(servo_id, _BUS_WATCHDOG, 0)
            except DeviceStatusError as exc:
                if not isinstance(exc.status, int) or exc.status & 0x7F != ErrorNumber.ACCESS:
                    raise
                log.warning(
                    "%s: servo %d has no Bus Watchdog (firmware before v38?): if it is cut off from the "
                    "agent it keeps its last goal velocity",
                    self.name,
                    servo_id,
                )
                self._no_watchdog.add(servo_id)
                watchdog = False
        self._write(servo_id, _GOAL_VELOCITY, 0)
        self._write(servo_id, _TORQUE, 1)
        if watchdog and self.bus_watchdog_units:
            self._write(servo_id, _BUS_WATCHDOG, self.bus_watchdog_units)
        self._watchdog_suspects.discard(servo_id)

    def _note_bus_gap(self) -> bool:
        """Suspect every servo when the bus has been quiet for half a watchdog period: the caller stalled,
        and a servo that heard nothing for the whole period has stopped and refuses goals."""
        if not self.bus_watchdog_units or self._last_transaction is None:
            return False
        quiet_s = time.monotonic() - self._last_transaction
        if quiet_s < 0.5 * self.bus_watchdog_units * BUS_WATCHDOG_UNIT_S:
            return False
        self._watchdog_suspects.update(self.ids)
        return True

    def _check_watchdogs(self, put_off_silent: bool = False) -> bool:
        """Read Bus Watchdog back from each suspect servo (from all of them once a second) and start again
        any that does not hold what was armed. True when one was started again (its goal is now 0).

        The read is retried as any read is (``retries``). A servo that still does not answer raises
        :class:`DeviceTimeout`, or with ``put_off_silent`` stays a suspect (counted and noted as a timeout)
        for the next check: a reply lost to a loaded host then costs the check, not what the caller did.

        One servo found stopped makes every servo a suspect in the same pass: what cut it off (a stalled
        caller, a pulled cable, a bus that lost a burst of packets) may have stopped the other wheel too,
        and a servo still latched would refuse the next goal while the one started again follows it, so the
        robot would pivot (a sync read stops at the first servo that does not answer, so a timeout names
        only one)."""
        now = time.monotonic()
        if now >= self._next_watchdog_check:
            self._watchdog_suspects.update(self.ids)
            self._next_watchdog_check = now + _WATCHDOG_CHECK_S
        restarted = False
        checked: set[int] = set()
        while pending := sorted(self._watchdog_suspects - self._no_watchdog - checked):
            servo_id = pending[0]
            checked.add(servo_id)
            try:
                value = self._retrying(functools.partial(self._read, servo_id, _BUS_WATCHDOG))
            except DeviceTimeout as exc:
                if not put_off_silent:
                    raise
                log.warning("%s: Bus Watchdog check put off: %s", self.name, exc)
                continue
            if value == self.bus_watchdog_units:
                self._watchdog_suspects.discard(servo_id)
                continue
            self._watchdog_suspects.update(set(self.ids) - checked)
            if value == BUS_WATCHDOG_EXPIRED:
                self.count("bus_watchdog_stops")
                self.note_error(f"servo {servo_id}: Bus Watchdog fired (it heard nothing for too long)")
                log.warning(
                    "%s: servo %d stopped by its Bus Watchdog; clearing it and starting the servo again",
                    self.name,
                    servo_id,
                )
            else:
                log.warning(
                    "%s: servo %d's Bus Watchdog reads %d, not %d (rebooted?); starting the servo again",
                    self.name,
                    servo_id,
                    value,
                    self.bus_watchdog_units,
                )
            self._start(servo_id)
            restarted = True
        self._watchdog_suspects.difference_update(self._no_watchdog)
        return restarted

    # -- one bus transaction -----------------------------------------------------------------------------
    def _bus(self) -> Any:
        """The open port, reopening it first if it was lost."""
        if not self.is_open and self._port is None:
            raise DeviceError("not open", self.name)
        if self._port_lost:
            try:
                self.reconnect()
            except DeviceError as exc:
                raise DeviceDisconnected(f"{self.port} is still gone: {exc}", self.name) from exc
        return self._port

    def _transact(self, what: str, call: Callable[..., Any], *args: Any) -> Any:
        port = self._bus()
        try:
            return call(port, *args)
        except _PORT_ERRORS as exc:
            self._port_lost = True
            self.count("disconnects")
            self.note_error(f"{what}: port lost: {exc}")
            self._drop_port()
            raise DeviceDisconnected(f"{what}: {self.port} went away ({exc})", self.name) from exc
        finally:
            # From its end: waiting for a reply that does not come is no stall of the caller's (the
            # servo that did not answer is suspect anyway; see _check).
            self._last_transaction = time.monotonic()
            # The SDK marks its port busy and leaves it so if a packet dies under it.
            if port is not None:
                port.is_using = False

    def _check(self, what: str, servo_id: int, result: int, error: int) -> None:
        if result == COMM_RX_TIMEOUT:
            # A servo that does not answer may not hear either: its Bus Watchdog may fire meanwhile.
            self._watchdog_suspects.add(servo_id)
            self.count("timeouts")
            self.note_error(f"servo {servo_id}: no answer to {what}")
            raise DeviceTimeout(f"servo {servo_id} did not answer {what}", self.name)
        if result == COMM_RX_CORRUPT:
            self.count("corrupt_replies")
            self.note_error(f"servo {servo_id}: corrupt reply to {what}")
            raise DeviceError(f"servo {servo_id}: corrupt status packet for {what}", self.name)
        if result != COMM_SUCCESS:
            self.count("comm_errors")
            text = self._ph.getTxRxResult(result)
            self.note_error(f"servo {servo_id}: {what}: {text}")
            raise DeviceError(f"servo {servo_id}: {what}: {text}", self.name)
        status = StatusError.from_byte(error)
        if status.alert and not self._hardware_error.get(servo_id):
            # Hardware Error Status latches until a reboot, so it is read once when the alert appears.
            self._alert_pending.add(servo_id)
        if status.failed:
            self.count("status_errors")
            self.note_error(f"servo {servo_id}: {what}: {status.describe()}")
            raise DeviceStatusError(
                f"servo {servo_id} refused {what}: {status.describe()}", self.name, status=error
            )

    def _read(self, servo_id: int, item: ControlItem) -> int:
        # readTxRx, not read{1,2,4}ByteTxRx: those index into the data even when a servo answered with an
        # error and no data, and die with IndexError.
        what = f"READ {item.name}"
        data, result, error = self._transact(what, self._ph.readTxRx, servo_id, item.address, item.size)
        self._check(what, servo_id, result, error)
        if len(data) != item.size:
            self.count("corrupt_replies")
            raise DeviceError(
                f"servo {servo_id}: {what} reply has {len(data)} bytes, not {item.size}", self.name
            )
        return item.decode(bytes(data))

    def _write(self, servo_id: int, item: ControlItem, value: int) -> None:
        if not item.in_range(value):
            raise ValueError(f"{item.name} must be {item.minimum}..{item.maximum}, not {value}")
        data = list(item.encode(value))
        result, error = self._transact(
            f"WRITE {item.name}", self._ph.writeTxRx, servo_id, item.address, item.size, data
        )
        self._check(f"WRITE {item.name}", servo_id, result, error)

    # -- WheelServos -------------------------------------------------------------------------------------
    def _ping_once(self) -> dict[int, int]:
        models = {}
        for servo_id in self.ids:
            model, result, error = self._transact("PING", self._ph.ping, servo_id)
            self._check("PING", servo_id, result, error)
            if model != MODEL_XL430_W250:
                log.warning(
                    "%s: servo %d is model %d, not an XL430-W250 (%d); its control table may differ",
                    self.name,
                    servo_id,
                    model,
                    MODEL_XL430_W250,
                )
            models[servo_id] = int(model)
        return models

    def ping(self) -> dict[int, int]:
        with self._lock:
            return self._retrying(self._ping_once)

    def _retrying(self, call: Callable[[], _T]) -> _T:
        for attempt in range(self.retries + 1):
            try:
                return call()
            except DeviceTimeout:
                if attempt == self.retries:
                    raise
                self.count("retries")
        raise AssertionError("unreachable")

    def velocity_units(self, servo_id: int, wheel_radps: float) -> int:
        """Goal Velocity units for a wheel speed on ``servo_id``, mirrored and clamped."""
        sign = self.signs[self.ids.index(servo_id)]
        if self.max_wheel_radps is not None:
            wheel_radps = max(-self.max_wheel_radps, min(self.max_wheel_radps, wheel_radps))
        units = round(sign * wheel_radps / RADPS_PER_VELOCITY_UNIT)
        limit = self._limit_units[servo_id]
        if abs(units) > limit:
            # A servo silently drops a sync-written goal beyond its Velocity Limit; clamp instead.
            self.count("clamped_commands")
            units = max(-limit, min(limit, units))
        return units

    def _sync_write_velocity(self, units: tuple[int, int]) -> None:
        def send(port: Any) -> int:
            group = GroupSyncWrite(port, self._ph, _GOAL_VELOCITY.address, _GOAL_VELOCITY.size)
            for servo_id, value in zip(self.ids, units, strict=True):
                group.addParam(servo_id, list(_GOAL_VELOCITY.encode(value)))
            return int(group.txPacket())

        result = self._transact("SYNC_WRITE Goal Velocity", send)
        if result != COMM_SUCCESS:
            self.count("comm_errors")
            raise DeviceError(f"SYNC_WRITE Goal Velocity: {self._ph.getTxRxResult(result)}", self.name)

    def set_velocity(self, left_radps: float, right_radps: float) -> None:
        if not (math.isfinite(left_radps) and math.isfinite(right_radps)):
            raise ValueError(f"wheel speeds must be finite, got ({left_radps}, {right_radps})")
        with self._lock:
            self._bus()
            units = (
                self.velocity_units(self.left_id, left_radps),
                self.velocity_units(self.right_id, right_radps),
            )
            gap = self._note_bus_gap()
            # Sent first in any case: whatever still listens takes it (a silent servo's check below would
            # time out, and the other wheel must not wait for that).
            self._sync_write_velocity(units)
            if gap and self._check_watchdogs():
                self._sync_write_velocity(units)  # the servos started again hold goal 0
            self.commanded_radps = (left_radps, right_radps)
            self.count("commands")

    def _read_once(self) -> WheelState:
        def sync_read(port: Any) -> tuple[int, int, list[tuple[bytes, int, int]]]:
            group = GroupSyncRead(port, self._ph, _READ_ADDRESS, _READ_LENGTH)
            for servo_id in self.ids:
                group.addParam(servo_id)
            sent = int(group.txPacket())
            # The servos sample when the instruction reaches them: take the host time right after sending.
            host_time_ns = time.monotonic_ns()
            replies: list[tuple[bytes, int, int]] = []
            if sent == COMM_SUCCESS:
                # GroupSyncRead.rxPacket() drops each servo's ERR byte (and with it the alert bit), so the
                # replies are collected here with readRx, which keeps it.
                for servo_id in self.ids:
                    data, result, error = self._ph.readRx(port, servo_id, _READ_LENGTH)
                    replies.append((bytes(data), int(result), int(error)))
                    if result != COMM_SUCCESS:
                        break
            return sent, host_time_ns, replies

        what = "SYNC_READ Present Velocity/Position"
        sent, host_time_ns, replies = self._transact(what, sync_read)
        if sent != COMM_SUCCESS:
            self.count("comm_errors")
            raise DeviceError(f"{what}: {self._ph.getTxRxResult(sent)}", self.name)
        positions, velocities = [], []
        for n, (data, result, error) in enumerate(replies):
            servo_id, sign = self.ids[n], self.signs[n]
            self._check(what, servo_id, result, error)
            if len(data) != _READ_LENGTH:
                self.count("corrupt_replies")
                raise DeviceError(
                    f"servo {servo_id}: {what} reply has {len(data)} bytes, not {_READ_LENGTH}", self.name
                )
            velocity = _PRESENT_VELOCITY.decode(data[:4])
            ticks = self._unwrap[servo_id].update(_PRESENT_POSITION.decode(data[4:]))
            velocities.append(sign * velocity * RADPS_PER_VELOCITY_UNIT)
            positions.append(sign * ticks * RAD_PER_TICK)
            if not StatusError.from_byte(error).alert:
                self._hardware_error[servo_id] = 0  # no alert bit: Hardware Error Status is 0
        for servo_id in sorted(self._alert_pending):
            self._refresh_hardware_error(servo_id)
        return WheelState(
            (positions[0], positions[1]),
            (velocities[0], velocities[1]),
            host_time_ns,
            (self._hardware_error[self.left_id], self._hardware_error[self.right_id]),
        )

    def _refresh_hardware_error(self, servo_id: int) -> None:
        bits = self._read(servo_id, _HARDWARE_ERROR)
        self._alert_pending.discard(servo_id)
        if bits and bits != self._hardware_error[servo_id]:
            self.count("hardware_alerts")
            text = describe_hardware_error(bits)
            self.note_error(f"servo {servo_id}: hardware error {text}")
            log.warning("%s: servo %d hardware error: %s", self.name, servo_id, text)
        self._hardware_error[servo_id] = bits

    def read(self) -> WheelState:
        with self._lock:
            self._note_bus_gap()
            state = self._retrying(self._read_once)
            self.count("reads")
            if self.bus_watchdog_units:
                # Both servos just answered, so a check gets its replies; one lost all the same leaves
                # its servo a suspect and the state just read is returned.
                self._check_watchdogs(put_off_silent=True)
            return state

    def torque(self, on: bool) -> None:
        with self._lock:
            for servo_id in self.ids:
                if on:
                    # From standstill, not from whatever goal was left in the register; watchdog armed.
                    self._start(servo_id)
                else:
                    self._write(servo_id, _TORQUE, 0)  # the Bus Watchdog only watches with torque on
            if on:
                self.commanded_radps = (0.0, 0.0)

    def hardware_errors(self) -> tuple[int, int]:
        with self._lock:
            for servo_id in self.ids:
                self._refresh_hardware_error(servo_id)
            return self._hardware_error[self.left_id], self._hardware_error[self.right_id]

    # -- diagnostics -------------------------------------------------------------------------------------
    def read_item(self, servo_id: int, name: str) -> int:
        """Any control table item by name (temperature, voltage, modes) from one servo."""
        with self._lock:
            return self._retrying(lambda: self._read(servo_id, _TABLE[name]))

    def write_item(self, servo_id: int, name: str, value: int) -> None:
        """Write one control table item; the servo's refusal comes back as DeviceStatusError."""
        with self._lock:
            self._write(servo_id, _TABLE[name], value)
