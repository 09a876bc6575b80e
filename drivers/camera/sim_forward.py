"""The simulated forward camera: colour frames of the world's walls and people (``sim.forward_render``).

Frames come at the model's frame rate on the simulation's clock, global shutter: frame n is exposed at
t_open + n / fps and ready at once. ``fetch`` waits for the next frame; a consumer that falls behind gets
the newest one and the skipped sequence numbers count as ``dropped``. Frames are BGR8, shape
(height, width, 3), or Mono8 when the settings ask for it; they live in a small pool of buffers and are
lent, never copied, as every camera's are. ``truth(sequence)`` gives each recent frame's ground truth (the
boxes of the people in view). ``stall()`` stops frames (a camera whose USB transfer hung). The timing,
stall switch, buffer pool and truth history are :mod:`drivers.camera.sim_base`'s, shared with the ceiling
camera.
"""

from __future__ import annotations

import dataclasses
import logging

import cv2
import numpy as np
import numpy.typing as npt

from drivers.camera.base import CameraSettings
from drivers.camera.sim_base import SimCameraBase
from drivers.errors import DeviceError
from drivers.samples import Frame
from drivers.sim.forward_render import ForwardRenderer, ForwardTruth, PersonState
from drivers.sim.forward_render_worker import ForwardRenderWorker
from drivers.sim.raycast import walls_array
from drivers.sim.simulation import Simulation
from drivers.sim.world import ForwardCameraModel

__all__ = ["SimForwardCamera", "people_states"]

log = logging.getLogger(__name__)


def people_states(simulation: Simulation, t: float) -> list[PersonState]:
    """Every person of the simulation at time ``t``, as the renderer takes them."""
    out = []
    for person in simulation.world.people:
        x, y, heading, walked = simulation.person_pose(person, t)
        out.append(PersonState(person, x, y, heading, walked))
    return out


class SimForwardCamera(SimCameraBase[ForwardTruth]):
    """The forward camera of the simulated robot.

    Args:
        simulation: the world and its clock.
        settings: ``width``/``height`` and ``frame_rate_hz`` override the world's ``[forward_camera]``;
            ``pixel_format`` BGR8 (default) or Mono8.
        seed: seeds the sensor noise.
        truth_history: how many recent frames keep their ground truth.
        render_process: draw the frames in a child process (:mod:`drivers.sim.forward_render_worker`), as
            a real camera delivers them without loading the process that reads them; the same frames.
    """

    def __init__(
        self,
        simulation: Simulation,
        *,
        settings: CameraSettings | None = None,
        seed: int = 0,
        truth_history: int = 64,
        render_process: bool = False,
        name: str = "sim-forward-camera",
    ) -> None:
        super().__init__(
            name,
            settings if settings is not None else CameraSettings(pixel_format="BGR8"),
            simulation,
            seed=seed,
            truth_history=truth_history,
        )
        model = simulation.world.forward_camera
        wanted = self.requested
        if wanted.width is not None:
            model = dataclasses.replace(model, width_px=wanted.width, cx_px=None)
        if wanted.height is not None:
            model = dataclasses.replace(model, height_px=wanted.height, cy_px=None)
        if wanted.frame_rate_hz is not None:
            model = dataclasses.replace(model, frame_rate_hz=wanted.frame_rate_hz)
        self.model: ForwardCameraModel = model
        self.render_process = render_process
        self._renderer: ForwardRenderer | ForwardRenderWorker | None = None

    # -- lifecycle ---------------------------------------------------------------------------------------
    def _start_renderer(self) -> None:
        kind = ForwardRenderWorker if self.render_process else ForwardRenderer
        self._renderer = kind(self.model, walls_array(self.simulation.world.walls), seed=self.seed)

    def _stop_renderer(self) -> None:
        if isinstance(self._renderer, ForwardRenderWorker):
            self._renderer.close()
        self._renderer = None

    # -- what it is --------------------------------------------------------------------------------------
    def settings(self) -> CameraSettings:
        m = self.model
        return CameraSettings(
            m.width_px, m.height_px, self.requested.pixel_format, None, None, m.frame_rate_hz
        )

    @property
    def frame_rate_hz(self) -> float:
        return self.model.frame_rate_hz

    @property
    def renderer(self) -> ForwardRenderer | ForwardRenderWorker:
        if self._renderer is None:
            raise DeviceError("camera is not open", self.name)
        return self._renderer

    # -- frames ------------------------------------------------------------------------------------------
    def _buffer_shape(self) -> tuple[int, ...]:
        return (self.model.height_px, self.model.width_px, 3)

    def _ready_delay_s(self) -> float:
        return 0.0  # global shutter: ready at its start

    def _draw(self, sequence: int, buffer: npt.NDArray[np.uint8]) -> tuple[Frame, ForwardTruth]:
        t = self._t_open + sequence * (1.0 / self.model.frame_rate_hz)
        image, truth = self.renderer.render(
            self.simulation.pose_at(t), people_states(self.simulation, t), t - self.simulation.t_start, buffer
        )
        lent: npt.NDArray[np.uint8] = image
        if self.requested.pixel_format == "Mono8":
            lent = np.asarray(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))
        frame = Frame(lent, sequence, round(t * 1e9), round((t - self._t_open) * 1e9), None)
        return frame, truth
