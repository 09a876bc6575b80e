"""The latency-critical path's right of way over background work in the same process.

The agent is one Python process: its threads share one interpreter lock, which CPython hands between
runnable threads every ``sys.getswitchinterval()`` with no notion of priority. While SLAM updates its
particles (tens of milliseconds of Python and numpy at scan rate), a camera frame on the hot path
(frame -> VLP fix -> fusion -> pose bytes, ~2 ms of work) would get the lock only every other slice and
take twice as long. So background loops call :meth:`HotPath.give_way` at points where they can pause
(between particles): while a frame waits in the camera mailbox or is being processed, it sleeps in short
steps (the lock released) until the frame's pose is written. A bounded wait (``max_wait_s`` per call)
keeps a stuck hot path from stalling SLAM for good; waits that hit the bound are counted.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

__all__ = ["HotPath"]

_STEP_S = 0.0002


class HotPath:
    """``pending``: whether a frame is waiting for the hot path (the camera mailbox holds one)."""

    def __init__(self, pending: Callable[[], bool], max_wait_s: float = 0.02) -> None:
        self._pending = pending
        self.max_wait_s = max_wait_s
        self._busy = False
        self._lock = threading.Lock()
        self.waits = 0  # give_way calls that waited
        self.waited_s = 0.0
        self.timeouts = 0  # waits cut at max_wait_s

    @contextmanager
    def busy(self) -> Iterator[None]:
        """Around one frame's processing on the hot path."""
        self._busy = True
        try:
            yield
        finally:
            self._busy = False

    def active(self) -> bool:
        return self._busy or self._pending()

    def give_way(self) -> None:
        """Return at once when the hot path is idle; else wait (lock released) until it is, at most
        ``max_wait_s``."""
        if not (self._busy or self._pending()):
            return
        start = time.monotonic()
        deadline = start + self.max_wait_s
        while self._busy or self._pending():
            now = time.monotonic()
            if now >= deadline:
                with self._lock:
                    self.timeouts += 1
                break
            time.sleep(_STEP_S)
        with self._lock:
            self.waits += 1
            self.waited_s += time.monotonic() - start
