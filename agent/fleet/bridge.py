"""The bridge: the agent's Unix socket (``agent.fleet.local_protocol``) <-> Zenoh (``agent.fleet.payloads``).

It runs in its own process (``vlp-agent bridge``), so the agent opens no network socket. Out, under
``<prefix>/<robot>/...``: ``pose`` for each pose the agent sends, ``status`` every ``status_period_s`` (the
agent's flags and the bridge's counters; ``"agent": false`` while no agent is connected), ``goal_state``
for each goal status, ``map`` and ``topology`` for each snapshot the agent sends (laser-derived). In:
``<prefix>/*/pose`` of the other robots, handed to the agent as peer poses, and ``<prefix>/<robot>/goal``,
handed to the agent as goals. A malformed or oversized message from the network
is counted (``rejected_<kind>``) and dropped: it never reaches the agent and never stops the bridge. The
agent going away is no fault: the bridge reconnects every ``reconnect_s`` and keeps its Zenoh session.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import os
import select
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

from agent.fleet import payloads
from agent.fleet.bridge_config import BridgeConfig
from agent.fleet.local_protocol import (
    FrameReader,
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
from agent.fleet.ros2_out import Ros2Out
from drivers.errors import DeviceNotFound
from firmware_protocol.command_frame import GoalReason, GoalState
from firmware_protocol.errors import ProtocolError

__all__ = ["Bridge"]

log = logging.getLogger(__name__)

SEND_TIMEOUT_S = 0.05


class Bridge:
    """``run(stop)`` until ``stop`` is set. ``open_session(zenoh_config)`` opens the Zenoh session
    (``zenoh.open`` unless a test gives another)."""

    def __init__(self, config: BridgeConfig, open_session: Callable[[Any], Any] | None = None) -> None:
        self.config = config
        self._open_session = open_session
        self.counts: collections.Counter[str] = collections.Counter()
        self._counts_lock = threading.Lock()
        self._agent: socket.socket | None = None
        self._agent_lock = threading.Lock()  # sends to the agent come from Zenoh's threads too
        self._status: StatusMessage | None = None
        self._session: Any = None
        self._publishers: dict[str, Any] = {}
        self._ros2: Ros2Out | None = None  # [ros2] enabled: the same pose, map, status as ROS 2 topics
        self.connected = threading.Event()  # the Zenoh session is up and declared

    def count(self, what: str, n: int = 1) -> None:
        with self._counts_lock:
            self.counts[what] += n

    def counters(self) -> dict[str, int]:
        with self._counts_lock:
            return dict(self.counts)

    # -- Zenoh ---------------------------------------------------------------------------------------------
    def _key(self, kind: str) -> str:
        return payloads.key(self.config.key_prefix, self.config.robot, kind)

    def _open(self) -> None:
        import zenoh

        opener = self._open_session or zenoh.open
        z = self.config.zenoh
        try:
            self._session = session = opener(z.zenoh_config())
        except Exception as exc:  # zenoh's ZError: an endpoint that cannot be resolved, bound or parsed
            where = f"listen {list(z.listen)}, connect {list(z.connect)}"
            raise DeviceNotFound(f"cannot open the Zenoh session ({where}): {exc}", "zenoh") from exc
        for kind in ("pose", "status", "goal_state", "map", "topology"):
            self._publishers[kind] = session.declare_publisher(self._key(kind))
        prefix = self.config.key_prefix
        self._subscribers = [
            session.declare_subscriber(f"{prefix}/*/pose", self._on_peer_pose),
            session.declare_subscriber(self._key("goal"), self._on_goal),
        ]
        if self.config.ros2.enabled:
            self._ros2 = Ros2Out(self.config.ros2, session, self.count)
        self.connected.set()
        log.info(
            "bridge %s: Zenoh %s, listen %s, connect %s, multicast scouting %s",
            self.config.robot,
            self.config.zenoh.mode,
            list(self.config.zenoh.listen),
            list(self.config.zenoh.connect),
            "on" if self.config.zenoh.multicast_scouting else "off",
        )

    def _publish(self, kind: str, data: bytes) -> None:
        try:
            self._publishers[kind].put(data)
        except Exception as exc:  # zenoh raises its own ZError; a failed put is counted, not fatal
            self.count(f"publish_errors_{kind}")
            log.warning("bridge: publishing %s failed: %s", kind, exc)
            return
        self.count(f"published_{kind}")

    @staticmethod
    def _payload(sample: Any, limit: int) -> bytes:
        """The sample's bytes, refused before copying when larger than ``limit``."""
        zbytes = sample.payload
        with contextlib.suppress(TypeError):
            if len(zbytes) > limit:
                raise payloads.FleetPayloadError(f"payload of {len(zbytes)} bytes, at most {limit}")
        return bytes(zbytes.to_bytes())

    def _on_peer_pose(self, sample: Any) -> None:
        try:
            robot = payloads.robot_of(self.config.key_prefix, str(sample.key_expr))
            if robot == self.config.robot:
                return  # our own, published above
            pose = payloads.decode_pose(self._payload(sample, payloads.MAX_PAYLOAD), robot)
        except ProtocolError as exc:
            self._reject("pose", exc)
            return
        except Exception as exc:  # never let a bad message take a Zenoh thread down
            self._reject("pose", exc)
            return
        self.count("peer_poses_in")
        self._to_agent(PeerPoseMessage(robot, pose))

    def _on_goal(self, sample: Any) -> None:
        try:
            goal = payloads.decode_goal(self._payload(sample, payloads.MAX_PAYLOAD), self.config.robot)
        except ProtocolError as exc:
            self._reject("goal", exc)
            return
        except Exception as exc:
            self._reject("goal", exc)
            return
        self.count("goals_in")
        if not self._to_agent(goal):
            # No agent to drive it: the sender hears so at once instead of waiting for a status.
            now_us = time.monotonic_ns() // 1000
            refused = GoalStateMessage(now_us, goal.goal_id, GoalState.REJECTED, GoalReason.NOT_LOCALIZED)
            self._publish("goal_state", payloads.encode_goal_state(self.config.robot, refused))

    def _reject(self, kind: str, exc: Exception) -> None:
        self.count(f"rejected_{kind}")
        log.info("bridge: rejected a %s message from the network: %s", kind, exc)

    # -- the agent's socket --------------------------------------------------------------------------------
    def _to_agent(self, message: Message) -> bool:
        with self._agent_lock:
            agent = self._agent
            if agent is None:
                self.count("to_agent_dropped_no_agent")
                return False
            try:
                agent.sendall(encode(message))
            except (OSError, LocalProtocolError) as exc:
                self.count("to_agent_send_errors")
                log.info("bridge: sending to the agent failed: %s", exc)
                return False
        self.count("to_agent")
        return True

    def _connect(self) -> socket.socket | None:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            sock.connect(os.fspath(self.config.socket))
        except OSError as exc:
            sock.close()
            log.debug("bridge: agent socket %s: %s", self.config.socket, exc)
            return None
        sock.settimeout(SEND_TIMEOUT_S)
        with self._agent_lock:
            self._agent = sock
        self.count("agent_connections")
        log.info("bridge: connected to the agent at %s", self.config.socket)
        return sock

    def _disconnect(self, reason: str) -> None:
        with self._agent_lock:
            sock, self._agent = self._agent, None
        self._status = None
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.close()
            self.count("agent_disconnects")
            log.info("bridge: agent gone: %s", reason)

    def _from_agent(self, message: Message) -> None:
        robot = self.config.robot
        if isinstance(message, PoseMessage):
            self._publish("pose", payloads.encode_pose(robot, message))
            if self._ros2 is not None:
                self._ros2.pose(message)
        elif isinstance(message, StatusMessage):
            self._status = message
        elif isinstance(message, GoalStateMessage):
            self._publish("goal_state", payloads.encode_goal_state(robot, message))
        elif isinstance(message, MapMessage):
            self._publish("map", payloads.encode_map(robot, message))
            if self._ros2 is not None:
                self._ros2.map(message)
        elif isinstance(message, TopologyMessage):
            try:
                data = payloads.encode_topology(robot, message)
            except payloads.FleetPayloadError as exc:
                self.count("agent_bad_topology")
                log.info("bridge: the agent's topology is not valid GeoJSON: %s", exc)
                return
            if len(data) > payloads.MAX_TOPOLOGY_PAYLOAD:
                self.count("oversized_topology")
                return
            self._publish("topology", data)
        else:
            self.count("agent_unexpected_messages")

    def _publish_status(self) -> None:
        data = payloads.encode_status(self.config.robot, self._status, self.counters())
        self._publish("status", data)
        if self._ros2 is not None:
            self._ros2.status(data.decode())

    # -- the loop ------------------------------------------------------------------------------------------
    def run(self, stop: threading.Event) -> None:
        self._open()
        reader = FrameReader()
        next_status = next_connect = 0.0
        try:
            while not stop.is_set():
                now = time.monotonic()
                if now >= next_status:
                    next_status = now + self.config.status_period_s
                    self._publish_status()
                agent = self._agent
                if agent is None and now >= next_connect:
                    next_connect = now + self.config.reconnect_s
                    agent = self._connect()
                    reader = FrameReader()
                deadline = next_status if agent is not None else min(next_status, next_connect)
                wait = max(0.0, deadline - time.monotonic())
                if agent is None:
                    stop.wait(min(wait, 0.25))
                    continue
                readable, _, _ = select.select([agent], [], [], min(wait, 0.25))
                if not readable:
                    continue
                result = receive(agent, reader)
                if result.malformed:
                    self.count("agent_malformed_frames")
                for message in result.messages:
                    self._from_agent(message)
                if result.close is not None:
                    self._disconnect(result.close)
        finally:
            self.close()

    def close(self) -> None:
        self._disconnect("bridge stopping")
        ros2_out, self._ros2 = self._ros2, None
        if ros2_out is not None:
            ros2_out.close()
        session, self._session = self._session, None
        if session is not None:
            with contextlib.suppress(Exception):
                session.close()
