"""The simulated forward camera: colour frames of the world's walls and people (``sim.forward_render``).

Frames come at the model's frame rate on the simulation's clock, global shutter: frame n is exposed at
t_open + n / fps and ready at once. ``fetch`` waits for the next frame; a consumer that falls behind gets
the newest one and the skipped sequence numbers count as ``dropped``. Frames are BGR8, shape
(height, width, 3), or Mono8 when the settings ask for it; they live in a small pool of buffers and are
lent, never copied, as every camera's are. ``truth(sequence)`` gives each recent frame's ground truth (the
boxes of the people in view). ``stall()`` stops frames (a camera whose USB transfer hung).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable

import cv2
import numpy as np
import numpy.typing as npt

from drivers.camera.base import Camera, CameraSettings
from drivers.errors import DeviceError, DeviceTimeout
from drivers.samples import Frame
from drivers.sim.forward_render import ForwardRenderer, ForwardTruth, PersonState
from drivers.sim.forward_render_worker import ForwardRenderWorker
from drivers.sim.raycast import walls_array
from drivers.sim.simulation import Simulation
from drivers.sim.world import ForwardCameraModel

__all__ = ["SimForwardCamera", "people_states"]

log = logging.getLogger(__name__)

_MAX_SLEEP_S = 0.02


def people_states(simulation: Simulation, t: float) -> list[PersonState]:
    """Every person of the simulation at time ``t``, as the renderer takes them."""
    out = []
    for person in simulation.world.people:
        x, y, heading, walked = simulation.person_pose(person, t)
        out.append(PersonState(person, x, y, heading, walked))
    return out


class SimForwardCamera(Camera):
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
        super().__init__(name, settings if settings is not None else CameraSettings(pixel_format="BGR8"))
        self.simulation = simulation
        self.seed = seed
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
        self._truths: collections.OrderedDict[int, ForwardTruth] = collections.OrderedDict()
        self._truth_history = truth_history
        self._truth_lock = threading.Lock()
        self._free: list[npt.NDArray[np.uint8]] = []
        self._t_open = 0.0
        self._last_sequence = -1
        self._stalled = threading.Event()

    def stall(self, stalled: bool = True) -> None:
        """While stalled no frame comes and ``fetch`` times out; frames due meanwhile count as dropped."""
        if stalled:
            self._stalled.set()
        else:
            self._stalled.clear()

    # -- lifecycle ---------------------------------------------------------------------------------------
    def _open(self) -> None:
        world = self.simulation.world
        kind = ForwardRenderWorker if self.render_process else ForwardRenderer
        self._renderer = kind(self.model, walls_array(world.walls), seed=self.seed)
        self._free = [self._new_buffer() for _ in range(3)]
        self._t_open = self.simulation.now()
        self._last_sequence = -1
        with self._truth_lock:
            self._truths.clear()

    def _close(self) -> None:
        if isinstance(self._renderer, ForwardRenderWorker):
            self._renderer.close()
        self._renderer = None
        self._free = []

    def _new_buffer(self) -> npt.NDArray[np.uint8]:
        return np.empty((self.model.height_px, self.model.width_px, 3), dtype=np.uint8)

    # -- what it is --------------------------------------------------------------------------------------
    def settings(self) -> CameraSettings:
        m = self.model
        return CameraSettings(
            m.width_px, m.height_px, self.requested.pixel_format, None, None, m.frame_rate_hz
        )

    def truth(self, sequence: int) -> ForwardTruth:
        """Ground truth of a recent frame. Raises KeyError when it is older than the kept history."""
        with self._truth_lock:
            return self._truths[sequence]

    @property
    def last_truth(self) -> ForwardTruth | None:
        with self._truth_lock:
            return next(reversed(self._truths.values()), None)

    # -- frames ------------------------------------------------------------------------------------------
    def _acquire(self, timeout_s: float) -> tuple[Frame, Callable[[], None]]:
        renderer = self._renderer
        if renderer is None:
            raise DeviceError("camera is not open", self.name)
        period = 1.0 / self.model.frame_rate_hz
        deadline = time.monotonic() + timeout_s
        wanted = self._last_sequence + 1
        while True:
            if self._stalled.is_set():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise DeviceTimeout(f"no frame within {timeout_s:g} s (the camera is stalled)", self.name)
                time.sleep(min(remaining, _MAX_SLEEP_S))
                continue
            now = self.simulation.now()
            newest = math.floor((now - self._t_open) / period)
            sequence = max(wanted, newest)
            ready = self._t_open + sequence * period
            if ready <= now:
                break
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise DeviceTimeout(
                    f"no frame within {timeout_s:g} s (next one in {ready - now:.3f} s of simulated time)",
                    self.name,
                )
            time.sleep(min(ready - now, remaining, _MAX_SLEEP_S))
        if sequence > wanted:
            self.count("dropped", sequence - wanted)
        self._last_sequence = sequence
        t = self._t_open + sequence * period
        buffer = self._free.pop() if self._free else self._new_buffer()
        image, truth = renderer.render(
            self.simulation.pose_at(t), people_states(self.simulation, t), t - self.simulation.t_start, buffer
        )
        with self._truth_lock:
            self._truths[sequence] = truth
            while len(self._truths) > self._truth_history:
                self._truths.popitem(last=False)
        lent: npt.NDArray[np.uint8] = image
        if self.requested.pixel_format == "Mono8":
            lent = np.asarray(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))
        frame = Frame(lent, sequence, round(t * 1e9), round((t - self._t_open) * 1e9), None)
        free = self._free

        def release() -> None:
            if free is self._free:
                free.append(buffer)

        return frame, release
