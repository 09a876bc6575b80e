"""GenICam cameras through harvesters and a GenTL producer (``.cti``).

The producer is the backend: a vendor's ``.cti`` drives real cameras, and ``viky.cti`` (shipped in the
``genicam`` wheel) is a simulated one the contract tests run against. Features are reached by their SFNC
names and only where the node map has them: viky has Width, Height, PixelFormat and AcquisitionFrameRate
but no ExposureTime or Gain, and its buffers have no timestamp (``NotAvailableException``), so frames then
carry only the host time (``reference/devices.md`` §4).

Frames are borrowed GenTL buffers: the image is a view of the producer's memory, and the buffer is queued
back to the producer when the ``fetch`` block ends.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from drivers.camera.base import Camera, CameraSettings
from drivers.errors import BackendUnavailable, DeviceDisconnected, DeviceError, DeviceNotFound, DeviceTimeout
from drivers.samples import Frame

__all__ = ["GenicamCamera", "viky_cti_path"]

log = logging.getLogger(__name__)

_INSTALL_HINT = "pip install harvesters genicam"


def viky_cti_path() -> str:
    """Path of the simulated GenTL producer shipped in the ``genicam`` wheel (may not exist)."""
    try:
        import genicam
    except ImportError as exc:
        raise BackendUnavailable(f"the genicam package is not installed: {_INSTALL_HINT}", "genicam") from exc
    return os.path.join(os.path.dirname(os.path.abspath(genicam.__file__)), "viky.cti")


class GenicamCamera(Camera):
    """A GenICam camera reached through the GenTL producer ``cti``.

    Args:
        cti: path of the producer (``.cti``) file.
        device_index: which of the producer's devices, when ``serial`` is not given.
        serial: pick the device by serial number instead.
        settings: what to apply on open (see :class:`~drivers.camera.base.CameraSettings`).
        name: for logs and health; defaults to the producer file and device.
    """

    def __init__(
        self,
        cti: str,
        device_index: int = 0,
        *,
        serial: str | None = None,
        settings: CameraSettings | None = None,
        name: str | None = None,
    ) -> None:
        super().__init__(name or f"genicam:{os.path.basename(cti)}#{serial or device_index}", settings)
        self.cti = cti
        self.device_index = device_index
        self.serial = serial
        self._harvester: Any = None
        self._acquirer: Any = None
        self._actual = CameraSettings()
        self._device_timestamps = True
        self._sequence = 0
        self._errors: tuple[type[BaseException], type[BaseException], type[BaseException]] | None = None

    # -- lifecycle ---------------------------------------------------------------------------------------
    def _open(self) -> None:
        if not os.path.isfile(self.cti):
            raise DeviceNotFound(f"GenTL producer file not found: {self.cti}", self.cti)
        try:
            from genicam.genapi import GenericException as GenapiError
            from genicam.gentl import GenericException, NotAvailableException, TimeoutException
            from harvesters.core import Harvester
        except ImportError as exc:
            raise BackendUnavailable(
                f"the genicam backend needs harvesters and genicam: {_INSTALL_HINT}", self.name
            ) from exc
        self._errors = (TimeoutException, NotAvailableException, GenericException)
        self._device_timestamps = True
        self._sequence = 0
        try:
            self._harvester = Harvester()
            self._harvester.add_file(self.cti)
            self._harvester.update()
            self._acquirer = self._create(self._select_device())
            self._apply(self.requested)
            self._acquirer.start()
        except (GenericException, GenapiError) as exc:
            self._teardown()
            raise DeviceError(f"the producer failed while opening the camera: {exc}", self.name) from exc
        except BaseException:
            self._teardown()
            raise

    def _select_device(self) -> int:
        infos = list(self._harvester.device_info_list)
        if not infos:
            raise DeviceNotFound(
                f"the producer {self.cti} lists no devices (no camera attached, or not a GenTL producer: "
                "harvesters logs why)",
                self.name,
            )
        if self.serial is not None:
            serials = [str(getattr(info, "serial_number", "")) for info in infos]
            if self.serial not in serials:
                raise DeviceNotFound(
                    f"no device with serial {self.serial!r}; the producer lists {serials}", self.name
                )
            return serials.index(self.serial)
        if not 0 <= self.device_index < len(infos):
            raise DeviceNotFound(
                f"device index {self.device_index} is out of range: the producer lists "
                f"{len(infos)} device(s)",
                self.name,
            )
        return self.device_index

    def _create(self, index: int) -> Any:
        assert self._errors is not None
        # harvesters installs its own SIGINT handler when created in the main thread; signals belong to the
        # process's main(), so the previous handler is put back.
        in_main = threading.current_thread() is threading.main_thread()
        previous = signal.getsignal(signal.SIGINT) if in_main else None
        try:
            return self._harvester.create(index)
        except self._errors[2] as exc:
            raise DeviceError(f"cannot open device {index}: {exc}", self.name) from exc
        finally:
            if in_main:
                signal.signal(signal.SIGINT, previous)

    def _close(self) -> None:
        self._teardown()

    def _teardown(self) -> None:
        """Stop, destroy, reset; each step guarded so a failing one does not leave the others undone."""
        acquirer, harvester = self._acquirer, self._harvester
        self._acquirer = self._harvester = None
        steps: list[tuple[str, Callable[[], object]]] = []
        if acquirer is not None:
            steps += [("stop", acquirer.stop), ("destroy", acquirer.destroy)]
        if harvester is not None:
            steps.append(("reset", harvester.reset))
        for what, step in steps:
            try:
                step()
            except Exception as exc:  # closing must go on; the failure is logged
                log.warning("%s: %s failed while closing: %s", self.name, what, exc)

    # -- settings ----------------------------------------------------------------------------------------
    def settings(self) -> CameraSettings:
        return self._actual

    def _apply(self, wanted: CameraSettings) -> None:
        node_map = self._acquirer.remote_device.node_map
        self._set_pixel_format(node_map, wanted.pixel_format)
        if wanted.width is not None:
            self._set_integer(node_map, "Width", wanted.width)
        if wanted.height is not None:
            self._set_integer(node_map, "Height", wanted.height)
        if wanted.exposure_s is not None:
            self._set_off(node_map, "ExposureAuto")
            # SFNC ExposureTime, or the older GigE Vision ExposureTimeAbs; both in microseconds.
            if not self._set_float(node_map, ("ExposureTime", "ExposureTimeAbs"), wanted.exposure_s * 1e6):
                log.warning("%s: the device has no ExposureTime feature; exposure left as it is", self.name)
        if wanted.gain_db is not None:
            self._set_off(node_map, "GainAuto")
            if not self._set_float(node_map, ("Gain",), wanted.gain_db):
                # GainRaw exists on some devices but has no defined unit, so a dB value cannot be mapped.
                log.warning("%s: the device has no Gain feature (dB); gain left as it is", self.name)
        if wanted.frame_rate_hz is not None:
            enable = _node(node_map, "AcquisitionFrameRateEnable")
            if enable is not None:
                self._try_set(enable, True, "AcquisitionFrameRateEnable")
            if not self._set_float(
                node_map, ("AcquisitionFrameRate", "AcquisitionFrameRateAbs"), wanted.frame_rate_hz
            ):
                log.warning(
                    "%s: the device has no AcquisitionFrameRate feature; it runs at its own rate", self.name
                )
        self._actual = self._read_back(node_map)
        log.info("%s: applied %s", self.name, self._actual)

    def _set_pixel_format(self, node_map: Any, pixel_format: str) -> None:
        node = _node(node_map, "PixelFormat")
        if node is None:
            log.warning(
                "%s: no PixelFormat feature; frames are checked to be %s as they come",
                self.name,
                pixel_format,
            )
            return
        offered = tuple(str(s) for s in getattr(node, "symbolics", ()))
        if offered and pixel_format == "BGR8" and "BGR8" not in offered and "RGB8" in offered:
            pixel_format = "RGB8"  # swapped to BGR as frames come (_image)
        if offered and pixel_format not in offered:
            raise DeviceError(
                f"the device does not offer {pixel_format} (it offers {list(offered)})", self.name
            )
        self._try_set(node, pixel_format, "PixelFormat")

    def _set_integer(self, node_map: Any, name: str, value: int) -> None:
        node = _node(node_map, name)
        if node is None:
            log.warning("%s: the device has no %s feature", self.name, name)
            return
        lo, hi, inc = int(node.min), int(node.max), max(int(getattr(node, "inc", 1) or 1), 1)
        # GenICam integers take min + k * inc within [min, max]; a request outside is moved to the nearest.
        fitted = min(max(value, lo), hi)
        fitted = lo + round((fitted - lo) / inc) * inc
        if fitted > hi:
            fitted -= inc
        if fitted != value:
            log.warning(
                "%s: %s %d is not possible (min %d, max %d, step %d); using %d",
                self.name,
                name,
                value,
                lo,
                hi,
                inc,
                fitted,
            )
        self._try_set(node, fitted, name)

    def _set_float(self, node_map: Any, names: tuple[str, ...], value: float) -> bool:
        for name in names:
            node = _node(node_map, name)
            if node is None:
                continue
            lo, hi = float(node.min), float(node.max)
            fitted = min(max(value, lo), hi)
            if fitted != value:
                log.warning("%s: %s %g is outside [%g, %g]; using %g", self.name, name, value, lo, hi, fitted)
            self._try_set(node, fitted, name)
            return True
        return False

    def _set_off(self, node_map: Any, name: str) -> None:
        node = _node(node_map, name)
        if node is not None:
            self._try_set(node, "Off", name)

    def _try_set(self, node: Any, value: object, name: str) -> None:
        try:
            node.value = value
        except Exception as exc:  # genapi raises several unrelated types; all mean "not applied"
            log.warning("%s: could not set %s to %r: %s", self.name, name, value, exc)

    def _read_back(self, node_map: Any) -> CameraSettings:
        def number(*names: str) -> float | None:
            for name in names:
                node = _node(node_map, name)
                if node is not None:
                    try:
                        return float(node.value)
                    except Exception:  # an unreadable node reads as "not there"
                        return None
            return None

        width, height = number("Width"), number("Height")
        exposure_us = number("ExposureTime", "ExposureTimeAbs")
        pixel_format = _node(node_map, "PixelFormat")
        return CameraSettings(
            width=None if width is None else int(width),
            height=None if height is None else int(height),
            pixel_format=str(pixel_format.value) if pixel_format is not None else self.requested.pixel_format,
            exposure_s=None if exposure_us is None else exposure_us * 1e-6,
            gain_db=number("Gain"),
            frame_rate_hz=number("AcquisitionFrameRate", "AcquisitionFrameRateAbs"),
        )

    # -- frames ------------------------------------------------------------------------------------------
    def _acquire(self, timeout_s: float) -> tuple[Frame, Callable[[], None]]:
        acquirer = self._acquirer
        if acquirer is None or self._errors is None:
            raise DeviceError("camera is not open", self.name)
        timeout_error, not_available, gentl_error = self._errors
        try:
            buffer = acquirer.fetch(timeout=timeout_s)
        except timeout_error as exc:
            raise DeviceTimeout(f"no frame within {timeout_s:g} s", self.name) from exc
        except gentl_error as exc:
            raise DeviceDisconnected(f"the stream failed: {exc}", self.name) from exc
        host_ns = time.monotonic_ns()
        if buffer is None:
            # harvesters hands back None when it had to discard a buffer it could not wrap.
            raise DeviceError("the producer delivered an unusable buffer (discarded)", self.name)
        try:
            image = self._image(buffer)
            sequence = self._frame_id(buffer)
            device_ns = None
            if self._device_timestamps:
                try:
                    device_ns = int(buffer.timestamp_ns)
                except not_available:
                    # viky (and some producers) have no buffer timestamp; asking again every frame costs
                    # an exception each time, so stop asking.
                    self._device_timestamps = False
                    log.info(
                        "%s: the producer gives no buffer timestamps; frames carry host time only", self.name
                    )
                except gentl_error as exc:
                    log.debug("%s: timestamp unreadable: %s", self.name, exc)
        except gentl_error as exc:
            buffer.queue()
            raise DeviceError(f"unreadable buffer: {exc}", self.name) from exc
        except BaseException:
            buffer.queue()
            raise
        frame = Frame(image, sequence, host_ns, device_ns, self._actual.exposure_s)
        return frame, buffer.queue

    def _image(self, buffer: Any) -> np.ndarray[Any, np.dtype[np.uint8]]:
        component = buffer.payload.components[0]
        data_format = str(component.data_format)
        wanted = self.requested.pixel_format
        # BGR8 frames from a BGR8 or RGB8 device (the channels swapped in a copy); Mono8 from Mono8.
        if data_format != wanted and not (wanted == "BGR8" and data_format == "RGB8"):
            raise DeviceError(f"the device sent {data_format}, not {wanted}", self.name)
        channels = 1 if data_format == "Mono8" else 3
        width, height = int(component.width), int(component.height)
        data = component.data
        # The component's data is flat; lines may carry x padding (harvesters does not strip it).
        stride = width * channels + int(getattr(component, "x_padding", 0) or 0)
        if data is None or data.size < stride * height:
            raise DeviceError(
                f"short buffer: {0 if data is None else data.size} bytes for {width}x{height}", self.name
            )
        lines = data[: stride * height].reshape(height, stride)[:, : width * channels]
        if channels == 1:
            image: np.ndarray[Any, np.dtype[np.uint8]] = lines
            return image
        colour: np.ndarray[Any, np.dtype[np.uint8]] = lines.reshape(height, width, 3)
        if data_format == "RGB8":
            colour = np.ascontiguousarray(colour[:, :, ::-1])
        return colour

    def _frame_id(self, buffer: Any) -> int:
        try:
            return int(buffer.module.frame_id)
        except Exception:  # producers without frame ids: count frames here
            self._sequence += 1
            return self._sequence


def _node(node_map: Any, name: str) -> Any:
    """The feature ``name``, or None when the node map does not have it."""
    try:
        return getattr(node_map, name)
    except Exception:  # genapi raises its own types for unknown features
        return None
