"""``vlp-agent sim --fault KIND@START+DURATION``: a fault lasts DURATION from when it was applied, even when a
busy machine applied it late (the fault-injection test judges its windows by that)."""

from __future__ import annotations

from typing import Any

from agent.commands.sim import Fault, FaultInjector


class Recording(FaultInjector):
    def __init__(self, faults: list[Fault]) -> None:
        super().__init__(faults, robot=None, agent=None)  # type: ignore[arg-type]
        self.calls: list[tuple[str, bool]] = []

    def set(self, kind: str, on: bool) -> None:
        self.calls.append((kind, on))


def test_a_fault_applied_late_still_lasts_its_duration() -> None:
    injector = Recording([Fault.parse("laser@3+4"), Fault.parse("camera@10+3")])
    injector.step(2.9)
    assert injector.calls == []
    injector.step(5.0)  # the main loop was held 2 s: the laser fault starts at 5.0 instead of 3.0
    assert injector.calls == [("laser", True)]
    injector.step(7.5)  # 7 s, where it was due to end, is not 4 s after it began
    assert injector.calls == [("laser", True)]
    injector.step(9.0)
    assert injector.calls == [("laser", True), ("laser", False)]
    injector.step(13.2)
    injector.step(16.2)
    assert injector.calls[2:] == [("camera", True), ("camera", False)]
    applied: list[dict[str, Any]] = injector.applied
    assert [(a["kind"], a["on"], a["t_s"]) for a in applied] == [
        ("laser", True, 5.0),
        ("laser", False, 9.0),
        ("camera", True, 13.2),
        ("camera", False, 16.2),
    ]


def test_a_fault_without_duration_stays() -> None:
    injector = Recording([Fault.parse("servo@1")])
    for t in (0.5, 1.0, 100.0):
        injector.step(t)
    assert injector.calls == [("servo", True)]
