"""Fleet faults, timed: how soon the fleet sees a robot again after its bridge is killed and restarted, and
after the Zenoh peer it connects to goes down and comes back. Prints one JSON object.

    python benchmarks/fleet_faults.py [--rounds 5]

The agent's end is a ``FleetLoop`` in this process (as in the agent, 20 poses/s); ``vlp-agent bridge`` is a
real process connecting to a Zenoh peer in this process on ``tcp/127.0.0.1`` (scouting off). Each round:
SIGKILL the bridge, start it again, and take the time from the new process's start to the first pose heard
(``reseen_after_restart_s``: issue 24 asks for <= 2 s; it includes the Python interpreter's start, which
``floor_interpreter_start_s`` measures in the same run: ``python -c "import agent.cli"``). Then
close the peer's session and open it again on the same endpoint: ``reseen_after_peer_back_s`` (Zenoh's
connect retry in the bridge). The agent's loop must run through all of it (``agent_alive``).
"""

from __future__ import annotations

import argparse
import json
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from agent.fusion import Estimate  # noqa: E402
from agent.runtime.fleet_loop import FleetLoop  # noqa: E402
from agent.runtime.health import Heartbeat  # noqa: E402
from firmware_protocol.pose_frame import PoseFlags  # noqa: E402

BUDGET_S = 2.0
WAIT_S = 60.0


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Poses:
    def __init__(self) -> None:
        self.times: list[float] = []
        self.cond = threading.Condition()

    def __call__(self, sample: Any) -> None:
        if str(sample.key_expr).endswith("/pose"):
            with self.cond:
                self.times.append(time.monotonic())
                self.cond.notify_all()

    def first_after(self, t0: float) -> float | None:
        deadline = time.monotonic() + WAIT_S
        with self.cond:
            while True:
                later = [t for t in self.times if t > t0]
                if later:
                    return later[0] - t0
                if time.monotonic() > deadline:
                    return None
                self.cond.wait(0.5)


def peer(port: int) -> Any:
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    return zenoh.open(conf)


def bridge(config: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "agent.cli", "bridge", "--config", str(config)],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )


def stats(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"median": None, "max": None}
    return {"median": float(np.median(values)), "max": float(max(values))}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    t = time.monotonic()
    subprocess.run([sys.executable, "-c", "import agent.cli"], cwd=REPO, check=True)
    floor = time.monotonic() - t
    with tempfile.TemporaryDirectory() as tmp:
        sock = Path(tmp) / "fleet.sock"
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
        agent = threading.Thread(
            target=loop.run, args=(Heartbeat("fleet", False, 10.0),), kwargs={"stop": stop}
        )
        agent.start()
        port = free_port()
        config = Path(tmp) / "bridge.toml"
        config.write_text(
            f'[bridge]\nrobot = "r1"\nsocket = "{sock}"\nreconnect_s = 0.1\n[zenoh]\n'
            f'connect = ["tcp/127.0.0.1:{port}"]\n'
        )
        poses = Poses()
        session = peer(port)
        session.declare_subscriber("fleet/**", poses)
        t_start = time.monotonic()
        proc = bridge(config)
        first = poses.first_after(t_start)
        restart: list[float] = []
        missed = 0
        back: list[float] = []
        try:
            for _ in range(args.rounds):
                proc.send_signal(signal.SIGKILL)
                proc.wait(WAIT_S)
                t0 = time.monotonic()
                proc = bridge(config)
                dt = poses.first_after(t0)
                if dt is None:
                    missed += 1
                else:
                    restart.append(dt)
            for _ in range(args.rounds):
                session.close()
                session = peer(port)
                t0 = time.monotonic()
                session.declare_subscriber("fleet/**", poses)
                dt = poses.first_after(t0)
                if dt is None:
                    missed += 1
                else:
                    back.append(dt)
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.wait(WAIT_S)
            session.close()
            alive = agent.is_alive()
            stop.set()
            agent.join(WAIT_S)
    out = {
        "rounds": args.rounds,
        "first_pose_s": first,
        "reseen_after_restart_s": stats(restart),
        "reseen_after_peer_back_s": stats(back),
        "missed": missed,
        "floor_interpreter_start_s": floor,
        "budget_s": BUDGET_S,
        "within_budget": bool(restart) and max(restart) <= BUDGET_S and not missed,
        "agent_alive": alive,
        "agent_counters": loop.counters(),
    }
    print(json.dumps(out, sort_keys=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
