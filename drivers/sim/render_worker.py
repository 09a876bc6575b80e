"""The rolling-shutter renderer in a process of its own, so that drawing frames does not load the process
that reads them.

A real camera exposes and transfers its frames in hardware and its driver waits in C for them, the
interpreter lock released: the agent's own threads (VLP, fusion, SLAM) never queue behind the camera. The
simulated camera draws each frame in Python and numpy (a few milliseconds per frame for the MV-UB300
model); done in the agent's process under ``vlp-agent sim`` it would compete with the very threads whose
latency the simulation is there to show. :class:`RenderWorker` keeps a
:class:`~drivers.sim.render.RollingShutterRenderer` in a child process (a fresh interpreter running
``python -m drivers.sim.render_worker FD``: never a ``fork`` of the threaded agent, and not
``multiprocessing``'s spawn, which re-imports the parent's main script) and has the same
``render(pose_at, t0_s, out)`` call: the parent samples the three poses the renderer needs (first, middle
and last row), the child draws the frame and sends back its ground truth and its pixels, which land
straight in the caller's buffer. They talk over a socketpair (AF_UNIX, no network). The parent waits on
it, the interpreter lock released, as it would in a camera driver.

Same seed, same frames as the in-process renderer (the child's renderer is built from the same
arguments and draws the same sequence). Each request is numbered and each answer names its request: a frame
whose wait ran out (``render`` raised) and that comes later is dropped, not handed out as the next frame's
(it was: the image of an earlier pose under a later frame's time, until the camera reopened). If the child
dies, ``render`` raises
:class:`~drivers.errors.DeviceDisconnected` (the camera then reopens, starting a new child).
"""

from __future__ import annotations

import logging
import multiprocessing.connection
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from drivers.child_process import child_connection, start_child, stop_child
from drivers.errors import DeviceDisconnected
from drivers.sim.render import FrameTruth, RenderedFrame, RollingShutterRenderer, pose_times_s, readout_time_s
from drivers.sim.world import CameraModel, Led, Mount, Pose2D, Scene

__all__ = ["RenderWorker"]

log = logging.getLogger(__name__)

# How long a frame may take to draw before the child counts as hung (a frame takes milliseconds).
_REPLY_TIMEOUT_S = 5.0


def _serve(conn: multiprocessing.connection.Connection) -> None:
    """The child: build the renderer from the first message, then draw every frame asked for until the
    parent hangs up."""
    args, kwargs = conn.recv()
    renderer = RollingShutterRenderer(*args, **kwargs)
    cam = renderer.camera
    image = np.empty((cam.output_height_px, cam.output_width_px), dtype=np.uint8)
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return
        if request is None:
            return
        number, t0_s, sampled = request

        def pose_at(t: float, sampled: list[tuple[float, Pose2D]] = sampled) -> Pose2D:
            # The renderer asks for the very row times the parent sampled at.
            return min(sampled, key=lambda item: abs(item[0] - t))[1]

        rendered = renderer.render(pose_at, t0_s, out=image)
        conn.send((number, rendered.truth))
        conn.send_bytes(image.data.cast("B"))


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m drivers.sim.render_worker FD``: serve the connection on file descriptor FD."""
    conn = child_connection("drivers.sim.render_worker", "RenderWorker", argv)
    if conn is None:
        return 2
    _serve(conn)
    return 0


class RenderWorker:
    """A :class:`RollingShutterRenderer` (same arguments) drawing in a child process."""

    def __init__(
        self,
        camera: CameraModel,
        leds: Sequence[Led],
        mount: Mount,
        *,
        tilt_rad: tuple[float, float] = (0.0, 0.0),
        gain_db: float = 0.0,
        seed: int = 0,
        scene: Scene | None = None,
    ) -> None:
        self.camera = camera
        self._args = (camera, tuple(leds), mount)
        self._kwargs: dict[str, Any] = {
            "tilt_rad": tilt_rad,
            "gain_db": gain_db,
            "seed": seed,
            "scene": scene,
        }
        self._requests = 0  # frames asked for; each answer names its request
        self._process, self._conn = start_child("drivers.sim.render_worker")
        self._conn.send((self._args, self._kwargs))

    @property
    def readout_s(self) -> float:
        """From the first row's exposure start to the last row's exposure end (as the renderer's)."""
        return readout_time_s(self.camera)

    def render(
        self, pose_at: Callable[[float], Pose2D], t0_s: float, out: npt.NDArray[np.uint8] | None = None
    ) -> RenderedFrame:
        """:meth:`RollingShutterRenderer.render` in the child: the same frame, drawn off this process."""
        cam = self.camera
        shape = (cam.output_height_px, cam.output_width_px)
        if out is None:
            out = np.empty(shape, dtype=np.uint8)
        elif out.shape != shape or out.dtype != np.uint8 or not out.flags.c_contiguous:
            raise ValueError(f"out must be C-contiguous uint8 of shape {shape}, got {out.dtype} {out.shape}")
        times = pose_times_s(cam, t0_s)
        self._requests += 1
        number = self._requests
        try:
            self._conn.send((number, t0_s, [(t, pose_at(t)) for t in times]))
            deadline = time.monotonic() + _REPLY_TIMEOUT_S
            while True:
                if not self._conn.poll(max(0.0, deadline - time.monotonic())):
                    raise DeviceDisconnected(
                        f"the render process gave no frame in {_REPLY_TIMEOUT_S:g} s", "sim-camera"
                    )
                reply: tuple[int, FrameTruth] = self._conn.recv()
                answered, truth = reply
                self._conn.recv_bytes_into(out.data.cast("B"))
                # A frame asked for earlier whose wait ran out (a loaded machine: a child slow to start)
                # arrives late: dropped, never taken for this one.
                if answered == number:
                    break
                log.warning(
                    "dropped a late frame from the render process (%d, waiting for %d)", answered, number
                )
        except (EOFError, OSError) as exc:
            raise DeviceDisconnected(f"the render process is gone: {exc}", "sim-camera") from exc
        return RenderedFrame(out, truth)

    def close(self) -> None:
        """Stop the child (idempotent)."""
        stop_child(self._process, self._conn, "render")


if __name__ == "__main__":
    sys.exit(main())
