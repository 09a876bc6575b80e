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
arguments and draws the same sequence). The exchange is :mod:`drivers.sim.render_protocol`'s, shared with
the forward camera's worker: each request is numbered and each answer names its request, so a frame whose
wait ran out (``render`` raised) and that comes later is dropped, not handed out as the next frame's. If
the child dies or hangs, ``render`` raises :class:`~drivers.errors.DeviceDisconnected` (the camera then
reopens, starting a new child).
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from drivers.child_process import child_connection
from drivers.sim.render import FrameTruth, RenderedFrame, RollingShutterRenderer, pose_times_s, readout_time_s
from drivers.sim.render_protocol import Draw, RenderClient, serve
from drivers.sim.world import CameraModel, Led, Mount, Pose2D, Scene

__all__ = ["RenderWorker"]

_MODULE = "drivers.sim.render_worker"


def _build(setup: tuple[tuple[Any, ...], dict[str, Any]]) -> Draw:
    """The child's renderer from the set-up message, and how it draws one requested frame."""
    args, kwargs = setup
    renderer = RollingShutterRenderer(*args, **kwargs)
    cam = renderer.camera
    image = np.empty((cam.output_height_px, cam.output_width_px), dtype=np.uint8)

    def draw(request: tuple[float, list[tuple[float, Pose2D]]]) -> tuple[FrameTruth, memoryview]:
        t0_s, sampled = request

        def pose_at(t: float) -> Pose2D:
            # The renderer asks for the very row times the parent sampled at.
            return min(sampled, key=lambda item: abs(item[0] - t))[1]

        rendered = renderer.render(pose_at, t0_s, out=image)
        return rendered.truth, image.data.cast("B")

    return draw


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m drivers.sim.render_worker FD``: serve the connection on file descriptor FD."""
    conn = child_connection(_MODULE, "RenderWorker", argv)
    if conn is None:
        return 2
    serve(conn, _build)
    return 0


class RenderWorker(RenderClient[FrameTruth]):
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
        kwargs: dict[str, Any] = {"tilt_rad": tilt_rad, "gain_db": gain_db, "seed": seed, "scene": scene}
        super().__init__(_MODULE, ((camera, tuple(leds), mount), kwargs), device="sim-camera", what="render")

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
        sampled = [(t, pose_at(t)) for t in pose_times_s(cam, t0_s)]
        return RenderedFrame(out, self.request((t0_s, sampled), out))


if __name__ == "__main__":
    sys.exit(main())
