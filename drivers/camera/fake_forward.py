"""A stand-in forward camera (``[camera.forward] backend = "fake"``): serves one still image over and over
at the frame rate, stamped like a real camera's frames (host monotonic clock).

For running the agent's person following without the camera on a bench or in a test (``docs/config.md``):
the image (PNG, JPEG or anything else OpenCV reads, or a NumPy ``.npy`` array of uint8 BGR) is read at
open; a file that is missing or not an 8-bit colour image fails the open with a clear error, as an
unplugged camera would. Frames stay in memory like every frame.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import numpy.typing as npt

from drivers.camera.base import Camera, CameraSettings
from drivers.errors import DeviceDisconnected, DeviceNotFound, DeviceTimeout
from drivers.samples import Frame

__all__ = ["FakeForwardCamera"]

DEFAULT_RATE_HZ = 15.0


def read_image(path: Path) -> npt.NDArray[np.uint8]:
    """The image in ``path`` as (height, width, 3) uint8 BGR; DeviceNotFound when it cannot be."""
    if not path.is_file():
        raise DeviceNotFound(f"no such image file: {path}", "fake-forward-camera")
    if path.suffix.lower() == ".npy":
        image = np.load(path, allow_pickle=False)
    else:
        import cv2

        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise DeviceNotFound(f"{path} is not an image OpenCV can read", "fake-forward-camera")
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise DeviceNotFound(
            f"{path} is not an 8-bit colour image (shape {image.shape}, {image.dtype})", "fake-forward-camera"
        )
    return np.ascontiguousarray(image)


class FakeForwardCamera(Camera):
    def __init__(
        self,
        image: str,
        *,
        settings: CameraSettings | None = None,
        name: str = "fake-forward-camera",
    ) -> None:
        super().__init__(name, settings if settings is not None else CameraSettings(pixel_format="BGR8"))
        self.path = Path(image)
        self._image: npt.NDArray[np.uint8] | None = None
        self._sequence = 0
        self._next_ns = 0
        self._closed = threading.Event()

    def _open(self) -> None:
        image = read_image(self.path)
        wanted = self.requested
        if (wanted.width is not None and wanted.width != image.shape[1]) or (
            wanted.height is not None and wanted.height != image.shape[0]
        ):
            raise DeviceNotFound(
                f"{self.path} is {image.shape[1]}x{image.shape[0]}, the settings ask for "
                f"{wanted.width}x{wanted.height}",
                self.name,
            )
        self._image = image
        self._next_ns = time.monotonic_ns()
        self._closed.clear()

    def _close(self) -> None:
        self._image = None
        self._closed.set()

    def settings(self) -> CameraSettings:
        image = self._image
        return CameraSettings(
            width=None if image is None else image.shape[1],
            height=None if image is None else image.shape[0],
            pixel_format="BGR8",
            frame_rate_hz=self._rate_hz,
        )

    @property
    def _rate_hz(self) -> float:
        rate = self.requested.frame_rate_hz
        return DEFAULT_RATE_HZ if rate is None else rate

    def _acquire(self, timeout_s: float) -> tuple[Frame, Callable[[], None]]:
        image = self._image
        if image is None:
            raise DeviceDisconnected("camera is not open", self.name)
        wait_s = (self._next_ns - time.monotonic_ns()) / 1e9
        if wait_s > timeout_s:
            self._closed.wait(timeout_s)
            raise DeviceTimeout("no frame yet (the next is due later)", self.name)
        if wait_s > 0 and self._closed.wait(wait_s):
            raise DeviceDisconnected("camera closed", self.name)
        now = time.monotonic_ns()
        self._next_ns = max(self._next_ns + round(1e9 / self._rate_hz), now)
        self._sequence += 1
        return Frame(image, self._sequence, now, None, None), lambda: None
