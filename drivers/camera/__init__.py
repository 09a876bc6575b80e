"""Cameras: one interface (:class:`Camera`, borrowed frames, applied settings) and its backends, chosen by
name through ``drivers.registry``: ``genicam`` (harvesters + a GenTL producer), ``v4l2`` (OpenCV) and
``sim`` (frames rendered from the simulated world). Backends import their vendor library only when used."""

from drivers.camera.base import PIXEL_FORMATS, Camera, CameraSettings

__all__ = ["PIXEL_FORMATS", "Camera", "CameraSettings"]
