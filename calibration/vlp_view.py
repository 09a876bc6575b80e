"""What the VLP pipeline is told about the camera, the LEDs and the mount, for the LED and VLP-error steps.

On the simulated robot: the world's *nominal* camera and *surveyed* LED map and the mount as designed
(``drivers.sim.worldfile.nominal_camera`` / ``surveyed_leds``), exactly what the agent is given; the truth
stays with the renderer. On a robot: the config's ``[vlp]`` camera, LED map and mount. A camera_info file
(the intrinsics step's) or an LED map file (the leds step's) can stand in for the config's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from agent.runtime.localizer import intrinsics_from_config
from agent.sim_view import nominal_intrinsics
from agent.vlp.model import CameraIntrinsics, CameraMount, LedMap, MapLed
from calibration.camera_info import parse_camera_info
from calibration.context import StepContext
from calibration.report import CalibrationError
from drivers.errors import ConfigError

__all__ = ["VlpView", "led_map_from_toml", "view_for"]


@dataclass(frozen=True, slots=True)
class VlpView:
    intrinsics: CameraIntrinsics
    led_map: LedMap | None
    mount: CameraMount
    source: str


def _with_camera_info(base: CameraIntrinsics, path: Path) -> CameraIntrinsics:
    """The camera_info's pinhole and distortion, keeping ``base``'s rolling-shutter timing."""
    try:
        info = parse_camera_info(path.read_text(encoding="utf-8"), str(path))
    except OSError as exc:
        raise CalibrationError(f"cannot read {path}: {exc.strerror or exc}") from exc
    except ConfigError as exc:
        raise CalibrationError(str(exc)) from exc
    if (info.width, info.height) != (base.width_px, base.height_px):
        raise CalibrationError(
            f"{path} is for {info.width}x{info.height} images; the camera gives "
            f"{base.width_px}x{base.height_px}"
        )
    d = (tuple(info.distortion) + (0.0,) * 5)[:5]
    return CameraIntrinsics(
        info.width,
        info.height,
        info.fx,
        info.fy,
        info.cx,
        info.cy,
        base.t_row_s,
        base.sensor_rows_per_row,
        base.sensor_row_offset,
        base.sensor_height_px,
        base.exposure_s,
        (d[0], d[1], d[2], d[3], d[4]),
    )


def led_map_from_toml(path: Path) -> LedMap:
    """An LED map file (``[[leds]]``: id, x_m, y_m, z_m, frequency_hz, duty, diameter_m)."""
    try:
        from agent.config import read_led_map

        leds = read_led_map(path, "led_map", str(path))
    except ConfigError as exc:
        raise CalibrationError(str(exc)) from exc
    return LedMap(tuple(MapLed.of(e) for e in leds))


def view_for(ctx: StepContext, *, camera_info: str | None = None, led_map: str | None = None) -> VlpView:
    """The pipeline's set-up for this context (see the module docstring)."""
    if ctx.sim is not None:
        world = ctx.sim.load()
        from drivers.sim.worldfile import surveyed_leds

        intrinsics = nominal_intrinsics(world)
        leds: LedMap | None = LedMap(tuple(MapLed.of(e) for e in surveyed_leds(world)))
        m = world.robot.camera_mount
        mount = CameraMount(m.x_m, m.y_m, m.z_m, m.yaw_rad, m.roll_rad, m.pitch_rad)
        source = f"world {world.name!r}: nominal camera, surveyed LED map"
    else:
        if ctx.config is None:
            raise CalibrationError("this step needs the robot: pass --config FILE or --sim")
        from agent.config import load_config

        try:
            config = load_config(ctx.config)
        except ConfigError as exc:
            raise CalibrationError(str(exc)) from exc
        vlp = config.vlp
        if vlp.intrinsics is None:
            raise CalibrationError(
                f"{ctx.config} has no camera calibration ([vlp] camera_info or [vlp.intrinsics])"
            )
        c = vlp.intrinsics
        if not c.t_row_s > 0:
            raise CalibrationError(
                f"{ctx.config}: [vlp.rolling_shutter] t_row_s is needed to read LED stripes"
            )
        intrinsics = intrinsics_from_config(c)
        leds = None
        if vlp.leds is not None:
            leds = LedMap(tuple(MapLed.of(e) for e in vlp.leds))
        m2 = vlp.mount
        mount = (
            CameraMount()
            if m2 is None
            else CameraMount(m2.x_m, m2.y_m, m2.z_m, m2.yaw_rad, m2.roll_rad, m2.pitch_rad)
        )
        source = f"the robot config {ctx.config}"
    if camera_info:
        intrinsics = _with_camera_info(intrinsics, Path(camera_info))
        source += f"; camera from {camera_info}"
    if led_map:
        leds = led_map_from_toml(Path(led_map))
        source += f"; LED map from {led_map}"
    return VlpView(intrinsics, leds, mount, source)
