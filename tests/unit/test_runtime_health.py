"""Heartbeats and the health monitor's notifications (READY once, WATCHDOG only while every critical loop
beats, STATUS, STOPPING), on an injected clock and a recording notifier."""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest

from agent.runtime.health import HealthMonitor


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


@dataclass
class RecordingNotifier:
    watchdog_interval_s: float | None = 5.0
    sent: list[str] = field(default_factory=list)

    def ready(self, status: str | None = None) -> bool:
        self.sent.append(f"READY {status}")
        return True

    def status(self, text: str) -> bool:
        self.sent.append(f"STATUS {text}")
        return True

    def watchdog_ping_if(self, all_alive: bool) -> bool:
        self.sent.append("WATCHDOG" if all_alive else "WITHHELD")
        return all_alive

    def stopping(self, status: str | None = None) -> bool:
        self.sent.append(f"STOPPING {status}")
        return True


def monitor(notifier: RecordingNotifier | None, clock: Clock) -> HealthMonitor:
    return HealthMonitor(notifier, lambda: "fine", status_interval_s=2.0, clock=clock)


def test_the_watchdog_is_fed_only_while_every_critical_loop_beats() -> None:
    clock, notifier = Clock(), RecordingNotifier()
    m = monitor(notifier, clock)
    camera = m.register("camera", critical=True, timeout_s=3.0)
    rfid = m.register("rfid", critical=False, timeout_s=3.0)
    m.tick()
    assert notifier.sent == []  # nothing before READY
    m.ready()
    m.ready()
    assert notifier.sent == ["READY fine"]
    m.tick()
    assert notifier.sent[-1] == "WATCHDOG"
    # The RFID loop hangs: it is not critical, the watchdog is still fed.
    clock.now += 5.0
    camera.beat()
    report = m.tick()
    assert report.stalled == ("rfid",) and report.all_critical_alive
    assert notifier.sent.count("WATCHDOG") == 2
    # The camera loop hangs: the pings stop.
    clock.now += 5.0
    rfid.beat()
    report = m.tick()
    assert report.stalled == ("camera",) and not report.all_critical_alive
    assert notifier.sent[-2:] == ["WITHHELD", "STATUS fine"]
    assert m.withheld == 1
    # ...and resume when it beats again.
    clock.now += 5.0
    camera.beat()
    rfid.beat()
    m.tick()
    assert "WATCHDOG" in notifier.sent[-2:]
    assert m.pings == 3


def test_pings_come_at_the_interval_and_status_at_its_own() -> None:
    clock, notifier = Clock(), RecordingNotifier(watchdog_interval_s=5.0)
    m = monitor(notifier, clock)
    beat = m.register("servos", critical=True, timeout_s=3.0)
    m.ready()
    sent = []
    for _ in range(40):  # 10 s in 0.25 s steps
        clock.now += 0.25
        beat.beat()
        before = len(notifier.sent)
        m.tick()
        sent.extend(notifier.sent[before:])
    assert sent.count("WATCHDOG") == 2
    assert sent.count("STATUS fine") == 5


def test_without_a_notifier_it_still_checks_and_stopping_is_sent() -> None:
    clock = Clock()
    m = monitor(None, clock)
    m.register("slam", critical=True, timeout_s=1.0)
    clock.now += 2.0
    assert m.tick().stalled == ("slam",)
    notifier = RecordingNotifier()
    m2 = monitor(notifier, clock)
    m2.stopping("bye")
    assert notifier.sent == ["STOPPING bye"]
    with pytest.raises(ValueError, match="already registered"):
        for _ in range(2):
            m2.register("x", True, 1.0)
