"""One simulated agent (``vlp-agent sim`` with ``[fleet] socket``), its bridge (``vlp-agent bridge``) and a
Zenoh peer in this test on loopback (multicast scouting off, explicit ``tcp/127.0.0.1`` endpoints): the
robot's pose arrives under ``fleet/<robot>/pose``; a malformed message published on the robot's goal key is
rejected and counted (the bridge's own status on ``fleet/<robot>/status`` says so), and the bridge keeps
publishing. Generous timeouts, no wall-clock assertion."""

from __future__ import annotations

import json
import math
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from agent.fleet import audit, payloads
from tests.integration.test_agent_accuracy import REPO, vlp_agent

zenoh = pytest.importorskip("zenoh")

_MAP_FIELDS = (
    "v",
    "robot",
    "t_us",
    "frame",
    "resolution_m",
    "origin_x_m",
    "origin_y_m",
    "width",
    "height",
    "encoding",
    "cells",
    "path",
)
OFFICE = REPO / "examples" / "worlds" / "office.toml"
TIMEOUT_S = 180.0


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Heard:
    def __init__(self) -> None:
        self.samples: list[tuple[str, bytes]] = []
        self.cond = threading.Condition()

    def __call__(self, sample: Any) -> None:
        with self.cond:
            self.samples.append((str(sample.key_expr), bytes(sample.payload.to_bytes())))
            self.cond.notify_all()

    def wait(self, predicate: Callable[[str, bytes], bool], timeout_s: float, why: str) -> bytes:
        deadline = time.monotonic() + timeout_s
        with self.cond:
            while True:
                for key, data in reversed(self.samples):
                    if predicate(key, data):
                        return data
                remaining = deadline - time.monotonic()
                assert remaining > 0, (
                    f"timed out waiting for {why}; heard keys {sorted({k for k, _ in self.samples})}"
                )
                self.cond.wait(min(remaining, 1.0))


def _stop(proc: subprocess.Popen[str]) -> tuple[str, str]:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        return proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.communicate()


def test_pose_arrives_under_the_robots_key_and_a_malformed_goal_is_counted(tmp_path: Path) -> None:
    sock = tmp_path / "fleet.sock"
    config = tmp_path / "robot.toml"
    text = (REPO / "examples" / "sim.toml").read_text().replace('"worlds/', f'"{OFFICE.parent}/')
    config.write_text(text + f'\n[fleet]\nsocket = "{sock}"\npose_rate_hz = 10\n')
    port, view_port = _free_port(), _free_port()
    bridge_config = tmp_path / "bridge.toml"
    bridge_config.write_text(
        f'[bridge]\nrobot = "r1"\nsocket = "{sock}"\nstatus_period_s = 0.5\n[zenoh]\nmode = "peer"\n'
        f'connect = ["tcp/127.0.0.1:{port}", "tcp/127.0.0.1:{view_port}"]\n'
    )
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    heard = Heard()
    session = zenoh.open(conf)
    procs: list[subprocess.Popen[str]] = []
    try:
        session.declare_subscriber("**", heard)  # everything on the network, for the privacy check below
        for args in (
            ("sim", "--config", str(config), "--seconds", "600"),
            ("bridge", "--config", str(bridge_config), "--json"),
        ):
            procs.append(
                subprocess.Popen(
                    vlp_agent(*args),
                    cwd=REPO,
                    stdout=subprocess.PIPE,
                    stderr=subprocess.PIPE,
                    text=True,
                    start_new_session=True,
                )
            )
        data = heard.wait(lambda k, d: k == "fleet/r1/pose", TIMEOUT_S, "the robot's pose")
        pose = payloads.decode_pose(data, "r1")
        assert math.isfinite(pose.x_m) and math.isfinite(pose.y_m) and pose.t_us > 0
        heard.wait(
            lambda k, d: k == "fleet/r1/status" and b'"agent":true' in d, TIMEOUT_S, "status, agent up"
        )

        def rejected(key: str, data: bytes) -> bool:
            if key != "fleet/r1/status":
                return False
            return payloads.decode_status(data, "r1").counters.get("rejected_goal", 0) >= 1

        # Published until the bridge's status counts it (a put before the bridge's subscription is known
        # to this peer would go nowhere): each put is one malformed message.
        deadline = time.monotonic() + TIMEOUT_S
        while True:
            session.put("fleet/r1/goal", b'{"v":1,"robot":"r1","goal_id":"not a number","x_m":1,"y_m":2}')
            try:
                heard.wait(rejected, 3.0, "the rejection counted")
                break
            except AssertionError:
                assert time.monotonic() < deadline, "the bridge never counted the malformed goal"
        status = payloads.decode_status(heard.wait(rejected, 1.0, "status"), "r1")
        assert status.counters.get("goals_in", 0) == 0  # nothing reached the agent
        count = len([1 for k, _ in heard.samples if k == "fleet/r1/pose"])
        heard.wait(
            lambda k, d: k == "fleet/r1/pose" and len([1 for k2, _ in heard.samples if k2 == k]) > count + 5,
            TIMEOUT_S,
            "poses still coming after the malformed message",
        )
        # The fleet view on "another machine": it listens where the bridge also connects.
        robots: list[dict[str, Any]] = []
        for _ in range(3):  # the bridge retries its connect endpoints with a back-off
            view = subprocess.run(
                vlp_agent(
                    "fleet", "list", "--listen", f"tcp/127.0.0.1:{view_port}", "--seconds", "8", "--json"
                ),
                cwd=REPO,
                capture_output=True,
                text=True,
                timeout=TIMEOUT_S,
            )
            assert view.returncode == 0, view.stderr[-2000:]
            robots = json.loads(view.stdout)["robots"]
            if robots:
                break
        assert [r["robot"] for r in robots] == ["r1"] and robots[0]["pose"] is not None
        # The robot's map (laser-built) comes too, and `fleet map` draws it.
        heard.wait(lambda k, d: k == "fleet/r1/map", TIMEOUT_S, "the robot's map")
        png = tmp_path / "merged.png"
        merged: dict[str, Any] = {}
        for _ in range(3):
            drawn = subprocess.run(
                vlp_agent(
                    "fleet",
                    "map",
                    "--listen",
                    f"tcp/127.0.0.1:{view_port}",
                    "--seconds",
                    "7",
                    "--json",
                    "--out",
                    str(png),
                ),
                cwd=REPO,
                capture_output=True,
                text=True,
                timeout=TIMEOUT_S,
            )
            merged = json.loads(drawn.stdout)
            if drawn.returncode == 0:
                break
        assert merged["out"] == str(png) and png.stat().st_size > 1000, drawn.stderr[-2000:]
        (robot,) = merged["robots"]
        assert robot["robot"] == "r1" and robot["map"]["occupied_cells"] > 0 and merged["pairs"] == []
        for proc in procs:
            assert proc.poll() is None, _stop(proc)[1][-2000:]
    finally:
        outputs = [_stop(p) for p in reversed(procs)]
        session.close()
    # Privacy: every key heard on "**" during the run is one of the robot's fleet keys, and every payload
    # decodes strictly as its documented JSON (poses, status flags and counters, goal states, laser-built
    # maps with the robot's path, topology): nothing else, no image, left the robot.
    assert heard.samples
    for key, data in heard.samples:
        if key == "fleet/r1/goal":
            continue  # this test's own malformed goal
        kind = key.removeprefix("fleet/r1/")
        assert kind in ("pose", "status", "goal_state", "map", "topology"), f"unexpected key {key}"
        assert audit.check("fleet", key, data) is None, audit.check("fleet", key, data)
        if kind in ("map", "topology"):
            obj = json.loads(data)
            assert set(obj) <= set(
                _MAP_FIELDS if kind == "map" else ("v", "robot", "t_us", "frame", "topology")
            )
            if kind == "map":  # the cells are the documented occupancy grid, nothing else
                cells = payloads.decode_map(data, "r1").grid.cells
                assert set(cells.ravel().tolist()) <= {-1, 0, 100}
            continue
        assert len(data) <= payloads.MAX_PAYLOAD
        assert set(json.loads(data)) <= {
            "v",
            "robot",
            "t_us",
            "x_m",
            "y_m",
            "yaw_rad",
            "sigma_xy_m",
            "sigma_yaw_rad",
            "flags",
            "pose_flags",
            "bits",
            "agent",
            "counters",
            "goal_id",
            "state",
            "reason",
            "remaining_m",
        }
    bridge_out = json.loads(outputs[0][0])
    assert bridge_out["error"] is None and bridge_out["counters"]["rejected_goal"] >= 1
    assert bridge_out["counters"].get("agent_malformed_frames", 0) == 0
