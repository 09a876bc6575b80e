"""The camera loop: grab frames and hand the newest to the hot path (``agent.runtime.vlp_loop``).

A stalled camera is reported and waited for; one that fails is closed and reopened.
"""

from __future__ import annotations

import contextlib

from agent.runtime.health import Heartbeat
from agent.runtime.hotpath import HotPath
from agent.runtime.loop_state import LoopState
from agent.runtime.mailbox import LatestMailbox
from drivers.camera.base import Camera
from drivers.errors import DeviceError, DeviceTimeout
from drivers.samples import Frame

__all__ = ["camera_loop"]


def camera_loop(
    state: LoopState,
    beat: Heartbeat,
    *,
    camera: Camera,
    hot_path: HotPath,
    frames: LatestMailbox[tuple[Frame, int]],
) -> None:
    state.realtime("camera")
    watch = state.watch["camera"]
    timeout_s = state.config.health.camera_stall_s
    while not state.stop.is_set():
        beat.beat()
        if not state.open("camera", camera):
            state.retry_wait(beat, 1.0)
            continue
        try:
            frame = camera.grab(timeout_s=timeout_s)
        except DeviceTimeout as exc:
            watch.bad(f"stalled: {exc}")
            continue
        except DeviceError as exc:
            watch.bad(f"failed: {exc}; reopening")
            with contextlib.suppress(DeviceError):
                camera.close()
            state.retry_wait(beat, 0.5)
            continue
        watch.good()
        arrival = state.clock_ns()
        state.last_frame_ns = arrival
        state.count("frames")
        hot_path.frame_queued()
        frames.put((frame, arrival))
