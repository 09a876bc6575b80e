"""SLAM in a process of its own, so that its filter updates never hold the hot path's interpreter lock.

The agent is one Python process: its threads share one interpreter lock. A SLAM filter update is tens of
milliseconds of numpy and Python; while it runs, the hot path (frame -> VLP fix -> fused pose -> bytes)
gets the lock back only every ``sys.getswitchinterval()`` after each OpenCV call that released it, and a
frame that meets an update pays for it in its latency. :class:`ProcessMapper` keeps the same
:class:`~agent.runtime.mapper.ScanMapper` (built by :func:`~agent.runtime.mapper.make_local_mapper` from
the same config) in a child process: the SLAM thread hands each scan over and waits on the socket, the lock
released, as it would in a device driver. The child runs at a lower CPU priority (``nice`` +5), so on a
busy core the hot path goes first; on the robot's four cores it has one to itself.

The child ignores SIGINT and SIGTERM (a terminal's Ctrl-C and systemd's stop reach every process of the
group) and ends when the agent hangs up, after it has saved the map through it. The child is a fresh
interpreter (``drivers.child_process``: ``python -m agent.runtime.slam_worker FD``, never a ``fork`` of the
threaded agent, and not ``multiprocessing``'s spawn, which re-imports the parent's main script); the two
talk over a socketpair (AF_UNIX, no network) with ``multiprocessing.connection`` framing: one request, one
reply, always from the SLAM thread (the agent's summary reads the counters kept from the last reply).

Where the map starts is the fused pose at a scan's time, which only the parent knows: until the child says
its filter has started, each scan goes with that pose (``start_pose``), and the child's mapper reads it
from there. If the child dies, the step is ``rejected`` with the reason, the death is counted and logged,
and a new child starts on the next scan (with a new map, from the fused pose: the old one was lost with the
process).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import multiprocessing.connection
import os
import resource
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from agent.config_slam import MountConfig, SlamConfig, SlamMode
from agent.runtime.mapper import MapperStep, Pose, make_local_mapper
from agent.runtime.types import AbsoluteFix
from agent.slam.malloc import tune_malloc
from drivers.child_process import child_connection, start_child, stop_child
from drivers.samples import Scan

__all__ = ["ProcessMapper"]

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

# How long one request may take before the child counts as hung (a filter update takes tens of ms; a map
# picture of a large building, a second or so).
_REPLY_TIMEOUT_S = 10.0
# The first answer comes from a new interpreter (niced) that has imported numpy and the SLAM package and
# built its filter: seconds on an idle Pi, several times that on a busy one. Slow is not hung there.
_START_TIMEOUT_S = 40.0
# The child's CPU priority below the agent's: on a busy core the hot path goes first.
_NICE = 5
# After the child died, the next one starts no sooner than this (a scan that kills it would otherwise have
# a new interpreter started for every scan).
_RESTART_AFTER_S = 5.0


# -- the child ------------------------------------------------------------------------------------------
class _StartPose:
    """The child mapper's ``start_pose``: the pose the parent sent with the current scan."""

    def __init__(self) -> None:
        self.pose: Pose | None = None

    def __call__(self, t_ns: int) -> Pose | None:
        return self.pose


def _peak_rss_kb() -> int:
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)


# How often the child re-reads its shared pages (reading /proc/self/smaps_rollup walks every mapping).
_SHARED_EVERY_S = 5.0


def _shared_kb() -> int:
    """This process's resident pages that other processes map too (``Shared_Clean`` + ``Shared_Dirty`` of
    /proc/self/smaps_rollup; 0 where there is none): the interpreter's and the libraries' code (numpy,
    OpenCV, SciPy), which the agent's process maps as well. They are in the child's peak RSS and in the
    agent's: counted once for the whole agent (``vlp-agent sim``'s ``peak_rss_mb``)."""
    try:
        text = Path("/proc/self/smaps_rollup").read_text()
    except OSError:
        return 0
    total = 0
    for line in text.splitlines():
        if line.startswith(("Shared_Clean:", "Shared_Dirty:")):
            total += int(line.split()[1])
    return total


def _serve(conn: multiprocessing.connection.Connection) -> None:
    """Build the mapper from the first message, then answer every request until the parent hangs up."""
    config, mount = conn.recv()
    start = _StartPose()
    mapper, why = make_local_mapper(config, mount, start)
    conn.send((mapper is not None, why, mapper.name if mapper is not None else ""))
    if mapper is None:
        return
    shared_kb, shared_at = 0, -math.inf
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return
        if request is None:
            return
        kind = request[0]
        reply: Any
        if kind == "update":
            _, scan, odom_pose, start.pose = request
            reply = mapper.update(scan, odom_pose)
        elif kind == "fix":
            _, fix, odom_pose = request
            mapper.add_fix(fix, odom_pose)
            reply = None
        elif kind == "pose":
            reply = mapper.pose(request[1])
        elif kind == "map":
            reply = mapper.map_image()
        elif kind == "trajectory":
            reply = mapper.trajectory()
        else:
            reply = ValueError(f"unknown request {kind!r}")
        counters = dict(mapper.counters())
        counters["worker_peak_rss_kb"] = _peak_rss_kb()
        if time.monotonic() - shared_at >= _SHARED_EVERY_S:
            shared_kb, shared_at = _shared_kb(), time.monotonic()
        counters["worker_shared_kb"] = shared_kb
        conn.send((reply, counters, mapper.pose() is not None))


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m agent.runtime.slam_worker FD``: serve the connection on file descriptor FD."""
    conn = child_connection("agent.runtime.slam_worker", "ProcessMapper", argv)
    if conn is None:
        return 2
    # Ctrl-C reaches the whole foreground process group, and systemd's stop every process of the unit: the
    # child stays until the agent, which saves the map through it while stopping, hangs up.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    with contextlib.suppress(OSError):
        os.nice(_NICE)
    tune_malloc()  # the filter's per-update distance fields: agent.slam.malloc
    _serve(conn)
    return 0


# -- the parent -----------------------------------------------------------------------------------------
class WorkerLost(RuntimeError):
    """The SLAM process died or stopped answering."""


class ProcessMapper:
    """A :class:`~agent.runtime.mapper.ScanMapper` (the one ``make_local_mapper`` builds for ``config``)
    running in a child process. Same calls, same results; called from the SLAM thread (``counters`` from
    any)."""

    def __init__(
        self, config: SlamConfig, mount: MountConfig, start_pose: Callable[[int], Pose | None]
    ) -> None:
        self.config = config
        self.mount = mount
        self.start_pose = start_pose
        self.name = "slam"
        self.restarts = 0
        self._started = False
        self._counters: dict[str, int] = {}
        self._counters_lock = threading.Lock()
        # One request at a time (the SLAM thread's; a map or trajectory asked for from elsewhere waits).
        self._call_lock = threading.RLock()
        self._conn: multiprocessing.connection.Connection | None = None
        self._process: subprocess.Popen[bytes] | None = None
        self._next_spawn_s = 0.0
        self._closed = False
        # The map last saved as the robot went (None: none yet); a child started after a death continues
        # it rather than starting the map again (``create_agent`` sets it to the map saver's).
        self.resume_map: Callable[[], Path | None] = lambda: None
        self._spawn(config)

    # -- the child's life ------------------------------------------------------------------------------
    def _spawn(self, config: SlamConfig) -> None:
        blas = {"OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS", "1")}
        self._process, self._conn = start_child("agent.runtime.slam_worker", blas)
        self._started = False
        ok, why, name = self._exchange((config, self.mount), _START_TIMEOUT_S)
        if not ok:
            self._stop_child()
            raise ValueError(f"the SLAM process could not build its filter: {why}")
        self.name = str(name)

    def _exchange(self, message: object, timeout_s: float = _REPLY_TIMEOUT_S) -> Any:
        conn = self._conn
        if conn is None:
            raise WorkerLost("the SLAM process is not running")
        try:
            conn.send(message)
            if not conn.poll(timeout_s):
                raise WorkerLost(f"the SLAM process gave no answer in {timeout_s:g} s")
            return conn.recv()
        except (EOFError, OSError) as exc:
            raise WorkerLost(f"the SLAM process is gone: {exc}") from exc

    def _call(self, *request: object) -> Any:
        """One request, its reply; the counters and whether the filter has started come with it."""
        with self._call_lock:
            if self._closed:
                raise WorkerLost("the SLAM process was closed")
            if self._conn is None:
                if time.monotonic() < self._next_spawn_s:
                    raise WorkerLost("the SLAM process is down (a new one starts shortly)")
                self.restarts += 1
                config = self._restart_config()
                if config.map is not None and config.mode is SlamMode.CONTINUE:
                    log.warning(
                        "starting a new SLAM process (restart %d), continuing %s", self.restarts, config.map
                    )
                else:
                    log.warning(
                        "starting a new SLAM process (restart %d); the map starts again", self.restarts
                    )
                try:
                    self._spawn(config)
                except ValueError as exc:
                    self._next_spawn_s = time.monotonic() + _RESTART_AFTER_S
                    raise WorkerLost(str(exc)) from exc
            try:
                reply, counters, started = self._exchange(request)
            except WorkerLost:
                self._next_spawn_s = time.monotonic() + _RESTART_AFTER_S
                self._stop_child()
                raise
        with self._counters_lock:
            self._counters = counters
        self._started = bool(started)
        if isinstance(reply, Exception):
            raise reply
        return reply

    def _restart_config(self) -> SlamConfig:
        """The config a new child starts with: continuing the last saved map when there is one that loads."""
        if self.config.mode is SlamMode.LOCALIZATION:
            return self.config
        saved = self.resume_map()
        if saved is None:
            return self.config
        from agent.slam.mapio import load_map
        from drivers.errors import ConfigError

        try:
            load_map(saved)
        except ConfigError as exc:
            log.error("cannot continue the saved map after a restart: %s", exc)
            return self.config
        return dataclasses.replace(self.config, mode=SlamMode.CONTINUE, map=saved)

    def close(self) -> None:
        """Stop the child for good (idempotent): later calls answer as a mapper without a filter."""
        self._closed = True
        self._stop_child()

    def _stop_child(self) -> None:
        """Stop the child (the next call starts a new one, unless closed)."""
        process, conn = self._process, self._conn
        self._process = self._conn = None
        self._started = False  # a new child's filter starts afresh
        if process is not None and conn is not None:
            stop_child(process, conn, "SLAM")

    # -- ScanMapper ------------------------------------------------------------------------------------
    def update(self, scan: Scan, odom_pose: Pose) -> MapperStep:
        start = None if self._started else self.start_pose(scan.host_time_ns)
        try:
            step: MapperStep = self._call("update", scan, odom_pose, start)
        except WorkerLost as exc:
            log.error("%s", exc)
            return MapperStep("rejected", reason=str(exc))
        return step

    def add_fix(self, fix: AbsoluteFix, odom_pose: Pose) -> None:
        try:
            self._call("fix", fix, odom_pose)
        except WorkerLost as exc:
            log.error("%s", exc)

    def pose(self, odom_pose: Pose | None = None) -> Pose | None:
        try:
            pose: Pose | None = self._call("pose", odom_pose)
        except WorkerLost:
            return None
        return pose

    def map_image(self) -> Any | None:
        try:
            return self._call("map")
        except WorkerLost:
            return None

    def trajectory(self) -> FloatArray:
        try:
            path: FloatArray = self._call("trajectory")
        except WorkerLost:
            return np.zeros((0, 3))
        return path

    def counters(self) -> dict[str, int]:
        with self._counters_lock:
            out = dict(self._counters)
        out["worker_restarts"] = self.restarts
        return out


if __name__ == "__main__":
    sys.exit(main())
