"""The monitor loop, every 0.25 s: READY once every critical device has been opened (or after
``health.ready_grace_s`` without them), then the systemd watchdog and the status line (``HealthMonitor``),
and the journal's warnings while the agent is not localizing."""

from __future__ import annotations

import logging
from typing import Protocol

from agent.runtime.collector import IdleCollector
from agent.runtime.health import HealthMonitor
from agent.runtime.loop_state import LoopState
from firmware_protocol.pose_frame import PoseFlags

__all__ = ["MonitorLoop", "Monitored"]

log = logging.getLogger(__name__)

_POSITION_FLAGS = PoseFlags.VLP | PoseFlags.SLAM | PoseFlags.ODOMETRY
# Not localizing for this long (past start-up) before the first warning: the first fix after the devices
# open takes a few seconds.
_NOT_LOCALIZING_GRACE_S = 5.0


class Monitored(Protocol):
    """What the monitor asks of the agent."""

    def flags(self, now_ns: int | None = None) -> PoseFlags: ...

    def missing(self, *, opened_once: bool = False) -> list[str]: ...

    def not_localizing_reason(self) -> str: ...

    def critical(self, name: str) -> bool: ...


class MonitorLoop:
    def __init__(
        self,
        state: LoopState,
        *,
        agent: Monitored,
        health: HealthMonitor,
        collector: IdleCollector,
        started_ns: int,
    ) -> None:
        self.state = state
        self.agent = agent
        self.health = health
        self.collector = collector
        self.started_ns = started_ns

    def run(self) -> None:
        state, agent = self.state, self.agent
        grace_s = state.config.health.ready_grace_s
        warn = NotLocalizingWarning(state.config.health.not_localizing_log_s)
        while not state.stop.wait(0.25):
            if not self.health.is_ready:
                critical = [w for name, w in state.watch.items() if agent.critical(name)]
                if all(w.opened_once for w in critical):
                    self._ready(agent.missing(opened_once=True), None)
                elif state.clock_ns() - self.started_ns > grace_s * 1e9:
                    self._ready(agent.missing(opened_once=True), grace_s)
            else:
                now = state.clock_ns()
                why = None if agent.flags(now) & _POSITION_FLAGS else agent.not_localizing_reason()
                warn.update(why, now * 1e-9)
            self.health.tick()
            self.collector.check()

    def _ready(self, missing: list[str], after_s: float | None) -> None:
        if missing:
            when = "" if after_s is None else f" after {after_s:.0f} s"
            log.warning("ready without %s%s (each is retried; see the status line)", ", ".join(missing), when)
        self.health.ready()


class NotLocalizingWarning:
    """The journal's side of "not localizing": a warning once it has lasted ``_NOT_LOCALIZING_GRACE_S``,
    repeated every ``every_s`` (or when the reason changes) while it lasts, and a line when it ends."""

    def __init__(self, every_s: float) -> None:
        self.every_s = every_s
        self.since_s: float | None = None
        self.next_s = 0.0
        self.last_reason = ""
        self.warned = False

    def update(self, reason: str | None, now_s: float) -> None:
        """``reason``: why the agent is not localizing now, None while it is."""
        if reason is None:
            if self.warned:
                log.warning("localizing again after %.0f s", now_s - (self.since_s or now_s))
            self.since_s, self.warned, self.last_reason = None, False, ""
            return
        if self.since_s is None:
            self.since_s, self.next_s = now_s, now_s + _NOT_LOCALIZING_GRACE_S
        if now_s >= self.next_s or (self.warned and reason != self.last_reason):
            log.warning("not localizing for %.0f s: %s", now_s - self.since_s, reason)
            self.next_s, self.last_reason, self.warned = now_s + self.every_s, reason, True
