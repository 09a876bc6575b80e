"""What the simulated cameras share (:mod:`drivers.camera.sim`, the ceiling camera;
:mod:`drivers.camera.sim_forward`, the forward one): frames due at the model's rate on the simulation's
clock, the wait for the next one, the stall switch, the buffer pool and the ground-truth history.

Frame n is due once ``t_open + n / fps + ready_delay`` has passed on the simulation's clock (the ceiling
camera's delay is its start jitter plus its rolling-shutter readout; the forward camera's global shutter
has none). ``fetch`` waits for the next frame; a consumer that falls behind gets the newest ready frame,
and the skipped sequence numbers are counted as ``dropped``, as a camera whose driver keeps only the latest
buffer. ``stall()`` stops frames (a camera whose trigger or USB transfer hung): ``fetch`` times out and the
frames due meanwhile count as dropped. Frames live in a small pool of buffers and are lent, never copied.
A subclass says how to start and stop its renderer, the buffer's shape, the delay, and how to draw one
frame.
"""

from __future__ import annotations

import abc
import collections
import math
import threading
import time
from collections.abc import Callable
from typing import Generic, TypeVar

import numpy as np
import numpy.typing as npt

from drivers.camera.base import Camera, CameraSettings
from drivers.errors import DeviceTimeout
from drivers.samples import Frame
from drivers.sim.simulation import Simulation

__all__ = ["SimCameraBase"]

TruthT = TypeVar("TruthT")

# Longest single sleep while waiting for a frame: bounds how late a frame is noticed when the simulation
# clock is not the wall clock (a test stepping time from another thread).
_MAX_SLEEP_S = 0.02

_POOL = 3  # buffers per open


class SimCameraBase(Camera, Generic[TruthT]):
    """A camera drawing the simulated world; ``TruthT`` is the ground truth each frame keeps."""

    def __init__(
        self,
        name: str,
        settings: CameraSettings | None,
        simulation: Simulation,
        *,
        seed: int,
        truth_history: int,
    ) -> None:
        super().__init__(name, settings)
        self.simulation = simulation
        self.seed = seed
        self._truths: collections.OrderedDict[int, TruthT] = collections.OrderedDict()
        self._truth_history = truth_history
        self._truth_lock = threading.Lock()
        self._free: list[npt.NDArray[np.uint8]] = []
        self._t_open = 0.0
        self._last_sequence = -1
        self._stalled = threading.Event()

    # -- what a subclass says ----------------------------------------------------------------------------
    @property
    @abc.abstractmethod
    def frame_rate_hz(self) -> float:
        """Frames per second of the model in use."""

    @abc.abstractmethod
    def _buffer_shape(self) -> tuple[int, ...]:
        """The shape of one frame's uint8 buffer."""

    @abc.abstractmethod
    def _start_renderer(self) -> None:
        """Build the renderer (in this process or a child) for this open."""

    @abc.abstractmethod
    def _stop_renderer(self) -> None:
        """Drop the renderer (stopping its child process, if any)."""

    @abc.abstractmethod
    def _ready_delay_s(self) -> float:
        """From frame n's nominal start ``t_open + n / fps`` to when it has surely been read out."""

    @abc.abstractmethod
    def _draw(self, sequence: int, buffer: npt.NDArray[np.uint8]) -> tuple[Frame, TruthT]:
        """Draw frame ``sequence`` into ``buffer``: the frame to lend and its ground truth."""

    # -- fault switch ------------------------------------------------------------------------------------
    def stall(self, stalled: bool = True) -> None:
        """Fault switch for tests and demonstrations: while stalled no frame comes and ``fetch`` times out,
        as from a camera whose trigger or USB transfer stopped. Frames due meanwhile count as ``dropped``."""
        if stalled:
            self._stalled.set()
        else:
            self._stalled.clear()

    # -- lifecycle ---------------------------------------------------------------------------------------
    def _open(self) -> None:
        self._start_renderer()
        self._free = [self._new_buffer() for _ in range(_POOL)]
        self._t_open = self.simulation.now()
        self._last_sequence = -1
        with self._truth_lock:
            self._truths.clear()

    def _close(self) -> None:
        self._stop_renderer()
        self._free = []

    def _new_buffer(self) -> npt.NDArray[np.uint8]:
        return np.empty(self._buffer_shape(), dtype=np.uint8)

    # -- ground truth ------------------------------------------------------------------------------------
    def truth(self, sequence: int) -> TruthT:
        """Ground truth of a recent frame. Raises KeyError when the frame is older than the kept history."""
        with self._truth_lock:
            return self._truths[sequence]

    @property
    def last_truth(self) -> TruthT | None:
        with self._truth_lock:
            return next(reversed(self._truths.values()), None)

    # -- frames ------------------------------------------------------------------------------------------
    def _acquire(self, timeout_s: float) -> tuple[Frame, Callable[[], None]]:
        delay = self._ready_delay_s()
        period = 1.0 / self.frame_rate_hz
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
            newest = math.floor((now - self._t_open - delay) / period)
            sequence = max(wanted, newest)
            ready = self._t_open + sequence * period + delay
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

        buffer = self._free.pop() if self._free else self._new_buffer()
        frame, truth = self._draw(sequence, buffer)
        with self._truth_lock:
            self._truths[sequence] = truth
            while len(self._truths) > self._truth_history:
                self._truths.popitem(last=False)
        free = self._free

        def release() -> None:
            # Back to this open's pool (a buffer lent before a close/open does not join the new pool).
            if free is self._free:
                free.append(buffer)

        return frame, release
