"""What the fleet tests and benchmarks share: Zenoh sessions and ``vlp-agent bridge`` processes on loopback
(explicit ``tcp/127.0.0.1`` endpoints, multicast scouting off), the agent's end of the local protocol as a
``FleetLoop`` on a thread with a fixed pose, a recorder of everything a Zenoh subscriber heard, and
``FakeSession``, the in-memory stand-in for a Zenoh session (the publish / subscribe calls the bridge makes).

Importable by ``benchmarks/`` (they put the repository on ``sys.path``) as by the tests; nothing here asserts
on wall-clock time: every wait has a generous timeout.
"""

from __future__ import annotations

import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from agent.fleet.bridge_config import ZenohConfig
from agent.fusion import Estimate
from agent.runtime.fleet_loop import FleetLoop
from agent.runtime.health import Heartbeat
from firmware_protocol.pose_frame import PoseFlags

REPO = Path(__file__).resolve().parents[1]
TIMEOUT_S = 180.0


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def loopback(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def open_session(mode: str = "peer", *, listen: Sequence[str] = (), connect: Sequence[str] = ()) -> Any:
    """A Zenoh session in this process (``mode`` peer, client or router), scouting off, configured as the
    bridge configures its own (``ZenohConfig.zenoh_config``)."""
    import zenoh

    return zenoh.open(ZenohConfig(mode, tuple(listen), tuple(connect), False).zenoh_config())


def write_bridge_config(
    path: Path,
    robot: str,
    sock: Path,
    *,
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    status_period_s: float = 0.5,
    reconnect_s: float = 0.1,
) -> Path:
    def array(endpoints: Sequence[str]) -> str:
        return "[" + ", ".join(f'"{e}"' for e in endpoints) + "]"

    path.write_text(
        f'[bridge]\nrobot = "{robot}"\nsocket = "{sock}"\nstatus_period_s = {status_period_s}\n'
        f'reconnect_s = {reconnect_s}\n[zenoh]\nmode = "{mode}"\nlisten = {array(listen)}\n'
        f"connect = {array(connect)}\n",
        encoding="utf-8",
    )
    return path


def vlp_agent(*args: str) -> list[str]:
    return [sys.executable, "-m", "agent.cli", *args]


def start(*args: str, capture: bool = True) -> subprocess.Popen[str]:
    """``vlp-agent ARGS`` in its own process group; stdout and stderr kept (``capture``) or dropped (a
    benchmark restarting a bridge many times reads neither)."""
    out = subprocess.PIPE if capture else subprocess.DEVNULL
    return subprocess.Popen(
        vlp_agent(*args),
        cwd=REPO,
        stdout=out,
        stderr=out,
        stdin=subprocess.DEVNULL,
        text=True,
        start_new_session=True,
    )


def start_bridge(config: Path, *, capture: bool = True) -> subprocess.Popen[str]:
    """``vlp-agent bridge --config CONFIG --json``: its counters are the last stdout at SIGTERM."""
    return start("bridge", "--config", str(config), "--json", capture=capture)


def stop(proc: subprocess.Popen[str]) -> tuple[str, str]:
    """SIGTERM (a process already gone is fine), then its stdout and stderr; SIGKILL after 60 s."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        out, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
    return out or "", err or ""


class SimRobot:
    """One simulated robot: ``vlp-agent sim`` (``examples/sim.toml`` on ``world``, ``[fleet] socket`` set, 10
    poses/s to the bridge) and its ``vlp-agent bridge`` (robot ``r1``, a status every 0.5 s) with the given
    Zenoh endpoints, files in ``folder``. ``stop()`` ends both (the bridge first) and returns their (stdout,
    stderr); twice is fine."""

    def __init__(
        self, folder: Path, world: Path, *, listen: Sequence[str] = (), connect: Sequence[str] = ()
    ) -> None:
        self.sock = folder / "fleet.sock"
        config = folder / "robot.toml"
        text = (REPO / "examples" / "sim.toml").read_text(encoding="utf-8")
        text, n = re.subn(r"(?m)^world\s*=.*$", f'world = "{world}"', text, count=1)
        assert n == 1, "examples/sim.toml has no world line"
        config.write_text(text + f'\n[fleet]\nsocket = "{self.sock}"\npose_rate_hz = 10\n', encoding="utf-8")
        bridge_config = write_bridge_config(
            folder / "bridge.toml", "r1", self.sock, listen=listen, connect=connect, status_period_s=0.5
        )
        self.sim = start("sim", "--config", str(config), "--seconds", "600")
        self.bridge = start_bridge(bridge_config)
        self._outputs: dict[str, tuple[str, str]] | None = None

    def assert_running(self) -> None:
        for proc in (self.sim, self.bridge):
            assert proc.poll() is None, stop(proc)[1][-2000:]

    def stop(self) -> dict[str, tuple[str, str]]:
        """``{"bridge": (stdout, stderr), "sim": (stdout, stderr)}``."""
        if self._outputs is None:
            self._outputs = {"bridge": stop(self.bridge), "sim": stop(self.sim)}
        return self._outputs


class AgentEnd:
    """The agent's end of the local protocol (``FleetLoop``, as in the agent: it listens on ``sock``) on a
    thread, sending a fixed pose at ``pose_rate_hz``; ``close()`` stops it (twice is fine)."""

    def __init__(
        self,
        sock: Path,
        *,
        x_m: float = 1.0,
        y_m: float = 2.0,
        pose_rate_hz: float = 20.0,
        status_period_s: float = 0.5,
        flags: PoseFlags = PoseFlags.VLP,
        bits: int = 3,
        **kwargs: Any,
    ) -> None:
        def pose() -> tuple[Estimate, PoseFlags]:
            return Estimate(time.monotonic_ns(), x_m, y_m, 0.5, 0.0, 0.0, np.eye(5) * 1e-4, 0), flags

        self.loop = FleetLoop(
            sock,
            pose_rate_hz=pose_rate_hz,
            status_period_s=status_period_s,
            pose=pose,
            status_bits=lambda: bits,
            clock_ns=time.monotonic_ns,
            **kwargs,
        )
        self._stop = threading.Event()
        self.beat = Heartbeat("fleet", False, 10.0)
        self.thread = threading.Thread(target=self.loop.run, args=(self.beat,), kwargs={"stop": self._stop})
        self.thread.start()

    def alive(self) -> bool:
        return self.thread.is_alive()

    def wait_for(
        self, predicate: Callable[[dict[str, int]], bool], why: str, timeout_s: float = TIMEOUT_S
    ) -> None:
        """Until ``predicate(self.loop.counters())`` holds."""
        deadline = time.monotonic() + timeout_s
        while not predicate(self.loop.counters()):
            assert time.monotonic() < deadline, f"timed out waiting for {why}: {self.loop.counters()}"
            self._stop.wait(0.02)

    def close(self) -> None:
        self._stop.set()
        self.thread.join(TIMEOUT_S)

    def __enter__(self) -> AgentEnd:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class BridgeThread:
    """``Bridge.run`` on a thread with ``FakeSession`` (or ``session``) for its Zenoh session, robot ``r1``
    unless told; ``close()`` stops it (twice is fine)."""

    def __init__(
        self,
        sock: Path,
        session: FakeSession | None = None,
        *,
        robot: str = "r1",
        status_period_s: float = 0.1,
        reconnect_s: float = 0.05,
    ) -> None:
        from agent.fleet.bridge import Bridge
        from agent.fleet.bridge_config import parse_bridge_config

        self.session = FakeSession() if session is None else session
        config = parse_bridge_config(
            {
                "bridge": {
                    "robot": robot,
                    "socket": str(sock),
                    "status_period_s": status_period_s,
                    "reconnect_s": reconnect_s,
                },
                "zenoh": {"listen": ["tcp/127.0.0.1:0"]},
            }
        )
        self.bridge = Bridge(config, open_session=lambda conf: self.session)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self.bridge.run, args=(self._stop,))
        self.thread.start()

    def close(self) -> None:
        self._stop.set()
        self.thread.join(TIMEOUT_S)


class FleetThreads:
    """Agents' ends and bridges on threads (a unit test's fleet, no network); ``close()`` stops them all,
    the last started first. The agents' defaults are the unit tests': 50 poses/s, a status every 0.1 s,
    VLP and odometry flags."""

    def __init__(self) -> None:
        self.started: list[AgentEnd | BridgeThread] = []

    def agent(self, sock: Path, **kwargs: Any) -> AgentEnd:
        options: dict[str, Any] = {
            "pose_rate_hz": 50.0,
            "status_period_s": 0.1,
            "flags": PoseFlags.VLP | PoseFlags.ODOMETRY,
        }
        end = AgentEnd(sock, **(options | kwargs))
        self.started.append(end)
        return end

    def bridge(self, sock: Path, session: FakeSession | None = None, **kwargs: Any) -> BridgeThread:
        bridge = BridgeThread(sock, session, **kwargs)
        self.started.append(bridge)
        return bridge

    def close(self) -> None:
        for thing in reversed(self.started):
            thing.close()


class Heard:
    """Every sample a Zenoh subscriber got, as (key, payload bytes), with a wait on a predicate."""

    def __init__(self) -> None:
        self.samples: list[tuple[str, bytes]] = []
        self.times: list[float] = []
        self.cond = threading.Condition()

    def __call__(self, sample: Any) -> None:
        with self.cond:
            self.samples.append((str(sample.key_expr), bytes(sample.payload.to_bytes())))
            self.times.append(time.monotonic())
            self.cond.notify_all()

    def count(self, key: str) -> int:
        with self.cond:
            return sum(1 for k, _ in self.samples if k == key)

    def first_after(self, key: str, t0: float, timeout_s: float = TIMEOUT_S) -> float | None:
        """Seconds from ``t0`` (``time.monotonic``) to the first sample on ``key`` heard after it; None
        when none came within ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        with self.cond:
            while True:
                for (k, _), t in zip(self.samples, self.times, strict=True):
                    if k == key and t > t0:
                        return t - t0
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self.cond.wait(min(remaining, 0.5))

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

    def wait_for(self, key: str, timeout_s: float = 30.0, count: int = 1) -> bytes:
        """The newest payload on `key` once at least `count` have been published there."""
        with self.changed:
            ok = self.changed.wait_for(lambda: sum(k == key for k, _ in self.published) >= count, timeout_s)
            assert ok, f"fewer than {count} published on {key}"
            return [d for k, d in self.published if k == key][-1]

    def close(self) -> None:
        pass
