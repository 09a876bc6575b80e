"""sd_notify(3) with the standard library: tell systemd the agent is ready, how it is, that it is alive.

The protocol is one datagram on an ``AF_UNIX``/``SOCK_DGRAM`` socket named by ``$NOTIFY_SOCKET``, holding
newline-separated ``KEY=value`` fields: ``READY=1``, ``STATUS=...``, ``WATCHDOG=1``, ``STOPPING=1``,
``EXTEND_TIMEOUT_USEC=...``. A name starting with ``@`` is in the abstract namespace (the ``@`` stands for
a NUL byte). The bytes are the same as the ``systemd-notify`` binary sends, minus its ``BARRIER=1``.

With ``$NOTIFY_SOCKET`` unset (a shell, a test, ``vlp-agent sim``) everything here is a no-op that returns
``False``. The watchdog is ours only when ``$WATCHDOG_USEC`` is set and ``$WATCHDOG_PID``, if set, is our
pid; the ping interval is half of ``$WATCHDOG_USEC``, as sd_watchdog_enabled(3) advises.

A failed send never raises into the caller: the agent must keep localizing even if systemd is being
re-executed. It is logged (once per run of failures) and counted in :meth:`Notifier.stats`. Sends do not
block: the health monitor that pings must not hang on a busy service manager.

Typical use, by the runtime (the only caller; this module configures no logging and prints nothing)::

    notifier = Notifier.from_environ(unset_environment=True)
    ...                                   # devices up
    notifier.ready("localizing: 3 LEDs, scan 10 Hz")
    every notifier.watchdog_interval_s:   # in the health monitor
        notifier.watchdog_ping_if(all(loop.alive for loop in critical_loops))
    notifier.stopping()
"""

from __future__ import annotations

import logging
import os
import socket
import threading
from collections.abc import Mapping, MutableMapping
from dataclasses import dataclass
from types import TracebackType
from typing import Self

log = logging.getLogger(__name__)

NOTIFY_SOCKET = "NOTIFY_SOCKET"
WATCHDOG_USEC = "WATCHDOG_USEC"
WATCHDOG_PID = "WATCHDOG_PID"

# MSG_NOSIGNAL is Linux-only in Python's socket module; sd_notify is Linux-only anyway.
_SEND_FLAGS = getattr(socket, "MSG_NOSIGNAL", 0)


@dataclass(frozen=True, slots=True)
class NotifierStats:
    """What the notifier has done so far, for the agent's health report."""

    sent: int  # datagrams that reached the socket
    send_failures: int  # datagrams that did not (receiver gone, queue full, bad address)
    watchdog_pings: int  # WATCHDOG=1 datagrams sent
    watchdog_withheld: int  # pings not sent because a critical loop was not alive
    last_error: str | None


def socket_address(value: str | None) -> bytes | None:
    """The ``sendto`` address for a ``$NOTIFY_SOCKET`` value, or None when it is unset or unusable.

    ``/path`` is a filesystem socket; ``@name`` is ``\\0name`` in the abstract namespace. Anything else
    (systemd >= 253 also knows ``vsock:``) is not supported: logged, and notification stays off.
    """
    if not value:
        return None
    if value.startswith("/"):
        return os.fsencode(value)
    if value.startswith("@") and len(value) > 1:
        return b"\0" + os.fsencode(value[1:])
    log.warning(
        "%s=%r is neither a path nor an abstract (@) socket: not notifying systemd", NOTIFY_SOCKET, value
    )
    return None


def _parse_positive_int(name: str, value: str | None) -> int | None:
    if value is None or value == "":
        return None
    try:
        number = int(value, 10)
    except ValueError:
        log.warning("%s=%r is not an integer: ignored", name, value)
        return None
    if number <= 0:
        log.warning("%s=%r is not positive: ignored", name, value)
        return None
    return number


def watchdog_usec(environ: Mapping[str, str] | None = None, pid: int | None = None) -> int | None:
    """``$WATCHDOG_USEC`` when systemd's watchdog applies to process ``pid`` (default: this one), else None.

    The same rule as sd_watchdog_enabled(3): the watchdog is on when ``WATCHDOG_USEC`` is a positive integer
    and ``WATCHDOG_PID`` is unset or equal to the pid. A ``WATCHDOG_PID`` that names another process means
    the variables were inherited from a parent: that process is watched, not this one.
    """
    env = os.environ if environ is None else environ
    usec = _parse_positive_int(WATCHDOG_USEC, env.get(WATCHDOG_USEC))
    if usec is None:
        return None
    raw_pid = env.get(WATCHDOG_PID)
    if raw_pid:
        watched = _parse_positive_int(WATCHDOG_PID, raw_pid)
        if watched is None or watched != (os.getpid() if pid is None else pid):
            return None
    return usec


def watchdog_interval_s(environ: Mapping[str, str] | None = None, pid: int | None = None) -> float | None:
    """Seconds between ``WATCHDOG=1`` pings (half of ``$WATCHDOG_USEC``), or None when not watched."""
    usec = watchdog_usec(environ, pid)
    return None if usec is None else usec / 2_000_000


def _address_text(address: bytes) -> str:
    return "@" + os.fsdecode(address[1:]) if address.startswith(b"\0") else os.fsdecode(address)


def _one_line(text: str) -> str:
    # A newline inside STATUS= would start a new field (a stray "READY=1" in a device name, say).
    return " ".join(text.split())


class Notifier:
    """Sends sd_notify datagrams for one process. Thread-safe; every method returns whether it sent.

    ``address`` is a ``$NOTIFY_SOCKET`` value (None: do nothing). ``watchdog_usec`` is the watchdog timeout
    that applies to this process (None: no watchdog); :meth:`from_environ` works both out the way systemd
    means them. ``pid`` is the process the watchdog belongs to: a forked child never pings for its parent.
    """

    def __init__(
        self, address: str | None, *, watchdog_usec: int | None = None, pid: int | None = None
    ) -> None:
        self._address = socket_address(address)
        self._watchdog_usec = watchdog_usec if watchdog_usec is not None and watchdog_usec > 0 else None
        self._pid = os.getpid() if pid is None else pid
        self._lock = threading.Lock()
        self._sock: socket.socket | None = None
        self._closed = False
        self._sent = 0
        self._failures = 0
        self._failing = False  # in a run of failures: log the first only
        self._pings = 0
        self._withheld = 0
        self._stalled = False  # pings are being withheld: log the transitions only
        self._last_error: str | None = None

    @classmethod
    def from_environ(
        cls, environ: MutableMapping[str, str] | None = None, *, unset_environment: bool = False
    ) -> Notifier:
        """A notifier for what systemd put in the environment (default: ``os.environ``).

        ``unset_environment=True`` removes ``NOTIFY_SOCKET``, ``WATCHDOG_USEC`` and ``WATCHDOG_PID`` from it
        afterwards, so that subprocesses (a vendor tool, a helper script) cannot notify in our name.
        """
        env = os.environ if environ is None else environ
        pid = os.getpid()
        notifier = cls(env.get(NOTIFY_SOCKET), watchdog_usec=watchdog_usec(env, pid), pid=pid)
        if unset_environment:
            for name in (NOTIFY_SOCKET, WATCHDOG_USEC, WATCHDOG_PID):
                env.pop(name, None)
        return notifier

    # -- what the caller can ask ---------------------------------------------------------------------
    @property
    def enabled(self) -> bool:
        """True when there is a notification socket to send to."""
        return self._address is not None and not self._closed

    @property
    def watchdog_enabled(self) -> bool:
        """True when systemd's watchdog watches this process and expects ``WATCHDOG=1`` pings."""
        return self.enabled and self._watchdog_usec is not None and os.getpid() == self._pid

    @property
    def watchdog_timeout_s(self) -> float | None:
        """systemd's ``WatchdogSec=`` as it applies to us, or None when there is no watchdog for us."""
        if self._watchdog_usec is None or not self.watchdog_enabled:
            return None
        return self._watchdog_usec / 1_000_000

    @property
    def watchdog_interval_s(self) -> float | None:
        """How often to ping: half the watchdog timeout, or None when there is no watchdog for us."""
        timeout_s = self.watchdog_timeout_s
        return None if timeout_s is None else timeout_s / 2

    def stats(self) -> NotifierStats:
        with self._lock:
            return NotifierStats(self._sent, self._failures, self._pings, self._withheld, self._last_error)

    # -- messages ------------------------------------------------------------------------------------
    def ready(self, status: str | None = None) -> bool:
        """``READY=1``: start-up is complete (devices up); systemd starts the watchdog from here."""
        return self.send("READY=1", *self._status_field(status))

    def status(self, text: str) -> bool:
        """``STATUS=``: a one-line health summary, shown by ``systemctl status``."""
        return self.send(*self._status_field(text))

    def stopping(self, status: str | None = None) -> bool:
        """``STOPPING=1``: shutdown has begun (wheels being stopped, devices closing)."""
        return self.send("STOPPING=1", *self._status_field(status))

    def extend_timeout(self, seconds: float) -> bool:
        """``EXTEND_TIMEOUT_USEC=``: start-up (or stop) needs up to ``seconds`` more than configured."""
        return self.send(f"EXTEND_TIMEOUT_USEC={max(0, round(seconds * 1_000_000))}")

    def watchdog_ping(self) -> bool:
        """``WATCHDOG=1``, if the watchdog is ours. Prefer :meth:`watchdog_ping_if`."""
        if not self.watchdog_enabled:
            return False
        sent = self.send("WATCHDOG=1")
        if sent:
            with self._lock:
                self._pings += 1
        return sent

    def watchdog_ping_if(self, all_alive: bool) -> bool:
        """Ping only while every critical loop is alive; the health monitor calls this every interval.

        When a loop stalls the pings stop and systemd kills and restarts the agent after ``WatchdogSec``:
        a stuck agent must not look alive because one healthy thread still runs.
        """
        if not self.watchdog_enabled:
            return False
        if not all_alive:
            with self._lock:
                self._withheld += 1
                first = not self._stalled
                self._stalled = True
            if first:
                log.warning(
                    "a critical loop is not alive: withholding watchdog pings; systemd restarts the agent "
                    "after %.1f s unless it recovers",
                    self.watchdog_timeout_s,
                )
            return False
        with self._lock:
            recovered = self._stalled
            self._stalled = False
        if recovered:
            log.warning("all critical loops alive again: watchdog pings resumed")
        return self.watchdog_ping()

    def send(self, *fields: str) -> bool:
        """Send ``KEY=value`` fields as one datagram. False when disabled or when the send failed."""
        address = self._address
        if not fields or address is None or self._closed:
            return False
        data = "\n".join(fields).encode("utf-8")
        with self._lock:
            try:
                if self._sock is None:
                    self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
                    self._sock.setblocking(False)
                self._sock.sendto(data, _SEND_FLAGS, address)
            except OSError as exc:
                ok = False
                self._failures += 1
                self._last_error = f"{type(exc).__name__}: {exc}"
                first_failure, recovered = not self._failing, False
                self._failing = True
            else:
                ok = True
                self._sent += 1
                first_failure, recovered = False, self._failing
                self._failing = False
            failures, error = self._failures, self._last_error
        if recovered:
            log.info("sd_notify to %s works again (%d failed sends so far)", _address_text(address), failures)
        elif first_failure:
            log.warning(
                "sd_notify to %s failed: %s (logged once until a send succeeds; %d failed so far)",
                _address_text(address),
                error,
                failures,
            )
        elif not ok:
            log.debug("sd_notify to %s failed again: %s", _address_text(address), error)
        return ok

    # -- lifecycle -----------------------------------------------------------------------------------
    def close(self) -> None:
        """Release the socket; later calls do nothing. Safe to call more than once."""
        with self._lock:
            self._closed = True
            if self._sock is not None:
                self._sock.close()
                self._sock = None

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- helpers -------------------------------------------------------------------------------------
    @staticmethod
    def _status_field(text: str | None) -> tuple[str, ...]:
        return () if text is None else (f"STATUS={_one_line(text)}",)
