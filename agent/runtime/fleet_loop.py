"""The fleet loop: the agent's end of the local protocol (``agent.fleet.local_protocol``) on a Unix socket.

The agent listens on ``[fleet] socket`` (AF_UNIX, stream; a stale socket file is replaced; a folder that is
not there is not made: it is retried every ``LISTEN_RETRY_S``, said once in the log) and serves one bridge at
a time (a new connection replaces the old one). To it, every ``1 / pose_rate_hz``: this robot's fused pose;
every ``status_period_s``: the status flags; with the next pose: each goal status the agent sends about a
fleet goal (the command loop's answers, with the fleet's goal id); the SLAM map (handed over by the SLAM loop
through :meth:`FleetLoop.on_map`) with the robot's recent path, and the exploration's topological graph, when
they changed (at most every ``MAP_PERIOD_S``) and every ``MAP_REFRESH_S``. From it: the other robots' poses
(kept in :attr:`FleetLoop.peers`, newest per robot, dropped when none came for ``peer_timeout_s``; the
navigation's costmap takes them as obstacles through :meth:`FleetLoop.obstacles`) and goals for this robot:
one more command source, handed to the command arbiter (``CommandArbiter.fleet_goal``: under the controller's
stop, velocity and goals, beside the missions) under a local goal id from :data:`FLEET_GOAL_IDS`. This process
opens no network socket: the bridge is another process.

Sends never block the loop for long: a bridge that stops reading for ``SEND_TIMEOUT_S`` is disconnected
(counted) and may reconnect. A malformed frame from it closes the connection (counted).
"""

from __future__ import annotations

import collections
import contextlib
import json
import logging
import math
import os
import select
import socket
import stat
import threading
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

from agent.fleet.local_protocol import (
    MAX_PATH_POINTS,
    MAX_SNAPSHOT_PAYLOAD,
    FrameReader,
    GoalMessage,
    GoalStateMessage,
    LocalProtocolError,
    MapMessage,
    Message,
    PeerPoseMessage,
    PoseMessage,
    StatusMessage,
    TopologyMessage,
    encode,
    receive,
)
from agent.fusion import Estimate
from agent.runtime.health import Heartbeat
from firmware_protocol.command_frame import NO_SEQUENCE, GoalCommand, GoalReason, GoalState, GoalStatus
from firmware_protocol.pose_frame import PoseFlags

__all__ = ["FLEET_GOAL_IDS", "LISTEN_RETRY_S", "MAP_PERIOD_S", "MAP_REFRESH_S", "SEND_TIMEOUT_S", "FleetLoop"]

log = logging.getLogger(__name__)

SEND_TIMEOUT_S = 0.05
LISTEN_RETRY_S = 2.0
# Map and topology snapshots: at most every MAP_PERIOD_S while they change, and every MAP_REFRESH_S even
# when they do not (so a listener that just came, `vlp-agent fleet map`, hears every robot's map).
MAP_PERIOD_S = 2.0
MAP_REFRESH_S = 5.0
PATH_STEP_M = 0.1  # the recent path sent with a map: a point every 10 cm, the last MAX_PATH_POINTS
_IDLE_WAIT_S = 0.25
_QUEUED_STATUSES = 64
# Fleet goals' local ids: below the missions' (agent.runtime.mission_loop.MISSION_GOAL_IDS, 0xC000..), above
# what a controller usually numbers; the fleet's own id goes back to the fleet with each status.
FLEET_GOAL_IDS = range(0x8000, 0xC000)
_ENDED = frozenset({GoalState.REJECTED, GoalState.REACHED, GoalState.FAILED, GoalState.CANCELLED})
_KEPT_GOALS = 256


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
        *,
        goals: Callable[[GoalCommand], object] | None = None,
        peer_timeout_s: float = 2.0,
        peer_radius_m: float = 0.105,
        topology: Callable[[], dict[str, Any] | None] | None = None,
    ) -> None:
        self.path = path
        self.period_s = 1.0 / pose_rate_hz
        self.status_period_s = status_period_s
        self.pose = pose
        self.status_bits = status_bits
        self.clock_ns = clock_ns
        # Takes a fleet goal (as a GoalCommand with a local id); its answers come back through on_status.
        # None: this agent drives no goals (no command line): fleet goals are answered REJECTED here.
        self.goals = goals
        self.peer_timeout_s = peer_timeout_s
        self.peer_radius_m = peer_radius_m
        self.counts: collections.Counter[str] = collections.Counter()
        # The other robots' newest poses: name -> (pose, agent clock ns when it came).
        self.peers: dict[str, tuple[PoseMessage, int]] = {}
        self._lock = threading.Lock()
        self._statuses: collections.deque[tuple[int, GoalStatus]] = collections.deque(maxlen=_QUEUED_STATUSES)
        self._fleet_ids: collections.OrderedDict[int, int] = collections.OrderedDict()  # local -> fleet id
        self._next_id = FLEET_GOAL_IDS.start
        self._server: socket.socket | None = None
        self._client: socket.socket | None = None
        self._reader = FrameReader()
        # Map snapshots: the newest map the SLAM loop handed over (on_map), the robot's recent path.
        self.topology = topology
        self._map: Any = None
        self._map_version = 0
        self._map_sent: tuple[int, int] = (-1, 0)  # (map version, ns when sent)
        self._topology_sent: tuple[bytes, int] = (b"", 0)
        self._path: collections.deque[tuple[float, float]] = collections.deque(maxlen=MAX_PATH_POINTS)

    def _count(self, what: str) -> None:
        with self._lock:
            self.counts[what] += 1

    def counters(self) -> dict[str, int]:
        """The loop's counters, named ``fleet_*`` (for the agent's status)."""
        with self._lock:
            return {f"fleet_{key}": n for key, n in self.counts.items()}

    # -- listeners -------------------------------------------------------------------------------------
    def on_status(self, status: GoalStatus) -> None:
        """A goal status the agent sent its controller: about a fleet goal, forwarded to the fleet too (with
        the fleet's goal id); the others stay between the agent and its controller."""
        with self._lock:
            fleet_id = self._fleet_ids.get(status.goal_id)
            if fleet_id is None:
                return
            self._statuses.append((fleet_id, status))
            if status.state in _ENDED:
                del self._fleet_ids[status.goal_id]

    def on_map(self, image: Any) -> None:
        """The SLAM loop's newest map (an ``agent.slam.render.OccupancyImage``); sent to the bridge within
        ``MAP_PERIOD_S``. Cheap: the conversion is done on this loop's thread when a map is due."""
        with self._lock:
            self._map = image
            self._map_version += 1

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
                    self._send_snapshots(now)
                self._expire_peers(now)
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
        if flags & (PoseFlags.VLP | PoseFlags.SLAM | PoseFlags.ODOMETRY) and math.isfinite(estimate.x_m):
            p = (float(estimate.x_m), float(estimate.y_m))
            if not self._path or math.dist(self._path[-1], p) >= PATH_STEP_M:
                self._path.append(p)

    def _send_snapshots(self, now_ns: int) -> None:
        """The map when it changed (at most every MAP_PERIOD_S) or every MAP_REFRESH_S; the topology
        alike (when there is one)."""
        with self._lock:
            image, version = self._map, self._map_version
        sent_version, sent_ns = self._map_sent
        age_s = (now_ns - sent_ns) * 1e-9
        if image is not None and (
            (version != sent_version and age_s >= MAP_PERIOD_S) or age_s >= MAP_REFRESH_S
        ):
            self._map_sent = (version, now_ns)
            message = self._map_message(image, now_ns)
            if message is not None and self._send(message):
                self._count("maps_sent")
        if self.topology is None:
            return
        blob, topo_ns = self._topology_sent
        topo_age_s = (now_ns - topo_ns) * 1e-9
        if topo_age_s < MAP_PERIOD_S:
            return
        try:
            geojson = self.topology()
        except (RuntimeError, ValueError, KeyError) as exc:  # the explorer's graph changing under us
            log.debug("fleet: topology not taken now: %s", exc)
            return
        if geojson is None:
            return
        data = json.dumps(geojson, allow_nan=False, separators=(",", ":")).encode()
        if data == blob and topo_age_s < MAP_REFRESH_S:
            return
        self._topology_sent = (data, now_ns)
        if len(data) + 8 > MAX_SNAPSHOT_PAYLOAD:
            self._count("snapshots_too_large")
            return
        if self._send(TopologyMessage(now_ns // 1000, data)):
            self._count("topologies_sent")

    def _map_message(self, image: Any, now_ns: int) -> MapMessage | None:
        from agent.fleet.maps import grid_from_image

        grid = grid_from_image(
            image.pixels,
            image.resolution_m,
            (image.origin[0], image.origin[1]),
            image.occupied_thresh,
            image.free_thresh,
        )
        h, w = grid.cells.shape
        cells = zlib.compress(grid.cells.tobytes(), 6)
        message = MapMessage(
            now_ns // 1000,
            grid.resolution_m,
            grid.origin_x_m,
            grid.origin_y_m,
            w,
            h,
            cells,
            tuple(self._path),
        )
        try:
            encode(message)
        except LocalProtocolError as exc:  # a map over the cap (or cells over MAX_MAP_CELLS)
            self._count("snapshots_too_large")
            log.warning("fleet: map not sent: %s", exc)
            return None
        return message

    def _send_goal_states(self, now_ns: int) -> None:
        with self._lock:
            pending = list(self._statuses)
            self._statuses.clear()
        for fleet_id, s in pending:
            remaining = s.remaining_m if s.remaining_m is not None else float("nan")
            if self._send(GoalStateMessage(now_ns // 1000, fleet_id, int(s.state), int(s.reason), remaining)):
                self._count("goal_states_sent")

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
                self._client, self._reader = conn, FrameReader()
                self._count("bridge_connections")
                log.info("fleet: bridge connected")
        if client is not None and client in readable and client is self._client:
            self._receive(client)

    def _receive(self, client: socket.socket) -> None:
        result = receive(client, self._reader)
        if result.malformed:
            self._count("malformed_frames")
        for message in result.messages:
            self._take(message)
        if result.close is not None:
            self._drop(result.close)

    def _take(self, message: Message) -> None:
        if isinstance(message, PeerPoseMessage):
            with self._lock:
                self.peers[message.robot] = (message.pose, self.clock_ns())
            self._count("peer_poses")
        elif isinstance(message, GoalMessage):
            self._take_goal(message)
        else:
            self._count("unexpected_messages")

    def _take_goal(self, message: GoalMessage) -> None:
        if self.goals is None:
            self._count("goals_refused")
            log.info("fleet: goal %d refused: this agent drives no goals", message.goal_id)
            now_us = self.clock_ns() // 1000
            state, reason = int(GoalState.REJECTED), int(GoalReason.UNKNOWN_TYPE)
            self._send(GoalStateMessage(now_us, message.goal_id, state, reason))
            return
        with self._lock:
            local = self._next_id
            self._next_id = local + 1 if local + 1 < FLEET_GOAL_IDS.stop else FLEET_GOAL_IDS.start
            self._fleet_ids.pop(local, None)
            self._fleet_ids[local] = message.goal_id
            while len(self._fleet_ids) > _KEPT_GOALS:  # goals that never ended (cannot happen): forgotten
                self._fleet_ids.popitem(last=False)
        self._count("goals_in")
        yaw = None if math.isnan(message.yaw_rad) else message.yaw_rad
        log.info("fleet: goal %d (here %d) to (%.2f, %.2f)", message.goal_id, local, message.x_m, message.y_m)
        self.goals(
            GoalCommand(
                NO_SEQUENCE, local, message.x_m, message.y_m, yaw, allow_unknown=message.allow_unknown
            )
        )

    def _expire_peers(self, now_ns: int) -> None:
        limit = now_ns - int(self.peer_timeout_s * 1e9)
        with self._lock:
            gone = [name for name, (_, seen_ns) in self.peers.items() if seen_ns < limit]
            for name in gone:
                del self.peers[name]
                self.counts["peers_dropped"] += 1
        for name in gone:
            log.info("fleet: %s dropped: no pose for %g s", name, self.peer_timeout_s)

    def obstacles(self) -> list[tuple[float, float, float]]:
        """The other robots as discs (x, y, radius) in the map frame: those heard within
        ``peer_timeout_s``, with ``peer_radius_m`` (for the navigation's costmap)."""
        limit = self.clock_ns() - int(self.peer_timeout_s * 1e9)
        with self._lock:
            return [
                (p.x_m, p.y_m, self.peer_radius_m) for p, seen_ns in self.peers.values() if seen_ns >= limit
            ]

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

        arbiter, commands = agent.arbiter, agent.commands
        goals: Callable[[GoalCommand], object] | None = None
        if arbiter is not None and commands is not None:

            def goals(goal: GoalCommand) -> None:
                for status in arbiter.fleet_goal(goal, commands.clock_s()):
                    commands.answer(status, None)

        radius = fc.peer_radius_m if fc.peer_radius_m > 0 else agent.config.navigation.radius_m

        def topology() -> dict[str, Any] | None:
            # The exploration's topological graph, when the robot explores with one (sp2atm).
            explorer = getattr(agent.missions, "explorer", None)
            source = getattr(explorer, "topology", None)
            return source() if callable(source) else None

        loop = cls(
            fc.socket,
            fc.pose_rate_hz,
            fc.status_period_s,
            agent.pose,
            bits,
            agent.clock_ns,
            goals=goals,
            peer_timeout_s=fc.peer_timeout_s,
            peer_radius_m=radius,
            topology=topology,
        )
        if commands is not None:
            commands.listeners.append(loop.on_status)
        if agent.navigation is not None:
            agent.navigation.others = loop.obstacles
        return loop
