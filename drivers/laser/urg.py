"""Hokuyo URG laser scanners (URG-04LX and SCIP 2.0 kin) over a serial port.

The port is opened with ``serial.serial_for_url``, so ``/dev/ttyACM0``, a pty path or ``loop://`` all work.
One worker thread owns the port: it runs the commands the public methods hand it (one at a time, each
with a deadline), reads MD scans in between, and when the port dies (unplugged: EIO / SerialException)
marks the link down, then reopens the same URL every ``reconnect_interval_s`` and, once the sensor
answers again, redoes the connect sequence and resumes streaming if it was on.

Connect sequence: QT (stops a stream left running and tells the mode: a 1-character status means SCIP 1.1,
``0E`` means time-adjust mode, left with TM2), SCIP2.0 (``0`` switched, ``0E`` already SCIP 2.0), VV, PP,
II, TM0/TM1 x N/TM2 for the clock, BM (``02`` = already on is fine).

Clock. The URG stamps each scan with its 24-bit millisecond counter at step 0 (spec p.12). ``Scan``
keeps that counter unwrapped (``device_time_ms``) and maps it to host time with :class:`DeviceClock`, a
bounded-drift estimator of ``offset = host_time - device_time``:

* every scan received at host time ``h`` gives an upper bound ``offset <= h - d - L``, where ``L`` is the
  least possible delay between step 0 and the data leaving the sensor: the time the mirror takes to reach
  the last requested step, ``(last_step + 1) / ARES * 60 / SCAN``;
* every TM1 round trip sent at ``s``, answered at ``r`` with clock value ``d`` bounds the offset on both
  sides: ``s - (d + 1 ms) <= offset <= r - d``;
* a bound taken at ``t_k`` loosens by ``rho * |t - t_k|`` (``rho`` = 200 ppm, above the drift of two
  crystal clocks), so old bounds age out without a window.

The estimate is the tightest upper bound (scans with the least queueing delay); if it ever falls below
the tightest lower bound, the delay model is wrong for this sensor and the lower bound is used instead
(counted as ``clock_inconsistent``). ``Scan.host_time_ns`` is then ``offset + device_time``: when step 0 of
the scan was measured, in ``time.monotonic_ns()``; beam ``i`` follows ``(first_step + i * cluster) / ARES``
revolutions later. Unwrapping uses the same estimate to pick the 2^24 ms turn a timestamp belongs to, so
it also works across gaps longer than a wrap; a timestamp that cannot belong to the current clock (the
sensor restarted: power loss, RS) starts a new clock epoch (``clock_resets``).
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import math
import os
import queue
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import CancelledError, Future
from concurrent.futures import TimeoutError as FutureTimeout
from typing import Any, TypeVar

import numpy as np
import serial

from drivers.errors import (
    ConfigError,
    DeviceDisconnected,
    DeviceError,
    DeviceNotFound,
    DeviceStatusError,
    DeviceTimeout,
)
from drivers.laser.base import LaserInfo, LaserScanner
from drivers.samples import Scan
from firmware_protocol import scip

log = logging.getLogger(__name__)

__all__ = [
    "DeviceClock",
    "UrgCommandError",
    "UrgHardwareFault",
    "UrgLaser",
    "UrgLaserOff",
    "UrgModeError",
    "UrgParameterError",
    "UrgStatusError",
    "raise_for_status",
]

T = TypeVar("T")

# A byte on an 8N1 serial line: start bit, 8 data bits, stop bit.
BITS_PER_BYTE = 10
# The scan period assumed before the sensor's PP reply gives its own (URG-04LX: 600 rpm).
NOMINAL_SCAN_PERIOD_S = 0.1
# The stall watchdog waits at least this many scan intervals of the link (see UrgLaser.stall_limit_s).
STALL_SCAN_INTERVALS = 2.0
# The tag of our commands: 6 hex digits (``UrgLaser._tag``); its length enters the size of a streamed scan.
_TAG_CHARS = 6


# -- status errors -----------------------------------------------------------------------------------------


class UrgStatusError(DeviceStatusError):
    """The URG answered a command with an error status. ``status`` is the SCIP code, ``command`` the echo."""

    def __init__(self, message: str, device: str = "", status: str | None = None, command: str = "") -> None:
        self.command = command
        super().__init__(message, device, status)


class UrgLaserOff(UrgStatusError):
    """GD/GS answered 10: the laser is off."""


class UrgParameterError(UrgStatusError):
    """The command's parameters were refused (steps, cluster, interval, count, bit rate)."""


class UrgCommandError(UrgStatusError):
    """0A..0I or an undocumented status: the sensor did not take the command at all."""


class UrgHardwareFault(UrgStatusError):
    """Laser or motor trouble reported by the sensor (BM 01, MD 21..49, 50..98)."""


class UrgModeError(UrgStatusError):
    """The sensor is in the wrong mode for the command (SCIP 1.1, time-adjust mode)."""


_STATUS_ERRORS: dict[scip.StatusKind, type[UrgStatusError]] = {
    scip.StatusKind.LASER_OFF: UrgLaserOff,
    scip.StatusKind.PARAMETER_ERROR: UrgParameterError,
    scip.StatusKind.COMMAND_ERROR: UrgCommandError,
    scip.StatusKind.UNSUPPORTED: UrgCommandError,
    scip.StatusKind.UNKNOWN: UrgCommandError,
    scip.StatusKind.HARDWARE_FAULT: UrgHardwareFault,
    scip.StatusKind.WRONG_STATE: UrgModeError,
    scip.StatusKind.SCIP1: UrgModeError,
}


def raise_for_status(reply: scip.ScipReply, device: str, accept: tuple[str, ...] = ("00",)) -> None:
    """Raise the typed :class:`UrgStatusError` for ``reply`` unless its status is one of ``accept``."""
    if reply.status in accept:
        return
    meaning = reply.meaning
    cls = _STATUS_ERRORS.get(meaning.kind, UrgCommandError)
    raise cls(f"{reply.echo!r} -> status {reply.status}: {meaning.text}", device, reply.status, reply.echo)


# -- clock -------------------------------------------------------------------------------------------------


class DeviceClock:
    """Maps the sensor's 24-bit millisecond counter to host ``monotonic_ns`` (see the module docstring).

    Pure bookkeeping: no I/O, no clock reads; every method takes the host times it needs. Offsets are
    ``host_ns - device_ms * 1e6``; internally host times are kept relative to the first sample so that
    float64 keeps sub-nanosecond precision.
    """

    def __init__(
        self, drift: float = 200e-6, max_stale_ms: float = 5_000, max_ahead_ms: float = 1_000
    ) -> None:
        self.drift = drift
        self.max_stale_ms = max_stale_ms
        self.max_ahead_ms = max_ahead_ms
        self.resets = 0
        self.inconsistent = 0
        self.reset()

    def reset(self) -> None:
        """Forget everything (the sensor's clock restarted); counters are kept."""
        self._t_ref: int | None = None
        # A bound b taken at relative time t_k holds at t as b +- drift * (t - t_k); storing b -+ drift * t_k
        # keeps only the tightest of each side: upper(t) = _upper + drift * t, lower(t) = _lower - drift * t.
        self._upper = math.inf
        self._lower = -math.inf
        self._last_ms: int | None = None
        self._t_last = 0.0  # relative host time of the latest bound

    def _rel(self, host_ns: int) -> float:
        if self._t_ref is None:
            self._t_ref = host_ns
        return float(host_ns - self._t_ref)

    def _offset_rel(self, at_ns: int) -> float | None:
        if self._t_ref is None:
            return None
        t = float(at_ns - self._t_ref)
        upper = self._upper + self.drift * t
        lower = self._lower - self.drift * t
        if math.isinf(upper):
            return None if math.isinf(lower) else lower
        # Scans bound the offset from above (tight: some scan always comes with little queueing delay); TM
        # bounds it from below. Below the lower bound, the delay model is wrong and the lower bound wins.
        return max(upper, lower)

    def offset_ns(self, at_ns: int) -> float | None:
        """Estimated ``host_ns - device_ms * 1e6`` at host time ``at_ns``, or None before any sample."""
        rel = self._offset_rel(at_ns)
        return None if rel is None or self._t_ref is None else self._t_ref + rel

    def unwrap(
        self, raw_ms: int, at_ns: int, min_delay_ns: float = 0.0, tolerance_ms: float | None = None
    ) -> int:
        """The unwrapped device time of ``raw_ms``, received at host time ``at_ns`` at least ``min_delay_ns``
        after it was taken. Starts a new epoch when the value cannot belong to the current clock: more than
        ``max_ahead_ms`` newer or ``max_stale_ms`` older than predicted (data can wait in buffers, it cannot
        come from the future), or off by more than ``tolerance_ms`` either way when the reading's age is
        known (a TM round trip)."""
        offset = self._offset_rel(at_ns)
        if offset is None or self._t_ref is None:
            # No estimate yet: the value nearest to the previous one, forwards or backwards.
            value = raw_ms if self._last_ms is None else self._last_ms + _centred(raw_ms - self._last_ms)
        else:
            t = float(at_ns - self._t_ref)
            predicted = round((t - min_delay_ns - offset) / 1e6)
            diff = _centred(raw_ms - predicted)
            # The estimate is only as good as its freshest bound: it may be off by the drift of both clocks
            # since then (a sensor that was idle for hours is not a restarted one).
            slack_ms = 2.0 * self.drift * max(0.0, t - self._t_last) / 1e6
            stale, ahead = (
                (self.max_stale_ms, self.max_ahead_ms) if tolerance_ms is None else (tolerance_ms,) * 2
            )
            if not -stale - slack_ms <= diff <= ahead + slack_ms:
                log.info("URG clock off its prediction by %d ms: new clock epoch", diff)
                self.resets += 1
                self.reset()
                return self.unwrap(raw_ms, at_ns, min_delay_ns, tolerance_ms)
            value = predicted + diff
        self._last_ms = value
        return value

    def observe_scan(self, device_ms: int, recv_ns: int, min_delay_ns: float) -> None:
        """A scan stamped ``device_ms`` (unwrapped) arrived at ``recv_ns``, at least ``min_delay_ns`` after
        step 0: ``offset <= recv - device - min_delay``."""
        t = self._rel(recv_ns)
        self._add_upper(t - device_ms * 1e6 - min_delay_ns, t)

    def observe_round_trip(self, device_ms: int, send_ns: int, recv_ns: int) -> None:
        """TM1 sent at ``send_ns`` was answered at ``recv_ns`` with the reading ``device_ms`` (unwrapped).

        The reading was taken between send and receive and shows whole milliseconds (rounded down), so
        ``send - (device + 1 ms) <= offset <= recv - device``."""
        t_send, t_recv = self._rel(send_ns), self._rel(recv_ns)
        self._add_upper(t_recv - device_ms * 1e6, t_recv)
        self._lower = max(self._lower, t_send - (device_ms + 1) * 1e6 + self.drift * t_send)
        self._check(t_recv)

    def _add_upper(self, bound: float, t: float) -> None:
        self._upper = min(self._upper, bound - self.drift * t)
        self._t_last = max(self._t_last, t)
        self._check(t)

    def _check(self, t: float) -> None:
        if self._upper + self.drift * t < self._lower - self.drift * t:
            self.inconsistent += 1

    def host_ns(self, device_ms: int, at_ns: int) -> int:
        """Host time of an unwrapped device time, with the estimate as of ``at_ns``."""
        offset = self._offset_rel(at_ns)
        if offset is None or self._t_ref is None:
            raise ValueError("no clock sample yet")
        return self._t_ref + round(offset + device_ms * 1e6)


def _is_serial_line(url: str) -> bool:
    """Whether bytes from ``url`` move at ``baudrate``. Not on a USB CDC-ACM port (``/dev/ttyACM*``, or a
    udev link such as ``/dev/urg`` to one: the URG's USB models move data at USB speed), a pseudo-terminal
    (a fake, which ignores the rate) or pyserial's ``loop://`` and ``socket://``; anything else is taken
    for a serial line."""
    scheme, sep, _ = url.partition("://")
    if sep:
        return scheme not in ("loop", "socket")
    real = os.path.realpath(url)
    return not (os.path.basename(real).startswith("ttyACM") or real.startswith("/dev/pts/"))


def _centred(delta_ms: int) -> int:
    """``delta_ms`` modulo 2^24, in [-2^23, 2^23)."""
    half = scip.TIMESTAMP_MODULUS // 2
    return (delta_ms + half) % scip.TIMESTAMP_MODULUS - half


# -- the driver --------------------------------------------------------------------------------------------


class UrgLaser(LaserScanner):
    """A Hokuyo URG over SCIP 2.0, streaming ``Scan`` s with MD.

    ``first_step``/``last_step``/``cluster`` select the beams (default: all 682 of a URG-04LX).
    ``timeout_s`` bounds each command; ``reconnect_interval_s`` paces reopening a lost port, and retrying a
    stream restart that failed; ``stall_timeout_s`` without a scan while streaming runs the connect
    sequence again and restarts MD.

    Link rate. On a serial line (``serial_line``; by default any port but a USB CDC-ACM one, where
    ``baudrate`` means nothing, or a pseudo-terminal) one scan takes ``scan_bytes * 10 / baudrate``
    seconds to arrive: 1.1 s for a full URG-04LX scan at 19200 bit/s, against the 0.1 s the sensor takes
    to measure it. The stall watchdog therefore waits at least :attr:`stall_limit_s`, twice the time
    between two scans on this link (the scan period plus one scan's transfer), and a command reply, which
    can queue behind a scan on its way, gets one scan's transfer time on top of ``timeout_s``. A rate that
    cannot carry a scan per period is logged as a warning naming ``laser.baudrate`` when the driver is
    built from the config, not refused: such a link still delivers scans, only fewer of them (an RS-232
    URG at its factory 19200 bit/s is a real set-up), and it may be what the robot can live with.

    After a silent spell the stream is taken back as soon as the sensor's scans come again: a restart
    whose QT went unanswered keeps the old stream's scans welcome, and is retried one scan interval after
    the sensor sends anything without a scan of ours coming (or every ``reconnect_interval_s``), not a
    whole stall limit later.

    Health counters, besides those of :class:`LaserScanner`: ``bad_frames``, ``discarded_bytes`` (decoder
    resyncs), ``disconnects``, ``reconnects``, ``command_timeouts``, ``unexpected_replies``,
    ``stale_scans`` (scans of a stream we did not start), ``stream_restarts``, ``clock_resets``,
    ``clock_inconsistent``, ``scans_missed`` (scans the sensor measured while we streamed that never reached
    the queue: corrupted, skipped for lack of line rate, lost in a silent spell or a restart; told by the
    gap between the timestamps of consecutive streamed scans, or between their host times across a sensor
    clock restart).
    """

    def __init__(
        self,
        url: str,
        baudrate: int = 115200,
        first_step: int = 44,
        last_step: int = 725,
        cluster: int = 1,
        name: str = "laser",
        *,
        queue_size: int = 4,
        timeout_s: float = 1.0,
        reconnect_interval_s: float = 0.5,
        stall_timeout_s: float = 1.0,
        time_sync_samples: int = 5,
        read_poll_s: float = 0.02,
        serial_line: bool | None = None,
    ) -> None:
        super().__init__(name, queue_size)
        if not 0 <= first_step <= last_step <= 9999:
            raise ConfigError(
                "laser.first_step", f"need 0 <= first_step <= last_step, got {first_step}, {last_step}"
            )
        if not 1 <= cluster <= 99:
            raise ConfigError("laser.cluster", f"cluster is 1..99, got {cluster}")
        if timeout_s <= 0 or reconnect_interval_s <= 0 or stall_timeout_s <= 0:
            raise ConfigError("laser", "timeouts and intervals must be positive")
        if baudrate <= 0:
            raise ConfigError("laser.baudrate", f"must be positive, got {baudrate}")
        self.url = url
        self.baudrate = baudrate
        self.first_step = first_step
        self.last_step = last_step
        self.cluster = cluster
        self.timeout_s = timeout_s
        self.reconnect_interval_s = reconnect_interval_s
        self.stall_timeout_s = stall_timeout_s
        self.time_sync_samples = time_sync_samples
        self.read_poll_s = read_poll_s
        self.clock = DeviceClock()
        # Slack for the TM continuity check: the estimate ages by 200 ppm while the sensor is away.
        self.clock_tolerance_ms = 50.0
        self._port: Any = None  # serial.SerialBase; untyped library
        self._decoder = scip.ScipDecoder()
        self._seen_bad = 0
        self._seen_discarded = 0
        self._stash: list[tuple[scip.ScipReply, int]] = []
        self._jobs: queue.Queue[tuple[Callable[[], Any], Future[Any]]] = queue.Queue()
        self._thread: threading.Thread | None = None
        self._closing = threading.Event()
        self._info: LaserInfo | None = None
        self._tags = itertools.count(1)
        self._want_stream = False
        self._stream_key: tuple[str, str] | None = None  # (echo body up to the scan count, tag) of our MD
        self._last_stream_tag = ""
        self._last_scan_mono = 0.0
        self._sequence = 0
        # (unwrapped device ms, host ns, clock epoch) of the latest streamed scan, for scans_missed.
        self._last_streamed: tuple[int, int, int] | None = None
        self._restart_retry_at: float | None = None  # a failed stream restart is retried from then
        self._link_warned = False
        if serial_line is None:
            serial_line = _is_serial_line(url)
        self.link_bytes_per_s: float | None = baudrate / BITS_PER_BYTE if serial_line else None
        md_echo = scip.encode_md(first_step, last_step, cluster, 0, 0, "0" * _TAG_CHARS).rstrip(b"\n")
        self.scan_bytes = scip.scan_reply_size(
            len(md_echo), scip.expected_value_count(first_step, last_step, cluster), 3
        )
        self._check_link_rate(NOMINAL_SCAN_PERIOD_S)

    # -- link rate -----------------------------------------------------------------------------------------
    def _scan_period_s(self) -> float:
        return self._info.scan_period_s if self._info is not None else NOMINAL_SCAN_PERIOD_S

    @property
    def scan_transfer_s(self) -> float:
        """Time one streamed scan's bytes take on the line (0 on USB)."""
        return 0.0 if self.link_bytes_per_s is None else self.scan_bytes / self.link_bytes_per_s

    @property
    def stall_limit_s(self) -> float:
        """How long the watchdog waits for a scan: ``stall_timeout_s``, but never less than two scan
        intervals of the link, so that it cannot fire between two scans that are both on their way."""
        interval_s = self._scan_period_s() + self.scan_transfer_s
        return max(self.stall_timeout_s, STALL_SCAN_INTERVALS * interval_s)

    def _check_link_rate(self, period_s: float) -> None:
        if self._link_warned or self.scan_transfer_s <= period_s:
            return
        self._link_warned = True
        # The sensor sends the first scan finished after the line came free (the previous scan has left).
        every = math.ceil(self.scan_transfer_s / period_s)
        log.warning(
            "laser.baudrate = %d cannot carry the configured scan: %d bytes take %.2f s at %d bit/s, the "
            "sensor measures one every %.2f s: about 1 scan in %d gets through (%.2f scans/s). Raise "
            "laser.baudrate (and the sensor's rate), or send fewer values (laser.first_step/last_step, "
            "laser.cluster)",
            self.baudrate,
            self.scan_bytes,
            self.scan_transfer_s,
            self.baudrate,
            period_s,
            every,
            1.0 / (every * period_s),
        )

    # -- lifecycle -----------------------------------------------------------------------------------------
    def _open(self) -> None:
        self._closing.clear()
        self._last_streamed = None  # a new session: the time since the last one was not missed
        self._port = self._open_port()
        try:
            self._initialise()
        except DeviceTimeout as exc:
            self._drop_port()
            raise DeviceNotFound(f"no SCIP 2.0 answer at {self.url} ({exc})", self.name) from exc
        except BaseException:
            self._drop_port()
            raise
        self._set_link(True)
        self._thread = threading.Thread(target=self._run, name=f"urg {self.url}", daemon=True)
        self._thread.start()

    def _close(self) -> None:
        self._want_stream = False
        self._closing.set()
        self._wake_readers()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=self._reply_timeout_s() + 2.0)
        self._fail_jobs(DeviceDisconnected("laser is closed", self.name))
        if self._port is not None:
            # Leave the sensor quiet (stream stopped, laser off); best effort, the port may be gone.
            with contextlib.suppress(OSError):
                self._port.write(scip.encode_qt())
        self._drop_port()
        self._set_streaming(False)
        self._set_link(False)

    # -- public API ----------------------------------------------------------------------------------------
    def info(self) -> LaserInfo:
        if self._info is None:
            raise DeviceError("laser has not been opened", self.name)
        return self._info

    def scan_once(self, timeout_s: float = 1.0) -> Scan:
        """One scan with GD (while streaming: the next streamed scan, as a GD would disturb nothing)."""
        if self.streaming:
            return self.read(timeout_s)
        deadline = time.monotonic() + timeout_s
        return self._call(lambda: self._job_get_scan(deadline), timeout_s)

    def start(self) -> None:
        """Start MD streaming. If the link is down (``DeviceDisconnected``), streaming starts by itself when
        the sensor is back; if the sensor refuses (a status error), it stays off."""
        self._want_stream = True
        try:
            self._call(self._job_start_stream, self._reply_timeout_s())
        except UrgStatusError:
            self._want_stream = False
            raise

    def stop(self) -> None:
        self._want_stream = False
        self._set_streaming(False)
        self._call(self._job_stop_stream, self._reply_timeout_s())

    def _call(self, fn: Callable[[], T], timeout_s: float) -> T:
        """Run ``fn`` on the worker thread and wait for it, never longer than ``timeout_s`` (+ slack)."""
        if not self.is_open:
            raise DeviceError("laser is not open", self.name)
        if not self.connected:
            raise DeviceDisconnected(f"laser link is down: {self.health().last_error}", self.name)
        fut: Future[T] = Future()
        self._jobs.put((fn, fut))
        try:
            # The job enforces its own deadline; the slack covers a job that was queued behind another one.
            return fut.result(timeout=timeout_s + self._reply_timeout_s())
        except FutureTimeout as exc:
            fut.cancel()
            self.count("command_timeouts")
            raise DeviceTimeout(f"no answer within {timeout_s:.3f} s", self.name) from exc
        except CancelledError as exc:
            raise DeviceDisconnected("laser closed while waiting", self.name) from exc

    # -- worker thread -------------------------------------------------------------------------------------
    def _run(self) -> None:
        while not self._closing.is_set():
            if self._port is None:
                self._fail_jobs(
                    DeviceDisconnected(f"laser link is down: {self.health().last_error}", self.name)
                )
                if self._closing.wait(self.reconnect_interval_s):
                    break
                self._try_reconnect()
                continue
            try:
                try:
                    fn, fut = self._jobs.get_nowait()
                except queue.Empty:
                    got = self._pump()
                    self._check_stall(got)
                    continue
                if not fut.set_running_or_notify_cancel():
                    continue
                try:
                    fut.set_result(fn())
                except OSError as exc:
                    fut.set_exception(DeviceDisconnected(f"port failed: {exc}", self.name))
                    raise
                except BaseException as exc:
                    fut.set_exception(exc)
            except OSError as exc:  # serial.SerialException is an OSError
                self._lose_link(exc)
            except Exception:  # a bug must not kill the reader silently; the next loop tries again
                log.exception("URG worker error on %s", self.url)
                self.note_error("internal error in the URG worker (see log)")
                self._closing.wait(self.read_poll_s)
        self._fail_jobs(DeviceDisconnected("laser is closed", self.name))

    def _fail_jobs(self, exc: DeviceError) -> None:
        while True:
            try:
                _, fut = self._jobs.get_nowait()
            except queue.Empty:
                return
            if fut.set_running_or_notify_cancel():
                fut.set_exception(exc)

    def _open_port(self) -> Any:
        try:
            return serial.serial_for_url(
                self.url, baudrate=self.baudrate, timeout=self.read_poll_s, write_timeout=self.timeout_s
            )
        except (OSError, ValueError) as exc:  # SerialException is an OSError; ValueError: bad URL/settings
            raise DeviceNotFound(f"cannot open {self.url}: {exc}", self.name) from exc

    def _drop_port(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            with contextlib.suppress(OSError):
                port.close()
        self._decoder.reset()
        self._stash.clear()

    def _lose_link(self, exc: BaseException) -> None:
        log.warning("URG on %s lost: %s", self.url, exc)
        # Count before the link shows down, so that whoever sees it down also sees why.
        self.count("disconnects")
        self._set_link(False, f"disconnected: {exc}")
        self._stream_key = None
        self._drop_port()

    def _try_reconnect(self) -> None:
        try:
            self._port = self._open_port()
        except DeviceNotFound:
            return
        try:
            self._initialise()
        except (DeviceError, ConfigError, OSError) as exc:
            log.info("URG on %s reopened but not ready: %s", self.url, exc)
            self.note_error(f"reconnect failed: {exc}")
            self._drop_port()
            return
        self.count("reconnects")
        log.info("URG on %s is back", self.url)
        self._set_link(True)
        if self._want_stream:
            try:
                self._job_start_stream()
            except DeviceError as exc:
                # The stall watchdog retries; the link itself is fine.
                self.note_error(f"restarting the stream failed: {exc}")

    # -- I/O on the worker thread --------------------------------------------------------------------------
    def _pump(self) -> bool:
        """Read what the port has (waiting at most ``read_poll_s``), dispatch scans, stash other replies.
        Returns whether anything came."""
        port = self._port
        if port is None:
            raise DeviceDisconnected("port is closed", self.name)
        data = port.read(max(1, port.in_waiting))
        if not data:
            return False
        rx_ns = time.monotonic_ns()
        replies = self._decoder.feed(data)
        # Counted before the scans that came with them are published: whoever reads a scan also sees the
        # bad frames that arrived before it.
        bad = self._decoder.bad_frames - self._seen_bad
        if bad:
            dropped = self._decoder.discarded_bytes - self._seen_discarded
            self._seen_bad, self._seen_discarded = self._decoder.bad_frames, self._decoder.discarded_bytes
            self.count("bad_frames", bad)
            self.count("discarded_bytes", dropped)
            for err in self._decoder.take_errors():
                log.debug("URG on %s: %s", self.url, err)
                self.note_error(str(err)[:200])
        for reply in replies:
            if reply.command in ("MD", "MS") and reply.status == "99":
                self._on_stream_scan(reply, rx_ns)
            else:
                self._stash.append((reply, rx_ns))
        return True

    def _transact(self, command: bytes, deadline: float | None = None) -> tuple[scip.ScipReply, int]:
        """Send ``command`` and wait for the reply whose echo matches it (not an MD scan); returns the reply
        and its host receive time. Replies that match nothing are dropped and counted."""
        port = self._port
        if port is None:
            raise DeviceDisconnected("port is closed", self.name)
        echo = command.rstrip(b"\r\n").decode("ascii")
        deadline = time.monotonic() + self._reply_timeout_s() if deadline is None else deadline
        if self._stash:
            self.count("unexpected_replies", len(self._stash))
            self._stash.clear()
        try:
            port.write(command)
        except serial.SerialTimeoutException as exc:
            # The sensor did not take the command within the write timeout (its side of the line was not
            # read: a stalled device, or a busy machine): a timeout like a missing reply, not the end of
            # the loop that opened it (the laser loop died of this once, on a starved machine).
            why = f"{echo}: the command was not taken within {self.timeout_s} s"
            raise DeviceTimeout(why, self.name) from exc
        while True:
            for i, (reply, rx_ns) in enumerate(self._stash):
                if reply.echo == echo:
                    if i:
                        self.count("unexpected_replies", i)
                    del self._stash[: i + 1]
                    return reply, rx_ns
            if self._stash:
                self.count("unexpected_replies", len(self._stash))
                self._stash.clear()
            if self._closing.is_set():
                raise DeviceDisconnected("laser is closing", self.name)
            if time.monotonic() >= deadline:
                self.count("command_timeouts")
                raise DeviceTimeout(f"no reply to {echo!r}", self.name)
            self._pump()

    def _reply_timeout_s(self) -> float:
        # A reply can queue behind a streamed scan that is on its way (1.1 s at 19200 bit/s).
        return self.timeout_s + self.scan_transfer_s

    def _tag(self) -> str:
        # A fresh tag per command, so that a late reply to an abandoned command is never taken for the
        # reply to the next one (the sensor echoes it; spec p.9).
        return f"{next(self._tags) & 0xFFFFFF:06x}"

    # -- connect sequence ----------------------------------------------------------------------------------
    def _initialise(self) -> None:
        port = self._port
        assert port is not None
        with contextlib.suppress(OSError, AttributeError):  # loop:// and some URLs have no input buffer
            port.reset_input_buffer()
        self._decoder.reset()
        self._stash.clear()
        # Our stream's key is kept until QT is answered: scans it sends before that are good ones, and if QT
        # goes unanswered (a silent sensor) the stream may well come back by itself.
        reply, _ = self._transact(scip.encode_qt())
        self._stream_key = None
        if reply.status == "0E":
            # Only time-adjust mode refuses QT (urg_c reads 0E to QT the same way).
            self._transact(scip.encode_tm(2))
        reply, _ = self._transact(scip.encode_scip2())
        raise_for_status(reply, self.name, accept=("0", "00", "0E"))
        vv, _ = self._transact(scip.encode_vv(self._tag()))
        raise_for_status(vv, self.name)
        pp, _ = self._transact(scip.encode_pp(self._tag()))
        raise_for_status(pp, self.name)
        ii, _ = self._transact(scip.encode_ii(self._tag()))
        if ii.status != "00":
            log.info("URG on %s: II refused (%s); going on without it", self.url, ii.status)
        info = self._make_info(vv.params, pp.params)
        if not info.first_step <= self.first_step <= self.last_step <= info.last_step:
            raise ConfigError(
                "laser.first_step",
                f"steps {self.first_step}..{self.last_step} outside the sensor's "
                f"{info.first_step}..{info.last_step}",
            )
        self._info = info
        self._check_link_rate(info.scan_period_s)  # the sensor's own period, if the nominal one was fine
        self._sync_clock()
        reply, _ = self._transact(scip.encode_bm(self._tag()))
        raise_for_status(reply, self.name, accept=("00", "02"))
        log.info("URG %s (%s, firmware %s) ready on %s", info.model, info.serial, info.firmware, self.url)

    def _make_info(self, vv: Mapping[str, str], pp: Mapping[str, str]) -> LaserInfo:
        numbers: dict[str, int] = {}
        for key in ("DMIN", "DMAX", "ARES", "AMIN", "AMAX", "AFRT", "SCAN"):
            try:
                numbers[key] = int(pp[key])
            except (KeyError, ValueError) as exc:
                raise DeviceError(f"PP reply lacks a numeric {key}: {dict(pp)}", self.name) from exc
        if (
            numbers["ARES"] <= 0
            or numbers["SCAN"] <= 0
            or not numbers["AMIN"] <= numbers["AFRT"] <= numbers["AMAX"]
        ):
            raise DeviceError(f"PP reply is inconsistent: {numbers}", self.name)
        return LaserInfo(
            model=pp.get("MODL", ""),
            serial=vv.get("SERI", ""),
            firmware=vv.get("FIRM", ""),
            protocol=vv.get("PROT", ""),
            min_range_mm=numbers["DMIN"],
            max_range_mm=numbers["DMAX"],
            steps_per_rev=numbers["ARES"],
            first_step=numbers["AMIN"],
            last_step=numbers["AMAX"],
            front_step=numbers["AFRT"],
            scan_rpm=numbers["SCAN"],
            vendor=vv.get("VEND", ""),
            product=vv.get("PROD", ""),
        )

    def _sync_clock(self) -> None:
        """TM round trips give the clock offset before the first scan (bounds on both sides)."""
        reply, _ = self._transact(scip.encode_tm(0, self._tag()))
        if reply.status not in ("00", "02"):
            log.info(
                "URG on %s: no time-adjust mode (%s); the clock is aligned from scans only",
                self.url,
                reply.status,
            )
            return
        resets = self.clock.resets
        try:
            for _ in range(self.time_sync_samples):
                sent_ns = time.monotonic_ns()
                reply, rx_ns = self._transact(scip.encode_tm(1, self._tag()))
                if reply.timestamp_ms is None:
                    log.info("URG on %s: TM1 refused (%s)", self.url, reply.status)
                    break
                mid_ns = (sent_ns + rx_ns) // 2
                # The reading is at most half a round trip from mid_ns: a value far from the prediction means
                # the sensor's clock restarted (after a power loss, even a short one looks like stale data).
                tolerance_ms = (rx_ns - sent_ns) / 2e6 + self.clock_tolerance_ms
                device_ms = self.clock.unwrap(reply.timestamp_ms, mid_ns, tolerance_ms=tolerance_ms)
                self.clock.observe_round_trip(device_ms, sent_ns, rx_ns)
        finally:
            self._transact(scip.encode_tm(2, self._tag()))
        if self.clock.resets != resets:
            self.count("clock_resets", self.clock.resets - resets)

    # -- scans ---------------------------------------------------------------------------------------------
    def _min_delay_ns(self, last_step: int) -> float:
        info = self.info()
        return (last_step + 1) / info.steps_per_rev * info.scan_period_s * 1e9

    def _make_scan(self, reply: scip.ScipReply, rx_ns: int) -> Scan:
        info = self.info()
        assert reply.timestamp_ms is not None and reply.first_step is not None and reply.last_step is not None
        delay_ns = self._min_delay_ns(reply.last_step)
        resets, inconsistent = self.clock.resets, self.clock.inconsistent
        device_ms = self.clock.unwrap(reply.timestamp_ms, rx_ns, delay_ns)
        self.clock.observe_scan(device_ms, rx_ns, delay_ns)
        if self.clock.resets != resets:
            self.count("clock_resets", self.clock.resets - resets)
        if self.clock.inconsistent != inconsistent:
            self.count("clock_inconsistent", self.clock.inconsistent - inconsistent)
        cluster = max(reply.cluster or 1, 1)
        ranges = np.fromiter(reply.values, dtype=np.int32, count=len(reply.values))
        self._sequence += 1
        # Angle of each value: the centre of its cluster of steps.
        return Scan(
            ranges_mm=ranges,
            angle_min_rad=info.angle_rad(reply.first_step + (cluster - 1) / 2.0),
            angle_increment_rad=cluster * info.step_angle_rad,
            min_range_mm=info.min_range_mm,
            max_range_mm=info.max_range_mm,
            sequence=self._sequence,
            host_time_ns=self.clock.host_ns(device_ms, rx_ns),
            device_time_ms=device_ms,
        )

    def _on_stream_scan(self, reply: scip.ScipReply, rx_ns: int) -> None:
        key = (reply.body[:13], reply.tag)
        if key != self._stream_key:
            if reply.tag != self._last_stream_tag:
                self.count("stale_scans")
            return
        self._last_scan_mono = time.monotonic()
        # Our stream is alive: a restart that failed while the sensor was silent is no longer needed.
        self._restart_retry_at = None
        scan = self._make_scan(reply, rx_ns)
        self._count_missed(scan)
        self._publish(scan)

    def _count_missed(self, scan: Scan) -> None:
        """Count the scans the sensor measured between the previous streamed scan and ``scan``."""
        assert scan.device_time_ms is not None
        epoch = self.clock.resets
        last, self._last_streamed = self._last_streamed, (scan.device_time_ms, scan.host_time_ns, epoch)
        if last is None:
            return
        period_ms = self._scan_period_s() * 1e3
        last_ms, last_host_ns, last_epoch = last
        if epoch == last_epoch:
            gap_ms = float(scan.device_time_ms - last_ms)  # both on the sensor's clock: exact
        else:
            # The sensor's clock restarted in between: only the host times (both estimates) compare.
            gap_ms = (scan.host_time_ns - last_host_ns) / 1e6
        missed = round(gap_ms / period_ms) - 1
        if missed > 0:
            self.count("scans_missed", missed)

    def _job_get_scan(self, deadline: float) -> Scan:
        for attempt in range(2):
            reply, rx_ns = self._transact(
                scip.encode_gd(self.first_step, self.last_step, self.cluster, self._tag()), deadline
            )
            if reply.status == "10" and attempt == 0:
                # The laser went off (QT from stop(), or a finished MD): switch it on and ask again.
                on, _ = self._transact(scip.encode_bm(self._tag()), deadline)
                raise_for_status(on, self.name, accept=("00", "02"))
                continue
            raise_for_status(reply, self.name)
            return self._make_scan(reply, rx_ns)
        raise AssertionError("unreachable")

    def _job_start_stream(self) -> None:
        tag = self._tag()
        command = scip.encode_md(self.first_step, self.last_step, self.cluster, 0, 0, tag)
        self._stream_key = (command.decode("ascii")[:13], tag)
        self._last_stream_tag = tag
        try:
            reply, _ = self._transact(command)
            raise_for_status(reply, self.name)
        except BaseException:
            self._stream_key = None
            raise
        self._last_scan_mono = time.monotonic()
        self._restart_retry_at = None
        self._set_streaming(True)

    def _job_stop_stream(self) -> None:
        self._stream_key = None
        self._last_streamed = None  # the gap until the next start() is wanted, not missed
        self._set_streaming(False)
        reply, _ = self._transact(scip.encode_qt())
        raise_for_status(reply, self.name)

    def _check_stall(self, got_bytes: bool) -> None:
        """Restart a stream that stopped delivering (the sensor dropped it or went quiet). ``got_bytes``:
        the last read brought something, so a sensor that did not answer the last restart is back."""
        if not self._want_stream or not self.streaming:
            return
        now = time.monotonic()
        retry_at = self._restart_retry_at
        if retry_at is not None:
            # The last restart went unanswered: try again at the reconnect pace rather than a whole stall
            # limit later, and soon after the sensor talks again; not at once, though: what it sends may be
            # the first bytes of a scan of our stream, which would make the restart needless.
            if got_bytes:
                scan_interval_s = self._scan_period_s() + self.scan_transfer_s
                retry_at = min(retry_at, now + scan_interval_s + self.read_poll_s)
                self._restart_retry_at = retry_at
            if now < retry_at:
                return
        elif now - self._last_scan_mono < self.stall_limit_s:
            return
        self.count("stream_restarts")
        if retry_at is None:
            self.note_error(f"no scan for {self.stall_limit_s:.1f} s: restarting the stream")
        self._restart_retry_at = None
        self._last_scan_mono = now
        try:
            # The whole connect sequence, not just MD: a sensor that rebooted (brown-out) is back in its boot
            # mode with its clock restarted, which only the TM check notices.
            self._initialise()
            self._job_start_stream()
        except (DeviceError, ConfigError) as exc:
            log.info("URG on %s: stream restart failed: %s", self.url, exc)
            if self._stream_key is not None and self._last_scan_mono > now:
                return  # QT went unanswered, but our old stream came back meanwhile and delivers
            self._restart_retry_at = time.monotonic() + self.reconnect_interval_s
