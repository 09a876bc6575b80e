"""The simulated camera: frames rendered from the simulated world by the rolling-shutter renderer.

Frames come at the camera's frame rate on the simulation's clock. Frame n starts exposing its first row at
t_open + n / fps plus a random offset of up to ``start_jitter_s`` (the camera runs unsynchronised with the
LEDs, so the stripe phase differs from frame to frame) and is ready once its last row is read out.
``fetch`` waits for the next frame; a consumer that falls behind gets the newest ready frame, and the
skipped sequence numbers are counted as ``dropped``, as a camera whose driver keeps only the latest buffer
(the timing, stall switch, buffer pool and truth history are :mod:`drivers.camera.sim_base`'s, shared with
the forward camera).

Times: ``host_time_ns`` is the mid-readout time (the time the ground-truth pose refers to) on the
simulation's clock, in ns; with the default clock (``time.monotonic``) it is comparable with
``time.monotonic_ns()``. ``device_time_ns`` is the first row's exposure start, counted from ``open()``, like
a camera's own free-running timestamp. ``truth(sequence)`` gives each recent frame's ground truth.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import numpy.typing as npt

from drivers.camera.base import CameraSettings
from drivers.camera.sim_base import SimCameraBase
from drivers.errors import ConfigError, DeviceError
from drivers.samples import Frame
from drivers.sim.render import FrameTruth, RollingShutterRenderer
from drivers.sim.render_worker import RenderWorker
from drivers.sim.simulation import Simulation
from drivers.sim.world import CameraModel

__all__ = ["SimCamera"]

log = logging.getLogger(__name__)


class SimCamera(SimCameraBase[FrameTruth]):
    """A camera looking at the simulated world's ceiling.

    Args:
        simulation: the world and its clock; the robot's true pose at every row comes from it.
        settings: width/height set the output size, ``exposure_s`` the exposure (the LED signal scales with
            it), ``gain_db`` the analog gain, ``frame_rate_hz`` the frame rate; absent ones keep the world's
            camera model.
        seed: seeds the renderer (LED phases, noise) and the frame-start jitter.
        start_jitter_s: each frame's start is delayed by a uniform draw in [0, start_jitter_s).
        truth_history: how many recent frames keep their ground truth.
        render_process: draw the frames in a child process (:mod:`drivers.sim.render_worker`), as a real
            camera delivers them without loading the process that reads them; the same frames.
    """

    def __init__(
        self,
        simulation: Simulation,
        *,
        settings: CameraSettings | None = None,
        seed: int = 0,
        start_jitter_s: float = 1e-3,
        truth_history: int = 64,
        render_process: bool = False,
        name: str = "sim-camera",
    ) -> None:
        super().__init__(name, settings, simulation, seed=seed, truth_history=truth_history)
        if start_jitter_s < 0:
            raise ValueError(f"start_jitter_s must be >= 0, got {start_jitter_s}")
        self.start_jitter_s = start_jitter_s
        self.model = self._model(simulation.world.camera, self.requested)
        self._gain_db = 0.0 if self.requested.gain_db is None else self.requested.gain_db
        self.render_process = render_process
        self._renderer: RollingShutterRenderer | RenderWorker | None = None
        self._rng = np.random.default_rng(seed)

    @staticmethod
    def _model(camera: CameraModel, wanted: CameraSettings) -> CameraModel:
        model = camera
        if wanted.width is not None:
            model = dataclasses.replace(model, output_width_px=wanted.width)
        if wanted.height is not None:
            model = dataclasses.replace(model, output_height_px=wanted.height)
        if wanted.frame_rate_hz is not None:
            model = dataclasses.replace(model, frame_rate_hz=wanted.frame_rate_hz)
        if wanted.exposure_s is not None:
            # The LED delivers a fixed photon rate: the signal at full on-time scales with the exposure.
            peak = model.led_peak_dn * wanted.exposure_s / model.exposure_s
            model = dataclasses.replace(model, exposure_s=wanted.exposure_s, led_peak_dn=peak)
        if model.exposure_s >= 1.0 / model.frame_rate_hz:
            raise ConfigError(
                "camera.exposure_s",
                f"{model.exposure_s:g} s does not fit in a frame at {model.frame_rate_hz:g} fps",
            )
        return model

    # -- lifecycle ---------------------------------------------------------------------------------------
    def _start_renderer(self) -> None:
        world = self.simulation.world
        kind = RenderWorker if self.render_process else RollingShutterRenderer
        self._renderer = kind(
            self.model,
            world.leds,
            world.robot.camera_mount,
            tilt_rad=world.errors.camera_tilt_rad,
            gain_db=self._gain_db,
            seed=self.seed,
            scene=world.scene,
        )

    def _stop_renderer(self) -> None:
        if isinstance(self._renderer, RenderWorker):
            self._renderer.close()
        self._renderer = None

    # -- what it is --------------------------------------------------------------------------------------
    def settings(self) -> CameraSettings:
        m = self.model
        return CameraSettings(
            m.output_width_px, m.output_height_px, "Mono8", m.exposure_s, self._gain_db, m.frame_rate_hz
        )

    @property
    def frame_rate_hz(self) -> float:
        return self.model.frame_rate_hz

    @property
    def renderer(self) -> RollingShutterRenderer | RenderWorker:
        if self._renderer is None:
            raise DeviceError("camera is not open", self.name)
        return self._renderer

    # -- frames ------------------------------------------------------------------------------------------
    def _buffer_shape(self) -> tuple[int, ...]:
        return (self.model.output_height_px, self.model.output_width_px)

    def _ready_delay_s(self) -> float:
        # Whatever its start jitter, a frame is read out this long after its nominal start.
        return self.start_jitter_s + self.renderer.readout_s

    def _draw(self, sequence: int, buffer: npt.NDArray[np.uint8]) -> tuple[Frame, FrameTruth]:
        period = 1.0 / self.model.frame_rate_hz
        t0 = self._t_open + sequence * period + float(self._rng.uniform(0.0, self.start_jitter_s))
        rendered = self.renderer.render(self.simulation.pose_at, t0, out=buffer)
        frame = Frame(
            buffer,
            sequence,
            round(rendered.truth.t_mid_s * 1e9),
            round((t0 - self._t_open) * 1e9),
            self.model.exposure_s,
        )
        return frame, rendered.truth
