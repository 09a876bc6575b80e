"""One simulated agent (``vlp-agent sim`` with ``[fleet] socket``) and its bridge (``vlp-agent bridge``):
the ``fleet_robot`` fixture; a Zenoh peer in this test on loopback (multicast scouting off, explicit
``tcp/127.0.0.1`` endpoints). The robot's pose arrives under ``fleet/<robot>/pose``; a malformed message
published on the robot's goal key is rejected and counted (the bridge's own status on
``fleet/<robot>/status`` says so), and the bridge keeps publishing. Generous timeouts, no wall-clock
assertion."""

from __future__ import annotations

import json
import math
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from agent.fleet import audit, payloads
from tests.fleet_helpers import REPO, TIMEOUT_S, Heard, SimRobot, free_port, loopback, open_session, vlp_agent

zenoh = pytest.importorskip("zenoh")

OFFICE = REPO / "examples" / "worlds" / "office.toml"


def test_pose_arrives_under_the_robots_key_and_a_malformed_goal_is_counted(
    tmp_path: Path, fleet_robot: Callable[..., SimRobot]
) -> None:
    port, view_port = free_port(), free_port()
    heard = Heard()
    session = open_session("peer", listen=[loopback(port)])
    session.declare_subscriber("**", heard)  # everything on the network, for the privacy check below
    robot = fleet_robot(OFFICE, connect=[loopback(port), loopback(view_port)])
    try:
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
                vlp_agent("fleet", "list", "--listen", loopback(view_port), "--seconds", "8", "--json"),
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
                    loopback(view_port),
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
        (drawn_robot,) = merged["robots"]
        assert drawn_robot["robot"] == "r1" and drawn_robot["map"]["occupied_cells"] > 0
        assert merged["pairs"] == []
        robot.assert_running()
    finally:
        try:
            outputs = robot.stop()
        finally:
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
        assert audit.check("fleet", key, data) is None, audit.check("fleet", key, data)  # and no other field
        if kind == "map":  # the cells are the documented occupancy grid, nothing else
            cells = payloads.decode_map(data, "r1").grid.cells
            assert set(cells.ravel().tolist()) <= {-1, 0, 100}
    bridge_out = json.loads(outputs["bridge"][0])
    assert bridge_out["error"] is None and bridge_out["counters"]["rejected_goal"] >= 1
    assert bridge_out["counters"].get("agent_malformed_frames", 0) == 0
