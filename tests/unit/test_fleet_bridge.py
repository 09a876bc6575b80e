"""The agent's fleet loop and the bridge together over a real Unix socket, with an in-memory stand-in for
the Zenoh session (``FakeSession``: the same publish / subscribe calls the bridge makes); no network.
Everything waits on events with generous timeouts: no wall-clock assertion."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agent.fleet import payloads
from agent.fleet.bridge import Bridge
from agent.fleet.bridge_config import parse_bridge_config
from agent.fleet.local_protocol import GoalMessage, PoseMessage
from agent.fusion import Estimate
from agent.runtime.arbiter import CommandArbiter, DriveSource
from agent.runtime.fleet_loop import FLEET_GOAL_IDS, FleetLoop
from agent.runtime.health import Heartbeat
from drivers.errors import ConfigError
from firmware_protocol.command_frame import GoalReason, GoalState, GoalStatus, StopCommand
from firmware_protocol.pose_frame import PoseFlags

TIMEOUT_S = 30.0


class _Bytes:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def __len__(self) -> int:
        return len(self.data)

    def to_bytes(self) -> bytes:
        return self.data


class _Sample:
    def __init__(self, key: str, data: bytes) -> None:
        self.key_expr, self.payload = key, _Bytes(data)


class FakeSession:
    """Publishers record what they put; ``deliver`` calls the subscribers whose key expression matches
    (``*`` = one chunk), as Zenoh would from its own thread."""

    def __init__(self) -> None:
        self.published: list[tuple[str, bytes]] = []
        self.subscribers: list[tuple[str, Callable[[Any], None]]] = []
        self.changed = threading.Condition()

    def declare_publisher(self, key: str) -> Any:
        session = self

        class Publisher:
            def put(self, data: bytes) -> None:
                with session.changed:
                    session.published.append((key, bytes(data)))
                    session.changed.notify_all()

        return Publisher()

    def declare_subscriber(self, key: str, callback: Callable[[Any], None]) -> Any:
        self.subscribers.append((key, callback))
        return object()

    def deliver(self, key: str, data: bytes) -> None:
        for pattern, callback in self.subscribers:
            p, k = pattern.split("/"), key.split("/")
            if len(p) == len(k) and all(a in ("*", b) for a, b in zip(p, k, strict=True)):
                callback(_Sample(key, data))

    def wait_for(self, key: str, timeout_s: float = TIMEOUT_S, count: int = 1) -> bytes:
        """The newest payload on `key` once at least `count` have been published there."""
        with self.changed:
            ok = self.changed.wait_for(lambda: sum(k == key for k, _ in self.published) >= count, timeout_s)
            assert ok, f"fewer than {count} published on {key}"
            return [d for k, d in self.published if k == key][-1]

    def close(self) -> None:
        pass


def _estimate(x_m: float) -> Estimate:
    return Estimate(time.monotonic_ns(), x_m, 2.0, 0.5, 0.0, 0.0, np.eye(5) * 1e-4, 0)


@pytest.fixture
def pair(tmp_path: Path) -> Iterator[tuple[FleetLoop, Bridge, FakeSession]]:
    sock = tmp_path / "fleet.sock"
    loop = FleetLoop(
        sock,
        pose_rate_hz=50.0,
        status_period_s=0.1,
        pose=lambda: (_estimate(1.0), PoseFlags.VLP | PoseFlags.ODOMETRY),
        status_bits=lambda: 3,
        clock_ns=time.monotonic_ns,
    )
    session = FakeSession()
    config = parse_bridge_config(
        {
            "bridge": {"robot": "r1", "socket": str(sock), "status_period_s": 0.1, "reconnect_s": 0.05},
            "zenoh": {"listen": ["tcp/127.0.0.1:0"]},
        }
    )
    bridge = Bridge(config, open_session=lambda conf: session)
    stop = threading.Event()
    threads = [
        threading.Thread(target=loop.run, args=(Heartbeat("fleet", False, 10.0),), kwargs={"stop": stop}),
        threading.Thread(target=bridge.run, args=(stop,)),
    ]
    for t in threads:
        t.start()
    yield loop, bridge, session
    stop.set()
    for t in threads:
        t.join(TIMEOUT_S)
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


def test_a_socket_path_that_cannot_be_listened_on_is_retried_not_fatal(tmp_path: Path) -> None:
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("")
    loop = FleetLoop(
        blocker / "fleet.sock",
        pose_rate_hz=10.0,
        status_period_s=1.0,
        pose=lambda: (_estimate(0.0), PoseFlags(0)),
        status_bits=lambda: 0,
        clock_ns=time.monotonic_ns,
    )
    stop = threading.Event()
    thread = threading.Thread(target=loop.run, args=(Heartbeat("fleet", False, 10.0),), kwargs={"stop": stop})
    thread.start()
    _wait(lambda: loop.counters().get("fleet_listen_failures", 0) >= 1)
    stop.set()
    thread.join(TIMEOUT_S)
    assert not thread.is_alive()


def test_the_agent_carries_on_through_a_bridge_restart(tmp_path: Path) -> None:
    sock = tmp_path / "fleet.sock"
    loop = FleetLoop(
        sock,
        pose_rate_hz=50.0,
        status_period_s=0.1,
        pose=lambda: (_estimate(1.0), PoseFlags.ODOMETRY),
        status_bits=lambda: 3,
        clock_ns=time.monotonic_ns,
    )
    config = parse_bridge_config(
        {
            "bridge": {"robot": "r1", "socket": str(sock), "status_period_s": 0.1, "reconnect_s": 0.05},
            "zenoh": {"listen": ["tcp/127.0.0.1:0"]},
        }
    )
    agent_stop = threading.Event()
    agent = threading.Thread(
        target=loop.run, args=(Heartbeat("fleet", False, 10.0),), kwargs={"stop": agent_stop}
    )
    agent.start()
    try:
        for round_ in (1, 2):
            session = FakeSession()
            bridge = Bridge(config, open_session=lambda conf, s=session: s)
            stop = threading.Event()
            thread = threading.Thread(target=bridge.run, args=(stop,))
            thread.start()
            payloads.decode_pose(session.wait_for("fleet/r1/pose"), "r1")
            stop.set()  # the bridge goes away (its socket closes); the agent notices and waits for the next
            thread.join(TIMEOUT_S)
            _wait(lambda r=round_: loop.counters().get("fleet_bridge_disconnects", 0) >= r)
        assert agent.is_alive() and loop.counters()["fleet_bridge_connections"] == 2
    finally:
        agent_stop.set()
        agent.join(TIMEOUT_S)


def test_with_no_bridge_the_loop_sleeps_instead_of_spinning(tmp_path: Path) -> None:
    loop = FleetLoop(
        tmp_path / "fleet.sock",
        pose_rate_hz=100.0,
        status_period_s=0.05,
        pose=lambda: (_estimate(0.0), PoseFlags(0)),
        status_bits=lambda: 0,
        clock_ns=time.monotonic_ns,
    )
    beat, stop = Heartbeat("fleet", False, 10.0), threading.Event()
    thread = threading.Thread(target=loop.run, args=(beat,), kwargs={"stop": stop})
    thread.start()
    _wait(lambda: (tmp_path / "fleet.sock").exists())
    before = beat.beats
    time.sleep(1.0)
    # A quarter-second idle wait: about 4 passes in that second (a loaded machine makes fewer, never more);
    # a loop that spins makes thousands.
    assert beat.beats - before <= 12
    stop.set()
    thread.join(TIMEOUT_S)


def test_a_bridge_without_its_agent_says_so_and_connects_when_it_comes(tmp_path: Path) -> None:
    sock = tmp_path / "fleet.sock"
    config = parse_bridge_config(
        {
            "bridge": {"robot": "r1", "socket": str(sock), "status_period_s": 0.05, "reconnect_s": 0.05},
            "zenoh": {"listen": ["tcp/127.0.0.1:0"]},
        }
    )
    session = FakeSession()
    bridge = Bridge(config, open_session=lambda conf: session)
    stop = threading.Event()
    thread = threading.Thread(target=bridge.run, args=(stop,))
    thread.start()
    try:
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
        loop = FleetLoop(
            sock, 50.0, 0.05, lambda: (_estimate(3.0), PoseFlags.ODOMETRY), lambda: 3, time.monotonic_ns
        )
        agent_stop = threading.Event()
        agent = threading.Thread(
            target=loop.run, args=(Heartbeat("fleet", False, 10.0),), kwargs={"stop": agent_stop}
        )
        agent.start()
        try:
            pose = payloads.decode_pose(session.wait_for("fleet/r1/pose"), "r1")
            assert pose.x_m == 3.0
        finally:
            agent_stop.set()
            agent.join(TIMEOUT_S)
    finally:
        stop.set()
        thread.join(TIMEOUT_S)
