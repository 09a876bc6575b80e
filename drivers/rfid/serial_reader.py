"""RFID readers on a serial line: 125 kHz ASCII readers (ID-12LA/ID-20LA, RDM6300) and ThingMagic Mercury
modules (M6e Nano/Micro), through ``serial.serial_for_url`` so a device path, a pty or ``spy://`` all work.

One reader thread owns the port. It decodes frames with :mod:`firmware_protocol.rfid`, publishes
:class:`~drivers.samples.TagRead` samples, and survives the faults a robot sees:

* the port vanishes (USB pulled): reported as ``DeviceDisconnected`` in :meth:`health`, then the thread
  reopens the same URL every ``reconnect_interval_s`` until it is back (a udev symlink keeps the name);
* junk or bad checksums on the line: skipped, counted (``discarded_bytes``, ``resyncs``, ``bad_checksums``);
* a Mercury module that stops talking: its continuous read sends a keep-alive about once a second, so
  ``keepalive_timeout_s`` of silence is reported as ``DeviceTimeout`` and the connect sequence is re-run.

``open()`` makes the first connection itself and raises (``DeviceNotFound``, ``DeviceTimeout``,
``DeviceStatusError``) so a wrong configuration fails at start-up, not silently in a thread.
"""

from __future__ import annotations

import contextlib
import enum
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import serial

from drivers.device import DeviceHealth
from drivers.errors import (
    ConfigError,
    DeviceDisconnected,
    DeviceError,
    DeviceNotFound,
    DeviceStatusError,
    DeviceTimeout,
)
from drivers.rfid.base import RfidReader
from drivers.samples import TagRead
from firmware_protocol.rfid import (
    AsciiFormat,
    AsciiFrameDecoder,
    MercuryKeepAlive,
    MercuryOpcode,
    MercuryResponse,
    MercuryResponseDecoder,
    MercuryTagRead,
    MercuryVersion,
    RfidError,
    decode_stream_message,
    decode_version,
    encode_set_antenna_search_list,
    encode_set_read_power,
    encode_set_reader_option,
    encode_set_region,
    encode_set_tag_protocol,
    encode_start_continuous_read,
    encode_stop_continuous_read,
    encode_version_request,
)

__all__ = ["RfidProtocol", "SerialRfidReader"]

log = logging.getLogger(__name__)


class _Stopping(Exception):
    """Raised inside the reader thread when close() interrupts a command that is still waiting."""


class RfidProtocol(enum.StrEnum):
    ID12LA = "id12la"
    RDM6300 = "rdm6300"
    MERCURY = "mercury"


DEFAULT_BAUDRATE = {
    RfidProtocol.ID12LA: 9600,  # ID-12LA datasheet: 9600 8N1, ASCII output
    RfidProtocol.RDM6300: 9600,  # arduino12/rdm6300
    RfidProtocol.MERCURY: 115200,  # the M6e Nano's power-on default (SparkFun examples)
}

REGION_NORTH_AMERICA = 0x0D

# How long one port read waits. It is also the idle gap after which a partial frame is treated as junk
# (a reader never pauses mid-frame: at 9600 bd bytes are ~1 ms apart, USB adapters flush every <= 16 ms).
_READ_TIMEOUT_S = 0.05


class SerialRfidReader(RfidReader):
    """A serial RFID reader speaking ``protocol`` ("id12la", "rdm6300" or "mercury").

    Mercury options: ``region`` (SparkFun region code, default 0x0D North America), ``read_power_dbm``
    (0..27; SparkFun's examples use 5 dBm when the board is powered over USB), ``antenna_ports`` (the
    module's ports to search, ``(1,)`` on a Nano, ``(1, 2)`` on an M6e Micro with two antennas),
    ``command_timeout_s`` for each command of the connect sequence and ``keepalive_timeout_s`` of silence
    before the module is declared stalled.
    """

    def __init__(
        self,
        url: str,
        protocol: RfidProtocol | str = RfidProtocol.ID12LA,
        baudrate: int | None = None,
        name: str = "rfid",
        *,
        debounce_s: float = 0.0,
        queue_size: int = 256,
        command_timeout_s: float = 1.0,
        keepalive_timeout_s: float = 3.0,
        reconnect_interval_s: float = 0.5,
        region: int = REGION_NORTH_AMERICA,
        read_power_dbm: float = 5.0,
        antenna_ports: tuple[int, ...] = (1,),
    ) -> None:
        try:
            self.protocol = RfidProtocol(protocol)
        except ValueError as exc:
            raise ConfigError(
                "rfid.protocol", f"unknown protocol {protocol!r}; one of {list(RfidProtocol)}"
            ) from exc
        for key, value in (
            ("rfid.command_timeout_s", command_timeout_s),
            ("rfid.keepalive_timeout_s", keepalive_timeout_s),
            ("rfid.reconnect_interval_s", reconnect_interval_s),
        ):
            if not value > 0:
                raise ConfigError(key, f"must be positive, got {value}")
        if not 0.0 <= read_power_dbm <= 27.0:
            raise ConfigError(
                "rfid.read_power_dbm", f"must be 0..27 dBm (the module's range), got {read_power_dbm}"
            )
        if not 0 <= region <= 0xFF:
            raise ConfigError("rfid.region", f"must be a one-byte region code, got {region}")
        if not antenna_ports or not all(1 <= p <= 15 for p in antenna_ports):
            raise ConfigError("rfid.antenna_ports", f"must be port numbers 1..15, got {antenna_ports!r}")
        if baudrate is not None and baudrate <= 0:
            raise ConfigError("rfid.baudrate", f"must be positive, got {baudrate}")
        try:
            super().__init__(name, queue_size=queue_size, debounce_s=debounce_s)
        except ValueError as exc:
            raise ConfigError("rfid", str(exc)) from exc
        self.url = url
        self.baudrate = baudrate if baudrate is not None else DEFAULT_BAUDRATE[self.protocol]
        self.command_timeout_s = command_timeout_s
        self.keepalive_timeout_s = keepalive_timeout_s
        self.reconnect_interval_s = reconnect_interval_s
        self.region = region
        self.read_power_centi_dbm = round(read_power_dbm * 100)
        self.antenna_ports = tuple(antenna_ports)
        self.version: MercuryVersion | None = None
        self._decoder: AsciiFrameDecoder | MercuryResponseDecoder = (
            MercuryResponseDecoder()
            if self.protocol is RfidProtocol.MERCURY
            else AsciiFrameDecoder(AsciiFormat(self.protocol.value))
        )
        self._port: Any = None
        self._link_ok = False
        self._last_rx = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- lifecycle ---------------------------------------------------------------------------------
    def _open(self) -> None:
        self._stop.clear()
        self._connect()
        self._thread = threading.Thread(target=self._run, name=f"rfid-{self.name}", daemon=True)
        self._thread.start()

    def _close(self) -> None:
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout=2.0)
            if thread.is_alive():
                log.warning("%s: reader thread did not stop within 2 s", self.name)
        port, self._port = self._port, None
        if port is not None:
            if self.protocol is RfidProtocol.MERCURY and self._link_ok:
                # Leave the module idle, as SparkFun's stopReading() does; the answer is not awaited.
                with contextlib.suppress(serial.SerialException, OSError):
                    port.write(encode_stop_continuous_read())
                    port.flush()
            with contextlib.suppress(serial.SerialException, OSError):
                port.close()
        self._link_ok = False
        self._shut_queue()

    @property
    def connected(self) -> bool:
        return self.is_open and self._link_ok

    def health(self) -> DeviceHealth:
        with self._health_lock:
            self._counters.update(self._decoder.counters())
        return super().health()

    # -- connecting ----------------------------------------------------------------------------------
    def _connect(self) -> None:
        """Open the port and, for Mercury, configure the module and start its continuous read."""
        try:
            port = serial.serial_for_url(
                self.url,
                baudrate=self.baudrate,
                timeout=_READ_TIMEOUT_S,
                write_timeout=self.command_timeout_s,
            )
        except ValueError as exc:
            raise ConfigError("rfid.port", f"{self.url!r}: {exc}") from exc
        except (serial.SerialException, OSError) as exc:
            raise DeviceNotFound(f"cannot open serial port: {exc}", self.url) from exc
        self._decoder.reset()
        self._last_rx = time.monotonic()
        try:
            if self.protocol is RfidProtocol.MERCURY:
                self._mercury_start(port)
        except BaseException:
            with contextlib.suppress(serial.SerialException, OSError):
                port.close()
            raise
        self._port = port
        self._link_ok = True
        log.info("%s: %s reader up on %s", self.name, self.protocol.value, self.url)

    def _mercury_start(self, port: Any) -> None:
        """The connect sequence of SparkFun's examples: stop any read left running, ask the version (the
        "is anybody there" check), set region, protocol, antennas, power, disable the read filter (so a tag
        that stays in the field keeps being reported), start the continuous read."""
        with contextlib.suppress(serial.SerialException, OSError):
            port.reset_input_buffer()
        self._write(port, encode_stop_continuous_read())
        version = self._command(port, encode_version_request(), MercuryOpcode.VERSION, "version query")
        try:
            self.version = decode_version(version)
        except RfidError as exc:
            raise DeviceError(f"bad version answer: {exc}", self.url) from exc
        log.info("%s: Mercury module firmware %s", self.name, self.version.firmware)
        ports = [(p, p) for p in self.antenna_ports]
        for request, opcode, what in (
            (encode_set_region(self.region), MercuryOpcode.SET_REGION, "set region"),
            (encode_set_tag_protocol(), MercuryOpcode.SET_TAG_PROTOCOL, "set tag protocol"),
            (encode_set_antenna_search_list(ports), MercuryOpcode.SET_ANTENNA_PORT, "set antenna ports"),
            (
                encode_set_read_power(self.read_power_centi_dbm),
                MercuryOpcode.SET_READ_TX_POWER,
                "set read power",
            ),
            (
                encode_set_reader_option(0x0C, 0x00),
                MercuryOpcode.SET_READER_OPTIONAL_PARAMS,
                "disable read filter",
            ),
        ):
            self._command(port, request, opcode, what)
        # The start answer echoes option 01; a late answer to the stop sent above would carry 02.
        self._command(
            port,
            encode_start_continuous_read(),
            MercuryOpcode.MULTI_PROTOCOL_TAG_OP,
            "start continuous read",
            accept=lambda r: r.data[:1] == b"\x01",
        )

    def _write(self, port: Any, data: bytes) -> None:
        try:
            port.write(data)
        except serial.SerialTimeoutException as exc:
            raise DeviceTimeout(
                f"write did not complete within {self.command_timeout_s} s", self.url
            ) from exc
        except (serial.SerialException, OSError) as exc:
            raise DeviceDisconnected(f"write failed: {exc}", self.url) from exc

    def _command(
        self,
        port: Any,
        request: bytes,
        opcode: int,
        what: str,
        accept: Callable[[MercuryResponse], bool] | None = None,
    ) -> MercuryResponse:
        """Send one request and wait for the answer with the same opcode; stream messages that arrive
        meanwhile (tag records of a read still running) are handled as usual."""
        self._write(port, request)
        deadline = time.monotonic() + self.command_timeout_s
        answer: MercuryResponse | None = None
        while answer is None:
            if self._stop.is_set():
                raise _Stopping
            if time.monotonic() >= deadline:
                self.count("timeouts")
                raise DeviceTimeout(f"no answer to {what} within {self.command_timeout_s} s", self.url)
            for response in self._receive(port):
                if answer is None and response.opcode == opcode and (accept is None or accept(response)):
                    answer = response
                else:
                    self._handle(response)
        if not answer.ok:
            raise DeviceStatusError(
                f"{what} failed with status {answer.status:04X}", self.url, status=answer.status
            )
        return answer

    def _receive(self, port: Any) -> list[Any]:
        """One port read (at most ``_READ_TIMEOUT_S``), decoded."""
        try:
            data = port.read(max(1, port.in_waiting))
        except (serial.SerialException, OSError, TypeError) as exc:
            # TypeError: pyserial's posix backend when the fd went away under it.
            raise DeviceDisconnected(f"read failed: {exc}", self.url) from exc
        resyncs = self._decoder.resyncs
        messages: list[Any] = []
        if data:
            self._last_rx = time.monotonic()
            messages = list(self._decoder.feed(data))
        elif self._decoder.pending:
            messages = list(self._decoder.flush())
        if self._decoder.resyncs != resyncs:
            log.debug("%s: skipped junk on the line: %s", self.name, self._decoder.last_error)
        return messages

    # -- the reader thread ---------------------------------------------------------------------------
    def _run(self) -> None:
        while not self._stop.is_set():
            if self._port is None:
                self._reconnect()
                continue
            try:
                for message in self._receive(self._port):
                    self._handle(message)
                if (
                    self.protocol is RfidProtocol.MERCURY
                    and time.monotonic() - self._last_rx > self.keepalive_timeout_s
                ):
                    self._restart_stalled()
            except DeviceDisconnected as exc:
                self._lost(exc)
            except _Stopping:
                return
            except Exception:  # a bug must show in the log and health, and not end the thread silently
                log.exception("%s: reader thread error", self.name)
                self.note_error("internal error in reader thread (see log)")
                self._stop.wait(self.reconnect_interval_s)

    def _reconnect(self) -> None:
        try:
            self._connect()
        except (DeviceError, ConfigError) as exc:
            self.note_error(f"{type(exc).__name__}: {exc}")
            self._stop.wait(self.reconnect_interval_s)
            return
        self.count("reconnects")

    def _lost(self, exc: DeviceError) -> None:
        log.warning("%s: %s", self.name, exc)
        self.note_error(f"{type(exc).__name__}: {exc}")
        self.count("disconnects")
        port, self._port = self._port, None
        self._link_ok = False
        if port is not None:
            with contextlib.suppress(serial.SerialException, OSError):
                port.close()

    def _restart_stalled(self) -> None:
        stall = DeviceTimeout(f"no keep-alive for {self.keepalive_timeout_s} s", self.url)
        log.warning("%s: %s; restarting the continuous read", self.name, stall)
        self.note_error(f"DeviceTimeout: {stall}")
        self.count("stalls")
        self._link_ok = False
        try:
            self._mercury_start(self._port)
        except DeviceDisconnected:
            raise
        except DeviceError as exc:
            self.note_error(f"{type(exc).__name__}: {exc}")
            # Try again after another keep-alive period rather than hammering a module that is busy.
            self._last_rx = time.monotonic()
            return
        self._link_ok = True
        self.count("restarts")

    # -- messages ------------------------------------------------------------------------------------
    def _handle(self, message: Any) -> None:
        now_ns = time.monotonic_ns()
        if isinstance(message, MercuryResponse):
            self._handle_mercury(message, now_ns)
        else:
            self._publish(TagRead(message.tag_id, now_ns, self.name))

    def _handle_mercury(self, response: MercuryResponse, now_ns: int) -> None:
        try:
            message = decode_stream_message(response)
        except RfidError as exc:
            self.count("bad_records")
            self.note_error(f"bad tag record: {exc}")
            return
        if isinstance(message, MercuryTagRead | MercuryKeepAlive) and not self._link_ok:
            # A module that resumes streaming by itself (it was only busy) needs no restart.
            self._link_ok = True
            self.count("recoveries")
        if isinstance(message, MercuryTagRead):
            if not message.epc_crc_ok:
                # The module checks the air-interface CRC itself, so a mismatch here hints at a layout the
                # decoder does not know; count it so it shows, but keep the read.
                self.count("epc_crc_mismatch")
            self._publish(
                TagRead(
                    message.epc_hex,
                    now_ns,
                    self.name,
                    rssi_dbm=float(message.rssi_dbm),
                    antenna=message.rx_antenna,
                )
            )
        elif isinstance(message, MercuryKeepAlive):
            self.count("keepalives")
            if message.temperature_throttled:
                self.count("temperature_throttled")
        else:
            self.count("other_responses")
            if not message.ok:
                self.note_error(
                    f"module reported status {message.status:04X} for opcode {message.opcode:02X}"
                )
