"""The fleet loop: the agent's end of the local protocol (``agent.fleet.local_protocol``) on a Unix socket.

The agent listens on ``[fleet] socket`` (AF_UNIX, stream; a stale socket file is replaced; a folder that is
not there is not made: it is retried every ``LISTEN_RETRY_S``, said once in the log) and serves one
bridge at a time (a new connection replaces the old one). To it, every ``1 / pose_rate_hz``: this robot's
fused pose; every ``status_period_s``: the status flags; with the next pose: each goal status the agent
sends (the command loop's answers). From it: the other robots' poses (kept in :attr:`FleetLoop.peers`,
newest per robot) and goals for this robot (counted and refused for now: fleet goals are not yet a
command source, docs/fleet.md). This process opens no network socket: the bridge is another process.

Sends never block the loop for long: a bridge that stops reading for ``SEND_TIMEOUT_S`` is disconnected
(counted) and may reconnect. A malformed frame from it closes the connection (counted).
"""

from __future__ import annotations

import collections
import contextlib
import logging
import os
import select
import socket
import stat
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from agent.fleet.local_protocol import (
    FrameDecoder,
    GoalMessage,
    GoalStateMessage,
    LocalProtocolError,
    Message,
    PeerPoseMessage,
    PoseMessage,
    StatusMessage,
    encode,
)
from agent.fusion import Estimate
from agent.runtime.health import Heartbeat
from firmware_protocol.command_frame import GoalStatus
from firmware_protocol.pose_frame import PoseFlags

__all__ = ["LISTEN_RETRY_S", "SEND_TIMEOUT_S", "FleetLoop"]

log = logging.getLogger(__name__)

SEND_TIMEOUT_S = 0.05
LISTEN_RETRY_S = 2.0
_IDLE_WAIT_S = 0.25
_QUEUED_STATUSES = 64


class FleetLoop:
    """Serves the bridge. ``pose()`` gives the fused pose and flags, ``status_bits()`` the
    :class:`StatusMessage` bits; :meth:`on_status` is a listener on the command loop's goal statuses."""

    def __init__(
        self,
        path: Path,
        pose_rate_hz: float,
        status_period_s: float,
        pose: Callable[[], tuple[Estimate, PoseFlags]],
        status_bits: Callable[[], int],
        clock_ns: Callable[[], int],
    ) -> None:
        self.path = path
        self.period_s = 1.0 / pose_rate_hz
        self.status_period_s = status_period_s
        self.pose = pose
        self.status_bits = status_bits
        self.clock_ns = clock_ns
        self.counts: collections.Counter[str] = collections.Counter()
        # The other robots' newest poses: name -> (pose, agent clock ns when it came).
        self.peers: dict[str, tuple[PoseMessage, int]] = {}
        self._lock = threading.Lock()
        self._statuses: collections.deque[GoalStatus] = collections.deque(maxlen=_QUEUED_STATUSES)
        self._server: socket.socket | None = None
        self._client: socket.socket | None = None
        self._decoder = FrameDecoder()

    def _count(self, what: str) -> None:
        with self._lock:
            self.counts[what] += 1

    def counters(self) -> dict[str, int]:
        """The loop's counters, named ``fleet_*`` (for the agent's status)."""
        with self._lock:
            return {f"fleet_{key}": n for key, n in self.counts.items()}

    # -- listeners -------------------------------------------------------------------------------------
    def on_status(self, status: GoalStatus) -> None:
        """A goal status the agent sent its controller: forwarded to the fleet too."""
        with self._lock:
            self._statuses.append(status)

    # -- the loop --------------------------------------------------------------------------------------
    def run(self, beat: Heartbeat, *, stop: threading.Event) -> None:
        while not self._listen():
            # A folder that is not there yet, a file in the way: said once, retried; the robot works alone.
            beat.beat()
            if stop.wait(LISTEN_RETRY_S):
                return
        next_pose_ns = next_status_ns = 0
        try:
            while not stop.is_set():
                beat.beat()
                now = self.clock_ns()
                if self._client is not None:
                    if now >= next_pose_ns:
                        next_pose_ns = now + int(self.period_s * 1e9)
                        self._send_pose()
                    if now >= next_status_ns:
                        next_status_ns = now + int(self.status_period_s * 1e9)
                        self._send(StatusMessage(now // 1000, int(self.pose()[1]), self.status_bits()))
                    self._send_goal_states(now)
                # Asleep until the next pose or status is due; with no bridge, until one connects (select
                # wakes on the listening socket), looking at the stop event four times a second.
                wait_s = _IDLE_WAIT_S
                if self._client is not None:
                    wait_s = min(
                        wait_s, max(0.0, (min(next_pose_ns, next_status_ns) - self.clock_ns()) * 1e-9)
                    )
                self._poll(wait_s)
        finally:
            self.close()

    def _send_pose(self) -> None:
        estimate, flags = self.pose()
        message = PoseMessage(
            max(estimate.t_ns, 0) // 1000,
            estimate.x_m,
            estimate.y_m,
            estimate.yaw_rad,
            estimate.sigma_xy_m,
            estimate.sigma_yaw_rad,
            int(flags),
        )
        if self._send(message):
            self._count("poses_sent")

    def _send_goal_states(self, now_ns: int) -> None:
        with self._lock:
            pending = list(self._statuses)
            self._statuses.clear()
        for s in pending:
            remaining = s.remaining_m if s.remaining_m is not None else float("nan")
            self._send(GoalStateMessage(now_ns // 1000, s.goal_id, int(s.state), int(s.reason), remaining))

    def _listen(self) -> bool:
        """Listen on the socket path; False (said once, counted) when it cannot be done now."""
        server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            with contextlib.suppress(FileNotFoundError):
                if stat.S_ISSOCK(os.lstat(self.path).st_mode):
                    os.unlink(self.path)  # a stale socket of an earlier run
            server.bind(os.fspath(self.path))
            server.listen(1)
        except OSError as exc:
            server.close()
            if not self.counts["listen_failures"]:
                log.warning(
                    "fleet: cannot listen on %s: %s (retrying every %g s)", self.path, exc, LISTEN_RETRY_S
                )
            self._count("listen_failures")
            return False
        server.setblocking(False)
        self._server = server
        log.info("fleet: serving the bridge on %s", self.path)
        return True

    def _poll(self, timeout_s: float) -> None:
        server, client = self._server, self._client
        readers = [s for s in (server, client) if s is not None]
        readable, _, _ = select.select(readers, [], [], timeout_s)
        if server is not None and server in readable:
            with contextlib.suppress(BlockingIOError, InterruptedError):
                conn, _ = server.accept()
                if self._client is not None:
                    self._drop("replaced by a new connection")
                conn.settimeout(SEND_TIMEOUT_S)
                self._client, self._decoder = conn, FrameDecoder()
                self._count("bridge_connections")
                log.info("fleet: bridge connected")
        if client is not None and client in readable and client is self._client:
            self._receive(client)

    def _receive(self, client: socket.socket) -> None:
        try:
            data = client.recv(65536)
        except (TimeoutError, BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._drop(f"receive failed: {exc}")
            return
        if not data:
            self._drop("bridge closed the connection")
            return
        try:
            messages = self._decoder.feed(data)
        except LocalProtocolError as exc:
            self._count("malformed_frames")
            self._drop(f"malformed frame: {exc}")
            return
        for message in messages:
            self._take(message)

    def _take(self, message: Message) -> None:
        if isinstance(message, PeerPoseMessage):
            with self._lock:
                self.peers[message.robot] = (message.pose, self.clock_ns())
            self._count("peer_poses")
        elif isinstance(message, GoalMessage):
            # Not yet a command source (docs/fleet.md, "Missing"): counted, never driven.
            self._count("goals_refused")
            log.info("fleet: goal %d refused (fleet goals are not driven yet)", message.goal_id)
        else:
            self._count("unexpected_messages")

    def _send(self, message: Message) -> bool:
        client = self._client
        if client is None:
            return False
        try:
            client.sendall(encode(message))
        except TimeoutError:
            self._count("send_timeouts")
            self._drop("the bridge stopped reading")
            return False
        except OSError as exc:
            self._drop(f"send failed: {exc}")
            return False
        return True

    def _drop(self, reason: str) -> None:
        client, self._client = self._client, None
        if client is not None:
            with contextlib.suppress(OSError):
                client.close()
            self._count("bridge_disconnects")
            log.info("fleet: bridge gone: %s", reason)

    def peer_poses(self) -> dict[str, tuple[PoseMessage, int]]:
        with self._lock:
            return dict(self.peers)

    def close(self) -> None:
        self._drop("stopping")
        server, self._server = self._server, None
        if server is not None:
            with contextlib.suppress(OSError):
                server.close()
            with contextlib.suppress(OSError):
                os.unlink(self.path)

    @classmethod
    def for_agent(cls, agent: Any) -> FleetLoop:
        """The loop for an ``agent.runtime.agent.Agent`` with ``[fleet] socket`` set: its fused pose, its
        readiness, and its goal statuses (a listener on its command loop)."""
        fc = agent.config.fleet
        assert fc.socket is not None

        def bits() -> int:
            localized = agent.pose()[1] & (PoseFlags.VLP | PoseFlags.SLAM | PoseFlags.ODOMETRY)
            return (StatusMessage.READY if agent.health.is_ready else 0) | (
                StatusMessage.LOCALIZED if localized else 0
            )

        loop = cls(fc.socket, fc.pose_rate_hz, fc.status_period_s, agent.pose, bits, agent.clock_ns)
        if agent.commands is not None:
            agent.commands.listeners.append(loop.on_status)
        return loop
