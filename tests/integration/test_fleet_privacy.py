"""Privacy over a whole fleet run (issue 24): a Zenoh peer in this test subscribes to ``**`` before
``vlp-agent sim --robots 2`` starts and until it ended (every robot's bridge connects to it,
``--fleet-connect``), and every message heard is audited (``agent.fleet.audit.check``): a documented fleet
key of one of the two robots, a payload that decodes strictly by its schema and carries no field beyond it.
The bridges run with ``[ros2] enabled`` (``--fleet-ros2``): their ROS 2 topics (rmw_zenoh keys, CDR) are heard
and audited in the same run, each strictly the layout of its type (``agent.fleet.ros2_decode``).
What the schemas allow is poses, status flags and counters, goals and goal states, laser-built maps and the
topology: no image, nothing from camera pixels beyond the pose the LED observations give.

A short run: the two robots each drive 0.3 m towards the other; it ends when both goals ended (or at 20 s,
``--seconds``); the test does not need them reached, only the run's traffic. Generous timeouts, no
wall-clock assertion."""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import pytest

from agent.fleet import audit, payloads, ros2_decode
from tests.fleet_helpers import REPO, TIMEOUT_S, Heard, free_port, loopback, open_session, vlp_agent

pytest.importorskip("zenoh")

OFFICE = REPO / "examples" / "worlds" / "office.toml"


def test_everything_a_two_robot_fleet_publishes_in_a_run_passes_the_privacy_audit(tmp_path: Path) -> None:
    # The office without its people: a walker on a goal would hold the run up (the goal is sent again until
    # she passed), and the traffic, not the meeting, is what is audited here.
    world = tmp_path / "office.toml"
    world.write_text(re.sub(r"(?ms)^\[\[people\]\]\n.*?(?=^# ---|^\[)", "", OFFICE.read_text()))
    assert "[[people]]" not in world.read_text() and "[[rooms]]" in world.read_text()
    port = free_port()
    heard = Heard()
    session = open_session("peer", listen=[loopback(port)])
    try:
        session.declare_subscriber("**", heard)
        argv = [
            "sim",
            "--robots",
            "2",
            "--world",
            str(world),
            "--spacing",
            "5",
            "--goal",
            "2.3,6.0",
            "--goal",
            "6.7,6.0",
        ]
        argv += ["--seconds", "20", "--json", "--out", str(tmp_path), "--fleet-connect", loopback(port)]
        argv += ["--fleet-ros2"]
        done = subprocess.run(vlp_agent(*argv), cwd=REPO, capture_output=True, text=True, timeout=TIMEOUT_S)
    finally:
        session.close()
    assert done.stdout, done.stderr[-2000:]
    summary = json.loads(done.stdout)
    with heard.cond:
        samples = list(heard.samples)
    kinds: dict[str, set[str]] = {"r1": set(), "r2": set()}
    for key, data in samples:
        kind, problem = audit.classify("fleet", key, data)
        assert problem is None, problem
        if kind.startswith("ros2_"):  # the bridge's ROS 2 topic of the robot: namespace /rI
            robot = ros2_decode.parse_topic_key(key).namespace.lstrip("/")
        else:
            robot = payloads.robot_of("fleet", key)
        assert robot in kinds, key
        kinds[robot].add(kind)
    # The run's traffic was heard: both robots' poses and statuses, as JSON and as ROS 2 topics, and the
    # laser-built maps (each robot sends its first when its SLAM has one: in a run this short, on a loaded
    # machine, one robot may end first).
    for robot, seen in kinds.items():
        assert {"pose", "status", "ros2_pose", "ros2_status"} <= seen, (robot, seen, summary["robots"])
    assert {"map", "ros2_map"} <= kinds["r1"] | kinds["r2"], (kinds, summary["robots"])
    # The command's own audit (its observer on "**") agrees.
    assert summary["privacy"]["failed"] == 0 and summary["privacy"]["messages"] > 0, summary["privacy"]
    assert {"ros2_pose", "ros2_status"} <= set(summary["privacy"]["by_kind"]), summary["privacy"]
