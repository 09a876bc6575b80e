"""Python's cyclic garbage collector, run between frames on the hot path's thread.

CPython starts a collection in whichever thread's allocation crosses the threshold (700 new container
objects for the youngest generation), holding the interpreter lock throughout: on the agent that is the
VLP thread in the middle of a frame, or another thread while a frame waits for the lock. Measured on
``vlp-agent sim`` (30 s, after start-up): 15 collections of 0.6-2.5 ms, each on some frame's latency.

:class:`IdleCollector` turns the automatic collector off and runs the same collections at a moment that
costs no frame: the hot path calls :meth:`IdleCollector.collect_if_due` after it has written a frame's
pose (or after a wait for a frame timed out), and it collects the generations CPython would have, with
CPython's own thresholds (the youngest when it holds ``threshold0`` more objects than it did, the middle
one every ``threshold1`` young collections). A full collection walks every object that survived since the
freeze (tens of milliseconds: longer than the gap between two frames), so where CPython waits until the
objects promoted since the last one are a quarter of those it holds, which Python cannot read, it runs at
most once per ``full_interval_s`` (60 s) here, and a new frame then waits for it once.

The hot path comes by at the camera's frame rate, or every quarter second when no frame comes, so
garbage is still collected when the camera is gone; if it stops coming by (its loop died or hangs),
:meth:`IdleCollector.check`, called by the agent's monitor, hands the work back to the automatic
collector. :meth:`IdleCollector.start` first collects everything and freezes what survived
(``gc.freeze``: modules, config, caches, which later full passes then skip); :meth:`IdleCollector.stop`
hands the work back too.
"""

from __future__ import annotations

import gc
import logging
import threading
import time
from collections.abc import Callable

__all__ = ["IdleCollector"]

log = logging.getLogger(__name__)


class IdleCollector:
    """``collections``: how many collections of each generation it ran."""

    def __init__(
        self,
        full_interval_s: float = 60.0,
        max_absence_s: float = 2.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.full_interval_s = full_interval_s
        self.max_absence_s = max_absence_s
        self._clock = clock
        self._last_full = clock()
        self._last_call = clock()
        self._lock = threading.Lock()
        self._active = False
        self._was_enabled = True
        self.collections = [0, 0, 0]

    @property
    def active(self) -> bool:
        return self._active

    def start(self) -> None:
        """Collect and freeze what is alive now, then collect only in :meth:`collect_if_due`."""
        with self._lock:
            gc.collect()
            gc.freeze()
            if self._active:
                return
            self._was_enabled = gc.isenabled()
            gc.disable()
            self._active = True
            self._last_full = self._last_call = self._clock()

    def stop(self) -> None:
        """The automatic collector again (if it was on before :meth:`start`). Safe to call twice."""
        with self._lock:
            if not self._active:
                return
            self._active = False
            if self._was_enabled:
                gc.enable()

    def check(self) -> bool:
        """Hand the work back to the automatic collector when :meth:`collect_if_due` has not been called for
        ``max_absence_s`` (the hot path's loop died or hangs); True when it did so now."""
        if not self._active or self._clock() - self._last_call < self.max_absence_s:
            return False
        self.stop()
        log.warning(
            "the hot path has not run the garbage collector for %.1f s: handed back to the automatic one",
            self.max_absence_s,
        )
        return True

    def collect_if_due(self) -> int | None:
        """Run the collection CPython's thresholds call for now, if any; returns its generation."""
        if not self._active:
            return None
        self._last_call = self._clock()
        t0, t1, t2 = gc.get_threshold()
        young, middle, old = gc.get_count()
        if t0 <= 0 or young < t0:
            return None
        # gc.get_count(): objects allocated since the last young collection, young collections since the
        # last middle one, middle collections since the last full one; a collection of a generation resets
        # its own count and those of the younger ones, and adds one to the next older's.
        generation = 1 if middle + 1 >= t1 else 0
        now = self._clock()
        if generation == 1 and old + 1 >= t2 and now - self._last_full >= self.full_interval_s:
            generation = 2
            self._last_full = now
        with self._lock:
            if not self._active:
                return None
            gc.collect(generation)
        self.collections[generation] += 1
        return generation
