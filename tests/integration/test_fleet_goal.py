"""A goal from the fleet, end to end: one simulated agent (``vlp-agent sim`` with ``[fleet] socket``, the
office without its route so nothing else drives the robot) and its bridge (``vlp-agent bridge``): the
``fleet_robot`` fixture; ``vlp-agent fleet goal r1 X Y --wait`` as another Zenoh peer on loopback
(multicast scouting off, explicit ``tcp/127.0.0.1`` endpoints). The goal is accepted, driven and reached,
and its statuses come back to the sender with the sender's goal id. Generous timeouts, no wall-clock
assertion."""

from __future__ import annotations

import json
import re
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.fleet_helpers import REPO, TIMEOUT_S, SimRobot, free_port, loopback, vlp_agent

pytest.importorskip("zenoh")

OFFICE = REPO / "examples" / "worlds" / "office.toml"
GOAL = (3.2, 6.0)  # 1.2 m east of the start along the corridor, in the laser's view from the start


def test_a_goal_sent_with_fleet_goal_is_reached_and_its_status_comes_back(
    tmp_path: Path, fleet_robot: Callable[..., SimRobot]
) -> None:
    world = tmp_path / "office.toml"
    # The route section out: the simulator's autopilot then sends no velocity (it would outrank the goal).
    text = OFFICE.read_text()
    world.write_text(re.sub(r"(?ms)^\[route\]\n.*?(?=^# ---|^\[)", "", text))
    assert "[route]" not in world.read_text()
    port = free_port()
    robot = fleet_robot(world, listen=[loopback(port)])
    goal = ["fleet", "goal", "r1", str(GOAL[0]), str(GOAL[1]), "--goal-id", "777", "--wait"]
    goal += ["--allow-unknown", "--connect", loopback(port), "--timeout", "240", "--json"]
    out: dict = {}
    deadline = time.monotonic() + TIMEOUT_S
    while True:  # early on the agent (or its bridge's connection) is not there yet: REJECTED, sent again
        sent = subprocess.run(
            vlp_agent(*goal), cwd=REPO, capture_output=True, text=True, timeout=TIMEOUT_S + 240
        )
        assert sent.returncode in (0, 1, 3), sent.stderr[-2000:]
        out = json.loads(sent.stdout)
        assert out["goal_id"] == 777
        final = out["final"]
        if final is not None and final["state"] == "reached":
            break
        assert final is None or (final["state"] == "rejected" and final["reason"] != "busy"), out
        robot.assert_running()
        assert time.monotonic() < deadline, f"the goal was never reached: {out}"
        time.sleep(1.0)  # not a timing assumption: a pause between attempts while the agent starts
    assert out["final"]["state"] == "reached", out
    assert sent.returncode == 0
    names = [s["state"] for s in out["states"]]
    assert names[0] == "accepted" and names[-1] == "reached", names
    robot.assert_running()
    bridge_out = json.loads(robot.stop()["bridge"][0])
    assert bridge_out["error"] is None and bridge_out["counters"]["goals_in"] >= 1
    assert bridge_out["counters"]["published_goal_state"] >= 2
