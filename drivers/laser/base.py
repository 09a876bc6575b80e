"""The laser scanner interface: what the agent may ask of any scanning laser backend.

A backend runs its own reader thread and hands finished scans to :meth:`LaserScanner.read` through a small
bounded queue. When the consumer is slow the *oldest* scan is dropped (and counted): SLAM wants the latest
scan, and latency must not grow. While the device is unplugged ``read`` raises ``DeviceDisconnected``
at once, so a caller never waits on a device that is not there; the backend reconnects on its own.
"""

from __future__ import annotations

import abc
import collections
import math
import threading
import time
from dataclasses import dataclass

from drivers.device import Device
from drivers.errors import DeviceDisconnected, DeviceError, DeviceTimeout
from drivers.samples import Scan

__all__ = ["LaserInfo", "LaserScanner"]


@dataclass(frozen=True, slots=True)
class LaserInfo:
    """What the device says about itself (for a URG: VV and PP replies).

    Steps are the device's angular indices: ``steps_per_rev`` per turn, step ``front_step`` straight ahead,
    ``first_step..last_step`` measurable. Angles are counter-clockwise, radians, zero straight ahead.
    """

    model: str
    serial: str
    firmware: str
    protocol: str
    min_range_mm: int
    max_range_mm: int
    steps_per_rev: int
    first_step: int
    last_step: int
    front_step: int
    scan_rpm: int
    vendor: str = ""
    product: str = ""

    @property
    def step_angle_rad(self) -> float:
        return 2.0 * math.pi / self.steps_per_rev

    @property
    def scan_period_s(self) -> float:
        return 60.0 / self.scan_rpm

    def angle_rad(self, step: float) -> float:
        """Angle of ``step`` (fractional steps allowed, e.g. the centre of a cluster)."""
        return (step - self.front_step) * self.step_angle_rad


class LaserScanner(Device):
    """A scanning laser. Subclasses implement ``_open``, ``_close``, :meth:`info`, :meth:`scan_once`,
    :meth:`start` and :meth:`stop`, and feed :meth:`read` through :meth:`_publish` and :meth:`_set_link`.

    Health counters kept here: ``scans`` (published), ``scans_dropped`` (overwritten before being read or
    lost with the link), ``read_timeouts``.
    """

    def __init__(self, name: str, queue_size: int = 4) -> None:
        super().__init__(name)
        if queue_size < 1:
            raise ValueError("queue_size must be at least 1")
        self._queue: collections.deque[Scan] = collections.deque(maxlen=queue_size)
        self._cond = threading.Condition()
        self._link_up = False
        self._streaming = False

    # -- the interface -------------------------------------------------------------------------------------
    @abc.abstractmethod
    def info(self) -> LaserInfo:
        """Device facts, read when the device was opened."""

    @abc.abstractmethod
    def scan_once(self, timeout_s: float = 1.0) -> Scan:
        """One scan on demand (while streaming: the next streamed scan)."""

    @abc.abstractmethod
    def start(self) -> None:
        """Start streaming scans into :meth:`read` (kept up across reconnects until :meth:`stop`)."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Stop streaming."""

    @property
    def streaming(self) -> bool:
        with self._cond:
            return self._streaming

    @property
    def connected(self) -> bool:
        return self.is_open and self._link_up

    def read(self, timeout_s: float = 1.0) -> Scan:
        """The oldest queued scan, waiting up to ``timeout_s`` for one.

        Raises ``DeviceDisconnected`` while the device is gone or after ``close()``, ``DeviceTimeout`` when
        no scan comes in time, and ``DeviceError`` when not streaming and nothing is queued.
        """
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                if not self.is_open:
                    raise DeviceDisconnected("laser is closed", self.name)
                if not self._link_up:
                    raise DeviceDisconnected(f"laser link is down: {self._last_error}", self.name)
                if self._queue:
                    return self._queue.popleft()
                if not self._streaming:
                    raise DeviceError("laser is not streaming: call start() first", self.name)
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    self.count("read_timeouts")
                    raise DeviceTimeout(f"no scan within {timeout_s:.3f} s", self.name)
                self._cond.wait(remaining)

    # -- for backends --------------------------------------------------------------------------------------
    def _publish(self, scan: Scan) -> None:
        """Queue a finished scan, dropping the oldest one when the queue is full."""
        with self._cond:
            if len(self._queue) == self._queue.maxlen:
                self.count("scans_dropped")
            self._queue.append(scan)
            self.count("scans")
            self._cond.notify_all()

    def _set_streaming(self, on: bool) -> None:
        with self._cond:
            self._streaming = on
            self._cond.notify_all()

    def _set_link(self, up: bool, reason: str | None = None) -> None:
        """Record that the device came (back) or went. Scans still queued when it goes are dropped: they
        belong to a session that ended, and ``read`` reports the loss instead."""
        with self._cond:
            self._link_up = up
            if not up:
                if self._queue:
                    self.count("scans_dropped", len(self._queue))
                self._queue.clear()
                if reason:
                    self.note_error(reason)
            self._cond.notify_all()

    def _wake_readers(self) -> None:
        with self._cond:
            self._cond.notify_all()
