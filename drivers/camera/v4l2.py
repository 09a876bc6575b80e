"""V4L2 cameras (UVC webcams, CSI cameras with a V4L2 driver) through OpenCV's ``CAP_V4L2`` backend.

Facts this relies on (OpenCV ``modules/videoio/src/cap_v4l.cpp``, ``reference/devices.md`` §4):

* ``CAP_PROP_AUTO_EXPOSURE`` maps to ``V4L2_CID_EXPOSURE_AUTO`` and takes the raw menu value: 1 is manual
  (``V4L2_EXPOSURE_MANUAL``), 3 aperture priority (what UVC cameras call auto). The folklore 0.25/0.75 only
  holds with range normalisation on, so it is switched off explicitly (``CAP_PROP_MODE`` = 0).
* ``CAP_PROP_EXPOSURE`` is ``V4L2_CID_EXPOSURE_ABSOLUTE``, in units of 100 us.
* ``CAP_PROP_GAIN`` is ``V4L2_CID_GAIN`` in the driver's own unit-less steps, so a gain in dB cannot be
  mapped; give ``gain_raw`` instead.
* ``set()`` ignores the driver clamping a value (or refusing it with ERANGE), so every value is read back
  with ``get()``, which returns -1 for a control the device lacks.
* ``CAP_PROP_POS_MSEC`` is the V4L2 buffer timestamp in ms (``CLOCK_MONOTONIC`` for UVC): the device time.
* A read waits for a frame up to ``OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT`` seconds (default 10), read once per
  process, and ``CAP_PROP_READ_TIMEOUT_MSEC`` is not implemented for V4L2; ``fetch(timeout_s)`` therefore
  cannot cut a read short. Set that variable in the process's ``main`` for a shorter stall detection.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from drivers.camera.base import Camera, CameraSettings
from drivers.errors import BackendUnavailable, DeviceDisconnected, DeviceError, DeviceNotFound, DeviceTimeout
from drivers.samples import Frame

__all__ = ["CaptureLike", "V4l2Camera"]

log = logging.getLogger(__name__)

# V4L2_EXPOSURE_MANUAL in enum v4l2_exposure_auto_type (linux/v4l2-controls.h).
V4L2_EXPOSURE_MANUAL = 1
# V4L2_CID_EXPOSURE_ABSOLUTE counts in 100 us units.
EXPOSURE_UNIT_S = 100e-6


class CaptureLike(Protocol):
    """The part of ``cv2.VideoCapture`` the driver uses (tests inject a stand-in)."""

    def isOpened(self) -> bool: ...  # OpenCV's name

    def set(self, prop_id: int, value: float) -> bool: ...

    def get(self, prop_id: int) -> float: ...

    def read(self) -> tuple[bool, Any]: ...

    def release(self) -> None: ...


class V4l2Camera(Camera):
    """A V4L2 camera, by index (``/dev/video<index>``) or device path.

    Args:
        device: index or path (``/dev/video0``, or a stable ``/dev/v4l/by-id/...`` link).
        settings: what to apply on open. ``gain_db`` is not applicable to V4L2 (see ``gain_raw``).
        gain_raw: the driver's own gain value, applied when given.
        capture_factory: ``(device, api) -> capture``; ``cv2.VideoCapture`` by default.
    """

    def __init__(
        self,
        device: int | str = 0,
        *,
        settings: CameraSettings | None = None,
        gain_raw: float | None = None,
        name: str | None = None,
        capture_factory: Callable[[int | str, int], CaptureLike] | None = None,
    ) -> None:
        super().__init__(name or f"v4l2:{device}", settings)
        self.device = device
        self.gain_raw = gain_raw
        self._factory = capture_factory
        self._cap: CaptureLike | None = None
        self._cv2: Any = None
        self._actual = CameraSettings()
        self._sequence = 0

    @property
    def device_path(self) -> str:
        return self.device if isinstance(self.device, str) else f"/dev/video{self.device}"

    # -- lifecycle ---------------------------------------------------------------------------------------
    def _open(self) -> None:
        try:
            import cv2
        except ImportError as exc:
            raise BackendUnavailable(
                "the v4l2 backend needs OpenCV: pip install 'opencv-python-headless>=4.10,<5'", self.name
            ) from exc
        self._cv2 = cv2
        factory = self._factory or cv2.VideoCapture
        cap = factory(self.device, cv2.CAP_V4L2)
        if not cap.isOpened():
            cap.release()
            raise DeviceNotFound(f"no V4L2 camera could be opened at {self.device_path}", self.name)
        self._cap = cap
        self._sequence = 0
        try:
            self._apply(self.requested)
        except BaseException:
            self._close()
            raise

    def _close(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()

    # -- settings ----------------------------------------------------------------------------------------
    def settings(self) -> CameraSettings:
        return self._actual

    def _apply(self, wanted: CameraSettings) -> None:
        cv2, cap = self._cv2, self._cap
        assert cap is not None
        # Raw V4L2 values (menu indices, 100 us units) instead of OpenCV's optional [0, 1) normalisation.
        cap.set(cv2.CAP_PROP_MODE, 0)
        if wanted.width is not None:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, wanted.width)
        if wanted.height is not None:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, wanted.height)
        if wanted.frame_rate_hz is not None and not cap.set(cv2.CAP_PROP_FPS, wanted.frame_rate_hz):
            log.warning("%s: the device refused a frame rate of %g fps", self.name, wanted.frame_rate_hz)
        if wanted.exposure_s is not None:
            if not cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, V4L2_EXPOSURE_MANUAL):
                log.warning("%s: the device has no manual exposure mode (V4L2_CID_EXPOSURE_AUTO)", self.name)
            steps = max(1, round(wanted.exposure_s / EXPOSURE_UNIT_S))
            if not cap.set(cv2.CAP_PROP_EXPOSURE, steps):
                log.warning(
                    "%s: the device has no V4L2_CID_EXPOSURE_ABSOLUTE; exposure left as it is", self.name
                )
        if wanted.gain_db is not None:
            log.warning(
                "%s: V4L2 gain has no unit, so gain_db %g is not applied; use gain_raw",
                self.name,
                wanted.gain_db,
            )
        if self.gain_raw is not None and not cap.set(cv2.CAP_PROP_GAIN, self.gain_raw):
            log.warning("%s: the device has no V4L2_CID_GAIN; gain left as it is", self.name)
        self._actual = self._read_back(wanted)
        log.info("%s: applied %s", self.name, self._actual)

    def _read_back(self, wanted: CameraSettings) -> CameraSettings:
        cv2, cap = self._cv2, self._cap
        assert cap is not None

        def prop(prop_id: int) -> float | None:
            value = float(cap.get(prop_id))
            return value if value >= 0 else None  # OpenCV returns -1 for a control the device lacks

        width, height = prop(cv2.CAP_PROP_FRAME_WIDTH), prop(cv2.CAP_PROP_FRAME_HEIGHT)
        fps = prop(cv2.CAP_PROP_FPS)
        exposure_steps = prop(cv2.CAP_PROP_EXPOSURE)
        actual = CameraSettings(
            width=None if not width else int(width),
            height=None if not height else int(height),
            pixel_format=wanted.pixel_format,
            exposure_s=None if exposure_steps is None else exposure_steps * EXPOSURE_UNIT_S,
            gain_db=None,
            frame_rate_hz=fps or None,
        )
        if wanted.exposure_s is not None:
            mode = prop(cv2.CAP_PROP_AUTO_EXPOSURE)
            if mode != V4L2_EXPOSURE_MANUAL:
                log.warning("%s: auto exposure is still %s after asking for manual (1)", self.name, mode)
        for name, asked, got in (
            ("width", wanted.width, actual.width),
            ("height", wanted.height, actual.height),
            ("frame_rate_hz", wanted.frame_rate_hz, actual.frame_rate_hz),
            ("exposure_s", wanted.exposure_s, actual.exposure_s),
        ):
            if asked is not None and (
                got is None or abs(got - asked) > 0.02 * abs(asked) + EXPOSURE_UNIT_S / 2
            ):
                log.warning("%s: asked for %s %g, the device reports %s", self.name, name, asked, got)
        return actual

    # -- frames ------------------------------------------------------------------------------------------
    def _acquire(self, timeout_s: float) -> tuple[Frame, Callable[[], None]]:
        cv2, cap = self._cv2, self._cap
        if cap is None:
            raise DeviceDisconnected("camera is not open", self.name)
        try:
            ok, image = cap.read()
        except cv2.error as exc:
            raise DeviceDisconnected(f"the capture failed: {exc}", self.name) from exc
        host_ns = time.monotonic_ns()
        if not ok or image is None:
            if not os.path.exists(self.device_path):
                raise DeviceDisconnected(f"{self.device_path} is gone", self.name)
            raise DeviceTimeout("no frame (OpenCV's V4L2 wait ran out, or the stream stalled)", self.name)
        grey = self._to_grey(image) if self.requested.pixel_format == "Mono8" else self._to_bgr(image)
        self._sequence += 1
        pos_ms = float(cap.get(cv2.CAP_PROP_POS_MSEC))
        device_ns = round(pos_ms * 1e6) if pos_ms > 0 else None
        # OpenCV hands back a fresh array each read: nothing is borrowed, nothing to give back.
        return Frame(grey, self._sequence, host_ns, device_ns, self._actual.exposure_s), _nothing

    def _to_bgr(self, image: Any) -> npt.NDArray[np.uint8]:
        """BGR8 frames: OpenCV's V4L2 backend converts to BGR by itself; a grey device is widened."""
        array = np.asarray(image)
        if array.ndim == 2 or (array.ndim == 3 and array.shape[2] == 1):
            array = np.asarray(self._cv2.cvtColor(array.reshape(array.shape[:2]), self._cv2.COLOR_GRAY2BGR))
        if array.ndim != 3 or array.shape[2] != 3 or array.dtype != np.uint8:
            raise DeviceError(f"unusable frame: {array.dtype} {array.shape}", self.name)
        bgr: npt.NDArray[np.uint8] = array
        return bgr

    def _to_grey(self, image: Any) -> npt.NDArray[np.uint8]:
        array = np.asarray(image)
        if array.ndim == 3 and array.shape[2] == 3:
            array = np.asarray(self._cv2.cvtColor(array, self._cv2.COLOR_BGR2GRAY))
        elif array.ndim == 3 and array.shape[2] == 1:
            array = array[:, :, 0]
        if array.ndim != 2 or array.dtype != np.uint8:
            raise DeviceError(f"unusable frame: {array.dtype} {array.shape}", self.name)
        grey: npt.NDArray[np.uint8] = array
        return grey


def _nothing() -> None:
    return None
