"""The pose stream: fused poses out on a serial line, as pose frames or MAVLink.

One :class:`PoseOutput` owns the port. The port is opened with ``serial.serial_for_url`` (a device path, a
pty, ``loop://``, ``spy://``), and a lone 0x00 goes out first so that a receiver drops whatever partial
frame it held (``docs/wire-format.md``). Each pose is one :class:`~firmware_protocol.pose_frame.PoseFrame`
encoded by ``firmware_protocol`` (COBS frame) or ``firmware_protocol.mavlink_out`` (VISION_POSITION_ESTIMATE
or ODOMETRY) and written whole.

Writes never block the hot path for long: the port has a write timeout (a receiver that stopped reading a
pty, a stuck USB adapter), a frame cut by it is counted (the receiver rejects the stub by its CRC and
resyncs at the next 0x00), and the sequence number moves on so the receiver sees the loss. A port that
fails is closed and reopened on a later write, no oftener than every ``reopen_interval_s``.

Latency is measured per frame from the *capture time* of the measurement that triggered it (a camera
frame's host time) to the moment the last byte was handed to the operating system.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import os
import queue
import select
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import serial

from agent.config import OutputConfig, OutputFormat
from agent.fusion import Estimate
from agent.runstats import StreamStats
from drivers.errors import DeviceNotFound
from firmware_protocol.pose_frame import PoseFlags, PoseFrame, encode_pose

__all__ = ["LatencyStats", "PoseOutput", "Written", "quality_for"]

log = logging.getLogger(__name__)

_SOURCE_BITS = PoseFlags.VLP | PoseFlags.SLAM | PoseFlags.ODOMETRY | PoseFlags.IMU


@dataclass(frozen=True, slots=True)
class Written:
    """One frame written: what it said, when its last byte was written, and what triggered it."""

    frame: PoseFrame
    done_ns: int
    trigger_ns: int | None
    nbytes: int
    arrival_ns: int | None = None


class LatencyStats:
    """Latencies in milliseconds: percentiles over the whole run in constant memory (``StreamStats``: log
    bins, within 0.5 %), and over the last ``window`` values exactly. Thread-safe."""

    def __init__(self, window: int = 2000) -> None:
        self._recent: collections.deque[float] = collections.deque(maxlen=window)
        self._all = StreamStats(low=1e-3, high=1e5)
        self._lock = threading.Lock()

    def add(self, ms: float) -> None:
        with self._lock:
            self._recent.append(ms)
            self._all.add(ms)

    def __len__(self) -> int:
        """How many values were added (all of them, not only the window's)."""
        with self._lock:
            return self._all.count

    def percentiles(self, *qs: float, last: int | None = None) -> list[float]:
        """Over the whole run, or (``last``) over the last ``last`` values, at most the window."""
        with self._lock:
            if not last:
                return self._all.percentiles(*qs)
            values = list(self._recent)[-last:]
        if not values:
            return [math.nan for _ in qs]
        return [float(v) for v in np.percentile(np.asarray(values), qs)]


def quality_for(flags: PoseFlags) -> int:
    """MAVLink ODOMETRY quality (0 unknown, 1..100, -1 failed) from which sources are live."""
    if not flags & _SOURCE_BITS:
        return -1
    if flags & PoseFlags.VLP:
        return 100
    if flags & PoseFlags.SLAM:
        return 70
    return 30


class PoseOutput:
    """Encodes and writes poses; thread-safe (the hot path and the fill-in from the odometry loop)."""

    def __init__(
        self,
        config: OutputConfig,
        url: str,
        *,
        observer: Callable[[Written], None] | None = None,
        reopen_interval_s: float = 0.5,
        clock_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self.config = config
        self.url = url
        self.observer = observer
        self.reopen_interval_s = reopen_interval_s
        self.clock_ns = clock_ns
        self._lock = threading.Lock()
        self._port: Any = None
        self._fd: int | None = None
        self._next_open_s = 0.0
        self._sequence = 0
        self._encode: Callable[[PoseFrame, PoseFlags], bytes] = self._make_encoder()
        # The latency budget's measure: the triggering frame captured by this computer (handed over
        # complete by its driver) -> last byte written.
        self.latency = LatencyStats()
        # The triggering measurement's own time (a frame: the middle of its exposure) -> last byte written:
        # the latency plus the camera's readout and transfer, which no agent can shorten.
        self.exposure_age = LatencyStats()
        self.age = LatencyStats()  # the pose's own time (its newest measurement) -> last byte written
        self.counts: collections.Counter[str] = collections.Counter()
        self.last_publish_ns = 0
        self._cut = False  # the last frame went out incomplete: end it with a 0x00 before the next

    def _make_encoder(self) -> Callable[[PoseFrame, PoseFlags], bytes]:
        if self.config.format is OutputFormat.FRAME:
            return lambda frame, flags: encode_pose(frame)
        from firmware_protocol.mavlink_out import MavlinkPoseEncoder

        encoder = MavlinkPoseEncoder(
            self.config.mavlink_message, self.config.mavlink_sysid, self.config.mavlink_compid
        )
        return lambda frame, flags: encoder.encode(frame, quality_for(flags))

    # -- lifecycle -------------------------------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        return self._port is not None

    def open(self) -> None:
        """Open the port now (raises DeviceNotFound if it cannot be); later failures reopen by themselves."""
        with self._lock:
            self._open_locked()

    def _open_locked(self) -> None:
        try:
            port = serial.serial_for_url(
                self.url, baudrate=self.config.baud, timeout=0, write_timeout=self.config.write_timeout_s
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            self._next_open_s = time.monotonic() + self.reopen_interval_s
            raise DeviceNotFound(f"cannot open the pose output {self.url}: {exc}", "output") from exc
        self._port = port
        # A device or pty: write its (non-blocking) descriptor directly. pyserial's write loops forever on
        # EAGAIN without a write timeout, and with one it raises after the timeout even when every byte went
        # out, so neither tells how much of a frame left. URL handlers (loop://, spy://) go through pyserial.
        self._fd = port.fileno() if type(port) is serial.Serial else None
        try:
            # A lone 0x00 ends any partial frame the receiver holds: it starts clean with our first frame.
            # If it cannot go out now, the first frame takes it along.
            self._cut = self._write_all(b"\x00") == 0
        except (serial.SerialException, OSError) as exc:
            self._drop_locked(f"first write failed: {exc}")
            raise DeviceNotFound(f"cannot write to the pose output {self.url}: {exc}", "output") from exc
        self.counts["opens"] += 1
        log.info("pose output on %s (%s, %d baud)", self.url, self.config.format.value, self.config.baud)

    def _drop_locked(self, reason: str) -> None:
        port, self._port, self._fd = self._port, None, None
        self._next_open_s = time.monotonic() + self.reopen_interval_s
        if port is not None:
            with contextlib.suppress(serial.SerialException, OSError):
                port.close()
        self.counts["errors"] += 1
        log.warning("pose output %s: %s; reopening", self.url, reason)

    def close(self) -> None:
        with self._lock:
            port, self._port, self._fd = self._port, None, None
        if port is not None:
            with contextlib.suppress(serial.SerialException, OSError):
                port.close()

    # -- writing ---------------------------------------------------------------------------------------
    def _write_all(self, data: bytes) -> int:
        """Write ``data`` within the write timeout; the number of bytes that went out."""
        fd = self._fd
        if fd is None:
            try:
                self._port.write(data)
            except (serial.SerialTimeoutException, queue.Full):  # loop:// says "no room" with queue.Full
                return 0
            return len(data)
        sent = 0
        deadline = time.monotonic() + self.config.write_timeout_s
        view = memoryview(data)
        while True:
            with contextlib.suppress(BlockingIOError, InterruptedError):
                sent += os.write(fd, view[sent:])
            remaining = deadline - time.monotonic()
            if sent >= len(data) or remaining <= 0:
                return sent
            select.select([], [fd], [], remaining)

    def read_available(self) -> bytes:
        """The bytes the controller has sent since the last call (commands); b"" when none or port down.

        Reads do not take the write lock: the port is opened non-blocking (``timeout=0``), and reading and
        writing one descriptor from two threads is safe."""
        port = self._port
        if port is None:
            return b""
        try:
            waiting = port.in_waiting
            return bytes(port.read(waiting)) if waiting else b""
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            # TypeError / AttributeError: the port was closed under us by a failing write.
            log.debug("pose output %s: read failed: %s", self.url, exc)
            return b""

    def _write_message_locked(self, data: bytes) -> tuple[int, int] | None:
        """Write one whole message, after the 0x00 that ends a frame cut before it: (bytes sent, bytes
        meant); a message cut short is ended by the next one's 0x00 (the receiver rejects the stub by its
        CRC). None when the port failed (it is dropped, and reopened later)."""
        if self._cut:
            data = b"\x00" + data
        try:
            sent = self._write_all(data)
        except (serial.SerialException, OSError) as exc:
            self._drop_locked(f"write failed: {exc}")
            return None
        self.counts["bytes"] += sent
        self._cut = 0 < sent < len(data)
        return sent, len(data)

    def send(self, data: bytes) -> bool:
        """Write one whole message other than a pose (a goal status) between pose frames; False if it did
        not go out complete (counted in ``message_write_failures``)."""
        with self._lock:
            written = self._write_message_locked(data) if self._port is not None else None
            if written is None or written[0] < written[1]:
                self.counts["message_write_failures"] += 1
                return False
            self.counts["messages"] += 1
            return True

    def publish(
        self,
        estimate: Estimate,
        flags: PoseFlags,
        trigger_ns: int | None = None,
        arrival_ns: int | None = None,
    ) -> Written | None:
        """Write ``estimate`` with ``flags``; None when the port is down or the write was cut (counted).

        ``trigger_ns``: the time of the measurement this pose answers (a camera frame's exposure);
        ``arrival_ns``: when its driver handed it over complete. Latencies are measured from both."""
        with self._lock:
            if self._port is None:
                if time.monotonic() < self._next_open_s:
                    self.counts["skipped_port_down"] += 1
                    return None
                try:
                    self._open_locked()
                except DeviceNotFound as exc:
                    self.counts["skipped_port_down"] += 1
                    log.debug("%s", exc)
                    return None
                self.counts["reopens"] += 1
            frame = PoseFrame(
                sequence=self._sequence,
                t_us=max(estimate.t_ns, 0) // 1000,
                x_m=estimate.x_m,
                y_m=estimate.y_m,
                yaw_rad=estimate.yaw_rad,
                sigma_xy_m=estimate.sigma_xy_m,
                sigma_yaw_rad=estimate.sigma_yaw_rad,
                flags=flags,
                reset_counter=estimate.reset_counter,
            )
            self._sequence = (self._sequence + 1) & 0xFFFF_FFFF
            result = self._write_message_locked(self._encode(frame, flags))
            if result is None:
                return None
            done_ns = self.clock_ns()
            sent, nbytes = result
            if sent < nbytes:
                self.counts["write_timeouts"] += 1
                return None
            self.last_publish_ns = done_ns
            self.counts["frames"] += 1
        written = Written(frame, done_ns, trigger_ns, nbytes, arrival_ns)
        if arrival_ns is not None:
            self.latency.add((done_ns - arrival_ns) * 1e-6)
        if trigger_ns is not None:
            self.exposure_age.add((done_ns - trigger_ns) * 1e-6)
        self.age.add((done_ns - estimate.t_ns) * 1e-6)
        if self.observer is not None:
            self.observer(written)
        return written
