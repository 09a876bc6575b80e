"""The rolling-shutter renderer in a process of its own, so that drawing frames does not load the process
that reads them.

A real camera exposes and transfers its frames in hardware and its driver waits in C for them, the
interpreter lock released: the agent's own threads (VLP, fusion, SLAM) never queue behind the camera. The
simulated camera draws each frame in Python and numpy (a few milliseconds per frame for the MV-UB300
model); done in the agent's process under ``vlp-agent sim`` it would compete with the very threads whose
latency the simulation is there to show. :class:`RenderWorker` keeps a
:class:`~drivers.sim.render.RollingShutterRenderer` in a child process (started with ``spawn``, never
``fork``: the agent is threaded) and has the same ``render(pose_at, t0_s, out)`` call: the parent samples
the three poses the renderer needs (first, middle and last row), the child draws the frame and sends back
its ground truth and its pixels, which land straight in the caller's buffer. The parent waits in the
pipe, the interpreter lock released, as it would in a camera driver.

Same seed, same frames as the in-process renderer (the child's renderer is built from the same
arguments and draws the same sequence). If the child dies, ``render`` raises
:class:`~drivers.errors.DeviceDisconnected` (the camera then reopens, starting a new child).
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import multiprocessing.connection
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from drivers.errors import DeviceDisconnected
from drivers.sim.render import FrameTruth, RenderedFrame, RollingShutterRenderer
from drivers.sim.world import CameraModel, Led, Mount, Pose2D

__all__ = ["RenderWorker"]

log = logging.getLogger(__name__)

# How long a frame may take to draw before the child counts as hung (a frame takes milliseconds).
_REPLY_TIMEOUT_S = 5.0


def _serve(
    conn: multiprocessing.connection.Connection, args: tuple[Any, ...], kwargs: dict[str, Any]
) -> None:
    """The child: draw every frame asked for until the parent hangs up."""
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
        t0_s, sampled = request

        def pose_at(t: float, sampled: list[tuple[float, Pose2D]] = sampled) -> Pose2D:
            # The renderer asks for the very row times the parent sampled at.
            return min(sampled, key=lambda item: abs(item[0] - t))[1]

        rendered = renderer.render(pose_at, t0_s, out=image)
        conn.send(rendered.truth)
        conn.send_bytes(image.data.cast("B"))


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
    ) -> None:
        self.camera = camera
        self._args = (camera, tuple(leds), mount)
        self._kwargs: dict[str, Any] = {"tilt_rad": tilt_rad, "gain_db": gain_db, "seed": seed}
        context = multiprocessing.get_context("spawn")
        self._conn, child = context.Pipe(duplex=True)
        self._process = context.Process(
            target=_serve, args=(child, self._args, self._kwargs), name="vlp-sim-render", daemon=True
        )
        self._process.start()
        child.close()

    @property
    def readout_s(self) -> float:
        """From the first row's exposure start to the last row's exposure end (as the renderer's)."""
        return (self.camera.sensor_height_px - 1) * self.camera.t_row_s + self.camera.exposure_s

    def row_time_s(self, t0_s: float, v_sensor: float) -> float:
        """Exposure centre of sensor row ``v_sensor`` in a frame starting at ``t0_s`` (as the renderer's)."""
        return t0_s + v_sensor * self.camera.t_row_s + 0.5 * self.camera.exposure_s

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
        rows = cam.sensor_height_px
        times = [self.row_time_s(t0_s, v) for v in (0.0, (rows - 1) / 2.0, rows - 1.0)]
        try:
            self._conn.send((t0_s, [(t, pose_at(t)) for t in times]))
            if not self._conn.poll(_REPLY_TIMEOUT_S):
                raise DeviceDisconnected(
                    f"the render process gave no frame in {_REPLY_TIMEOUT_S:g} s", "sim-camera"
                )
            truth: FrameTruth = self._conn.recv()
            self._conn.recv_bytes_into(out.data.cast("B"))
        except (EOFError, OSError) as exc:
            raise DeviceDisconnected(f"the render process is gone: {exc}", "sim-camera") from exc
        return RenderedFrame(out, truth)

    def close(self) -> None:
        """Stop the child (idempotent)."""
        if self._process.is_alive():
            with contextlib.suppress(OSError):
                self._conn.send(None)
            self._process.join(2.0)
            if self._process.is_alive():
                log.warning("the render process did not stop; terminating it")
                self._process.terminate()
                self._process.join(1.0)
        self._conn.close()
