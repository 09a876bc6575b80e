"""The agent's fleet loop and the bridge together over a real Unix socket, with an in-memory stand-in for
the Zenoh session (``FakeSession``: the same publish / subscribe calls the bridge makes); no network.
Everything waits on events with generous timeouts: no wall-clock assertion."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from agent.fleet import payloads
from agent.fleet.bridge import Bridge
from agent.fleet.bridge_config import parse_bridge_config
from agent.fleet.local_protocol import GoalMessage, PoseMessage
from agent.runtime.arbiter import CommandArbiter, DriveSource
from agent.runtime.fleet_loop import FLEET_GOAL_IDS, FleetLoop
from drivers.errors import ConfigError
from firmware_protocol.command_frame import GoalReason, GoalState, GoalStatus, StopCommand
from firmware_protocol.pose_frame import PoseFlags
from tests.fleet_helpers import FakeSession, FleetThreads

TIMEOUT_S = 30.0


@pytest.fixture
def pair(tmp_path: Path, fleet_threads: FleetThreads) -> Iterator[tuple[FleetLoop, Bridge, FakeSession]]:
    sock = tmp_path / "fleet.sock"
    loop = fleet_threads.agent(sock).loop
    bridge = fleet_threads.bridge(sock)
    yield loop, bridge.bridge, bridge.session
    fleet_threads.close()
    assert not sock.exists()  # the agent removes its socket on the way out


def _wait(predicate: Callable[[], bool]) -> None:
    deadline = time.monotonic() + TIMEOUT_S
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_pose_status_and_goal_state_go_out_under_the_robots_keys(pair: Any) -> None:
    loop, bridge, session = pair
    pose = payloads.decode_pose(session.wait_for("fleet/r1/pose"), "r1")
    assert (pose.x_m, pose.y_m) == (1.0, 2.0)
    assert pose.flags == int(PoseFlags.VLP | PoseFlags.ODOMETRY)
    _wait(lambda: bridge.counters().get("published_status", 0) >= 2 and bridge._status is not None)
    status = payloads.decode_status(session.wait_for("fleet/r1/status"), "r1")
    assert status.robot == "r1"
    loop.on_status(GoalStatus(1, 2, 77, GoalState.REJECTED, GoalReason.OUTSIDE_MAP))  # not a fleet goal's
    assert loop.counters().get("fleet_goal_states_sent", 0) == 0


def test_a_fleet_goal_goes_to_the_arbiter_and_its_statuses_come_back_with_the_fleets_id(pair: Any) -> None:
    loop, bridge, session = pair
    arbiter = CommandArbiter(0.2, 1.0)
    loop.goals = lambda goal: [loop.on_status(s) for s in arbiter.fleet_goal(goal, time.monotonic())]
    _wait(lambda: loop._client is not None and bridge._agent is not None)
    session.deliver("fleet/r1/goal", payloads.encode_goal("r1", GoalMessage(0, 4242, 1.5, -0.5, math.nan)))
    _wait(lambda: any(k == "fleet/r1/goal_state" for k, _ in session.published))
    accepted = payloads.decode_goal_state(session.wait_for("fleet/r1/goal_state"), "r1")
    assert (accepted.goal_id, accepted.state) == (4242, GoalState.ACCEPTED)
    directive = arbiter.directive(time.monotonic())[0]
    assert directive.source is DriveSource.FLEET and directive.goal is not None
    assert directive.goal.goal_id in FLEET_GOAL_IDS and (directive.goal.x_m, directive.goal.yaw_rad) == (
        1.5,
        None,
    )
    # The navigator reaches it: the end goes out with the fleet's id too.
    done = arbiter.goal_finished(directive.goal.goal_id, GoalState.REACHED)
    assert done is not None
    loop.on_status(done)
    # The agent's side counts a state when it hands it to the bridge; the bridge publishes it after.
    reached = payloads.decode_goal_state(session.wait_for("fleet/r1/goal_state", count=2), "r1")
    assert (reached.goal_id, reached.state, reached.remaining_m) == (4242, GoalState.REACHED, 0.0)
    # A stop from the controller: the next fleet goal is refused and says why.
    arbiter.command(StopCommand(1), time.monotonic())
    session.deliver("fleet/r1/goal", payloads.encode_goal("r1", GoalMessage(0, 4243, 1.0, 1.0)))
    refused = payloads.decode_goal_state(session.wait_for("fleet/r1/goal_state", count=3), "r1")
    assert (refused.goal_id, refused.state, refused.reason) == (4243, GoalState.REJECTED, GoalReason.STOPPED)
    assert arbiter.directive(time.monotonic())[0].source is DriveSource.STOPPED


def test_a_robot_that_vanishes_is_dropped_after_the_timeout(pair: Any) -> None:
    loop, bridge, session = pair
    loop.peer_timeout_s = 0.3
    _wait(lambda: loop._client is not None and bridge._agent is not None)
    session.deliver("fleet/r2/pose", payloads.encode_pose("r2", PoseMessage(5, 3.0, 4.0, 0.1, 0.0, 0.0, 1)))
    _wait(lambda: "r2" in loop.peer_poses())
    assert loop.obstacles() in ([(3.0, 4.0, loop.peer_radius_m)], [])  # [] only if this thread was late
    _wait(lambda: "r2" not in loop.peer_poses())  # nothing more from r2: dropped
    assert loop.counters()["fleet_peers_dropped"] == 1 and loop.obstacles() == []


def test_other_robots_poses_reach_the_agent_and_our_own_does_not(pair: Any) -> None:
    loop, bridge, session = pair
    _wait(lambda: loop._client is not None and bridge._agent is not None)  # both ends connected
    other = PoseMessage(5, 3.0, 4.0, 0.1, 0.0625, 0.015625, 1)  # sigmas exact in float32
    session.deliver("fleet/r2/pose", payloads.encode_pose("r2", other))
    session.deliver("fleet/r1/pose", payloads.encode_pose("r1", other))  # our own echo: ignored
    _wait(lambda: "r2" in loop.peer_poses())
    assert loop.peer_poses()["r2"][0] == other
    assert set(loop.peer_poses()) == {"r2"}


def test_malformed_and_oversized_network_messages_are_counted_and_never_reach_the_agent(pair: Any) -> None:
    loop, bridge, session = pair
    _wait(lambda: loop._client is not None and bridge._agent is not None)  # both ends connected
    bad = [
        ("fleet/r1/goal", b"\x00garbage"),
        ("fleet/r1/goal", b'{"v":1,"robot":"r2","goal_id":1,"x_m":0,"y_m":0}'),  # not our name
        ("fleet/r1/goal", b"{" + b" " * (payloads.MAX_PAYLOAD + 10) + b"}"),
        ("fleet/r3/pose", b'{"v":1,"robot":"r3","t_us":-1}'),
        ("fleet/r3/pose", b"x" * 1_000_000),
    ]
    for key, data in bad:
        session.deliver(key, data)
    counts = bridge.counters()
    assert counts["rejected_goal"] == 3 and counts["rejected_pose"] == 2
    session.deliver("fleet/r1/goal", payloads.encode_goal("r1", _goal()))
    _wait(lambda: loop.counts["goals_refused"] >= 1)  # the one valid goal reached the agent
    assert loop.counts["goals_refused"] == 1 and "r3" not in loop.peer_poses()
    assert loop.counts["malformed_frames"] == 0
    counters = loop.counters()
    assert counters.get("fleet_peer_poses", 0) == 0 and counters["fleet_bridge_connections"] == 1


def _goal() -> Any:
    from agent.fleet.local_protocol import GoalMessage

    return GoalMessage(0, 9, 1.0, 1.0)


@pytest.mark.parametrize(
    ("data", "key"),
    [
        (
            {"bridge": {"robot": "a b", "socket": "/x"}, "zenoh": {"listen": ["tcp/1.2.3.4:1"]}},
            "bridge.robot",
        ),
        ({"bridge": {"robot": "a"}, "zenoh": {"listen": ["tcp/1.2.3.4:1"]}}, "bridge.socket"),
        ({"bridge": {"robot": "a", "socket": "/x"}, "zenoh": {}}, "zenoh.connect"),
        ({"bridge": {"robot": "a", "socket": "/x"}, "zenoh": {"listen": "tcp/1:2"}}, "zenoh.listen"),
        (
            {"bridge": {"robot": "a", "socket": "/x"}, "zenoh": {"listen": ["t/1"], "mode": "router"}},
            "zenoh.mode",
        ),
        (
            {"bridge": {"robot": "a", "socket": "/x", "key_prefix": "f/*"}, "zenoh": {"listen": ["t/1"]}},
            "bridge.key_prefix",
        ),
        (
            {"bridge": {"robot": "a", "socket": "/x", "robott": 1}, "zenoh": {"listen": ["t/1"]}},
            "bridge.robott",
        ),
    ],
)
def test_bridge_config_errors_name_the_key(data: dict[str, Any], key: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_bridge_config(data, "b.toml")
    assert info.value.key == key


def test_scouting_is_off_unless_configured() -> None:
    config = parse_bridge_config(
        {"bridge": {"robot": "a", "socket": "/x"}, "zenoh": {"connect": ["tcp/h:1"]}}
    )
    assert config.zenoh.multicast_scouting is False and config.zenoh.mode == "peer"


def test_fleet_config_is_off_by_default_and_checked() -> None:
    from agent.config import parse_config

    base = '[servos]\nbackend = "dynamixel"\nport = "/dev/null"\n[output]\nurl = "/dev/null"\n'
    assert parse_config(base).fleet.socket is None
    config = parse_config(base + '[fleet]\nsocket = "/run/vlp-agent/fleet.sock"\npose_rate_hz = 20\n')
    assert config.fleet.socket == Path("/run/vlp-agent/fleet.sock") and config.fleet.pose_rate_hz == 20
    with pytest.raises(ConfigError) as info:
        parse_config(base + '[fleet]\nsocket = "/' + "x" * 120 + '"\n')
    assert info.value.key == "fleet.socket"
    with pytest.raises(ConfigError) as info:
        parse_config(base + "[fleet]\npose_rate_hz = 0\n")
    assert info.value.key == "fleet.pose_rate_hz"


def test_a_socket_path_that_cannot_be_listened_on_is_retried_not_fatal(
    tmp_path: Path, fleet_threads: FleetThreads
) -> None:
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("")
    agent = fleet_threads.agent(
        blocker / "fleet.sock", pose_rate_hz=10.0, status_period_s=1.0, flags=PoseFlags(0), bits=0
    )
    _wait(lambda: agent.loop.counters().get("fleet_listen_failures", 0) >= 1)
    agent.close()
    assert not agent.alive()


def test_the_agent_carries_on_through_a_bridge_restart(tmp_path: Path, fleet_threads: FleetThreads) -> None:
    sock = tmp_path / "fleet.sock"
    agent = fleet_threads.agent(sock, flags=PoseFlags.ODOMETRY)
    for round_ in (1, 2):
        bridge = fleet_threads.bridge(sock)
        payloads.decode_pose(bridge.session.wait_for("fleet/r1/pose"), "r1")
        bridge.close()  # the bridge goes away (its socket closes); the agent notices and waits for the next
        _wait(lambda r=round_: agent.loop.counters().get("fleet_bridge_disconnects", 0) >= r)
    assert agent.alive() and agent.loop.counters()["fleet_bridge_connections"] == 2


def test_with_no_bridge_the_loop_sleeps_instead_of_spinning(
    tmp_path: Path, fleet_threads: FleetThreads
) -> None:
    agent = fleet_threads.agent(
        tmp_path / "fleet.sock", pose_rate_hz=100.0, status_period_s=0.05, flags=PoseFlags(0), bits=0
    )
    _wait(lambda: (tmp_path / "fleet.sock").exists())
    before = agent.beat.beats
    time.sleep(1.0)
    # A quarter-second idle wait: about 4 passes in that second (a loaded machine makes fewer, never more);
    # a loop that spins makes thousands.
    assert agent.beat.beats - before <= 12


def test_a_bridge_without_its_agent_says_so_and_connects_when_it_comes(
    tmp_path: Path, fleet_threads: FleetThreads
) -> None:
    sock = tmp_path / "fleet.sock"
    running = fleet_threads.bridge(sock, status_period_s=0.05)
    bridge, session = running.bridge, running.session
    status = payloads.decode_status(session.wait_for("fleet/r1/status"), "r1")
    assert status.state == "agent-down" and not status.agent_connected
    session.deliver("fleet/r1/goal", payloads.encode_goal("r1", _goal()))  # nobody to hand it to
    assert bridge.counters()["to_agent_dropped_no_agent"] == 1
    refused = payloads.decode_goal_state(session.wait_for("fleet/r1/goal_state"), "r1")
    assert (refused.goal_id, refused.state, refused.reason) == (
        9,
        GoalState.REJECTED,
        GoalReason.NOT_LOCALIZED,
    )
    fleet_threads.agent(sock, x_m=3.0, status_period_s=0.05, flags=PoseFlags.ODOMETRY)
    pose = payloads.decode_pose(session.wait_for("fleet/r1/pose"), "r1")
    assert pose.x_m == 3.0
