"""Fleet pose latency on loopback: this robot's pose handed to its bridge -> delivered by the other robot's
bridge to its agent. Prints one JSON object.

    python benchmarks/fleet_latency.py [--poses 300] [--interval-ms 20]

Two real ``vlp-agent bridge`` processes (robots ``a`` and ``b``, Zenoh peer mode, multicast scouting off,
``b`` connects to ``a``'s ``tcp/127.0.0.1`` endpoint); the two agents are stand-ins in this process that
speak the local protocol on each bridge's Unix socket. Each pose carries its send time (this machine's
monotonic clock) as ``t_us``; agent ``b``'s stand-in takes the difference when the peer pose arrives. The
floor measured in the same run: one local-protocol frame over a Unix socket between two threads of this
process (the two socket hops the path has at least); ``ratio_to_floor`` = p50 / floor p50. The budget
(issue 24) is p95 <= 5 ms.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from agent.fleet.local_protocol import FrameDecoder, PeerPoseMessage, PoseMessage, encode  # noqa: E402

BUDGET_P95_MS = 5.0


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def now_us() -> int:
    return time.monotonic_ns() // 1000


def percentiles(values: list[float]) -> dict[str, float]:
    a = np.asarray(values)
    return {
        "p50_ms": float(np.percentile(a, 50)),
        "p95_ms": float(np.percentile(a, 95)),
        "max_ms": float(a.max()),
    }


def floor_ms(n: int) -> list[float]:
    """One pose frame over a Unix socket pair, sender thread -> receiver thread."""
    left, right = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    out: list[float] = []

    def receive() -> None:
        decoder = FrameDecoder()
        while len(out) < n:
            for m in decoder.feed(right.recv(4096)):
                assert isinstance(m, PoseMessage)
                out.append((now_us() - m.t_us) / 1000)

    thread = threading.Thread(target=receive)
    thread.start()
    for _ in range(n):
        left.sendall(encode(PoseMessage(now_us(), 0, 0, 0, 0, 0, 0)))
        time.sleep(0.002)
    thread.join(30)
    left.close()
    right.close()
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--poses", type=int, default=300)
    ap.add_argument("--interval-ms", type=float, default=20.0)
    ap.add_argument("--connect-timeout-s", type=float, default=60.0)
    args = ap.parse_args()
    port = free_port()
    with tempfile.TemporaryDirectory(prefix="fleet-bench-") as tmp:
        servers: dict[str, socket.socket] = {}
        procs = []
        for robot, zenoh in (
            ("a", f'listen = ["tcp/127.0.0.1:{port}"]'),
            ("b", f'connect = ["tcp/127.0.0.1:{port}"]'),
        ):
            path = os.path.join(tmp, f"{robot}.sock")
            server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            server.bind(path)
            server.listen(1)
            servers[robot] = server
            config = Path(tmp) / f"{robot}.toml"
            config.write_text(f'[bridge]\nrobot = "{robot}"\nsocket = "{path}"\n[zenoh]\n{zenoh}\n')
            procs.append(
                subprocess.Popen(
                    [sys.executable, "-m", "agent.cli", "bridge", "--config", str(config), "--json"],
                    cwd=REPO,
                    stdout=subprocess.PIPE,
                    stderr=subprocess.DEVNULL,
                    text=True,
                )
            )
        try:
            for server in servers.values():
                server.settimeout(args.connect_timeout_s)
            a, _ = servers["a"].accept()
            b, _ = servers["b"].accept()
            b.settimeout(0.2)
            decoder = FrameDecoder()
            latencies: list[float] = []
            lost = 0
            # Until the two Zenoh peers found each other: poses sent then are not delivered.
            deadline = time.monotonic() + args.connect_timeout_s
            warm = False
            while not warm and time.monotonic() < deadline:
                a.sendall(encode(PoseMessage(now_us(), 0, 0, 0, 0, 0, 0)))
                with contextlib.suppress(TimeoutError):
                    warm = any(isinstance(m, PeerPoseMessage) for m in decoder.feed(b.recv(65536)))
            if not warm:
                print(json.dumps({"error": "the bridges did not connect"}))
                return 1
            time.sleep(0.5)
            drain(b)
            decoder = FrameDecoder()
            b.settimeout(2.0)
            for i in range(args.poses):
                a.sendall(encode(PoseMessage(now_us(), float(i), 0, 0, 0, 0, 0)))
                got = None
                try:
                    while got is None:
                        for m in decoder.feed(b.recv(65536)):
                            if isinstance(m, PeerPoseMessage) and m.pose.x_m == float(i):
                                got = m
                except TimeoutError:
                    lost += 1
                    continue
                latencies.append((now_us() - got.pose.t_us) / 1000)
                time.sleep(args.interval_ms / 1000)
            a.close()
            b.close()
        finally:
            for p in procs:
                p.terminate()
            for p in procs:
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
    floor = floor_ms(args.poses)
    result = {
        "benchmark": "fleet_latency",
        "path": "agent a socket -> bridge a -> Zenoh tcp loopback -> bridge b -> agent b socket",
        "poses": args.poses,
        "delivered": len(latencies),
        "lost": lost,
        **percentiles(latencies),
        "floor_unix_socket": percentiles(floor),
        "ratio_to_floor": float(np.percentile(latencies, 50) / max(np.percentile(floor, 50), 1e-6)),
        "budget_p95_ms": BUDGET_P95_MS,
        "within_budget": bool(np.percentile(latencies, 95) <= BUDGET_P95_MS),
    }
    print(json.dumps(result, indent=2))
    return 0


def drain(sock: socket.socket) -> None:
    """Read and discard whatever is queued on ``sock`` (the warm-up's poses)."""
    sock.settimeout(0.05)
    try:
        while sock.recv(65536):
            pass
    except TimeoutError:
        pass


if __name__ == "__main__":
    sys.exit(main())
