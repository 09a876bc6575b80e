"""The bridge's optional ROS 2 side (``[ros2]`` in the bridge config, off unless ``enabled = true``): this
robot's pose, map and status also published the way rmw_zenoh publishes ROS 2 topics (``agent.fleet.ros2``
encodes; docs/fleet.md, "ROS 2 over rmw_zenoh"), so a ROS 2 node on the same Zenoh network subscribes to
``<namespace>/pose`` (``geometry_msgs/msg/PoseWithCovarianceStamped``), ``<namespace>/map``
(``nav_msgs/msg/OccupancyGrid``, latched: TRANSIENT_LOCAL, keep last 1) and ``<namespace>/status``
(``std_msgs/msg/String``, the fleet status JSON). Publish only: nothing from ROS 2 reaches the agent
through this side."""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from agent.fleet import ros2
from agent.fleet.local_protocol import LocalProtocolError, MapMessage, PoseMessage, inflate_cells
from agent.fleet.payloads import MAP_FRAME
from drivers.toml_table import TomlTable, type_name

__all__ = ["Ros2Config", "Ros2Out", "parse_ros2_table"]

log = logging.getLogger(__name__)

MAX_DOMAIN_ID = 232  # ROS 2's documented domain id range is 0..232 on every platform
POSE, MAP, STATUS = "pose", "map", "status"
_TYPES = {POSE: ros2.POSE_WITH_COVARIANCE_STAMPED, MAP: ros2.OCCUPANCY_GRID, STATUS: ros2.STRING}


@dataclass(frozen=True)
class Ros2Config:
    """``[ros2]``: whether to publish, the ROS domain, the namespace of the topics, the node name shown
    in the ROS graph, and whether to declare the graph (liveliness) tokens."""

    enabled: bool = False
    domain_id: int = 0
    namespace: str = "/"
    node: str = "vlp_bridge"
    graph_tokens: bool = True


def parse_ros2_table(data: Mapping[str, Any], robot: str, file: str) -> Ros2Config:
    """The ``[ros2]`` table (``data``; empty when absent). The default namespace is ``/<robot>`` with
    ``-`` written ``_`` (ROS names allow letters, digits and ``_``)."""
    t = TomlTable(data, "ros2", file)
    enabled = t.boolean("enabled", False)
    domain_id = 0
    if t.has("domain_id"):
        domain_id = t.take("domain_id")
        if type(domain_id) is not int or not 0 <= domain_id <= MAX_DOMAIN_ID:
            raise t.error("domain_id", f"must be an integer 0..{MAX_DOMAIN_ID}, not {domain_id!r}")
    namespace = "/" + robot.replace("-", "_")
    if t.has("namespace"):
        namespace = t.take("namespace")
        if not isinstance(namespace, str):
            raise t.error("namespace", f"must be a string, not {type_name(namespace)}")
    if not ros2.valid_namespace(namespace):
        raise t.error(
            "namespace",
            f"{namespace!r} is not a ROS 2 namespace (/ or /a/b: letters, digits, '_', no leading digit)",
        )
    node = "vlp_bridge"
    if t.has("node"):
        node = t.take("node")
        if not isinstance(node, str) or not ros2.valid_namespace("/" + node) or "/" in node:
            raise t.error("node", f"must be a ROS 2 node name (letters, digits, '_'), not {node!r}")
    graph_tokens = t.boolean("graph_tokens", True)
    t.finish()
    return Ros2Config(enabled, domain_id, namespace, node, graph_tokens)


def _latched_publisher(session: Any, key: str) -> Any:
    """As rmw_zenoh (``rmw_publisher_data.cpp``) declares a TRANSIENT_LOCAL, RELIABLE publisher of depth 1:
    a Zenoh AdvancedPublisher that late subscribers detect, with a 1-sample cache they query and sporadic
    heartbeats (500 ms) for missed-sample recovery."""
    from zenoh import ext

    return ext.declare_advanced_publisher(
        session,
        key,
        cache=ext.CacheConfig(max_samples=1),
        sample_miss_detection=ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=0.5),
        publisher_detection=True,
    )


class Ros2Out:
    """Declares the three publishers (and the graph tokens) on ``session``; ``pose``, ``map`` and
    ``status`` encode and put with rmw_zenoh's attachment. ``count(name)`` counts ``ros2_published_<kind>``
    and ``ros2_errors_<kind>`` in the bridge's counters."""

    def __init__(self, config: Ros2Config, session: Any, count: Callable[[str], None]) -> None:
        self.config = config
        self._count = count
        zid = str(session.info.zid())
        node_id = 0
        self.topics = {
            kind: ros2.Ros2Topic.make(
                config.domain_id,
                zid,
                node_id,
                i + 1,
                config.namespace,
                config.node,
                kind,
                ros_type,
                kind == MAP,
            )
            for i, (kind, ros_type) in enumerate(_TYPES.items())
        }
        self._publishers = {
            kind: _latched_publisher(session, t.key) if t.latched else session.declare_publisher(t.key)
            for kind, t in self.topics.items()
        }
        self.tokens: list[str] = []
        self._tokens: list[Any] = []
        if config.graph_tokens:
            node = ros2.node_token(config.domain_id, zid, node_id, config.namespace, config.node)
            self.tokens = [node, *(t.token for t in self.topics.values())]
            self._tokens = [session.liveliness().declare_token(k) for k in self.tokens]
        log.info(
            "bridge: ROS 2 topics %s in domain %d%s",
            [t.topic for t in self.topics.values()],
            config.domain_id,
            ", graph tokens declared" if config.graph_tokens else "",
        )

    def _put(self, kind: str, payload: bytes, stamp_ns: int) -> None:
        topic = self.topics[kind]
        try:
            self._publishers[kind].put(payload, attachment=topic.next_attachment(stamp_ns))
        except Exception as exc:  # zenoh's ZError: counted, never fatal
            self._count(f"ros2_errors_{kind}")
            log.warning("bridge: publishing ROS 2 %s failed: %s", topic.topic, exc)
            return
        self._count(f"ros2_published_{kind}")

    def pose(self, pose: PoseMessage) -> None:
        """Stamped with the bridge's wall clock when it hands the pose on (the agent's ``t_us`` is its
        monotonic clock, not a ROS time)."""
        now = time.time_ns()
        self._put(POSE, ros2.encode_pose(pose, now, MAP_FRAME), now)

    def map(self, message: MapMessage) -> None:
        now = time.time_ns()
        try:
            cells = inflate_cells(message.cells_zlib, message.width * message.height)
        except LocalProtocolError as exc:
            self._count("ros2_errors_map")
            log.info("bridge: the agent's map cells do not inflate: %s", exc)
            return
        payload = ros2.encode_occupancy_grid(
            cells,
            message.width,
            message.height,
            message.resolution_m,
            message.origin_x_m,
            message.origin_y_m,
            now,
            MAP_FRAME,
        )
        self._put(MAP, payload, now)

    def status(self, text: str) -> None:
        now = time.time_ns()
        self._put(STATUS, ros2.encode_string(text), now)

    def close(self) -> None:
        for entity in (*self._tokens, *self._publishers.values()):
            with contextlib.suppress(Exception):
                entity.undeclare()
        self._tokens, self._publishers = [], {}
