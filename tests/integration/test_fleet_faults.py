"""Fleet faults with real processes on loopback (explicit ``tcp/127.0.0.1`` endpoints, multicast scouting
off): the agents' ends are FleetLoops in this process (as in the agent), the bridges are ``vlp-agent bridge``
processes (``tests/fleet_helpers.py``).

* the bridge killed (SIGKILL) and started again: the fleet loop runs on untouched, the new bridge connects
  and the robot's poses are heard again; the peer it connects to down and back: poses flow again;
* two robots meeting at a router (``vlp-agent fleet router``, bridges in client mode): each sees the other;
  the router killed: each drops the other after ``peer_timeout_s``; the router back on its port: each sees
  the other again, the bridges reconnecting on their own; malformed and oversized messages from the network
  rejected and counted by both bridges, reaching neither agent; one robot vanishing (its bridge killed): the
  other drops it after the timeout.

How fast each comes back: ``benchmarks/fleet_faults.py``. Generous timeouts, no wall-clock assertion."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import time
from pathlib import Path

import pytest

from agent.fleet import payloads
from agent.fleet.local_protocol import PoseMessage
from tests.fleet_helpers import (
    TIMEOUT_S,
    AgentEnd,
    Heard,
    free_port,
    loopback,
    open_session,
    start,
    start_bridge,
    stop,
    write_bridge_config,
)

pytest.importorskip("zenoh")


def _poses_after(heard: Heard, n: int) -> None:
    heard.wait(lambda k, d: k == "fleet/r1/pose" and heard.count(k) > n, TIMEOUT_S, f"more than {n} poses")


def test_bridge_killed_and_restarted_and_the_peer_down_and_back(tmp_path: Path) -> None:
    sock = tmp_path / "fleet.sock"
    port = free_port()
    config = write_bridge_config(tmp_path / "bridge.toml", "r1", sock, connect=[loopback(port)])
    heard = Heard()
    session = open_session("peer", listen=[loopback(port)])
    session.declare_subscriber("fleet/**", heard)
    with AgentEnd(sock) as agent:
        bridge = start_bridge(config)
        try:
            _poses_after(heard, 0)
            # Killed: no goodbye. The agent's end notices the closed socket and runs on.
            bridge.send_signal(signal.SIGKILL)
            bridge.wait(TIMEOUT_S)
            agent.wait_for(lambda c: c.get("fleet_bridge_disconnects", 0) >= 1, "the bridge noticed gone")
            assert agent.alive()
            count = heard.count("fleet/r1/pose")
            bridge = start_bridge(config)
            _poses_after(heard, count)
            assert agent.loop.counters()["fleet_bridge_connections"] == 2 and agent.alive()
            # The peer down and back on the same endpoint: the bridge reconnects on its own.
            session.close()
            session = open_session("peer", listen=[loopback(port)])
            heard2 = Heard()
            session.declare_subscriber("fleet/**", heard2)
            heard2.wait(lambda k, d: k == "fleet/r1/pose", TIMEOUT_S, "a pose after the peer came back")
            assert bridge.poll() is None, stop(bridge)[1][-2000:]
        finally:
            out, err = stop(bridge)
            session.close()
    counters = json.loads(out)["counters"]
    assert counters["agent_connections"] == 1 and counters.get("agent_malformed_frames", 0) == 0, err[-2000:]


def _listening(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def start_router(port: int) -> subprocess.Popen[str]:
    """``vlp-agent fleet router`` on ``port``, returned once it accepts connections (a client's session
    cannot open before)."""
    router = start("fleet", "router", "--listen", loopback(port), "--json")
    deadline = time.monotonic() + TIMEOUT_S
    while not _listening(port):
        assert router.poll() is None, stop(router)[1][-2000:]
        assert time.monotonic() < deadline, "the router never listened"
        time.sleep(0.05)
    return router


def _sees(agent: AgentEnd, other: str) -> bool:
    return other in agent.loop.peer_poses()


def _wait(predicate: object, why: str) -> None:
    assert callable(predicate)
    deadline = time.monotonic() + TIMEOUT_S
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {why}"
        time.sleep(0.02)


def test_two_robots_through_a_router_down_and_back_bad_messages_and_a_vanished_robot(tmp_path: Path) -> None:
    port = free_port()
    router = start_router(port)
    ends = {}
    bridges: dict[str, subprocess.Popen[str]] = {}
    session = None
    try:
        for i, name in enumerate(("r1", "r2")):
            sock = tmp_path / f"{name}.sock"
            # peer_timeout_s 1 s: the robots drop each other soon after the router goes.
            ends[name] = AgentEnd(sock, x_m=1.0 + 4 * i, peer_timeout_s=1.0)
            config = tmp_path / f"{name}.toml"
            write_bridge_config(config, name, sock, mode="client", connect=[loopback(port)])
            bridges[name] = start_bridge(config)
        r1, r2 = ends["r1"], ends["r2"]
        _wait(lambda: _sees(r1, "r2") and _sees(r2, "r1"), "the robots to see each other")
        assert r1.loop.peer_poses()["r2"][0].x_m == 5.0 and r2.loop.peer_poses()["r1"][0].x_m == 1.0

        # The router killed: nothing flows; each robot drops the other after its peer timeout.
        router.send_signal(signal.SIGKILL)
        router.wait(TIMEOUT_S)
        _wait(lambda: not _sees(r1, "r2") and not _sees(r2, "r1"), "the robots to drop each other")
        assert (
            r1.loop.counters()["fleet_peers_dropped"] >= 1 and r2.loop.counters()["fleet_peers_dropped"] >= 1
        )
        # Back on the same port: the bridges reconnect on their own (Zenoh's connect retry, docs/fleet.md).
        router = start_router(port)
        _wait(lambda: _sees(r1, "r2") and _sees(r2, "r1"), "the robots to see each other again")
        for name in bridges:
            assert bridges[name].poll() is None, stop(bridges[name])[1][-2000:]

        # Malformed and oversized messages from the network, through the router: rejected and counted by
        # both bridges (their statuses say so), never handed to either agent.
        session = open_session("client", connect=[loopback(port)])
        heard = Heard()
        session.declare_subscriber("fleet/*/status", heard)
        ghost = session.declare_publisher("fleet/r9/pose")
        goal = session.declare_publisher("fleet/r1/goal")
        bad_poses = [
            b"\x89PNG\r\n\x1a\n" + bytes(64),
            b'{"v":1,"robot":"r9","t_us":-1}',
            payloads.encode_pose("r2", PoseMessage(5, 3.0, 4.0, 0.1, 0.0, 0.0, 1)),  # names another robot
            b"x" * 1_000_000,
        ]
        bad_goals = [
            b"{" + b" " * (payloads.MAX_PAYLOAD + 10) + b"}",
            b'{"v":1,"robot":"r2","goal_id":1,"x_m":0,"y_m":0}',  # r1 takes goals under its own name
        ]

        def counted(robot: str, kind: str, n: int) -> bool:
            with heard.cond:
                for key, data in reversed(heard.samples):
                    if key == f"fleet/{robot}/status":
                        return payloads.decode_status(data, robot).counters.get(f"rejected_{kind}", 0) >= n
            return False

        def all_counted() -> bool:
            return counted("r1", "pose", 4) and counted("r2", "pose", 4) and counted("r1", "goal", 2)

        # Sent again until both bridges' statuses count them: a put goes only to the subscriptions the
        # router knows of by then (both bridges declared theirs again when it came back, maybe not yet).
        deadline = time.monotonic() + TIMEOUT_S
        while not all_counted():
            assert time.monotonic() < deadline, "timed out waiting for both bridges to count the bad messages"
            for data in bad_poses:
                ghost.put(data)
            for data in bad_goals:
                goal.put(data)
            wait_until = time.monotonic() + 3.0
            while not all_counted() and time.monotonic() < wait_until:
                time.sleep(0.05)
        assert "r9" not in r1.loop.peer_poses() and "r9" not in r2.loop.peer_poses()
        for end in (r1, r2):
            c = end.loop.counters()
            assert c.get("fleet_goals_in", 0) == 0 and c.get("fleet_malformed_frames", 0) == 0, c

        # r2 vanishes (its bridge killed, no goodbye): r1 drops it after the timeout; r2's agent runs on.
        _wait(lambda: _sees(r1, "r2"), "r1 to see r2")  # (a pause over 1 s under load drops it early too)
        dropped = r1.loop.counters()["fleet_peers_dropped"]
        bridges["r2"].send_signal(signal.SIGKILL)
        bridges["r2"].wait(TIMEOUT_S)
        _wait(lambda: not _sees(r1, "r2"), "r1 to drop the vanished r2")
        assert r1.loop.counters()["fleet_peers_dropped"] > dropped and r2.alive() and r1.alive()
        assert bridges["r1"].poll() is None, stop(bridges["r1"])[1][-2000:]
    finally:
        if session is not None:
            session.close()
        outputs = {name: stop(proc) for name, proc in bridges.items()}
        stop(router)
        for end in ends.values():
            end.close()
    counters = json.loads(outputs["r1"][0])["counters"]
    assert counters["rejected_pose"] >= 4 and counters["rejected_goal"] >= 2, outputs["r1"][1][-2000:]
    assert counters["agent_connections"] == 1 and counters.get("agent_malformed_frames", 0) == 0
