"""The forward camera loop: grab colour frames for person following and keep the newest in memory.

Frames never leave the process (``ARCHITECTURE.md``): the newest is held in a mailbox for the follower,
and nothing else keeps an image. A stalled camera is reported and waited for; one that fails is closed and
reopened. The loop gives way to the hot path before each grab, so that the ceiling camera's pose latency
does not pay for the second camera.
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

__all__ = ["FORWARD_CAMERA", "forward_camera_loop"]

# The name of the forward camera in the device health and the loop list.
FORWARD_CAMERA = "forward_camera"


def forward_camera_loop(
    state: LoopState,
    beat: Heartbeat,
    *,
    camera: Camera,
    hot_path: HotPath,
    frames: LatestMailbox[Frame],
    stall_s: float,
) -> None:
    watch = state.watch[FORWARD_CAMERA]
    while not state.stop.is_set():
        beat.beat()
        if not state.open(FORWARD_CAMERA, camera):
            state.retry_wait(beat, 1.0)
            continue
        hot_path.give_way()
        try:
            frame = camera.grab(timeout_s=stall_s)
        except DeviceTimeout as exc:
            watch.bad(f"stalled: {exc}")
            state.count("forward_frame_timeouts")
            continue
        except DeviceError as exc:
            watch.bad(f"failed: {exc}; reopening")
            with contextlib.suppress(DeviceError):
                camera.close()
            state.retry_wait(beat, 0.5)
            continue
        watch.good()
        state.last_forward_frame_ns = state.clock_ns()
        state.count("forward_frames")
        frames.put(frame)
