"""What the agent's loops share: the config, the devices and their watches, the stop event, the counters,
and the few timestamps one loop writes and the status word reads.

Each loop (``agent.runtime.*_loop``) takes this and, explicitly, the pieces of the pose pipeline it works
on; :class:`~agent.runtime.agent.Agent` builds both and composes the loops. Nothing here imports the agent.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from agent.config import AgentConfig
from agent.recording.messages import HealthSample
from agent.runtime.devices import Devices
from agent.runtime.health import Heartbeat
from agent.runtime.output import LatencyStats
from agent.runtime.priority import realtime_thread
from drivers.device import Device
from drivers.errors import DeviceError
from drivers.samples import TagRead

__all__ = ["DeviceState", "DeviceWatch", "LoopState", "RecordSample"]

# The flight recorder's entry (``agent.recording.writer.McapRecorder.record``): (kind, time ns, sample).
RecordSample = Callable[[str, int, Any], None]


def _record_nothing(kind: str, t_ns: int, sample: Any) -> None:
    pass


log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class DeviceState:
    name: str
    ok: bool
    reason: str
    since_ns: int
    failures: int
    recoveries: int


class DeviceWatch:
    """One device's state as its loop sees it: transitions are logged once, not every failed read."""

    def __init__(self, name: str, clock_ns: Callable[[], int]) -> None:
        self.name = name
        self.clock_ns = clock_ns
        self.ok = False
        self.opened_once = False
        self.reason = "not opened yet"
        self.since_ns = clock_ns()
        self.last_good_ns = 0
        self.failures = 0
        self.recoveries = 0
        self._lock = threading.Lock()
        self.record: RecordSample = _record_nothing  # the flight recorder's health channel

    def good(self) -> bool:
        """A successful operation; True when this ends a fault (a recovery)."""
        now = self.clock_ns()
        with self._lock:
            self.last_good_ns = now
            if self.ok:
                return False
            recovered = self.opened_once
            self.ok, self.reason, self.since_ns = True, "", now
            self.opened_once = True
            if recovered:
                self.recoveries += 1
        if recovered:
            log.warning("%s: recovered", self.name)
        else:
            log.info("%s: up", self.name)
        self.record("health", now, HealthSample(now, self.name, True, "recovered" if recovered else "up"))
        return recovered

    def bad(self, reason: str) -> None:
        now = self.clock_ns()
        with self._lock:
            self.failures += 1
            first = self.ok or not self.reason or self.reason == "not opened yet"
            if self.ok:
                self.since_ns = now
            self.ok, self.reason = False, reason
        if first:
            log.warning("%s: %s", self.name, reason)
            self.record("health", now, HealthSample(now, self.name, False, reason))
        else:
            log.debug("%s: %s", self.name, reason)

    def state(self) -> DeviceState:
        with self._lock:
            return DeviceState(self.name, self.ok, self.reason, self.since_ns, self.failures, self.recoveries)


class LoopState:
    """The state the loops share with each other and with the agent's status."""

    def __init__(self, config: AgentConfig, devices: Devices, clock_ns: Callable[[], int]) -> None:
        self.config = config
        self.devices = devices
        self.clock_ns = clock_ns
        self.stop = threading.Event()
        self.watch: dict[str, DeviceWatch] = {name: DeviceWatch(name, clock_ns) for name in devices.all()}
        self.counts: collections.Counter[str] = collections.Counter()
        self.counts_lock = threading.Lock()
        self.no_fix: collections.Counter[str] = collections.Counter()  # under counts_lock too
        self.vlp_ms = LatencyStats()
        self.hot_cpu_ms = LatencyStats()
        self.tags: collections.deque[TagRead] = collections.deque(maxlen=64)
        # Written by one loop each, read by the status word.
        self.last_frame_ns = 0
        self.last_forward_frame_ns = 0
        self.last_scan_ns = 0
        self.slam_good = False  # the last SLAM filter update matched and was fused
        self.hardware_error = (0, 0)
        # When the wheel read in progress started (agent clock), 0 between reads: a read that hangs is a
        # servo fault, a loop that is merely late (the machine stalled) is not.
        self.servo_read_since_ns = 0
        # The flight recorder (``set_recorder``); a no-op while nothing records.
        self.record: RecordSample = _record_nothing
        self.recording = False

    def set_recorder(self, record: RecordSample) -> None:
        """Every loop (and every device watch's state change) hands its samples to ``record`` from now on."""
        self.record = record
        self.recording = True
        for watch in self.watch.values():
            watch.record = record

    def count(self, what: str, n: int = 1) -> None:
        with self.counts_lock:
            self.counts[what] += n

    def open(self, name: str, device: Device, after: Callable[[], None] | None = None) -> bool:
        """Open ``device`` if it is closed; False (and reported) when it cannot be yet."""
        if device.is_open:
            return True
        try:
            device.open()
            if after is not None:
                after()
        except DeviceError as exc:
            self.watch[name].bad(f"cannot open: {exc}")
            with contextlib.suppress(DeviceError):
                device.close()
            return False
        self.watch[name].good()
        return True

    def retry_wait(self, beat: Heartbeat, seconds: float) -> None:
        """Wait before the next attempt, beating while waiting."""
        end = time.monotonic() + seconds
        while not self.stop.is_set():
            beat.beat()
            remaining = end - time.monotonic()
            if remaining <= 0:
                return
            self.stop.wait(min(remaining, 0.25))

    def wait_period(self, t_next: float, period_s: float) -> float:
        """Sleep until the next period of a fixed-rate loop (``t_next`` + ``period_s``, never in the past);
        returns when that period started."""
        t_next += period_s
        now_s = time.monotonic()
        if t_next < now_s:
            t_next = now_s
        self.stop.wait(t_next - now_s)
        return t_next

    def realtime(self, loop: str) -> None:
        """Put the calling loop's thread under real-time scheduling when configured and permitted."""
        priority = self.config.scheduling.realtime_priority
        refused = realtime_thread(priority)
        with self.counts_lock:
            self.counts[f"{loop}_realtime"] = int(refused is None)
        if refused is None:
            log.info("%s thread at SCHED_FIFO priority %d", loop, priority)
        elif priority:
            log.warning("%s thread time-shared: real-time scheduling %s", loop, refused)
