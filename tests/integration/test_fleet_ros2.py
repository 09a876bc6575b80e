"""The bridge with ``[ros2] enabled`` over a real Zenoh session on loopback: Zenoh subscribers declared
as rmw_zenoh declares its own, on the key expressions rmw_zenoh would subscribe to (written out here
literally from rmw_zenoh's convention, not built by the code under test), hear the pose, the map and the
status, each with the attachment rmw_zenoh requires; ``rosbags`` decodes the payloads and zenoh's
deserializer the attachments; a liveliness query sees the graph tokens. Waits are on events with generous
timeouts, no timing assertion."""

from __future__ import annotations

import socket
import threading
import time
import tomllib
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agent.fleet import audit, ros2_decode
from agent.fleet.bridge import Bridge
from agent.fleet.bridge_config import parse_bridge_config
from agent.fleet.local_protocol import MapMessage, PoseMessage, StatusMessage, encode

zenoh = pytest.importorskip("zenoh")
typesys = pytest.importorskip("rosbags.typesys")

TIMEOUT_S = 60.0
DOMAIN = 3
KEYS = {
    "pose": "3/r1/pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/"
    "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e",
    "map": "3/r1/map/nav_msgs::msg::dds_::OccupancyGrid_/"
    "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7",
    "status": "3/r1/status/std_msgs::msg::dds_::String_/"
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
}


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Heard:
    def __init__(self) -> None:
        self.samples: dict[str, list[tuple[bytes, bytes | None]]] = {k: [] for k in KEYS}
        self.cond = threading.Condition()

    def callback(self, kind: str) -> Any:
        def on_sample(sample: Any) -> None:
            attachment = sample.attachment
            with self.cond:
                self.samples[kind].append(
                    (bytes(sample.payload.to_bytes()), None if attachment is None else attachment.to_bytes())
                )
                self.cond.notify_all()

        return on_sample

    def all_heard(self, n: int) -> bool:
        with self.cond:
            return all(len(v) >= n for v in self.samples.values())


def test_a_ros2_subscriber_on_rmw_zenohs_keys_decodes_the_bridges_topics(tmp_path: Path) -> None:
    from zenoh import ext
    from zenoh.ext import Int64, z_deserialize

    store = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
    port = _free_port()
    sock_path = tmp_path / "fleet.sock"
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(str(sock_path))
    server.listen(1)
    server.settimeout(TIMEOUT_S)

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{port}"]')
    ros = zenoh.open(conf)
    heard = Heard()
    # As rmw_zenoh_cpp subscribes (rmw_subscription_data.cpp): an AdvancedSubscriber, for a TRANSIENT_LOCAL
    # RELIABLE subscription (rviz's and nav2's map) with late-publisher history and heartbeat recovery;
    # the status through a plain subscriber.
    subscribers = [
        ext.declare_advanced_subscriber(ros, KEYS["pose"], heard.callback("pose")),
        ext.declare_advanced_subscriber(
            ros,
            KEYS["map"],
            heard.callback("map"),
            history=ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
            recovery=ext.RecoveryConfig(periodic_queries=None, heartbeat=True),
            subscriber_detection=True,
        ),
        ros.declare_subscriber(KEYS["status"], heard.callback("status")),
    ]

    config = parse_bridge_config(
        tomllib.loads(
            f'[bridge]\nrobot = "r1"\nsocket = "{sock_path}"\nstatus_period_s = 0.2\n'
            f'[zenoh]\nmode = "peer"\nconnect = ["tcp/127.0.0.1:{port}"]\n'
            f"[ros2]\nenabled = true\ndomain_id = {DOMAIN}\n"
        )
    )
    bridge = Bridge(config)
    stop = threading.Event()
    thread = threading.Thread(target=bridge.run, args=(stop,), daemon=True)
    thread.start()
    cells = np.full((4, 6), -1, np.int8)
    cells[1, :] = 0
    cells[2, 3] = 100
    pose = PoseMessage(1_000, 2.5, -0.75, 1.0, 0.03, 0.01, 5)
    grid = MapMessage(2_000, 0.05, -1.0, 0.5, 6, 4, zlib.compress(cells.tobytes()), ((0.0, 0.0),))
    try:
        agent, _ = server.accept()
        with agent:
            agent.sendall(encode(StatusMessage(500, 5, StatusMessage.LOCALIZED)))
            deadline = time.monotonic() + TIMEOUT_S
            # Zenoh routes a subscription to a new peer asynchronously: the agent sends until heard.
            while not heard.all_heard(2):
                assert time.monotonic() < deadline, {k: len(v) for k, v in heard.samples.items()}
                agent.sendall(encode(pose) + encode(grid))
                with heard.cond:
                    heard.cond.wait(0.2)
            # A TRANSIENT_LOCAL subscriber that joins after the last map still gets it (rviz, nav2 joining
            # late), from the publisher's cache.
            late = Heard()
            late_sub = ext.declare_advanced_subscriber(
                ros,
                KEYS["map"],
                late.callback("map"),
                history=ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
                recovery=ext.RecoveryConfig(periodic_queries=None, heartbeat=True),
                subscriber_detection=True,
            )
            subscribers.append(late_sub)
            with late.cond:
                assert late.cond.wait_for(lambda: late.samples["map"], TIMEOUT_S), (
                    "no map for a late subscriber"
                )
            tokens = sorted(str(r.ok.key_expr) for r in ros.liveliness().get(f"@ros2_lv/{DOMAIN}/**") if r.ok)
    finally:
        stop.set()
        thread.join(TIMEOUT_S)
        for s in subscribers:
            s.undeclare()
        ros.close()
        server.close()

    counters = bridge.counters()
    assert counters["ros2_published_pose"] >= 2 and counters["ros2_published_map"] >= 2
    assert not any(k.startswith("ros2_errors") for k in counters)

    for kind, samples in heard.samples.items():
        decoded = [z_deserialize(tuple[Int64, Int64, bytes], zenoh.ZBytes(a)) for _, a in samples if a]
        assert len(decoded) == len(samples), f"{kind}: a sample without the attachment rmw_zenoh requires"
        seqs = [d[0] for d in decoded]
        assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs) and seqs[0] >= 1
        assert {d[2] for d in decoded} == {decoded[0][2]} and len(decoded[0][2]) == 16
        assert all(d[1] > 1_600_000_000 * 10**9 for d in decoded)  # wall-clock ns

    data, att = heard.samples["pose"][-1]
    msg = store.deserialize_cdr(data, "geometry_msgs/msg/PoseWithCovarianceStamped")
    assert msg.header.frame_id == "map"
    assert (msg.pose.pose.position.x, msg.pose.pose.position.y) == (2.5, -0.75)
    q = msg.pose.pose.orientation
    assert np.isclose(2 * np.arctan2(q.z, q.w), 1.0)
    assert msg.pose.covariance[0] == pytest.approx(0.03**2) and msg.pose.covariance[35] == pytest.approx(
        0.01**2
    )
    assert att is not None
    stamp_ns = z_deserialize(tuple[Int64, Int64, bytes], zenoh.ZBytes(att))[1]
    assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == stamp_ns

    data, _ = heard.samples["map"][-1]
    late_data, late_att = late.samples["map"][0]
    assert (late_data, late_att) in heard.samples["map"]  # one of the maps published, attachment and all
    grid_msg = store.deserialize_cdr(data, "nav_msgs/msg/OccupancyGrid")
    assert (grid_msg.info.width, grid_msg.info.height) == (6, 4)
    assert grid_msg.info.resolution == pytest.approx(0.05)
    assert (grid_msg.info.origin.position.x, grid_msg.info.origin.position.y) == (-1.0, 0.5)
    assert np.array_equal(np.asarray(grid_msg.data, np.int8).reshape(4, 6), cells)

    data, _ = heard.samples["status"][-1]
    status = store.deserialize_cdr(data, "std_msgs/msg/String").data
    assert '"robot":"r1"' in status

    # The privacy audit accepts every sample the bridge's ROS 2 side put out, and its graph token keys.
    for kind, samples in heard.samples.items():
        for payload, _ in samples:
            assert audit.classify("fleet", KEYS[kind], payload) == (f"ros2_{kind}", None)
    for token in tokens:
        ros2_decode.parse_token_key(token)
        assert audit.check("fleet", token, b"") is None

    zid = tokens[0].split("/")[2]
    assert f"@ros2_lv/{DOMAIN}/{zid}/0/0/NN/%/%r1/vlp_bridge" in tokens
    for kind, key in KEYS.items():
        dds_type, type_hash = key.rsplit("/", 2)[1:]
        qos = ":1:,1:,:,:,," if kind == "map" else "::,:,:,:,,"  # TRANSIENT_LOCAL keep last 1; the default
        assert any(
            t.startswith(f"@ros2_lv/{DOMAIN}/{zid}/0/")
            and f"/MP/%/%r1/vlp_bridge/%r1%{kind}/{dds_type}/{type_hash}/{qos}" in t
            for t in tokens
        ), (kind, tokens)
