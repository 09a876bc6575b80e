"""Fleet faults with real processes on loopback (Zenoh peer mode, multicast scouting off): the agent's end
(a FleetLoop in this process, as in the agent) serves ``vlp-agent bridge``; a Zenoh peer in this test
listens where the bridge connects.

* the bridge killed (SIGKILL) and started again: the fleet loop runs on untouched, the new bridge connects
  and the robot's poses are heard again (how fast: ``benchmarks/fleet_faults.py``);
* the peer down and back on the same endpoint: the bridge keeps its session and reconnects; poses flow.

Generous timeouts, no wall-clock assertion."""

from __future__ import annotations

import json
import signal
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agent.fusion import Estimate
from agent.runtime.fleet_loop import FleetLoop
from agent.runtime.health import Heartbeat
from firmware_protocol.pose_frame import PoseFlags
from tests.integration.test_agent_accuracy import REPO, vlp_agent
from tests.integration.test_fleet_bridge import TIMEOUT_S, Heard, _free_port, _stop

zenoh = pytest.importorskip("zenoh")


def _peer(port: int) -> Any:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    return zenoh.open(conf)


def _bridge(config: Path) -> subprocess.Popen[str]:
    return subprocess.Popen(
        vlp_agent("bridge", "--config", str(config), "--json"),
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )


def _poses_after(heard: Heard, n: int) -> None:
    heard.wait(
        lambda k, d: k == "fleet/r1/pose" and sum(1 for k2, _ in heard.samples if k2 == k) > n,
        TIMEOUT_S,
        f"more than {n} poses",
    )


def test_bridge_killed_and_restarted_and_the_peer_down_and_back(tmp_path: Path) -> None:
    sock = tmp_path / "fleet.sock"
    loop = FleetLoop(
        sock,
        pose_rate_hz=20.0,
        status_period_s=0.5,
        pose=lambda: (
            Estimate(time.monotonic_ns(), 1.0, 2.0, 0.0, 0.0, 0.0, np.eye(5) * 1e-4, 0),
            PoseFlags.VLP,
        ),
        status_bits=lambda: 3,
        clock_ns=time.monotonic_ns,
    )
    stop = threading.Event()
    agent = threading.Thread(target=loop.run, args=(Heartbeat("fleet", False, 10.0),), kwargs={"stop": stop})
    agent.start()
    port = _free_port()
    config = tmp_path / "bridge.toml"
    config.write_text(
        f'[bridge]\nrobot = "r1"\nsocket = "{sock}"\nreconnect_s = 0.1\n[zenoh]\n'
        f'connect = ["tcp/127.0.0.1:{port}"]\n'
    )
    heard = Heard()
    session = _peer(port)
    session.declare_subscriber("fleet/**", heard)
    bridge = _bridge(config)
    try:
        _poses_after(heard, 0)
        # Killed: no goodbye. The agent's end notices the closed socket and runs on.
        bridge.send_signal(signal.SIGKILL)
        bridge.wait(TIMEOUT_S)
        deadline = time.monotonic() + TIMEOUT_S
        while loop.counters().get("fleet_bridge_disconnects", 0) < 1:
            assert time.monotonic() < deadline, "the fleet loop never noticed the bridge was gone"
            stop.wait(0.05)
        assert agent.is_alive()
        count = sum(1 for k, _ in heard.samples if k == "fleet/r1/pose")
        bridge = _bridge(config)
        _poses_after(heard, count)
        assert loop.counters()["fleet_bridge_connections"] == 2 and agent.is_alive()
        # The peer down and back on the same endpoint: the bridge reconnects on its own.
        session.close()
        session = _peer(port)
        heard2 = Heard()
        session.declare_subscriber("fleet/**", heard2)
        _poses_after(heard2, 0)
        assert bridge.poll() is None, _stop(bridge)[1][-2000:]
    finally:
        out, err = _stop(bridge)
        session.close()
        stop.set()
        agent.join(TIMEOUT_S)
    counters = json.loads(out)["counters"]
    assert counters["agent_connections"] == 1 and counters.get("agent_malformed_frames", 0) == 0, err[-2000:]
