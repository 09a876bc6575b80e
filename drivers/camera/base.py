"""The camera interface every backend implements (GenICam, V4L2, the simulated camera).

Frames are borrowed: ``with camera.fetch(timeout_s) as frame:`` hands out an image that may live in the
device's own buffer (a GenTL buffer, a reused render target) and gives that buffer back to the device when
the block ends, as harvesters' ``Buffer`` does. Nothing is copied on the hot path; whoever needs the image
after the block uses ``grab()``, which returns a copy.

Settings are requested with :class:`CameraSettings` (``None`` leaves the device's own value). Each backend
applies what its device supports, logs (and does not fail on) what the device lacks, and reads the actual
values back; ``settings()`` reports those, with ``None`` for what the device does not have.
"""

from __future__ import annotations

import abc
import contextlib
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from drivers.device import Device
from drivers.errors import ConfigError, DeviceError, DeviceTimeout
from drivers.samples import Frame

__all__ = ["PIXEL_FORMATS", "Camera", "CameraSettings"]

log = logging.getLogger(__name__)

# Frames are 8-bit (drivers.samples.Frame): single channel for the ceiling camera, whose pipeline has no use
# for colour; BGR8 (OpenCV's channel order) for the forward camera, whose tracker follows clothing colours.
PIXEL_FORMATS = ("Mono8", "BGR8")
_MIN_TIMEOUT_S = 1e-3


@dataclass(frozen=True, slots=True)
class CameraSettings:
    """What to ask of a camera; ``None`` means "leave the device's value".

    ``exposure_s`` and ``frame_rate_hz`` are in SI units whatever the device's own (GenICam ExposureTime is
    in microseconds, V4L2 exposure in 100 us steps). ``gain_db`` is analog gain in decibels.
    """

    width: int | None = None
    height: int | None = None
    pixel_format: str = "Mono8"
    exposure_s: float | None = None
    gain_db: float | None = None
    frame_rate_hz: float | None = None

    def validate(self, section: str = "camera") -> None:
        """Reject values no device could take, naming the key (``camera.exposure_s``)."""
        if self.pixel_format not in PIXEL_FORMATS:
            raise ConfigError(
                f"{section}.pixel_format", f"must be one of {list(PIXEL_FORMATS)}, got {self.pixel_format!r}"
            )
        for name in ("width", "height"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value <= 0):
                raise ConfigError(f"{section}.{name}", f"must be a positive integer, got {value!r}")
        for name in ("exposure_s", "frame_rate_hz"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ConfigError(f"{section}.{name}", f"must be > 0, got {value!r}")


class Camera(Device):
    """A camera producing 8-bit frames: (height, width) for Mono8, (height, width, 3) for BGR8.

    Subclasses implement ``_open``/``_close`` (from :class:`~drivers.device.Device`), ``_acquire`` and
    ``settings``. One thread fetches at a time; ``close()`` may come from another thread.
    """

    def __init__(self, name: str, settings: CameraSettings | None = None) -> None:
        super().__init__(name)
        self.requested = CameraSettings() if settings is None else settings
        self.requested.validate()

    @contextlib.contextmanager
    def fetch(self, timeout_s: float = 1.0) -> Iterator[Frame]:
        """Wait up to ``timeout_s`` for the next frame and lend it for the duration of the ``with`` block.

        The image may be the device's own memory: do not keep it (or views of it) after the block.

        Raises:
            DeviceTimeout: no frame within ``timeout_s``.
            DeviceDisconnected: the device went away.
            DeviceError: the camera is not open, or another device failure.
        """
        if not self.is_open:
            raise DeviceError("camera is not open", self.name)
        try:
            # A zero or negative timeout polls; backends such as harvesters would read 0 as "forever".
            frame, release = self._acquire(max(timeout_s, _MIN_TIMEOUT_S))
        except DeviceTimeout as exc:
            self.count("timeouts")
            self.note_error(str(exc))
            raise
        except DeviceError as exc:
            self.count("errors")
            self.note_error(str(exc))
            raise
        self.count("frames")
        try:
            yield frame
        finally:
            release()

    def grab(self, timeout_s: float = 1.0) -> Frame:
        """The next frame as a copy the caller owns (convenience; ``fetch`` avoids the copy)."""
        with self.fetch(timeout_s) as frame:
            return Frame(
                frame.image.copy(), frame.sequence, frame.host_time_ns, frame.device_time_ns, frame.exposure_s
            )

    @abc.abstractmethod
    def _acquire(self, timeout_s: float) -> tuple[Frame, Callable[[], None]]:
        """The next frame and the function that gives its buffer back to the device."""

    @abc.abstractmethod
    def settings(self) -> CameraSettings:
        """The settings in effect, read back from the device (``None``: the device has no such feature)."""
