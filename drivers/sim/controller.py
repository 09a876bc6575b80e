"""The simulated controller at the other end of the pose stream, in a process of its own.

On a robot the pose stream goes out on a serial line to another chip (the motor controller's firmware,
or a flight controller speaking MAVLink) that decodes it. Under ``vlp-agent sim`` the line is a
pseudo-terminal and this is that chip: it reads the pty's master side and decodes every frame, counting
good and bad ones, as the firmware would (``firmware_protocol.pose_frame.PoseFrameDecoder``, or pymavlink
for MAVLink output).

It runs in a child process (``python -m drivers.sim.controller FD``, started through
:mod:`drivers.child_process`), not a thread of the agent, for the reason the camera's renderer does: the
controller is another chip on the robot, and a reader thread in the agent's process would be woken by
every pose the agent writes, at the moment the hot path returns from its write and wants the interpreter
lock back. (On this development machine the write's wall-time p99 stayed 1.2-4 ms either way, against
0.1-0.2 ms of CPU: what it waits for there is the cores and the hypervisor, see docs/benchmarks.md.)
The child makes the pty pair itself (raw on both sides), tells the parent the slave's name to write to,
and answers requests for its counts over the socketpair; asked to stop, it takes in what is still in the
pty, sends its final counts and ends.
"""

from __future__ import annotations

import contextlib
import importlib
import multiprocessing.connection
import os
import select
import sys
import tty
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from drivers.child_process import child_connection, start_child, stop_child
from drivers.errors import DeviceDisconnected

__all__ = ["ControllerCounts", "SimulatedController"]

_REPLY_TIMEOUT_S = 5.0


@dataclass(frozen=True)
class ControllerCounts:
    """What the controller has taken in: decoded frames, frames it rejected, bytes."""

    frames: int = 0
    bad: int = 0
    bytes: int = 0


class _Decoder:
    """The controller's decoding: pose frames, or MAVLink through pymavlink."""

    def __init__(self, mavlink: bool) -> None:
        self.frames = self.bad = self.bytes = 0
        self._mav: Any = None
        self._pose: Any = None
        if mavlink:
            os.environ.setdefault("MAVLINK20", "1")
            common = importlib.import_module("pymavlink.dialects.v20.common")
            self._mav = common.MAVLink(None)
            self._mav.robust_parsing = True
        else:
            from firmware_protocol.pose_frame import PoseFrameDecoder

            self._pose = PoseFrameDecoder()

    def take(self, data: bytes) -> None:
        self.bytes += len(data)
        if self._pose is not None:
            self.frames += len(self._pose.feed(data))
            self.bad = self._pose.bad_frames
            return
        for msg in self._mav.parse_buffer(data) or []:
            if msg.get_type() == "BAD_DATA":
                self.bad += 1
            else:
                self.frames += 1

    def counts(self) -> tuple[int, int, int]:
        # A plain tuple over the connection: the child's module is ``__main__``, whose classes the parent
        # cannot unpickle.
        return (self.frames, self.bad, self.bytes)


def _drain(fd: int, decoder: _Decoder) -> None:
    while select.select([fd], [], [], 0)[0]:
        try:
            data = os.read(fd, 4096)
        except OSError:
            return
        if not data:
            return
        decoder.take(data)


def _serve(conn: multiprocessing.connection.Connection) -> None:
    """The child: make the pty, report its name, then decode what comes until asked to stop."""
    mavlink = bool(conn.recv())
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    decoder = _Decoder(mavlink)
    conn.send(os.ttyname(slave))
    try:
        while True:
            ready, _, _ = select.select([master, conn.fileno()], [], [], 1.0)
            if master in ready:
                try:
                    data = os.read(master, 4096)
                except OSError:
                    data = b""
                decoder.take(data)
            if conn.fileno() in ready:
                try:
                    request = conn.recv()
                except (EOFError, OSError):
                    return
                if request is None:
                    _drain(master, decoder)
                    conn.send(decoder.counts())
                    return
                conn.send(decoder.counts())
    finally:
        os.close(master)
        os.close(slave)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m drivers.sim.controller FD``: serve the connection on file descriptor FD."""
    conn = child_connection("drivers.sim.controller", "SimulatedController", argv)
    if conn is None:
        return 2
    _serve(conn)
    return 0


class SimulatedController:
    """The controller child: ``url`` is the pty to write the pose stream to; :meth:`counts` what it decoded
    so far; :meth:`stop` takes in the rest and ends it (its last counts stay readable)."""

    def __init__(self, mavlink: bool = False) -> None:
        self._process, self._conn = start_child("drivers.sim.controller")
        self._final: ControllerCounts | None = None
        try:
            self._conn.send(mavlink)
            if not self._conn.poll(_REPLY_TIMEOUT_S):
                raise DeviceDisconnected("the simulated controller did not start", "output")
            self.url: str = self._conn.recv()
        except BaseException:
            stop_child(self._process, self._conn, "simulated controller")
            raise

    def counts(self) -> ControllerCounts:
        if self._final is not None:
            return self._final
        try:
            self._conn.send("counts")
            if self._conn.poll(_REPLY_TIMEOUT_S):
                return ControllerCounts(*self._conn.recv())
        except (EOFError, OSError):
            pass
        raise DeviceDisconnected("the simulated controller is gone", "output")

    @property
    def frames(self) -> int:
        return self.counts().frames

    @property
    def bad(self) -> int:
        return self.counts().bad

    def stop(self) -> None:
        """Take in what is still in the pty, keep the final counts, end the child. Safe to call twice."""
        if self._final is not None:
            return
        final = ControllerCounts()
        with contextlib.suppress(EOFError, OSError):
            self._conn.send(None)
            if self._conn.poll(_REPLY_TIMEOUT_S):
                final = ControllerCounts(*self._conn.recv())
        self._final = final
        stop_child(self._process, self._conn, "simulated controller")


if __name__ == "__main__":
    sys.exit(main())
