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

**The stop.** When the agent stops (:meth:`ProcessMapper.begin_stop`, first thing in ``Agent.stop``), the
parent sends ``("stop",)`` at once, even while a request is out, and wakes the SLAM thread from its wait
(a self-pipe beside the socket): that request is abandoned (an update is answered ``rejected``), no scan
or fix is sent any more and no new child is started. The child looks at its socket at every ``give_way``
point of the filter (between the stages of an update, every 64 nodes of a loop closure's map rebuild): a
message there, while it serves a request, can only be the stop, so it leaves the update unfinished (the
maps stay as they were before it: the rebuild is built aside and put in place only whole) and from then
on answers only for the map, the trajectory, the pose and the final optimisation (``finish``). Everything
asked after the stop (the final map, the final optimisation, the map again) is answered within ``grace_s``
of it (:data:`_STOP_GRACE_S`), or the child is killed and the log says what that lost (a final map
not yet taken out; ``mapper.save_final_map`` takes it out before the optimisation). Then the agent hangs
up and the child exits at once (``os._exit``: no interpreter teardown), by the same deadline (at least 2 s
after the hang-up) or killed.
Where the system allows it, the child gets the agent's CPU priority back at the stop (its nice +5 was for
the hot path, which has stopped).

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
from agent.runtime.mapper import MapperStep, Pose, RbpfMapper, make_local_mapper
from agent.runtime.types import AbsoluteFix
from agent.slam.malloc import tune_malloc
from drivers.child_process import child_connection, kill_child, start_child, stop_child
from drivers.samples import Scan

__all__ = ["ProcessMapper", "WorkerLost", "WorkerStopping"]

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
# From the agent's stop: how long the SLAM process has to hand over the final map and trajectory before it
# is killed (the stop's other waits, the threads' 1.5 s and the map saver's up to 5 s, run alongside;
# systemd's TimeoutStopSec is 15 s). On the robot the answers take well under a second.
_STOP_GRACE_S = 8.0
# After the child died, the next one starts no sooner than this (a scan that kills it would otherwise have
# a new interpreter started for every scan).
_RESTART_AFTER_S = 5.0


class WorkerLost(RuntimeError):
    """The SLAM process died or stopped answering."""


class WorkerStopping(WorkerLost):
    """The agent is stopping: the request was abandoned (or never sent), not lost to a fault."""


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


class _Interrupted(Exception):
    """Raised at a ``give_way`` point of the filter when the agent asked the process to stop."""


def _stop_check(conn: multiprocessing.connection.Connection) -> Callable[[], None]:
    """The filter's ``give_way`` in the child: a message on the socket while a request is being served can
    only be the agent's stop (the agent sends one request at a time otherwise), so the request is left."""

    def give_way() -> None:
        if conn.poll(0):
            raise _Interrupted

    return give_way


def _serve(conn: multiprocessing.connection.Connection) -> None:
    """Build the mapper from the first message, then answer every request until the parent hangs up."""
    try:
        first = conn.recv()
    except (EOFError, OSError):
        return
    if first is None:  # hung up before the start (the agent stopped as it started this process)
        return
    config, mount = first
    start = _StartPose()
    mapper, why = make_local_mapper(config, mount, start)
    conn.send((mapper is not None, why, mapper.name if mapper is not None else ""))
    if mapper is None:
        return
    if isinstance(mapper, RbpfMapper):  # before its first update, which hands it to the filter
        mapper.give_way = _stop_check(conn)
    shared_kb, shared_at = 0, -math.inf
    stopping = False  # the agent is stopping: no scan or fix reaches the filter any more
    interrupted = 0
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return
        if request is None:
            return
        kind = request[0]
        reply: Any = None
        rebuilds = mapper.counters().get("loop_rebuilds", 0)
        try:
            if kind == "stop":
                stopping = True
            elif kind == "update":
                _, scan, odom_pose, start.pose = request
                if stopping:
                    reply = MapperStep("rejected", reason="the SLAM process is stopping", stopped=True)
                else:
                    reply = mapper.update(scan, odom_pose)
            elif kind == "fix":
                _, fix, odom_pose = request
                if not stopping:
                    mapper.add_fix(fix, odom_pose)
            elif kind == "pose":
                reply = mapper.pose(request[1])
            elif kind == "map":
                reply = mapper.map_image()
            elif kind == "trajectory":
                reply = mapper.trajectory()
            elif kind == "finish":  # the final optimisation, asked after the stop, before the final map
                reply = mapper.finish()
            else:
                reply = ValueError(f"unknown request {kind!r}")
        except _Interrupted:
            # The filter's state is half-way through this update: it takes nothing more. Its maps are those
            # from before the update (a loop closure's rebuild is put in place only whole).
            stopping = True
            interrupted += 1
            if kind == "finish":  # not run: the map is the one from before it
                log.info("the SLAM process left its final optimisation unfinished for the stop")
                reply = False
            else:
                what = "filter update"
                if mapper.counters().get("loop_rebuilds", 0) > rebuilds:
                    what = "loop closure's map rebuild (the map is the one from before that loop closure)"
                # A step, not an exception: this module runs as __main__ here, and its classes would not
                # unpickle.
                reply = MapperStep(
                    "rejected",
                    reason=f"the SLAM process left its {what} unfinished for the stop",
                    stopped=True,
                )
        counters = dict(mapper.counters())
        counters["worker_peak_rss_kb"] = _peak_rss_kb()
        if time.monotonic() - shared_at >= _SHARED_EVERY_S:
            shared_kb, shared_at = _shared_kb(), time.monotonic()
        counters["worker_shared_kb"] = shared_kb
        counters["worker_interrupted"] = interrupted
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
    # Hung up on: the agent is stopping and waits for this exit. Nothing here is left to write (no files;
    # stderr flushed), so the interpreter's teardown (freeing every module and array, seconds for a niced
    # process on a busy machine) is skipped: the kernel frees the memory at once.
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):
            stream.flush()
    os._exit(0)


# -- the parent -----------------------------------------------------------------------------------------
class ProcessMapper:
    """A :class:`~agent.runtime.mapper.ScanMapper` (the one ``make_local_mapper`` builds for ``config``)
    running in a child process. Same calls, same results; called from the SLAM thread (``counters`` from
    any; :meth:`begin_stop` from the thread that stops the agent)."""

    # The child's module (``python -m MODULE FD``); a test runs a child of its own making.
    worker_module = "agent.runtime.slam_worker"

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
        # Sending is also done by begin_stop, while a request is out: requests sent and replies received
        # on this connection (the replies come in order; one to an abandoned request is read and dropped).
        self._send_lock = threading.Lock()
        self._sent = 0
        self._received = 0
        self._conn: multiprocessing.connection.Connection | None = None
        self._process: subprocess.Popen[bytes] | None = None
        self._next_spawn_s = 0.0
        self._closed = False
        # Set by begin_stop: until when the child may take to answer (monotonic s); None: not stopping.
        self._stop_deadline: float | None = None
        self._grace_s = _STOP_GRACE_S
        # After the stop began: the final map was asked for / taken out of the child (for the log).
        self._final_map_asked = False
        self._final_map = False
        # Written once by begin_stop: wakes the SLAM thread waiting for a reply.
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_w, False)
        # The map last saved as the robot went (None: none yet); a child started after a death continues
        # it rather than starting the map again (``create_agent`` sets it to the map saver's).
        self.resume_map: Callable[[], Path | None] = lambda: None
        try:
            self._spawn(config)
        except BaseException:
            self._close_wake()
            raise

    # -- the child's life ------------------------------------------------------------------------------
    def _spawn(self, config: SlamConfig) -> None:
        blas = {"OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS", "1")}
        process, conn = start_child(self.worker_module, blas)
        with self._send_lock:  # the config first on the connection, before a stop begin_stop may send
            self._process, self._conn = process, conn
            self._sent, self._received = 1, 0
            interruptible = self._stop_deadline is None
            with contextlib.suppress(OSError):  # gone at once: the wait below says so
                conn.send((config, self.mount))
        self._started = False
        if not interruptible:  # the stop began as this process started: it answers what comes after
            raise WorkerStopping("the agent is stopping: the new SLAM process takes no scans")
        ok, why, name = self._await(conn, 1, _START_TIMEOUT_S, interruptible)
        if not ok:
            self._stop_child()
            raise ValueError(f"the SLAM process could not build its filter: {why}")
        self.name = str(name)

    def _exchange(self, message: object, timeout_s: float = _REPLY_TIMEOUT_S) -> Any:
        """Send ``message`` and wait for its reply: at most ``timeout_s``, and once the agent is stopping
        until the stop's deadline. A request out when the stop begins is abandoned (WorkerStopping)."""
        conn = self._conn
        if conn is None:
            raise WorkerLost("the SLAM process is not running")
        try:
            with self._send_lock:
                interruptible = self._stop_deadline is None
                conn.send(message)
                self._sent += 1
                mine = self._sent
        except OSError as exc:
            raise WorkerLost(f"the SLAM process is gone: {exc}") from exc
        return self._await(conn, mine, timeout_s, interruptible)

    def _await(
        self, conn: multiprocessing.connection.Connection, mine: int, timeout_s: float, interruptible: bool
    ) -> Any:
        """The reply to request number ``mine``, those before it (abandoned) read and dropped. Up to
        ``timeout_s``, and no later than the stop's deadline; ``interruptible``: sent before the stop
        began, so the stop ends the wait (WorkerStopping)."""
        waiting_on: list[Any] = [conn, self._wake_r] if interruptible else [conn]
        try:
            deadline = time.monotonic() + timeout_s
            while True:
                stop_deadline = self._stop_deadline
                limit = deadline if stop_deadline is None else min(deadline, stop_deadline)
                ready = multiprocessing.connection.wait(waiting_on, max(0.0, limit - time.monotonic()))
                if conn in ready:
                    reply = conn.recv()
                    self._received += 1
                    if self._received == mine:
                        return reply
                    self._dropped(reply)
                elif ready:
                    raise WorkerStopping("the agent is stopping: the request to the SLAM process was left")
                elif time.monotonic() >= limit:
                    if stop_deadline is not None and limit == stop_deadline:
                        raise WorkerLost(
                            f"the SLAM process gave no answer within {self._grace_s:g} s of the stop"
                        )
                    raise WorkerLost(f"the SLAM process gave no answer in {timeout_s:g} s")
        except (EOFError, OSError) as exc:
            raise WorkerLost(f"the SLAM process is gone: {exc}") from exc

    def _dropped(self, reply: Any) -> None:
        """A reply to a request abandoned at the stop (or the stop's own): its counters kept."""
        if isinstance(reply, tuple) and len(reply) == 3 and isinstance(reply[1], dict):
            self._take_counters(reply[0], reply[1])
        # else the answer to a new child's start

    def _take_counters(self, answer: Any, counters: dict[str, int]) -> None:
        """The counters a reply came with; an update the child left unfinished for the stop is logged."""
        with self._counters_lock:
            before = self._counters.get("worker_interrupted", 0)
            self._counters = counters
        if counters.get("worker_interrupted", 0) > before and isinstance(answer, MapperStep):
            log.info("%s: its scan is not in the map", answer.reason)

    def _call(self, *request: object) -> Any:
        """One request, its reply; the counters and whether the filter has started come with it."""
        with self._call_lock:
            if self._closed:
                raise WorkerLost("the SLAM process was closed")
            stopping = self._stop_deadline is not None
            if stopping and request[0] in ("update", "fix"):
                raise WorkerStopping("the agent is stopping: no more scans for the SLAM process")
            if self._conn is None:
                if stopping:
                    raise WorkerLost("the SLAM process is not running (the agent is stopping)")
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
            except WorkerStopping:
                raise  # the child is well: it answers the stop and what is asked after it
            except WorkerLost as exc:
                if self._stop_deadline is not None:
                    self._kill_child(str(exc))
                else:
                    self._next_spawn_s = time.monotonic() + _RESTART_AFTER_S
                    self._drop_child()
                raise
        self._take_counters(reply, counters)
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

    def begin_stop(self, grace_s: float = _STOP_GRACE_S) -> None:
        """The agent is stopping (idempotent; returns at once): the child is told now, even in the middle
        of an update, which it then leaves at its next ``give_way`` point; a request out is abandoned
        (the SLAM thread's wait ends now); no scan or fix is sent any more, no new child started. What is
        asked from now on (the final map, the trajectory) is waited for until ``grace_s`` from now, then
        the child is killed."""
        if self._closed or self._stop_deadline is not None:
            return
        self._grace_s = grace_s
        self._stop_deadline = time.monotonic() + grace_s
        with self._send_lock:
            conn = self._conn
            if conn is not None:
                try:
                    conn.send(("stop",))
                    self._sent += 1
                except OSError:
                    pass  # gone: the next request says so
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"\0")
        self._renice()
        log.info(
            "stopping the SLAM process (the agent is stopping): %g s to hand over its final map", grace_s
        )

    def _renice(self) -> None:
        """The child back at the agent's own CPU priority where the system allows it (root, or a NICE
        limit that does): its lower one was for the hot path, which has stopped, and on a busy machine it
        hands over the final map sooner. Refused (an unprivileged service): it stays niced."""
        process = self._process
        if process is None:
            return
        try:
            os.setpriority(os.PRIO_PROCESS, process.pid, os.getpriority(os.PRIO_PROCESS, 0))
        except OSError as exc:
            log.debug("the SLAM process keeps its lower CPU priority for the stop: %s", exc)

    def close(self) -> None:
        """Stop the child for good (idempotent): later calls answer as a mapper without a filter. After
        :meth:`begin_stop` the child is hung up on at once and has until the stop's deadline (at least
        2 s) to exit, the replies it still owes read meanwhile (so that it is never blocked sending one);
        then it is killed."""
        if self._closed:
            return
        stopping = self._stop_deadline is not None
        wait_s = 2.0 if self._stop_deadline is None else max(0.0, self._stop_deadline - time.monotonic())
        locked = self._call_lock.acquire(timeout=wait_s + 1.0)
        try:
            self._closed = True
            if stopping:
                self._hang_up()
            else:
                self._stop_child()
        finally:
            if locked:
                self._call_lock.release()
            self._close_wake()

    def _hang_up(self) -> None:
        """After the stop: ``None`` to the child, then its exit waited for until the stop's deadline (at
        least 2 s from now), what it still sends read and dropped; killed after that."""
        process, conn = self._process, self._conn
        self._process = self._conn = None
        self._started = False
        if process is None or conn is None:
            return
        assert self._stop_deadline is not None
        deadline = max(self._stop_deadline, time.monotonic() + 2.0)
        with self._send_lock, contextlib.suppress(OSError):
            conn.send(None)
        try:
            while process.poll() is None:
                left = deadline - time.monotonic()
                if left <= 0.0 or not conn.poll(left):
                    break
                self._dropped(conn.recv())
        except (EOFError, OSError):  # its end closed: it is exiting
            with contextlib.suppress(subprocess.TimeoutExpired):
                process.wait(max(0.0, deadline - time.monotonic()))
        conn.close()
        if process.poll() is None:
            self._process = process
            self._kill_child(f"the SLAM process had not exited {self._grace_s:g} s after the stop began")
            return
        log.info("SLAM process stopped (exit status %s)", process.returncode)

    def _close_wake(self) -> None:
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._wake_r = self._wake_w = -1

    def _kill_child(self, why: str) -> None:
        """After the stop: the child is killed, and the log says what that lost."""
        process, conn = self._process, self._conn
        self._process = self._conn = None
        self._started = False
        if process is None:
            return
        if self._final_map_asked and not self._final_map:
            log.error(
                "%s: killing it; its final map was not taken out (the map on disk, if any, is the last "
                "one saved as the robot went)",
                why,
            )
        else:
            lost = "its final map had been taken out" if self._final_map else "no final map was asked of it"
            log.warning("%s: killing it (%s)", why, lost)
        kill_child(process, conn)

    def _drop_child(self) -> None:
        """A child that died or stopped answering: killed if it is still there (asking it to stop is of no
        use: it is not reading). The next call starts a new one."""
        process, conn = self._process, self._conn
        self._process = self._conn = None
        self._started = False
        if process is not None and process.poll() is None:
            kill_child(process)
        if conn is not None:
            conn.close()

    def _stop_child(self) -> None:
        """Stop the child (the next call starts a new one, unless closed or stopping)."""
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
        except WorkerStopping as exc:
            return MapperStep("rejected", reason=str(exc), stopped=True)
        except WorkerLost as exc:
            log.error("%s", exc)
            return MapperStep("rejected", reason=str(exc))
        return step

    def add_fix(self, fix: AbsoluteFix, odom_pose: Pose) -> None:
        try:
            self._call("fix", fix, odom_pose)
        except WorkerStopping:
            pass
        except WorkerLost as exc:
            log.error("%s", exc)

    def pose(self, odom_pose: Pose | None = None) -> Pose | None:
        try:
            pose: Pose | None = self._call("pose", odom_pose)
        except WorkerLost:
            return None
        return pose

    def map_image(self) -> Any | None:
        stopping = self._stop_deadline is not None
        self._final_map_asked = self._final_map_asked or stopping
        try:
            image = self._call("map")
            self._final_map = self._final_map or (stopping and image is not None)
            return image
        except WorkerStopping:
            return None  # a periodic fetch the stop cut short: the final one comes after
        except WorkerLost as exc:
            if self._stop_deadline is not None:
                log.error("no final map from the SLAM process: %s", exc)
            return None

    def finish(self) -> bool:
        """The child's final optimisation (``RbpfMapper.finish``), waited for until the stop's deadline
        after the stop (then the child is killed: take the final map out first, as
        ``mapper.save_final_map`` does)."""
        try:
            return bool(self._call("finish"))
        except WorkerLost as exc:
            if not isinstance(exc, WorkerStopping):
                log.error("no final optimisation from the SLAM process: %s", exc)
            return False

    def trajectory(self) -> FloatArray:
        try:
            path: FloatArray = self._call("trajectory")
        except WorkerLost as exc:
            if self._stop_deadline is not None and not isinstance(exc, WorkerStopping):
                log.error("no final trajectory from the SLAM process: %s", exc)
            return np.zeros((0, 3))
        return path

    def counters(self) -> dict[str, int]:
        with self._counters_lock:
            out = dict(self._counters)
        out["worker_restarts"] = self.restarts
        return out


if __name__ == "__main__":
    sys.exit(main())
