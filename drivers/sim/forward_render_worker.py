"""The forward camera's renderer in a process of its own (as :mod:`drivers.sim.render_worker` is for the
ceiling camera): a real camera delivers its frames without loading the process that reads them, so under
``vlp-agent sim`` the simulated one should not either.

``python -m drivers.sim.forward_render_worker FD`` serves a :class:`ForwardRenderer` built from the first
message; each request is the base pose, the people's states and the time, the answer the frame's ground
truth and its pixels, received straight into the caller's buffer. A socketpair (AF_UNIX, no network); a
fresh interpreter, never a fork of the threaded agent. Same seed, same frames as in-process. If the child
dies or hangs, ``render`` raises :class:`~drivers.errors.DeviceDisconnected` (the camera reopens).
"""

from __future__ import annotations

import logging
import multiprocessing.connection
import sys
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from drivers.child_process import child_connection, start_child, stop_child
from drivers.errors import DeviceDisconnected
from drivers.sim.forward_render import ForwardRenderer, ForwardTruth, PersonState
from drivers.sim.world import ForwardCameraModel, Pose2D

__all__ = ["ForwardRenderWorker"]

log = logging.getLogger(__name__)

_REPLY_TIMEOUT_S = 5.0


def _serve(conn: multiprocessing.connection.Connection) -> None:
    model, walls, seed = conn.recv()
    renderer = ForwardRenderer(model, walls, seed=seed)
    image = np.empty((model.height_px, model.width_px, 3), dtype=np.uint8)
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return
        if request is None:
            return
        base, people, t_s = request
        _, truth = renderer.render(base, people, t_s, image)
        conn.send(truth)
        conn.send_bytes(image.data.cast("B"))


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m drivers.sim.forward_render_worker FD``: serve the connection on file descriptor FD."""
    conn = child_connection("drivers.sim.forward_render_worker", "ForwardRenderWorker", argv)
    if conn is None:
        return 2
    _serve(conn)
    return 0


class ForwardRenderWorker:
    """A :class:`ForwardRenderer` (same arguments) drawing in a child process."""

    def __init__(self, model: ForwardCameraModel, walls: npt.NDArray[np.float64], seed: int = 0) -> None:
        self.model = model
        self._process, self._conn = start_child("drivers.sim.forward_render_worker")
        self._conn.send((model, np.asarray(walls, dtype=np.float64), seed))

    def render(
        self,
        base: Pose2D,
        people: Sequence[PersonState],
        t_s: float,
        out: npt.NDArray[np.uint8] | None = None,
    ) -> tuple[npt.NDArray[np.uint8], ForwardTruth]:
        """:meth:`ForwardRenderer.render` in the child: the same frame, drawn off this process."""
        m = self.model
        shape = (m.height_px, m.width_px, 3)
        if out is None:
            out = np.empty(shape, dtype=np.uint8)
        elif out.shape != shape or out.dtype != np.uint8 or not out.flags.c_contiguous:
            raise ValueError(f"out must be C-contiguous uint8 of shape {shape}, got {out.dtype} {out.shape}")
        try:
            self._conn.send((base, list(people), t_s))
            if not self._conn.poll(_REPLY_TIMEOUT_S):
                raise DeviceDisconnected(
                    f"the render process gave no frame in {_REPLY_TIMEOUT_S:g} s", "sim-forward-camera"
                )
            truth: ForwardTruth = self._conn.recv()
            self._conn.recv_bytes_into(out.data.cast("B"))
        except (EOFError, OSError) as exc:
            raise DeviceDisconnected(f"the render process is gone: {exc}", "sim-forward-camera") from exc
        return out, truth

    def close(self) -> None:
        """Stop the child (idempotent)."""
        stop_child(self._process, self._conn, "forward render")


if __name__ == "__main__":
    sys.exit(main())
