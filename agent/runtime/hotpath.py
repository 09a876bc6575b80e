"""The latency-critical path's right of way over background work in the same process.

The agent is one Python process: its threads share one interpreter lock, which CPython hands between
runnable threads every ``sys.getswitchinterval()`` with no notion of priority. While SLAM updates its
particles, or the IMU and servo loops run, a camera frame on the hot path (frame -> VLP fix -> fusion ->
pose bytes, a few milliseconds of work) would get the lock only in turns and take several times as long.
So background loops call :meth:`HotPath.give_way` where they can pause (before a device read, between
the stages of a SLAM update): while a frame waits in the camera mailbox or is being processed, they block
on an event, the lock released, until the frame's pose is written. A bound (``max_wait_s`` per call)
keeps a stuck hot path from stalling them for good; waits that hit it are counted.

The camera thread calls :meth:`frame_queued` before it hands a frame over; the hot path's thread wraps each
frame in :meth:`busy` and calls :meth:`settle` after a frame it did not process.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

__all__ = ["HotPath"]


class HotPath:
    """``pending``: whether a frame is waiting for the hot path (the camera mailbox holds one)."""

    def __init__(self, pending: Callable[[], bool], max_wait_s: float = 0.02) -> None:
        self._pending = pending
        self.max_wait_s = max_wait_s
        self._idle = threading.Event()
        self._idle.set()
        self._lock = threading.Lock()
        self._closed = False
        self.waits = 0  # give_way calls that waited
        self.waited_s = 0.0
        self.timeouts = 0  # waits cut at max_wait_s

    def frame_queued(self) -> None:
        """A frame is about to be handed to the hot path: background work should wait."""
        if not self._closed:
            self._idle.clear()

    def close(self) -> None:
        """The hot path is stopping: nobody waits for it any more (a frame left in the mailbox would
        otherwise hold every background loop at the bound until the process ends)."""
        self._closed = True
        self._idle.set()

    @contextmanager
    def busy(self) -> Iterator[None]:
        """Around one frame's processing on the hot path."""
        if not self._closed:
            self._idle.clear()
        try:
            yield
        finally:
            self.settle()

    def settle(self) -> None:
        """The hot path is done with its frame: idle again unless another one is already waiting."""
        if self._closed or not self._pending():
            self._idle.set()

    def active(self) -> bool:
        return not self._idle.is_set()

    def give_way(self) -> None:
        """Return at once when the hot path is idle; else wait (lock released) until it is, at most
        ``max_wait_s``."""
        if self._idle.is_set():
            return
        start = time.monotonic()
        if not self._idle.wait(self.max_wait_s):
            with self._lock:
                self.timeouts += 1
        with self._lock:
            self.waits += 1
            self.waited_s += time.monotonic() - start
