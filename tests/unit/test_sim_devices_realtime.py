"""The simulated robot's fakes: each serving thread asks for real-time scheduling first ([sim]
device_priority, docs/config.md) and reports how late it woke (``sim_devices`` in the summary)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

from drivers.sim.harness import SimulatedRobot
from drivers.sim.worldfile import load_world

OFFICE = Path(__file__).resolve().parents[2] / "examples" / "worlds" / "office.toml"


def settled(predicate: Callable[[], bool], within_s: float = 10.0) -> bool:
    """The threads start on their own time: wait for them (a loaded machine may take a while)."""
    end = time.monotonic() + within_s
    while not predicate():
        if time.monotonic() > end:
            return False
        time.sleep(0.01)
    return True


def test_each_fake_asks_for_real_time_from_its_own_thread_and_says_whether_it_took() -> None:
    asked: list[str] = []
    lock = threading.Lock()

    def refuse() -> str | None:
        with lock:
            asked.append(threading.current_thread().name)
        return "not permitted (test)"

    world = load_world(OFFICE)
    with SimulatedRobot(world, realtime=refuse) as robot:
        assert settled(lambda: len(robot.device_realtime) == 3)
        report = robot.lateness()
    assert sorted(report) == ["laser", "rfid", "servos"]
    assert len(asked) == 3 and all(name.startswith("fake-pty") for name in asked)
    assert not any(r["realtime"] for r in report.values())
    assert all(r["late_max_s"] >= 0.0 and r["late_count"] >= 0 for r in report.values())
    with SimulatedRobot(world, realtime=lambda: None) as robot:
        assert settled(lambda: len(robot.device_realtime) == 3)
        assert all(r["realtime"] for r in robot.lateness().values())
    with SimulatedRobot(world) as robot:
        assert not any(r["realtime"] for r in robot.lateness().values())
