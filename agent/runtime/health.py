"""Per-loop heartbeats and the health monitor that turns them into systemd notifications.

Every loop of the runtime owns a :class:`Heartbeat` and beats it once per iteration, including the
iterations in which its device is failing: a heartbeat says the *loop* is alive (not hung in a call that
never returns), not that its device is fine; device faults are reported separately, in the pose flags and
the status line. The :class:`HealthMonitor` is ticked by the runtime's monitor thread and, through a
notifier (``agent.sdnotify.Notifier``, or anything with the same methods):

* ``READY=1`` once the runtime says its devices are up (:meth:`HealthMonitor.ready`);
* ``WATCHDOG=1`` every ``watchdog_interval_s``, but only while every *critical* loop has beaten within its
  timeout: a hung critical loop stops the pings and systemd restarts the agent;
* ``STATUS=`` with a one-line summary every ``status_interval_s``;
* ``STOPPING=1`` when shutdown begins.

It logs each loop's transitions between alive and stalled. Without a notifier (a shell, a test) it still
checks and logs.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

__all__ = ["HealthMonitor", "HealthReport", "Heartbeat", "NotifierLike"]

log = logging.getLogger(__name__)


class NotifierLike(Protocol):
    """What the monitor needs of ``agent.sdnotify.Notifier``."""

    @property
    def watchdog_interval_s(self) -> float | None: ...

    def ready(self, status: str | None = None) -> bool: ...

    def status(self, text: str) -> bool: ...

    def watchdog_ping_if(self, all_alive: bool) -> bool: ...

    def stopping(self, status: str | None = None) -> bool: ...


class Heartbeat:
    """A loop's sign of life. ``beat()`` is cheap and is called by that loop only."""

    def __init__(
        self, name: str, critical: bool, timeout_s: float, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.name = name
        self.critical = critical
        self.timeout_s = timeout_s
        self._clock = clock
        self.last_s = clock()
        self.beats = 0

    def beat(self) -> None:
        self.last_s = self._clock()
        self.beats += 1

    def age_s(self, now_s: float | None = None) -> float:
        return (self._clock() if now_s is None else now_s) - self.last_s

    def alive(self, now_s: float | None = None) -> bool:
        return self.age_s(now_s) <= self.timeout_s


@dataclass(frozen=True, slots=True)
class HealthReport:
    all_critical_alive: bool
    stalled: tuple[str, ...]  # every loop past its timeout, critical or not
    ages_s: dict[str, float]


class HealthMonitor:
    """Watches heartbeats and feeds the notifier; ``status_line`` gives the ``STATUS=`` text."""

    def __init__(
        self,
        notifier: NotifierLike | None,
        status_line: Callable[[], str],
        *,
        status_interval_s: float = 2.0,
        watchdog: bool = True,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.notifier = notifier
        self.status_line = status_line
        self.status_interval_s = status_interval_s
        self.watchdog = watchdog
        self.clock = clock
        self._beats: dict[str, Heartbeat] = {}
        self._stalled: set[str] = set()
        self._lock = threading.Lock()
        self._ready = False
        self._next_ping = clock()
        self._next_status = clock() + status_interval_s
        self.pings = 0
        self.withheld = 0

    def register(self, name: str, critical: bool, timeout_s: float) -> Heartbeat:
        with self._lock:
            if name in self._beats:
                raise ValueError(f"a loop named {name!r} is already registered")
            beat = Heartbeat(name, critical, timeout_s, self.clock)
            self._beats[name] = beat
            return beat

    def heartbeat(self, name: str) -> Heartbeat | None:
        """The heartbeat registered as ``name``, if any."""
        with self._lock:
            return self._beats.get(name)

    @property
    def heartbeats(self) -> list[Heartbeat]:
        with self._lock:
            return list(self._beats.values())

    def check(self) -> HealthReport:
        now = self.clock()
        beats = self.heartbeats
        stalled = tuple(b.name for b in beats if not b.alive(now))
        all_alive = not any(b.critical and not b.alive(now) for b in beats)
        for name in stalled:
            if name not in self._stalled:
                log.warning("loop %r has not beaten for %.1f s: stalled", name, self._beats[name].age_s(now))
        for name in self._stalled - set(stalled):
            log.warning("loop %r is alive again", name)
        self._stalled = set(stalled)
        return HealthReport(all_alive, stalled, {b.name: round(b.age_s(now), 3) for b in beats})

    @property
    def is_ready(self) -> bool:
        return self._ready

    def ready(self) -> None:
        """Start-up is complete: READY=1, once."""
        if self._ready:
            return
        self._ready = True
        if self.notifier is not None:
            self.notifier.ready(self.status_line())

    def tick(self) -> HealthReport:
        """One round: check the heartbeats, ping the watchdog when due (and deserved), refresh STATUS=."""
        report = self.check()
        now = self.clock()
        if self.notifier is None:
            return report
        interval = self.notifier.watchdog_interval_s
        if self._ready and self.watchdog and interval is not None and now >= self._next_ping:
            self._next_ping = now + interval
            if self.notifier.watchdog_ping_if(report.all_critical_alive):
                self.pings += 1
            elif not report.all_critical_alive:
                self.withheld += 1
        if self._ready and now >= self._next_status:
            self._next_status = now + self.status_interval_s
            self.notifier.status(self.status_line())
        return report

    def run(self, stop: threading.Event, period_s: float = 0.25) -> None:
        """:meth:`tick` every ``period_s`` until ``stop`` is set."""
        while not stop.wait(period_s):
            self.tick()

    def stopping(self, text: str = "stopping") -> None:
        """STOPPING=1 (shutdown has begun)."""
        if self.notifier is not None:
            self.notifier.stopping(text)
