"""The forward camera's renderer in a process of its own (as :mod:`drivers.sim.render_worker` is for the
ceiling camera): a real camera delivers its frames without loading the process that reads them, so under
``vlp-agent sim`` the simulated one should not either.

``python -m drivers.sim.forward_render_worker FD`` serves a :class:`ForwardRenderer` built from the first
message; each request is the base pose, the people's states and the time, the answer the frame's ground
truth and its pixels, received straight into the caller's buffer. A socketpair (AF_UNIX, no network); a
fresh interpreter, never a fork of the threaded agent. Same seed, same frames as in-process. The exchange
is :mod:`drivers.sim.render_protocol`'s, shared with the ceiling camera's worker: requests are numbered and
an answer that comes after its wait ran out is dropped, not handed out as the next frame's. If the child
dies or hangs, ``render`` raises :class:`~drivers.errors.DeviceDisconnected` (the camera reopens).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from drivers.child_process import child_connection
from drivers.sim.forward_render import ForwardRenderer, ForwardTruth, PersonState
from drivers.sim.render_protocol import Draw, RenderClient, serve
from drivers.sim.world import ForwardCameraModel, Pose2D

__all__ = ["ForwardRenderWorker"]

_MODULE = "drivers.sim.forward_render_worker"


def _build(setup: tuple[ForwardCameraModel, npt.NDArray[np.float64], int]) -> Draw:
    """The child's renderer from the set-up message, and how it draws one requested frame."""
    model, walls, seed = setup
    renderer = ForwardRenderer(model, walls, seed=seed)
    image = np.empty((model.height_px, model.width_px, 3), dtype=np.uint8)

    def draw(request: tuple[Pose2D, list[PersonState], float]) -> tuple[ForwardTruth, memoryview]:
        base, people, t_s = request
        _, truth = renderer.render(base, people, t_s, image)
        return truth, image.data.cast("B")

    return draw


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m drivers.sim.forward_render_worker FD``: serve the connection on file descriptor FD."""
    conn = child_connection(_MODULE, "ForwardRenderWorker", argv)
    if conn is None:
        return 2
    serve(conn, _build)
    return 0


class ForwardRenderWorker(RenderClient[ForwardTruth]):
    """A :class:`ForwardRenderer` (same arguments) drawing in a child process."""

    def __init__(self, model: ForwardCameraModel, walls: npt.NDArray[np.float64], seed: int = 0) -> None:
        self.model = model
        setup = (model, np.asarray(walls, dtype=np.float64), seed)
        super().__init__(_MODULE, setup, device="sim-forward-camera", what="forward render")

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
        return out, self.request((base, list(people), t_s), out)


if __name__ == "__main__":
    sys.exit(main())
