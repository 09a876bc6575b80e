"""SIGTERM / SIGINT turned into a request the main loop waits on, without a lock in the handler.

A Python signal handler runs in the main thread between two bytecodes, possibly while that thread holds a
lock. ``threading.Event.set`` takes the event's lock, so a handler that sets an event the main thread is
waiting on can deadlock the process (the main thread inside ``Event.wait`` before it releases the
condition's lock): a service that never stops on SIGTERM. :class:`ShutdownRequest` only stores the signal
number and writes one byte to a non-blocking self-pipe, both safe at any point; :meth:`ShutdownRequest.wait`
selects on the pipe, so the main loop wakes at once.

The main loop then stops its threads from ordinary code, where taking locks is safe::

    with ShutdownRequest() as shutdown:
        while not shutdown.wait(0.2):
            ...
        stop_event.set()
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import time
from collections.abc import Callable, Iterable
from types import FrameType, TracebackType
from typing import Any

__all__ = ["AgentRequests", "ShutdownRequest", "SignalCall"]

_Handler = Callable[[int, FrameType | None], Any] | int | signal.Handlers | None


class ShutdownRequest:
    """Installs handlers for ``signals`` on enter and restores the previous ones on exit."""

    def __init__(self, signals: Iterable[signal.Signals] = (signal.SIGTERM, signal.SIGINT)) -> None:
        self.signals = tuple(signals)
        self.signum: int | None = None
        self._read_fd = -1
        self._write_fd = -1
        self._previous: dict[signal.Signals, _Handler] = {}
        # When the signal came: monotonic time and this process's CPU time.
        self._at: tuple[float, float] | None = None

    @property
    def requested(self) -> bool:
        """Whether one of the signals arrived."""
        return self.signum is not None

    def why(self, otherwise: str) -> str:
        """Why the agent stops, for the log: the signal's name (``SIGTERM``), else ``otherwise``."""
        if self.signum is None:
            return otherwise
        try:
            return signal.Signals(self.signum).name
        except ValueError:
            return f"signal {self.signum}"

    def wait(self, timeout_s: float) -> bool:
        """Sleep up to ``timeout_s``, waking at once on a signal; returns :attr:`requested`."""
        if self.signum is None and timeout_s > 0.0:
            if self._read_fd < 0:
                raise RuntimeError("ShutdownRequest.wait outside its with-block")
            # The handler runs while select waits (EINTR, PEP 475): its byte makes the retried select return.
            select.select([self._read_fd], [], [], timeout_s)
        return self.signum is not None

    def stop_times(self) -> dict[str, float] | None:
        """The stop so far in the process's own terms, from the first signal: ``wall_s`` (monotonic) and
        ``cpu_s`` (CPU time of every thread of this process; a SLAM worker process is waited on, not
        counted). ``cpu_s`` is the stop's own work, which a loaded machine hardly inflates; ``wall_s`` adds
        the waits and the time the process waited for a CPU. None: no signal came."""
        if self._at is None:
            return None
        wall, cpu = self._at
        return {"wall_s": round(time.monotonic() - wall, 3), "cpu_s": round(time.process_time() - cpu, 3)}

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        if self.signum is None:  # clocks read, no lock taken: safe in a handler
            self._at = (time.monotonic(), time.process_time())
        self.signum = signum
        with contextlib.suppress(OSError):  # a full pipe already wakes the reader
            os.write(self._write_fd, b"\0")

    def __enter__(self) -> ShutdownRequest:
        self._read_fd, self._write_fd = os.pipe()
        os.set_blocking(self._read_fd, False)
        os.set_blocking(self._write_fd, False)
        for signum in self.signals:
            self._previous[signum] = signal.signal(signum, self._on_signal)
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler if handler is not None else signal.SIG_DFL)
        self._previous.clear()
        for fd in (self._read_fd, self._write_fd):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._read_fd = self._write_fd = -1


class SignalCall:
    """Calls ``action`` when ``signum`` arrives (e.g. SIGUSR1: save the map now), between enter and exit.

    ``action`` runs inside the signal handler, so it must take no lock (set a flag, as
    ``Agent.request_map_save`` does); the previous handler comes back on exit."""

    def __init__(self, signum: signal.Signals, action: Callable[[], None]) -> None:
        self.signum = signum
        self.action = action
        self._previous: _Handler = None

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        self.action()

    def __enter__(self) -> SignalCall:
        self._previous = signal.signal(self.signum, self._on_signal)
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        signal.signal(self.signum, self._previous if self._previous is not None else signal.SIG_DFL)


def _dropped() -> None:
    """A request before there is anyone to take it: dropped, not fatal."""


class AgentRequests:
    """The agent's two operator signals, for ``vlp-agent run`` and ``sim`` alike: SIGUSR1 saves the map
    now, SIGUSR2 writes a flight-recorder snapshot (``systemctl kill -s USR1 vlp-agent``). Installed on
    enter, before the agent exists (a signal then is dropped, not the default's death); :meth:`attach`
    points them at the agent once it does; the previous handlers come back on exit. The actions run inside
    the signal handler, so they only set a flag or append to a deque (:class:`SignalCall`)."""

    def __init__(self) -> None:
        self.map_save = SignalCall(signal.SIGUSR1, _dropped)
        self.snapshot = SignalCall(signal.SIGUSR2, _dropped)

    def attach(self, map_save: Callable[[], None], snapshot: Callable[[], None] | None) -> None:
        """``map_save``: e.g. ``Agent.request_map_save``; ``snapshot``: the flight recorder's
        ``request_snapshot`` (None: no recorder, the signal stays dropped)."""
        self.map_save.action = map_save
        self.snapshot.action = snapshot if snapshot is not None else _dropped

    def __enter__(self) -> AgentRequests:
        self.map_save.__enter__()
        try:
            self.snapshot.__enter__()
        except BaseException:
            self.map_save.__exit__(None, None, None)
            raise
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.snapshot.__exit__(exc_type, exc, tb)
        self.map_save.__exit__(exc_type, exc, tb)
