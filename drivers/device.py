"""What every driver shares: explicit lifecycle and a health report.

Drivers are context managers; ``open()`` brings the device up, ``close()`` releases it and may be called
any number of times. ``health()`` says whether the device is live, what last went wrong, and counts what
was lost (bad frames, resyncs, timeouts, reconnects), so the agent can report instead of guessing.
"""

from __future__ import annotations

import abc
import threading
from collections import Counter
from dataclasses import dataclass, field
from types import TracebackType
from typing import Self


@dataclass(frozen=True, slots=True)
class DeviceHealth:
    name: str
    connected: bool
    last_error: str | None = None
    counters: dict[str, int] = field(default_factory=dict)


class Device(abc.ABC):
    """Base of every driver. Subclasses implement ``_open`` and ``_close``."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._opened = False
        self._last_error: str | None = None
        self._counters: Counter[str] = Counter()
        self._health_lock = threading.Lock()

    # -- lifecycle ---------------------------------------------------------------------------------
    def open(self) -> None:
        if not self._opened:
            self._open()
            self._opened = True

    def close(self) -> None:
        if self._opened:
            self._opened = False
            self._close()

    @property
    def is_open(self) -> bool:
        return self._opened

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    @abc.abstractmethod
    def _open(self) -> None: ...

    @abc.abstractmethod
    def _close(self) -> None: ...

    # -- health ------------------------------------------------------------------------------------
    def count(self, what: str, n: int = 1) -> None:
        with self._health_lock:
            self._counters[what] += n

    def note_error(self, message: str) -> None:
        with self._health_lock:
            self._last_error = message

    @property
    def connected(self) -> bool:
        return self._opened

    def _live_counters(self) -> dict[str, int]:
        """Counters a subclass keeps elsewhere (a codec's discarded bytes, say), merged into ``health()``."""
        return {}

    def health(self) -> DeviceHealth:
        live = self._live_counters()
        with self._health_lock:
            counters = dict(self._counters)
            counters.update(live)
            return DeviceHealth(self.name, self.connected, self._last_error, counters)
