"""The laser loop: read scans, hand each to the navigation (its collision monitor acts on every scan, in
this thread) and queue them for SLAM (``agent.runtime.slam_loop``).

The laser driver reconnects by itself while it is open: a lost laser is reported and waited for.
"""

from __future__ import annotations

from collections.abc import Callable

from agent.runtime.health import Heartbeat
from agent.runtime.loop_state import LoopState
from agent.runtime.mailbox import BoundedQueue
from drivers.errors import DeviceDisconnected, DeviceError, DeviceTimeout
from drivers.laser.base import LaserScanner
from drivers.samples import Scan

__all__ = ["laser_loop"]


def laser_loop(
    state: LoopState,
    beat: Heartbeat,
    *,
    laser: LaserScanner,
    scans: BoundedQueue[Scan] | None,
    on_scan: Callable[[Scan], None] | None = None,
) -> None:
    """``scans``: where the scans go (None without SLAM: they are only counted); ``on_scan``: called with
    every scan in this thread as it arrives (the navigation's collision monitor)."""
    watch = state.watch["laser"]
    while not state.stop.is_set():
        beat.beat()
        if not state.open("laser", laser, laser.start):
            state.retry_wait(beat, 1.0)
            continue
        try:
            scan = laser.read(timeout_s=0.25)
        except DeviceDisconnected as exc:
            # The driver reconnects by itself while it is open; wait for it.
            watch.bad(f"lost: {exc}")
            state.slam_good = False
            state.retry_wait(beat, 0.1)
            continue
        except DeviceTimeout:
            if state.clock_ns() - state.last_scan_ns > state.config.health.laser_lost_s * 1e9:
                watch.bad("no scan within the timeout")
            continue
        except DeviceError as exc:
            watch.bad(f"failed: {exc}")
            state.retry_wait(beat, 0.25)
            continue
        watch.good()
        state.last_scan_ns = state.clock_ns()
        state.count("scans")
        state.record("scan", scan.host_time_ns, scan)
        if on_scan is not None:
            on_scan(scan)
        if scans is not None:
            scans.put(scan)
