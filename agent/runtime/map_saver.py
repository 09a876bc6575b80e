"""The SLAM map saved as the robot goes: every ``slam.save_interval_s`` and on request (SIGUSR1 to
``vlp-agent run``), so that a power cut or ``kill -9`` loses at most one interval of mapping.

The SLAM thread owns the mapper, so it is the one that takes the map out of it (between two scans, one
fetch shared with the navigation's map and the flight recorder's ``/map``) and hands it over with
:meth:`MapSaver.submit`; the files are written on this module's own thread (``agent-map-saver``), so
neither the SLAM thread nor the hot path waits on the disk. Writing is ``agent.slam.mapio.save_map``: the
image under a new name, then one rename of the YAML as the commit, the replaced pair kept as
``map.prev.yaml``. A newer map handed over while one is being written replaces the one waiting (only the
latest is worth writing). The picture for people (``map.png``) is left to the save at the end: drawing it
costs more than the map itself.

**The bound.** A map's *content time* is when it was taken out of the mapper (every scan the SLAM loop had
handed the mapper by then is in it); it is written into the image's header comment as
``content_monotonic_ns <CLOCK_MONOTONIC ns>``. The mapping a kill loses is the kill time minus the content
time of the map on disk then. For that to stay within ``interval_s`` at every instant, the next save is
due ``lead`` *before* the last content time plus the interval, ``lead`` being 1.5 times the longest of the
last 32 saves' lags (from the instant a save was due to its commit: the SLAM thread's turn, the fetch,
the queue and the write with its fsyncs; at least 10 ms, at most half the interval). A save whose lag
exceeded the lead of its time is counted (``map_saves_late``): there the bound was not kept.

**The topological map.** With :attr:`MapSaver.topology` set (the mission loop's ``topology``: the
explorer's HTM or the map's rooms, with the named places), each map written is followed by its topological
map beside it, ``<name>.topology.geojson`` (``agent.slam.mapio.save_topology``: atomic, format in
docs/exploration.md), on this thread; a failure there is logged and counted (``topology_save_failures``),
the occupancy map stays written.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from drivers.errors import ConfigError

if TYPE_CHECKING:  # the SLAM package is imported only where it is used (the agent runs without it)
    from agent.slam.render import OccupancyImage

__all__ = ["CONTENT_STAMP_KEY", "MapSaver", "content_stamp_ns", "save_lead_s", "save_topology_beside"]

# The image header comment line that carries a saved map's content time.
CONTENT_STAMP_KEY = "content_monotonic_ns"
_LEAD_FACTOR = 1.5
_MIN_LEAD_S = 0.01
_LAG_HISTORY = 32


def save_lead_s(lags_s: Iterable[float], interval_s: float) -> float:
    """How far ahead of ``last content + interval`` a save is due: 1.5 times the longest recent lag, at
    least 10 ms, at most half the interval."""
    longest = max(lags_s, default=0.0)
    return min(max(_LEAD_FACTOR * longest, _MIN_LEAD_S), 0.5 * interval_s)


def content_stamp_ns(pgm: bytes) -> int | None:
    """The content time a saved image's header comment carries (None: not one of the saver's)."""
    for line in pgm[:4096].split(b"\n"):
        if line.startswith(b"#") and CONTENT_STAMP_KEY.encode() in line:
            tail = line.split(CONTENT_STAMP_KEY.encode(), 1)[1].strip()
            if tail.isdigit():
                return int(tail)
        elif line[:1].isdigit():  # the width/height line: the comments are over
            break
    return None


log = logging.getLogger(__name__)


def save_topology_beside(yaml_path: Path, topology: Callable[[], dict[str, Any] | None]) -> list[str]:
    """Write ``topology()`` beside the map ``yaml_path`` (``<stem>.topology.geojson``); the file written,
    or nothing (no topology, or a failure: logged)."""
    from agent.slam import mapio

    try:
        data = topology()
        if data is None:
            return []
        return [str(mapio.save_topology(data, mapio.topology_path(yaml_path)))]
    except (ConfigError, ValueError) as exc:
        log.error("topological map save failed: %s", exc)
        return []


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
        self.late = 0  # saves whose lag exceeded the lead: the bound was not kept there
        # The topological map written beside each map (None: none); called on this saver's thread.
        self.topology: Callable[[], dict[str, Any] | None] | None = None
        self.topology_saves = 0
        self.topology_failures = 0
        self.max_lag_ms = 0.0
        # The interval counts from the last map's content time (or the start, or a skip).
        self._base_s = clock_s()
        self._lags: collections.deque[float] = collections.deque(maxlen=_LAG_HISTORY)
        self.lead_s = save_lead_s((), interval_s) if interval_s > 0 else 0.0
        # The map waiting to be written: (image, content time, when it was due).
        self._pending: tuple[OccupancyImage, float, float] | None = None
        self.committed_content_s: float | None = None  # the content time of the map on disk
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

    def due_at_s(self) -> float | None:
        """When the next periodic save is due (the saver's clock; None: only on request): ``lead``
        before the last content time plus the interval."""
        if self.interval_s <= 0.0:
            return None
        return self._base_s + self.interval_s - self.lead_s

    def seconds_until_due(self) -> float | None:
        """How long the SLAM thread may wait for a scan before a save is due (0: now; None: never)."""
        if self.requested:
            return 0.0
        due = self.due_at_s()
        return None if due is None else max(0.0, due - self.clock_s())

    def due(self) -> bool:
        """Whether the SLAM thread should hand over its map now (requested, or the interval is up)."""
        if self.requested:
            return True
        due = self.due_at_s()
        return due is not None and self.clock_s() >= due

    def submit(self, image: OccupancyImage, fetch_s: float = 0.0, content_s: float | None = None) -> None:
        """Queue ``image`` to be written (replacing one not written yet); returns at once. ``fetch_s``: what
        taking it out of the mapper cost the caller (for the counters); ``content_s``: when it was taken
        (the saver's clock; default: now less ``fetch_s``)."""
        now = self.clock_s()
        content = now - fetch_s if content_s is None else content_s
        due = self.due_at_s()
        # The lag runs from when the save was due (a request: from the fetch).
        scheduled = content if self.requested or due is None else min(due, content)
        self.max_fetch_ms = max(self.max_fetch_ms, fetch_s * 1e3)
        self.requested = False
        self._base_s = content
        with self._wake:
            if self._closed:
                return
            if self._pending is not None:
                self.dropped += 1
            self._pending = (image, content, scheduled)
            self._wake.notify()

    def skip(self) -> None:
        """Nothing to save yet (no map): count the interval from now, drop the request."""
        self.requested = False
        self._base_s = self.clock_s()

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
            "map_save_lag_max_us": round(self.max_lag_ms * 1e3),
            "map_save_lead_us": round(self.lead_s * 1e6),
            "map_saves_late": self.late,
            "topology_saves": self.topology_saves,
            "topology_save_failures": self.topology_failures,
        }

    def _run(self) -> None:
        from agent.slam import mapio

        while True:
            with self._wake:
                while self._pending is None and not self._closed:
                    self._wake.wait()
                pending = self._pending
                self._pending = None
                if pending is None:  # closed, nothing left
                    self._wake.notify_all()
                    return
                self._busy = True
            image, content_s, scheduled_s = pending
            t0 = time.perf_counter()
            cpu0 = time.thread_time()
            comment = f"{self.comment}\n{CONTENT_STAMP_KEY} {round(content_s * 1e9)}"
            try:
                mapio.save_map(image, self.yaml_path, comment=comment)
                self.saves += 1
                self.committed_content_s = content_s
                self._lagged(self.clock_s() - scheduled_s)
                self._save_topology()
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

    def _save_topology(self) -> None:
        from agent.slam import mapio

        if self.topology is None:
            return
        try:
            data = self.topology()
            if data is not None:
                mapio.save_topology(data, mapio.topology_path(self.yaml_path))
                self.topology_saves += 1
        except (ConfigError, ValueError) as exc:
            self.topology_failures += 1
            log.error("topological map save failed: %s", exc)

    def _lagged(self, lag_s: float) -> None:
        if self.interval_s <= 0.0:
            return
        if lag_s > self.lead_s:
            self.late += 1
        self.max_lag_ms = max(self.max_lag_ms, lag_s * 1e3)
        self._lags.append(lag_s)
        self.lead_s = save_lead_s(self._lags, self.interval_s)
