"""Camera frames -> absolute fixes: the :class:`FrameLocalizer` protocol and its VLP adapter.

The runtime's camera consumer calls ``process(frame, tilt, prior)`` on the hot path and fuses what comes
back. :class:`VlpLocalizer` adapts ``agent.vlp.pipeline.VlpPipeline``; :func:`make_localizer` builds it from
the config (on the simulated robot: the world's nominal camera and surveyed LED map, what a calibrated and
surveyed robot believes) or says why it cannot, in which case the agent runs without VLP and never sets
the VLP flag.
"""

from __future__ import annotations

import logging
import math
from typing import Any, Protocol

import numpy as np

from agent.config import IntrinsicsConfig, VlpConfig
from agent.runtime.types import AbsoluteFix, NoFix, Prior, Tilt
from drivers.samples import Frame
from drivers.sim.world import World

__all__ = ["FrameLocalizer", "VlpLocalizer", "make_localizer"]

log = logging.getLogger(__name__)


class FrameLocalizer(Protocol):
    """Anything that turns a camera frame into a pose of the base (or says why not). Not thread-safe:
    one camera consumer calls it."""

    name: str

    def process(self, frame: Frame, tilt: Tilt | None, prior: Prior | None) -> AbsoluteFix | NoFix: ...


class VlpLocalizer:
    """``agent.vlp.pipeline.VlpPipeline`` behind the :class:`FrameLocalizer` protocol."""

    name = "vlp"

    def __init__(self, pipeline: Any) -> None:
        from agent.vlp.model import Motion, PosePrior, VlpFix
        from agent.vlp.model import Tilt as VlpTilt

        self.pipeline = pipeline
        self._motion = Motion
        self._prior = PosePrior
        self._tilt = VlpTilt
        self._fix_type = VlpFix
        self.last_reason = ""
        self.last_total_ms = math.nan

    def process(self, frame: Frame, tilt: Tilt | None, prior: Prior | None) -> AbsoluteFix | NoFix:
        vlp_prior = vlp_motion = None
        if prior is not None:
            vlp_prior = self._prior(
                prior.x_m, prior.y_m, prior.yaw_rad, prior.sigma_xy_m, prior.sigma_yaw_rad
            )
            vlp_motion = self._motion(prior.vx_mps, prior.vy_mps, prior.yaw_rate_radps)
        vlp_tilt = self._tilt(tilt.roll_rad, tilt.pitch_rad) if tilt is not None else None
        result = self.pipeline.process(
            frame.image, frame.host_time_ns * 1e-9, tilt=vlp_tilt, prior=vlp_prior, motion=vlp_motion
        )
        self.last_total_ms = float(result.timings.total_ms)
        if not isinstance(result, self._fix_type):
            self.last_reason = str(result.reason)
            return NoFix(frame.host_time_ns, self.last_reason)
        self.last_reason = ""
        cov = np.asarray(result.covariance, dtype=np.float64)
        return AbsoluteFix(
            frame.host_time_ns,
            float(result.x_m),
            float(result.y_m),
            float(result.yaw_rad),
            cov,
            bool(result.degraded),
            # The LED observations go along for the flight recorder (a reference, nothing copied).
            {
                "ids": result.ids,
                "residual_rms": result.residual_rms,
                "flags": result.flags,
                "leds": result.leds,
            },
            float(result.protection_level_m),
        )


def intrinsics_from_config(c: IntrinsicsConfig) -> Any:
    """The ``[vlp.intrinsics]`` of a config as the pipeline's ``CameraIntrinsics``."""
    from agent.vlp.model import CameraIntrinsics

    return CameraIntrinsics.from_output(
        width_px=c.width_px,
        height_px=c.height_px,
        fx_px=c.fx_px,
        fy_px=c.fy_px,
        cx_px=c.cx_px,
        cy_px=c.cy_px,
        t_row_s=c.t_row_s,
        sensor_height_px=c.sensor_height_px,
        exposure_s=c.exposure_s,
        distortion=c.distortion,
    )


def make_localizer(
    config: VlpConfig, world: World | None, frame_size: tuple[int, int] | None = None
) -> tuple[FrameLocalizer | None, str]:
    """The VLP localizer for this config, or None and the reason it is not available.

    ``world``: the simulated world (under ``[sim]``), whose nominal camera, surveyed LEDs and camera mount
    stand in for the config's when it does not give them. ``frame_size``: (width, height) the camera will
    deliver, checked against the calibration.
    """
    if not config.enabled:
        return None, "disabled in the config"
    try:
        from agent.vlp.calibration import parse_calibration
        from agent.vlp.model import CameraMount, LedMap, MapLed
        from agent.vlp.pipeline import VlpPipeline
    except ImportError as exc:
        return None, f"the VLP package is not usable: {exc}"
    if config.intrinsics is not None:
        intrinsics = intrinsics_from_config(config.intrinsics)
    elif world is not None:
        from agent.sim_view import nominal_intrinsics

        intrinsics = nominal_intrinsics(world)
    else:
        return None, "no camera calibration"
    if config.leds is not None:
        leds = tuple(MapLed.of(led) for led in config.leds)
    elif world is not None:
        from drivers.sim.worldfile import surveyed_leds

        leds = tuple(MapLed.of(led) for led in surveyed_leds(world))
    else:
        return None, "no LED map"
    m = config.mount
    if m is None and world is not None:
        wm = world.robot.camera_mount
        mount = CameraMount(wm.x_m, wm.y_m, wm.z_m, wm.yaw_rad, wm.roll_rad, wm.pitch_rad)
    elif m is not None:
        mount = CameraMount(m.x_m, m.y_m, m.z_m, m.yaw_rad, m.roll_rad, m.pitch_rad)
    else:
        mount = CameraMount()
    if frame_size is not None and frame_size != (intrinsics.width_px, intrinsics.height_px):
        return None, (
            f"the camera gives {frame_size[0]}x{frame_size[1]} frames but the calibration is for "
            f"{intrinsics.width_px}x{intrinsics.height_px}"
        )
    calibration = (
        parse_calibration(config.calibration, config.calibration_file) if config.calibration else None
    )
    try:
        pipeline = VlpPipeline(intrinsics, LedMap(leds), mount, calibration=calibration)
    except (TypeError, ValueError) as exc:
        return None, f"the VLP pipeline refused the set-up: {exc}"
    return VlpLocalizer(pipeline), ""
