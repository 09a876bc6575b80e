"""The simulated camera: frames rendered from the simulated world by the rolling-shutter renderer.

Frames come at the camera's frame rate on the simulation's clock. Frame n starts exposing its first row at
t_open + n / fps plus a random offset of up to ``start_jitter_s`` (the camera runs unsynchronised with the
LEDs, so the stripe phase differs from frame to frame) and is ready once its last row is read out.
``fetch`` waits for the next frame; a consumer that falls behind gets the newest ready frame, and the
skipped sequence numbers are counted as ``dropped``, as a camera whose driver keeps only the latest buffer.

Times: ``host_time_ns`` is the mid-readout time (the time the ground-truth pose refers to) on the
simulation's clock, in ns; with the default clock (``time.monotonic``) it is comparable with
``time.monotonic_ns()``. ``device_time_ns`` is the first row's exposure start, counted from ``open()``, like
a camera's own free-running timestamp. ``truth(sequence)`` gives each recent frame's ground truth.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from drivers.camera.base import Camera, CameraSettings
from drivers.errors import ConfigError, DeviceError, DeviceTimeout
from drivers.samples import Frame
from drivers.sim.render import FrameTruth, RollingShutterRenderer
from drivers.sim.render_worker import RenderWorker
from drivers.sim.simulation import Simulation
from drivers.sim.world import CameraModel

__all__ = ["SimCamera"]

log = logging.getLogger(__name__)

# Longest single sleep while waiting for a frame: bounds how late a frame is noticed when the simulation
# clock is not the wall clock (a test stepping time from another thread).
_MAX_SLEEP_S = 0.02


class SimCamera(Camera):
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
        super().__init__(name, settings)
        if start_jitter_s < 0:
            raise ValueError(f"start_jitter_s must be >= 0, got {start_jitter_s}")
        self.simulation = simulation
        self.seed = seed
        self.start_jitter_s = start_jitter_s
        self.model = self._model(simulation.world.camera, self.requested)
        self._gain_db = 0.0 if self.requested.gain_db is None else self.requested.gain_db
        self.render_process = render_process
        self._renderer: RollingShutterRenderer | RenderWorker | None = None
        self._rng = np.random.default_rng(seed)
        self._truths: collections.OrderedDict[int, FrameTruth] = collections.OrderedDict()
        self._truth_history = truth_history
        self._truth_lock = threading.Lock()
        self._free: list[npt.NDArray[np.uint8]] = []
        self._t_open = 0.0
        self._last_sequence = -1
        self._stalled = threading.Event()

    def stall(self, stalled: bool = True) -> None:
        """Fault switch for tests and demonstrations: while stalled no frame comes and ``fetch`` times out,
        as from a camera whose trigger or USB transfer stopped. Frames due meanwhile count as ``dropped``."""
        if stalled:
            self._stalled.set()
        else:
            self._stalled.clear()

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
    def _open(self) -> None:
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
        shape = (self.model.output_height_px, self.model.output_width_px)
        self._free = [np.empty(shape, dtype=np.uint8) for _ in range(3)]
        self._t_open = self.simulation.now()
        self._last_sequence = -1
        with self._truth_lock:
            self._truths.clear()

    def _close(self) -> None:
        if isinstance(self._renderer, RenderWorker):
            self._renderer.close()
        self._renderer = None
        self._free = []

    # -- what it is --------------------------------------------------------------------------------------
    def settings(self) -> CameraSettings:
        m = self.model
        return CameraSettings(
            m.output_width_px, m.output_height_px, "Mono8", m.exposure_s, self._gain_db, m.frame_rate_hz
        )

    @property
    def renderer(self) -> RollingShutterRenderer | RenderWorker:
        if self._renderer is None:
            raise DeviceError("camera is not open", self.name)
        return self._renderer

    def truth(self, sequence: int) -> FrameTruth:
        """Ground truth of a recent frame. Raises KeyError when the frame is older than the kept history."""
        with self._truth_lock:
            return self._truths[sequence]

    @property
    def last_truth(self) -> FrameTruth | None:
        with self._truth_lock:
            return next(reversed(self._truths.values()), None)

    # -- frames ------------------------------------------------------------------------------------------
    def _ready_time(self, sequence: int) -> float:
        """When frame ``sequence`` has surely been read out, whatever its start jitter."""
        period = 1.0 / self.model.frame_rate_hz
        return self._t_open + sequence * period + self.start_jitter_s + self.renderer.readout_s

    def _acquire(self, timeout_s: float) -> tuple[Frame, Callable[[], None]]:
        renderer = self.renderer
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
            # The newest frame that is ready now; at least the one after the last delivered.
            newest = math.floor((now - self._t_open - self.start_jitter_s - renderer.readout_s) / period)
            sequence = max(wanted, newest)
            ready = self._ready_time(sequence)
            if ready <= now:
                break
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise DeviceTimeout(
                    f"no frame within {timeout_s:g} s (next one due in {ready - now:.3f} s of "
                    "simulated time)",
                    self.name,
                )
            time.sleep(min(ready - now, remaining, _MAX_SLEEP_S))
        if sequence > wanted:
            self.count("dropped", sequence - wanted)
        self._last_sequence = sequence

        t0 = self._t_open + sequence * period + float(self._rng.uniform(0.0, self.start_jitter_s))
        buffer = (
            self._free.pop()
            if self._free
            else np.empty((self.model.output_height_px, self.model.output_width_px), dtype=np.uint8)
        )
        rendered = renderer.render(self.simulation.pose_at, t0, out=buffer)
        with self._truth_lock:
            self._truths[sequence] = rendered.truth
            while len(self._truths) > self._truth_history:
                self._truths.popitem(last=False)
        frame = Frame(
            buffer,
            sequence,
            round(rendered.truth.t_mid_s * 1e9),
            round((t0 - self._t_open) * 1e9),
            self.model.exposure_s,
        )
        free = self._free

        def release() -> None:
            # Back to this open's pool (a buffer lent before a close/open does not join the new pool).
            if free is self._free:
                free.append(buffer)

        return frame, release
