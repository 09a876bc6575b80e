"""The RFID loop: read tags, keep the last ones for the status, and, with ``[following] tag_id``, feed the
coarse layer of person following (``agent.following.coarse``: where the tagged person is, roughly) once per
read cycle. The reader's driver reconnects by itself."""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass

from agent.following.coarse import CoarseEstimate, CoarseFilter, observation_from_reads
from agent.runtime.health import Heartbeat
from agent.runtime.loop_state import LoopState
from drivers.errors import DeviceError
from drivers.rfid.base import RfidReader
from drivers.samples import TagRead

__all__ = ["CoarseLayer", "CoarseStatus", "rfid_loop"]

Pose = tuple[float, float, float]  # x_m, y_m, yaw_rad in the map frame


@dataclass(frozen=True, slots=True)
class CoarseStatus:
    """The coarse layer's latest answer and how many cycles it has taken."""

    estimate: CoarseEstimate
    cycles: int
    t_ns: int

    def as_dict(self) -> dict[str, float | int]:
        e = self.estimate
        return {
            "bearing_deg": round(math.degrees(e.bearing_rad), 1),
            "spread_deg": round(math.degrees(e.spread_rad), 1),
            "range_m": round(e.range_m, 2),
            "confidence": round(e.confidence, 3),
            "p_absent": round(e.p_absent, 3),
            "p_front": round(e.p_front, 3),
            "cycles": self.cycles,
        }


class CoarseLayer:
    """Runs a :class:`CoarseFilter` on the reader's reads: collects one cycle's reads of ``tag_id``, then
    predicts with the robot's motion over the cycle (from ``pose()``, the fused pose) and updates.

    Used from the RFID loop's thread; :attr:`latest` may be read from any thread (an immutable snapshot)."""

    def __init__(self, coarse: CoarseFilter, tag_id: str, cycle_s: float, pose: Callable[[], Pose]) -> None:
        self.filter = coarse
        self.tag_id = tag_id.upper()
        self.cycle_ns = int(cycle_s * 1e9)
        self.pose = pose
        self._reads: list[TagRead] = []
        self._last_ns: int | None = None
        self._last_pose: Pose | None = None
        self._cycles = 0
        self._lock = threading.Lock()
        self._latest: CoarseStatus | None = None
        self._retag: str | None = None  # a tag to switch to, applied on the RFID loop's thread

    def retag(self, tag_id: str) -> None:
        """Follow another tag from the next read on: the filter starts afresh (its belief was about the
        other tag). Any thread; applied on the RFID loop's."""
        with self._lock:
            self._retag = tag_id.upper()

    def _apply_retag(self) -> None:
        with self._lock:
            tag, self._retag = self._retag, None
            if tag is None or tag == self.tag_id:
                return
            self._latest = None
        self.tag_id = tag
        self.filter.reset()
        self._reads.clear()
        self._last_ns = self._last_pose = None

    @property
    def latest(self) -> CoarseStatus | None:
        with self._lock:
            return self._latest

    def add(self, read: TagRead) -> None:
        self._apply_retag()
        if read.tag_id.upper() == self.tag_id:
            self._reads.append(read)

    def tick(self, now_ns: int) -> None:
        """Close the cycle when it is due: predict over the time and motion since the last, then update."""
        self._apply_retag()
        if self._last_ns is None:
            self._last_ns, self._last_pose = now_ns, self.pose()
            self._reads.clear()
            return
        if now_ns - self._last_ns < self.cycle_ns:
            return
        pose = self.pose()
        assert self._last_pose is not None
        x0, y0, yaw0 = self._last_pose
        dx, dy = pose[0] - x0, pose[1] - y0
        c, s = math.cos(yaw0), math.sin(yaw0)
        # The robot's move in its frame at the cycle's start, and its turn.
        forward, left = c * dx + s * dy, -s * dx + c * dy
        turn = math.remainder(pose[2] - yaw0, math.tau)
        self.filter.predict((now_ns - self._last_ns) / 1e9, forward, left, turn)
        self.filter.update(observation_from_reads(self._reads, self.filter.table.ports, self.tag_id))
        self._reads.clear()
        self._last_ns, self._last_pose = now_ns, pose
        self._cycles += 1
        status = CoarseStatus(self.filter.estimate(), self._cycles, now_ns)
        with self._lock:
            self._latest = status


def rfid_loop(
    state: LoopState, beat: Heartbeat, *, rfid: RfidReader, coarse: CoarseLayer | None = None
) -> None:
    watch = state.watch["rfid"]
    # With the coarse layer the loop wakes often enough to close its cycles on time.
    timeout_s = 0.25 if coarse is None else min(0.25, coarse.cycle_ns / 4e9)
    while not state.stop.is_set():
        beat.beat()
        if not state.open("rfid", rfid):
            state.retry_wait(beat, 1.0)
            continue
        try:
            tag = rfid.read(timeout_s=timeout_s)
        except DeviceError as exc:
            watch.bad(f"failed: {exc}")
            state.retry_wait(beat, 0.5)
            continue
        if rfid.health().connected:
            watch.good()
        if tag is not None:
            state.tags.append(tag)
            state.count("tag_reads")
            state.record("tag", tag.host_time_ns, tag)
            if coarse is not None:
                coarse.add(tag)
        if coarse is not None:
            coarse.tick(state.clock_ns())
