"""Serve a fake serial device on a pseudo-terminal, so any client (our drivers, dynamixel-sdk, urg_c,
a terminal program) can open its path like a real port.

The fake keeps the master side; the slave side is what clients open. ``unplug()`` closes the master, which
is what a client sees when a USB-serial device is pulled (reads fail with EIO / "device disconnected"), and
``replug()`` brings a new pty up. With ``link=`` the server keeps a symlink pointing at the current slave,
the way a udev rule keeps ``/dev/urg`` pointing at whichever ``ttyACM`` the sensor came up as. The link
never replaces anything but a link of its own kind: see :func:`check_link_path`.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import secrets
import select
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import Protocol, runtime_checkable

from drivers.errors import ConfigError

log = logging.getLogger(__name__)

# Where pty slaves live: a link into here whose pty is gone was left by a fake that was killed.
_PTS_DIR = "/dev/pts/"


def check_link_path(path: Path) -> None:
    """Refuse a link path that would destroy something: ``path`` may be absent (its folder must exist) or
    a dangling symlink into /dev/pts (a fake killed before it could remove its link); any file, folder,
    live link or link elsewhere is someone else's. Raises ConfigError naming the path."""
    if not path.parent.is_dir():
        raise ConfigError("link", f"the folder {path.parent} does not exist", str(path))
    if path.is_symlink():
        target = os.readlink(path)
        if target.startswith(_PTS_DIR) and not os.path.exists(target):
            return
        raise ConfigError(
            "link", f"is already a link (to {target}) that this fake did not make; remove it first", str(path)
        )
    if path.exists():
        kind = "a folder" if path.is_dir() else "a file"
        raise ConfigError("link", f"is {kind}; the link would replace it: choose another path", str(path))


class ByteDevice(Protocol):
    """The device side of a fake: bytes in, bytes out, plus output that falls due with time."""

    def receive(self, data: bytes, now: float) -> bytes:
        """Take bytes the host wrote; return the bytes to answer with right away (may be empty)."""
        ...

    def poll(self, now: float) -> bytes:
        """Return unsolicited bytes due by monotonic time ``now`` (streamed scans, tag reads)."""
        ...


@runtime_checkable
class ScheduledByteDevice(ByteDevice, Protocol):
    """A device that knows when its next unsolicited output falls due: the server then sleeps until then
    (or until bytes arrive) instead of polling it every ``poll_interval_s``."""

    def next_output_in(self, now: float) -> float | None:
        """Seconds from monotonic time ``now`` until :meth:`poll` has bytes to send (0: now), or None when
        nothing is scheduled."""
        ...


# How long after a scheduled device's output falls due the server wakes for it.
_SCHEDULE_SLACK_S = 0.0005


def _no_wait() -> None:
    return None


class PtyServer:
    """Runs a :class:`ByteDevice` on a pty in a background thread."""

    def __init__(
        self, device: ByteDevice, link: str | os.PathLike[str] | None = None, poll_interval_s: float = 0.002
    ) -> None:
        """``poll_interval_s``: how often the device is polled for output of its own; for a
        :class:`ScheduledByteDevice`, the longest the server sleeps (it wakes when the output falls due)."""
        self.device = device
        self._schedule = device.next_output_in if isinstance(device, ScheduledByteDevice) else None
        self.link = Path(link) if link is not None else None
        self.poll_interval_s = poll_interval_s
        self._master: int | None = None
        self._slave: int | None = None
        self._slave_path = ""
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        # A pipe in the serving thread's select that ``unplug()`` writes to, so the thread leaves at once
        # however long it was told to sleep: a thread that outlived ``unplug()`` (joined with a timeout)
        # woke later in a select whose fd number had meanwhile been reused by the next pty, and read the
        # next client's first command (a test's first QT went unanswered that way, after a test whose
        # server slept 5 s).
        self._wake: tuple[int, int] | None = None
        self._lock = threading.Lock()
        self.bytes_in = 0
        self.bytes_out = 0
        # How late the serving thread woke past the timeout it slept for, at worst, and how often by more
        # than ``late_warn_s`` (logged): a fake that shares a loaded machine with its client can be starved
        # where real hardware would not be (``vlp-agent sim``'s summary reports it).
        self.late_warn_s = 0.25
        self.late_max_s = 0.0
        self.late_count = 0
        # Called before the device handles bytes or is polled. A fake shares the process of the program
        # it serves under ``vlp-agent sim``, where real hardware would not: the simulation sets this so
        # that the fake waits while the agent's hot path runs (agent.runtime.hotpath).
        self.give_way: Callable[[], None] = _no_wait
        # Called first in the serving thread (``SimulatedRobot`` puts it under real-time scheduling there:
        # a fake stands in for hardware, which keeps its time whatever the computer's load).
        self.on_thread_start: Callable[[], None] = _no_wait

    # -- lifecycle ---------------------------------------------------------------------------------
    @property
    def path(self) -> str:
        """The path clients open: the symlink if one was asked for, else the pty slave."""
        return str(self.link) if self.link is not None else self._slave_path

    @property
    def plugged(self) -> bool:
        return self._master is not None

    def start(self) -> str:
        self.replug()
        return self.path

    def replug(self) -> None:
        """Bring a fresh pty up (the device is plugged back in)."""
        with self._lock:
            if self._master is not None:
                return
            master, slave = os.openpty()
            tty.setraw(slave)
            tty.setraw(master)
            self._master, self._slave = master, slave
            self._slave_path = os.ttyname(slave)
            if self.link is not None:
                try:
                    self._place_link()
                except BaseException:
                    for fd in (master, slave):
                        os.close(fd)
                    self._master = self._slave = None
                    raise
            self._stop.clear()
            self._wake = os.pipe()
            self._thread = threading.Thread(
                target=self._run,
                args=(master, self._wake[0]),
                name=f"fake-pty {self._slave_path}",
                daemon=True,
            )
            self._thread.start()
        log.debug("fake device up on %s", self.path)

    def unplug(self) -> None:
        """Pull the device: the pty goes away under any client that has it open."""
        with self._lock:
            thread = self._thread
            self._stop.set()
            if self._wake is not None:
                with contextlib.suppress(OSError):
                    os.write(self._wake[1], b"x")
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=2.0)
            if thread.is_alive():
                log.warning("fake device on %s: its thread did not stop within 2 s", self.path)
        with self._lock:
            for fd in (self._master, self._slave, *(self._wake or ())):
                if fd is not None:
                    with contextlib.suppress(OSError):
                        os.close(fd)
            self._master = self._slave = self._wake = None
            self._thread = None
            if self.link is not None and self._owns_link():
                with contextlib.suppress(FileNotFoundError):
                    self.link.unlink()

    def _owns_link(self) -> bool:
        try:
            return os.readlink(self.link) == self._slave_path if self.link is not None else False
        except OSError:
            return False

    def _place_link(self) -> None:
        """Point the link at the new slave with one rename, after checking it replaces nothing of anyone
        else's (on a replug, the old link is this server's own and was removed when it was unplugged)."""
        assert self.link is not None
        check_link_path(self.link)
        # A name of our own for the new link: a fixed "PATH.tmp" could be someone's file.
        while True:
            tmp = self.link.with_name(f".{self.link.name}.{secrets.token_hex(4)}.tmp")
            try:
                tmp.symlink_to(self._slave_path)
                break
            except FileExistsError:
                continue
            except OSError as exc:
                raise self._link_error(exc) from exc
        try:
            os.replace(tmp, self.link)
        except OSError as exc:
            with contextlib.suppress(OSError):
                tmp.unlink()
            raise self._link_error(exc) from exc

    def _link_error(self, exc: OSError) -> ConfigError:
        return ConfigError("link", f"cannot make the link: {exc.strerror or exc}", str(self.link))

    def close(self) -> None:
        self.unplug()

    def __enter__(self) -> PtyServer:
        if not self.plugged:
            self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # -- the serving thread ------------------------------------------------------------------------
    def _write(self, master: int, data: bytes) -> None:
        view = memoryview(data)
        while view and not self._stop.is_set():
            try:
                n = os.write(master, view)
            except BlockingIOError:
                time.sleep(0.001)
                continue
            except OSError as exc:
                if exc.errno in (errno.EIO, errno.EBADF):
                    return
                raise
            view = view[n:]
            self.bytes_out += n

    def _run(self, master: int, wake: int) -> None:
        self.on_thread_start()
        while not self._stop.is_set():
            timeout = self.poll_interval_s
            if self._schedule is not None:
                due_in = self._schedule(time.monotonic())
                if due_in is not None:
                    # Just past the due time: woken a hair early, the device would have nothing yet.
                    timeout = min(max(due_in, 0.0) + _SCHEDULE_SLACK_S, timeout)
            slept = time.monotonic()
            try:
                ready, _, _ = select.select([master, wake], [], [], timeout)
            except (OSError, ValueError):
                return
            if self._stop.is_set():
                return  # unplugged: the fds may already be closed, their numbers someone else's
            ready = [fd for fd in ready if fd == master]
            self.give_way()
            now = time.monotonic()
            # Past the timeout slept for; a wait that bytes ended counts whole (when they came is not known).
            late = now - slept - (0.0 if ready else timeout)
            if late > self.late_max_s:
                self.late_max_s = late
            if late > self.late_warn_s:
                self.late_count += 1
                log.debug("fake device on %s: its thread ran %.2f s late", self.path, late)
            try:
                if ready:
                    data = os.read(master, 4096)
                    if data:
                        self.bytes_in += len(data)
                        reply = self.device.receive(data, now)
                        if reply:
                            self._write(master, reply)
                due = self.device.poll(now)
                if due:
                    self._write(master, due)
            except OSError as exc:
                if exc.errno in (errno.EIO, errno.EBADF):
                    if self._stop.wait(self.poll_interval_s):
                        return
                    continue
                log.exception("fake device on %s failed", self.path)
                return
            except Exception:  # a bug in a fake must not kill the test run silently
                log.exception("fake device on %s failed", self.path)
                return
