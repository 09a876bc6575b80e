"""The RFID reader interface: tag detections handed out of a bounded queue.

A reader backend runs its own thread and calls :meth:`RfidReader._publish` for every detection; consumers
call :meth:`RfidReader.read` (or iterate :meth:`RfidReader.reads`). The queue is bounded so that a stalled
consumer costs memory only up to ``queue_size`` reads: the oldest are dropped and counted (``dropped``),
never silently. Readers that repeat a frame while a tag stays in the field (the RDM6300 every ~220 ms, a
Mercury continuous read several times a second) can be debounced.
"""

from __future__ import annotations

import abc
import collections
import threading
import time
from collections.abc import Iterator

from drivers.device import Device
from drivers.errors import DeviceError
from drivers.samples import TagRead

__all__ = ["RfidReader"]


class RfidReader(Device, abc.ABC):
    """Base of every RFID backend.

    ``debounce_s``: a read of a tag seen less than ``debounce_s`` ago (reported or not) is dropped and
    counted as ``debounced``, so a tag held at the reader is reported once per presence. 0 reports every
    read, which is what person following wants (RSSI over time).
    """

    def __init__(self, name: str, queue_size: int = 256, debounce_s: float = 0.0) -> None:
        super().__init__(name)
        if queue_size < 1:
            raise ValueError("queue_size must be at least 1")
        if debounce_s < 0:
            raise ValueError("debounce_s must not be negative")
        self.queue_size = queue_size
        self.debounce_s = debounce_s
        self._queue: collections.deque[TagRead] = collections.deque()
        self._queue_cv = threading.Condition()
        self._last_seen_ns: dict[str, int] = {}

    # -- consumer side -----------------------------------------------------------------------------
    def read(self, timeout_s: float | None = None) -> TagRead | None:
        """The next detection, waiting up to ``timeout_s`` (None: until one comes); None on timeout.

        Device faults after ``open()`` (unplug, a silent reader) do not raise here: the backend reconnects
        by itself and reports them in :meth:`health`. Reading a closed reader raises :class:`DeviceError`.
        """
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._queue_cv:
            while True:
                if not self.is_open:
                    raise DeviceError("reader is closed", self.name)
                if self._queue:
                    return self._queue.popleft()
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None
                # Bounded waits so that close() from another thread is noticed even without a notify.
                self._queue_cv.wait(0.1 if remaining is None else min(remaining, 0.1))

    def reads(self, timeout_s: float | None = None) -> Iterator[TagRead]:
        """Detections as they come; ends after ``timeout_s`` without one, or when the reader is closed."""
        while True:
            try:
                tag = self.read(timeout_s)
            except DeviceError:
                if self.is_open:
                    raise
                return
            if tag is None:
                return
            yield tag

    def drain(self) -> list[TagRead]:
        """Everything queued right now, without waiting."""
        with self._queue_cv:
            tags = list(self._queue)
            self._queue.clear()
            return tags

    # -- backend side ------------------------------------------------------------------------------
    def _publish(self, tag: TagRead) -> None:
        if self.debounce_s > 0:
            last = self._last_seen_ns.get(tag.tag_id)
            self._last_seen_ns[tag.tag_id] = tag.host_time_ns
            if len(self._last_seen_ns) > 4096:
                self._forget_old(tag.host_time_ns)
            if last is not None and tag.host_time_ns - last < self.debounce_s * 1e9:
                self.count("debounced")
                return
        with self._queue_cv:
            if len(self._queue) >= self.queue_size:
                self._queue.popleft()
                self.count("dropped")
            self._queue.append(tag)
            self._queue_cv.notify_all()
        self.count("tag_reads")

    def _forget_old(self, now_ns: int) -> None:
        horizon = now_ns - int(self.debounce_s * 1e9)
        for tag_id in [t for t, seen in self._last_seen_ns.items() if seen < horizon]:
            del self._last_seen_ns[tag_id]

    def _shut_queue(self) -> None:
        """Forget queued reads and wake consumers blocked in :meth:`read` (backends call this from
        ``_close``): after close() a reader hands out nothing, so a consumer cannot mistake old reads
        for a live reader."""
        with self._queue_cv:
            self._queue.clear()
            self._last_seen_ns.clear()
            self._queue_cv.notify_all()
