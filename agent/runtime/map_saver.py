"""The SLAM map saved as the robot goes: every ``slam.save_interval_s`` and on request (SIGUSR1 to
``vlp-agent run``), so that a power cut or ``kill -9`` loses at most one interval of mapping.

The SLAM thread owns the mapper, so it is the one that takes the map out of it (between two scans, the
same call that feeds the navigation its map) and hands it over with :meth:`MapSaver.submit`; the files are
written on this module's own thread (``agent-map-saver``), so neither the SLAM thread nor the hot path
waits on the disk. Writing is ``agent.slam.mapio.save_map``: the image under a new name, then one rename
of the YAML as the commit, the replaced pair kept as ``map.prev.yaml``. A newer map handed over while one
is being written replaces the one waiting (only the latest is worth writing). The picture for people
(``map.png``) is left to the save at the end: drawing it costs more than the map itself.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from drivers.errors import ConfigError

if TYPE_CHECKING:  # the SLAM package is imported only where it is used (the agent runs without it)
    from agent.slam.render import OccupancyImage

__all__ = ["MapSaver"]

log = logging.getLogger(__name__)


class MapSaver:
    """Writes the maps handed to it to ``directory/<name>.yaml`` on a thread of its own.

    ``interval_s``: how often :meth:`due` says a save is wanted (0: only on request). ``clock_s``: the
    clock :meth:`due` reads (monotonic seconds).
    """

    def __init__(
        self,
        directory: Path,
        interval_s: float,
        name: str = "map",
        comment: str = "vlp-agent slam",
        clock_s: Callable[[], float] = time.monotonic,
    ) -> None:
        if interval_s < 0.0:
            raise ValueError("interval_s must be >= 0")
        self.yaml_path = Path(directory) / f"{name}.yaml"
        self.interval_s = interval_s
        self.comment = comment
        self.clock_s = clock_s
        # Set by a signal handler: a plain attribute, no lock (a handler may run while a lock is held).
        self.requested = False
        self.saves = 0
        self.failures = 0
        self.dropped = 0  # maps replaced by a newer one before they were written
        self.last_save_ms = 0.0
        self.max_save_ms = 0.0  # wall time of one write, on this thread (mostly the fsyncs)
        self.max_save_cpu_ms = 0.0  # CPU time of one write: what it can take from the other threads
        self.max_fetch_ms = 0.0  # what taking the map out cost the SLAM thread (given to submit)
        self._last_handover_s = clock_s()
        self._pending: OccupancyImage | None = None
        self._closed = False
        self._wake = threading.Condition()
        self._busy = False
        self._thread = threading.Thread(target=self._run, name="agent-map-saver", daemon=True)
        self._thread.start()

    def last_saved(self) -> Path | None:
        """The map this saver has written (its YAML), None before its first save."""
        return self.yaml_path if self.saves > 0 else None

    def request(self) -> None:
        """Ask for a save at the SLAM thread's next turn. Safe from a signal handler."""
        self.requested = True

    def due(self) -> bool:
        """Whether the SLAM thread should hand over its map now (requested, or the interval is up)."""
        if self.requested:
            return True
        return self.interval_s > 0.0 and self.clock_s() - self._last_handover_s >= self.interval_s

    def submit(self, image: OccupancyImage, fetch_s: float = 0.0) -> None:
        """Queue ``image`` to be written (replacing one not written yet); returns at once. ``fetch_s``: what
        taking it out of the mapper cost the caller (for the counters)."""
        self.max_fetch_ms = max(self.max_fetch_ms, fetch_s * 1e3)
        self.requested = False
        self._last_handover_s = self.clock_s()
        with self._wake:
            if self._closed:
                return
            if self._pending is not None:
                self.dropped += 1
            self._pending = image
            self._wake.notify()

    def skip(self) -> None:
        """Nothing to save yet (no map): count the interval from now, drop the request."""
        self.requested = False
        self._last_handover_s = self.clock_s()

    def flush(self, timeout_s: float = 5.0) -> bool:
        """Wait until every map handed over has been written; False on timeout."""
        deadline = time.monotonic() + timeout_s
        with self._wake:
            while self._pending is not None or self._busy:
                left = deadline - time.monotonic()
                if left <= 0.0:
                    return False
                self._wake.wait(left)
        return True

    def close(self, timeout_s: float = 5.0) -> None:
        """Write what is waiting, then stop the thread (idempotent). The caller's final save comes after:
        one writer per map folder at a time."""
        with self._wake:
            if self._closed:
                return
            self._closed = True
            self._wake.notify_all()
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            log.warning("the map saver did not finish writing in %.1f s", timeout_s)

    def counters(self) -> dict[str, int]:
        return {
            "map_saves": self.saves,
            "map_save_failures": self.failures,
            "map_saves_replaced": self.dropped,
            "map_save_last_us": round(self.last_save_ms * 1e3),
            "map_save_max_us": round(self.max_save_ms * 1e3),
            "map_save_cpu_max_us": round(self.max_save_cpu_ms * 1e3),
            "map_fetch_max_us": round(self.max_fetch_ms * 1e3),
        }

    def _run(self) -> None:
        from agent.slam import mapio

        while True:
            with self._wake:
                while self._pending is None and not self._closed:
                    self._wake.wait()
                image = self._pending
                self._pending = None
                if image is None:  # closed, nothing left
                    self._wake.notify_all()
                    return
                self._busy = True
            t0 = time.perf_counter()
            cpu0 = time.thread_time()
            try:
                mapio.save_map(image, self.yaml_path, comment=self.comment)
                self.saves += 1
            except ConfigError as exc:
                # A full or read-only disk must not stop the robot: said, counted, tried again next time.
                self.failures += 1
                log.error("periodic map save failed: %s", exc)
            finally:
                elapsed_ms = (time.perf_counter() - t0) * 1e3
                self.max_save_cpu_ms = max(self.max_save_cpu_ms, (time.thread_time() - cpu0) * 1e3)
                self.last_save_ms = elapsed_ms
                self.max_save_ms = max(self.max_save_ms, elapsed_ms)
                with self._wake:
                    self._busy = False
                    self._wake.notify_all()
