"""Simulated worlds from TOML files (the format is ``docs/world.md``).

``load_world(path)`` returns a :class:`~drivers.sim.world.World`. Every field of the dataclasses in
``drivers.sim.world`` can be set from the file under its own name (``[camera] t_row_s = 32e-6``); what is
absent keeps the dataclass default. Angles may be given in degrees instead: ``yaw_deg`` for ``yaw_rad``.

Everything is checked on load, and a mistake raises :class:`~drivers.errors.ConfigError` naming the file
and the exact key (``leds[3].frequency_hz``): unknown or missing keys, wrong types, values out of range,
counts and sizes over their limits (``MAX_*`` below, checked before anything is built from them), LED
signatures the decoder could not tell apart, routes and people's paths that go through walls. Things
that are legal but probably not meant (an LED frequency that aliases after the downsampling, a frame rate
the readout cannot keep up with) are logged as warnings.

``surveyed_leds`` and ``nominal_camera`` give the agent's view of a world: the truth bent by the world's
``[errors]``, for wiring the simulated agent exactly as a surveyed and calibrated robot would be.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
import os
import random
import tomllib
import types
import typing
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from drivers.errors import ConfigError
from drivers.sim.world import (
    CameraModel,
    Clothing,
    Door,
    ErrorModel,
    ForwardCameraModel,
    LaserModel,
    Led,
    Occluder,
    Person,
    Place,
    RfidModel,
    RobotSpec,
    Scene,
    StrayLight,
    Wall,
    World,
    door_scheduled_closed,
)
from drivers.toml_table import TomlTable, as_float, as_int, type_name

__all__ = ["load_world", "map_indices", "nominal_camera", "parse_world", "survey", "surveyed_leds"]

log = logging.getLogger(__name__)

Point = tuple[float, float]

_SIDES = ("south", "north", "west", "east")
# Dynamixel Protocol 2.0 unicast ids (253 and up are reserved or broadcast).
_MAX_SERVO_ID = 252
# Two distinct LED signatures closer than both of these are legal but hard to separate from the stripes.
_CLOSE_FREQUENCY_HZ = 200.0
_CLOSE_DUTY = 0.1
# The fundamental's contrast after the exposure box filter is |sinc(f T_exp)|; below this stripes fade.
_MIN_STRIPE_CONTRAST = 0.3
# Above this many signatures in a grid the best row shift is not searched for (the search is O(n^3)).
_MAX_SEARCHED_SIGNATURES = 48
# A camera tilt beyond this is a mounting mistake, not an error model (and leaves the LEDs out of view).
_MAX_TILT_RAD = math.radians(20.0)
# A stated LED survey uncertainty beyond this is no survey (and would let any LED fit anywhere).
_MAX_SURVEY_SIGMA_M = 1.0
# A camera whose true row time or focal length is off its configured one by more than this is another
# camera, not an error; a distortion coefficient (error) beyond this is no lens the model describes.
_MAX_ERROR_FRACTION = 0.5
_MAX_DISTORTION = 10.0
# An LED or stray light brighter than this many times led_peak_dn only saturates a larger blob.
_MAX_BRIGHTNESS = 100.0
# An occluder's ``at`` must be within this of the LED it hides.
_OCCLUDER_REACH_M = 0.5
_SHAPES = ("disk", "rectangle")

# LED keys of [led_defaults], [[leds]] and [[led_grids]] beyond position, size and signature: their checks.
_LED_EXTRAS: dict[str, _Check] = {
    "brightness": (
        lambda v: 0 < v <= _MAX_BRIGHTNESS,
        f"must be > 0 and at most {_MAX_BRIGHTNESS:g} (relative to camera.led_peak_dn; "
        "a dark LED is dead = true)",
    ),
    "frequency_drift_hz_per_s": (lambda v: abs(v) <= 1000.0, "must be within +-1000 Hz/s"),
    "frequency_walk_hz_per_sqrt_s": (lambda v: 0 <= v <= 1000.0, "must be in [0, 1000] Hz/sqrt(s)"),
}
_DEFAULT_EXTRAS = {"brightness": 1.0, "frequency_drift_hz_per_s": 0.0, "frequency_walk_hz_per_sqrt_s": 0.0}

# Bounds on every count and size in a world file (docs/world.md, "Limits"). Each is checked on the number
# itself, before anything is built from it, so that a slip such as ``ny = 100000000`` fails at once with
# its key instead of allocating gigabytes (or, at 2**63 - 1, never finishing).
MAX_LEDS = 4096  # all [[leds]] plus every grid's nx * ny; also the signatures of one grid
MAX_SENSOR_SIDE_PX = 8192  # sensor_width_px, sensor_height_px
MAX_OUTPUT_SIDE_PX = 4096  # output_width_px, output_height_px: the renderer keeps ~64 bytes per pixel
MAX_STEPS_PER_REV = 10_000  # SCIP 2.0 writes step numbers with 4 digits (0..9999)
MAX_RANGE_MM = 262_143  # the largest range SCIP's 3-character encoding carries (18 bits)
MAX_SCAN_RPM = 6000  # 100 scans/s, beyond any URG; sets how many scans the fake makes per second
MAX_FRAME_RATE_HZ = 1000.0  # sets how many frames the renderer makes per second
MAX_WALLS = 4096  # wall segments from [[walls]], [[polygons]] and [[rooms]] together
MAX_OUTLINE_POINTS = MAX_WALLS  # points of one [[walls]] or [[polygons]] entry
MAX_PATH_POINTS = 256  # a person's path, the route's waypoints (each leg is checked against every wall)
MAX_PEOPLE = 16
MAX_DOORS = 64  # doors of one room
MAX_STRAY_LIGHTS = 256  # [[scene.stray_lights]]: each is rendered every frame like an LED
MAX_SCHEDULED_DOORS = 256  # [[doors]]: doors that open and close
MAX_PLACES = 256  # [[places]]

CLOTHING_PATTERNS = ("plain", "stripes", "checks")
_RGB_REASON = "must be three numbers (red, green, blue), each 0-255"

_Check = tuple[Callable[[Any], bool], str]
_POSITIVE: _Check = (lambda v: v > 0, "must be > 0")
_NON_NEGATIVE: _Check = (lambda v: v >= 0, "must be >= 0")
_FRACTION_OPEN: _Check = (lambda v: 0 < v < 1, "must be strictly between 0 and 1")
_UNIT_INTERVAL: _Check = (lambda v: 0 <= v <= 1, "must be between 0 and 1")
_SERVO_ID: _Check = (lambda v: 0 <= v <= _MAX_SERVO_ID, f"must be a Dynamixel id 0..{_MAX_SERVO_ID}")


def _up_to(limit: float, what: str) -> _Check:
    return (lambda v: 0 < v <= limit, f"must be > 0 and at most {limit:g} ({what})")


_SENSOR_SIDE = _up_to(MAX_SENSOR_SIDE_PX, "the limit on a sensor side")
_OUTPUT_SIDE = _up_to(MAX_OUTPUT_SIDE_PX, "the limit on a rendered frame side")

# Range checks on single fields, by "Class.field". Cross-field checks are in the section readers below.
_RULES: dict[str, _Check] = {
    "CameraModel.sensor_width_px": _SENSOR_SIDE,
    "CameraModel.sensor_height_px": _SENSOR_SIDE,
    "CameraModel.pixel_size_m": _POSITIVE,
    "CameraModel.focal_length_m": _POSITIVE,
    "CameraModel.t_row_s": _POSITIVE,
    "CameraModel.exposure_s": _POSITIVE,
    "CameraModel.output_width_px": _OUTPUT_SIDE,
    "CameraModel.output_height_px": _OUTPUT_SIDE,
    "CameraModel.frame_rate_hz": _up_to(MAX_FRAME_RATE_HZ, "frames per second"),
    "CameraModel.led_peak_dn": _POSITIVE,
    "CameraModel.black_level_dn": (lambda v: 0 <= v < 255, "must be in [0, 255)"),
    "CameraModel.read_noise_dn": _NON_NEGATIVE,
    "CameraModel.full_well_e": _POSITIVE,
    "CameraModel.blur_sigma_px": _NON_NEGATIVE,
    "CameraModel.radial_falloff": _UNIT_INTERVAL,
    "CameraModel.bloom_fraction": (lambda v: 0 <= v <= 0.5, "must be between 0 and 0.5"),
    "CameraModel.jpeg_quality": (lambda v: 0 <= v <= 100, "must be 0 (no compression) or a quality 1..100"),
    "LaserModel.min_range_mm": _NON_NEGATIVE,
    "LaserModel.max_range_mm": _up_to(MAX_RANGE_MM, "what SCIP can send"),
    "LaserModel.steps_per_rev": _up_to(MAX_STEPS_PER_REV, "SCIP step numbers have 4 digits"),
    "LaserModel.first_step": _NON_NEGATIVE,
    "LaserModel.front_step": _NON_NEGATIVE,
    "LaserModel.last_step": _NON_NEGATIVE,
    "LaserModel.scan_rpm": _up_to(MAX_SCAN_RPM, "100 scans per second"),
    "LaserModel.range_noise_mm": _NON_NEGATIVE,
    "LaserModel.dropout": (lambda v: 0 <= v < 1, "must be in [0, 1)"),
    "RobotSpec.wheel_radius_m": _POSITIVE,
    "RobotSpec.track_m": _POSITIVE,
    "RobotSpec.left_id": _SERVO_ID,
    "RobotSpec.right_id": _SERVO_ID,
    "RobotSpec.max_wheel_radps": _POSITIVE,
    "RobotSpec.max_wheel_accel_radps2": _POSITIVE,
    "RobotSpec.radius_m": _POSITIVE,
    "RfidModel.range_m": _POSITIVE,
    "RfidModel.repeat_s": _POSITIVE,
    "RfidModel.antenna_yaws_rad": (lambda v: len(v) <= 4, "at most 4 antennas (ports 1-4)"),
    "RfidModel.antenna_radius_m": _NON_NEGATIVE,
    "RfidModel.beamwidth_rad": (lambda v: 0 < v <= 2 * math.pi, "must be in (0, 2 pi]"),
    "RfidModel.front_to_back_db": _NON_NEGATIVE,
    "RfidModel.wall_reflection": _UNIT_INTERVAL,
    "RfidModel.scatterers": (lambda v: 0 <= v <= 256, "must be 0..256"),
    "RfidModel.scatter_amplitude": _UNIT_INTERVAL,
    "RfidModel.body_loss_db": _NON_NEGATIVE,
    "RfidModel.noise_db": _NON_NEGATIVE,
    "Led.diameter_m": _POSITIVE,
    "Led.frequency_hz": _POSITIVE,
    "Led.duty": _FRACTION_OPEN,
    "Person.speed_mps": _POSITIVE,
    "Person.radius_m": _POSITIVE,
    # The simulation keeps 2 s of the robot's poses to look back on.
    "Person.reaction_s": (lambda v: 0 <= v <= 1.5, "must be in [0, 1.5] s"),
    "ForwardCameraModel.width_px": _OUTPUT_SIDE,
    "ForwardCameraModel.height_px": _OUTPUT_SIDE,
    "ForwardCameraModel.hfov_rad": (lambda v: 0 < v < math.radians(170.0), "must be in (0, 170) degrees"),
    "ForwardCameraModel.frame_rate_hz": _up_to(MAX_FRAME_RATE_HZ, "frames per second"),
    "ForwardCameraModel.wall_height_m": _POSITIVE,
    "ForwardCameraModel.wall_rgb": (lambda v: all(0 <= c <= 255 for c in v), _RGB_REASON),
    "ForwardCameraModel.floor_rgb": (lambda v: all(0 <= c <= 255 for c in v), _RGB_REASON),
    "ForwardCameraModel.ceiling_rgb": (lambda v: all(0 <= c <= 255 for c in v), _RGB_REASON),
    "ForwardCameraModel.light_variation": (lambda v: 0 <= v < 1, "must be in [0, 1)"),
    "ForwardCameraModel.light_period_s": _POSITIVE,
    "ForwardCameraModel.noise_dn": (lambda v: 0 <= v <= 50, "must be in [0, 50] DN"),
    "Clothing.shirt_rgb": (lambda v: all(0 <= c <= 255 for c in v), _RGB_REASON),
    "Clothing.trousers_rgb": (lambda v: all(0 <= c <= 255 for c in v), _RGB_REASON),
    "Clothing.skin_rgb": (lambda v: all(0 <= c <= 255 for c in v), _RGB_REASON),
    "Clothing.hair_rgb": (lambda v: all(0 <= c <= 255 for c in v), _RGB_REASON),
    "Clothing.pattern_rgb": (lambda v: all(0 <= c <= 255 for c in v), _RGB_REASON),
    "Clothing.pattern": (lambda v: v in CLOTHING_PATTERNS, f"must be one of {list(CLOTHING_PATTERNS)}"),
    "Clothing.pattern_period_m": (lambda v: 0.01 <= v <= 1.0, "must be 0.01-1 m"),
    "Clothing.height_m": (lambda v: 0.5 <= v <= 2.3, "must be 0.5-2.3 m"),
    "Person.start_s": _NON_NEGATIVE,
    "ErrorModel.led_survey_error_m": _NON_NEGATIVE,
    "ErrorModel.led_height_error_m": _NON_NEGATIVE,
    "ErrorModel.t_row_error_fraction": (
        lambda v: abs(v) <= _MAX_ERROR_FRACTION,
        f"must be within +-{_MAX_ERROR_FRACTION:g} (a fraction: 0.03 is 3 %)",
    ),
    "ErrorModel.focal_length_error_fraction": (
        lambda v: abs(v) <= _MAX_ERROR_FRACTION,
        f"must be within +-{_MAX_ERROR_FRACTION:g} (a fraction: 0.01 is 1 %)",
    ),
    "ErrorModel.distortion_error": (
        lambda v: all(abs(c) <= _MAX_DISTORTION for c in v),
        f"each coefficient must be within +-{_MAX_DISTORTION:g}",
    ),
    "ErrorModel.camera_tilt_rad": (
        lambda v: all(abs(a) <= _MAX_TILT_RAD for a in v),
        f"each angle must be within +-{math.degrees(_MAX_TILT_RAD):.0f} degrees",
    ),
    "Mount.roll_rad": (
        lambda v: abs(v) <= _MAX_TILT_RAD,
        f"must be within +-{math.degrees(_MAX_TILT_RAD):.0f} degrees",
    ),
    "Mount.pitch_rad": (
        lambda v: abs(v) <= _MAX_TILT_RAD,
        f"must be within +-{math.degrees(_MAX_TILT_RAD):.0f} degrees",
    ),
}


# -- entry points --------------------------------------------------------------------------------------------
def load_world(path: str | os.PathLike[str]) -> World:
    """Read and check a world file. Raises ConfigError (with the file and the key) on any mistake."""
    file = os.fspath(path)
    try:
        with open(file, "rb") as fp:
            data = tomllib.load(fp)
    except tomllib.TOMLDecodeError as exc:
        # The message carries "(at line L, column C)".
        raise ConfigError("", f"not valid TOML: {exc}", file) from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(
            "", f"not UTF-8 text (TOML files must be): {exc.reason} at byte {exc.start}", file
        ) from exc
    except OSError as exc:
        raise ConfigError("", f"cannot read the world file: {exc.strerror or exc}", file) from exc
    return parse_world(data, source=file)


def parse_world(data: Mapping[str, Any] | str, source: str | None = None) -> World:
    """Build a World from TOML text or an already parsed table. ``source`` names it in errors."""
    if isinstance(data, str):
        try:
            data = tomllib.loads(data)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError("", f"not valid TOML: {exc}", source) from exc
    return _WorldReader(dict(data), source).read()


def surveyed_leds(world: World) -> tuple[Led, ...]:
    """The LED map the agent is given: the true LEDs moved by the world's survey errors, without the LEDs
    missing from the map (``mapped = false``). Dead LEDs stay: the map does not know they are dark.

    Each coordinate is off by a normal draw with standard deviation ``errors.led_survey_error_m`` (x, y)
    and ``errors.led_height_error_m`` (z), seeded by ``errors.seed`` so every run sees the same map.
    """
    return tuple(led for led in survey(world) if led is not None)


def survey(world: World) -> tuple[Led | None, ...]:
    """Each of ``world.leds`` as the map states it (see :func:`surveyed_leds`), None where the map leaves
    it out: aligned with ``world.leds``, for comparing the map with the truth LED by LED. Every LED draws
    its survey error, mapped or not, so marking one unmapped leaves the others where they were."""
    errors = world.errors
    rng = random.Random(errors.seed)
    out: list[Led | None] = []
    for led in world.leds:
        moved = dataclasses.replace(
            led,
            x_m=led.x_m + rng.gauss(0.0, errors.led_survey_error_m),
            y_m=led.y_m + rng.gauss(0.0, errors.led_survey_error_m),
            z_m=led.z_m + rng.gauss(0.0, errors.led_height_error_m),
        )
        out.append(moved if led.mapped else None)
    return tuple(out)


def map_indices(world: World) -> tuple[int | None, ...]:
    """For each of ``world.leds``, its index in :func:`surveyed_leds` (None: not in the map)."""
    out: list[int | None] = []
    n = 0
    for led in world.leds:
        out.append(n if led.mapped else None)
        n += int(led.mapped)
    return tuple(out)


def nominal_camera(world: World) -> CameraModel:
    """The camera as the agent's calibration knows it.

    ``world.camera`` is the truth (the renderer uses it). The nominal principal point is the true one minus
    ``errors.principal_point_error_px`` (sensor pixels), i.e. the truth is off the nominal by the error; the
    nominal row time and focal length are the true ones divided by (1 + their ``*_error_fraction``); the
    nominal distortion is the true one minus ``errors.distortion_error``.
    """
    cam = world.camera
    e = world.errors
    cx, cy = cam.principal_point_px
    ex, ey = e.principal_point_error_px
    nominal = dataclasses.replace(cam, cx_px=cx - ex, cy_px=cy - ey)
    if e.t_row_error_fraction or e.focal_length_error_fraction or any(e.distortion_error):
        dist = tuple(t - d for t, d in zip(cam.distortion, e.distortion_error, strict=True))
        nominal = dataclasses.replace(
            nominal,
            t_row_s=cam.t_row_s / (1.0 + e.t_row_error_fraction),
            focal_length_m=cam.focal_length_m / (1.0 + e.focal_length_error_fraction),
            distortion=(dist[0], dist[1], dist[2], dist[3], dist[4]),
        )
    return nominal


# -- a table being read --------------------------------------------------------------------------------------
class _Table(TomlTable):
    """One table of a world file (see :class:`drivers.toml_table.TomlTable`) with the world's getters."""

    # typed getters ---------------------------------------------------------------------------------
    def number(self, name: str, default: float | None = None, *, required: bool = False) -> float:
        if not self.has(name):
            if required or default is None:
                raise self.error(name, "missing (a number is required)")
            return default
        return as_float(self.take(name), self.key(name), self.file)

    def integer(self, name: str, default: int | None = None) -> int:
        if not self.has(name):
            if default is None:
                raise self.error(name, "missing (an integer is required)")
            return default
        return as_int(self.take(name), self.key(name), self.file)

    def string(self, name: str, default: str | None = None, *, allow_int: bool = False) -> str:
        if not self.has(name):
            if default is None:
                raise self.error(name, "missing (a string is required)")
            return default
        value = self.take(name)
        if allow_int and isinstance(value, int) and not isinstance(value, bool):
            return str(value)
        if not isinstance(value, str):
            raise self.error(name, f"must be a string, not {type_name(value)}")
        if not value.strip():
            raise self.error(name, "must not be empty")
        return value

    def points(
        self, name: str, *, minimum: int = 1, maximum: int, required: bool = True
    ) -> tuple[Point, ...]:
        if not self.has(name):
            if required:
                raise self.error(name, "missing (a list of [x, y] points in metres is required)")
            return ()
        value = self.take(name)
        if not isinstance(value, list):
            raise self.error(name, f"must be a list of [x, y] points, not {type_name(value)}")
        if len(value) > maximum:
            raise self.error(name, f"has {len(value)} points, more than the limit of {maximum}")
        pts = tuple(_as_point(p, f"{self.key(name)}[{i}]", self.file) for i, p in enumerate(value))
        if len(pts) < minimum:
            raise self.error(
                name, f"needs at least {minimum} point{'s' if minimum > 1 else ''}, got {len(pts)}"
            )
        return pts

    def table(self, name: str) -> _Table:
        path = self.key(name)
        if not self.has(name):
            return _Table({}, path, self.file)
        value = self.take(name)
        if not isinstance(value, dict):
            raise ConfigError(
                path, f"must be a table ([{path}] or {{...}}), not {type_name(value)}", self.file
            )
        return _Table(value, path, self.file)

    def tables(self, name: str, maximum: int) -> list[_Table]:
        if not self.has(name):
            return []
        value = self.take(name)
        path = self.key(name)
        if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
            raise ConfigError(
                path, f"must be an array of tables ([[{path}]]), not {type_name(value)}", self.file
            )
        if len(value) > maximum:
            raise ConfigError(path, f"has {len(value)} entries, more than the limit of {maximum}", self.file)
        return [_Table(v, f"{path}[{i}]", self.file) for i, v in enumerate(value)]


def _as_point(value: object, key: str, file: str | None) -> Point:
    if not isinstance(value, list) or len(value) != 2:
        raise ConfigError(key, f"must be a point [x, y] in metres, not {value!r}", file)
    return as_float(value[0], f"{key}[0]", file), as_float(value[1], f"{key}[1]", file)


# -- dataclasses from tables, field by field -----------------------------------------------------------------
def _read_dataclass(cls: type[Any], table: _Table) -> Any:
    """Build ``cls`` from ``table``: every field under its own name (``*_rad`` also as ``*_deg``), with its
    type from the annotations, its range from ``_RULES``, and the dataclass default when absent."""
    hints = typing.get_type_hints(cls)
    kwargs: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        name = f.name
        table.expect(name)
        scale = 1.0
        if name.endswith("_rad"):
            alias = name[: -len("_rad")] + "_deg"
            table.expect(alias)
            if table.has(name) and table.has(alias):
                raise table.error(alias, f"give either {name} or {alias}, not both")
            if table.has(alias):
                name, scale = alias, math.pi / 180.0
        if not table.has(name):
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                hint = f" (or {name[: -len('_rad')]}_deg)" if name.endswith("_rad") else ""
                raise table.error(name, f"missing{hint}: it has no default")
            continue
        value = _convert(hints[f.name], table, name, scale)
        rule = _RULES.get(f"{cls.__name__}.{f.name}")
        if rule is not None and not rule[0](value):
            raise table.error(name, f"{rule[1]}, got {_show(table.data[name])}")
        kwargs[f.name] = value
    return cls(**kwargs)


def _show(value: object) -> str:
    return repr(value) if not isinstance(value, float) else f"{value:g}"


def _convert(tp: Any, table: _Table, name: str, scale: float) -> Any:
    key = table.key(name)
    origin = typing.get_origin(tp)
    if origin in (types.UnionType, typing.Union):
        # Optional fields (``float | None``): TOML has no null, so a present value is the non-None type.
        inner = [a for a in typing.get_args(tp) if a is not type(None)]
        return _convert(inner[0], table, name, scale)
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        sub = table.table(name)
        value = _read_dataclass(tp, sub)
        sub.finish()
        return value
    raw = table.take(name)
    if tp is float:
        return as_float(raw, key, table.file) * scale
    if tp is int:
        return as_int(raw, key, table.file)
    if tp is str:
        if not isinstance(raw, str):
            raise ConfigError(key, f"must be a string, not {type_name(raw)}", table.file)
        return raw
    if tp is bool:
        if not isinstance(raw, bool):
            raise ConfigError(key, f"must be true or false, not {type_name(raw)}", table.file)
        return raw
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(raw, list):
            raise ConfigError(key, f"must be an array, not {type_name(raw)}", table.file)
        if len(args) == 2 and args[1] is Ellipsis and args[0] is float:
            return tuple(as_float(v, f"{key}[{i}]", table.file) * scale for i, v in enumerate(raw))
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_as_point(p, f"{key}[{i}]", table.file) for i, p in enumerate(raw))
        if len(raw) != len(args):
            raise ConfigError(key, f"must be an array of {len(args)} numbers, got {len(raw)}", table.file)
        return tuple(as_float(v, f"{key}[{i}]", table.file) * scale for i, v in enumerate(raw))
    raise ConfigError(key, f"cannot be set from a world file (type {tp})", table.file)


# -- geometry helpers ----------------------------------------------------------------------------------------
def _cross(o: Point, a: Point, b: Point) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _segments_cross(p1: Point, p2: Point, q1: Point, q2: Point) -> bool:
    """Proper or touching intersection of two closed segments (orientation tests, with collinear overlap)."""
    d1, d2 = _cross(q1, q2, p1), _cross(q1, q2, p2)
    d3, d4 = _cross(p1, p2, q1), _cross(p1, p2, q2)
    if ((d1 > 0) != (d2 > 0)) and ((d3 > 0) != (d4 > 0)) and d1 != 0 and d2 != 0 and d3 != 0 and d4 != 0:
        return True

    def on(a: Point, b: Point, c: Point, d: float) -> bool:
        return (
            abs(d) < 1e-12
            and min(a[0], b[0]) - 1e-12 <= c[0] <= max(a[0], b[0]) + 1e-12
            and min(a[1], b[1]) - 1e-12 <= c[1] <= max(a[1], b[1]) + 1e-12
        )

    return on(q1, q2, p1, d1) or on(q1, q2, p2, d2) or on(p1, p2, q1, d3) or on(p1, p2, q2, d4)


def _point_segment_distance(p: Point, a: Point, b: Point) -> float:
    ex, ey = b[0] - a[0], b[1] - a[1]
    length2 = ex * ex + ey * ey
    s = 0.0 if length2 == 0 else max(0.0, min(1.0, ((p[0] - a[0]) * ex + (p[1] - a[1]) * ey) / length2))
    return math.hypot(p[0] - a[0] - s * ex, p[1] - a[1] - s * ey)


def _segment_distance(p1: Point, p2: Point, q1: Point, q2: Point) -> float:
    if _segments_cross(p1, p2, q1, q2):
        return 0.0
    return min(
        _point_segment_distance(p1, q1, q2),
        _point_segment_distance(p2, q1, q2),
        _point_segment_distance(q1, p1, p2),
        _point_segment_distance(q2, p1, p2),
    )


def _best_row_shift(n: int, dx_m: float, dy_m: float) -> int:
    """The shift s that keeps equal signatures farthest apart when LED (ix, iy) gets (ix + s iy) mod n.

    LEDs (ix, iy) and (ix + a, iy + b) share a signature when a + s b = 0 (mod n); the nearest such pair is
    found over one period of the pattern, and the s with the largest nearest distance wins.
    """
    if n <= 1:
        return 0
    if n > _MAX_SEARCHED_SIGNATURES:
        # The search is O(n^3); a golden-ratio shift is the classic low-discrepancy choice for large n.
        return max(1, round(n * (3 - math.sqrt(5)) / 2)) % n
    dx, dy = abs(dx_m) or 1.0, abs(dy_m) or 1.0
    best, best_gap = 0, -1.0
    for s in range(n):
        gap = min(
            math.hypot(a * dx, b * dy)
            for b in range(n)
            for a in range(-n, n + 1)
            if (a, b) != (0, 0) and (a + s * b) % n == 0
        )
        if gap > best_gap + 1e-12:
            best, best_gap = s, gap
    return best


def _wall_boxes(walls: list[Wall]) -> npt.NDArray[np.float64]:
    """Each wall's bounding box as a row (x_min, x_max, y_min, y_max)."""
    ends = np.array([[w.x1_m, w.x2_m, w.y1_m, w.y2_m] for w in walls], dtype=np.float64).reshape(-1, 4)
    return np.column_stack(
        (ends[:, :2].min(axis=1), ends[:, :2].max(axis=1), ends[:, 2:].min(axis=1), ends[:, 2:].max(axis=1))
    )


def _walls_near(a: Point, b: Point, boxes: npt.NDArray[np.float64], margin_m: float) -> list[int]:
    """Indices, in order, of the walls whose bounding box comes within ``margin_m`` of the segment a-b's.

    A wall whose box is farther than that can neither cross the segment nor come closer than the margin,
    so the exact tests only run on these: checking every leg against every wall took over a second per
    path at the wall limit."""
    slack = margin_m + 1e-9  # at least the exact tests' own tolerance
    near = (
        (boxes[:, 0] <= max(a[0], b[0]) + slack)
        & (boxes[:, 1] >= min(a[0], b[0]) - slack)
        & (boxes[:, 2] <= max(a[1], b[1]) + slack)
        & (boxes[:, 3] >= min(a[1], b[1]) - slack)
    )
    return [int(n) for n in np.flatnonzero(near)]


def _close_signature_pairs(
    signatures: list[tuple[Led, str]],
) -> list[tuple[tuple[int, Led, str], tuple[int, Led, str]]]:
    """Pairs of signatures closer than both _CLOSE_FREQUENCY_HZ and _CLOSE_DUTY, each pair in file order.

    Sorted by frequency, only the neighbours within _CLOSE_FREQUENCY_HZ are compared: the all-pairs loop
    took seconds at the LED limit."""
    ranked = sorted(
        ((i, led, key) for i, (led, key) in enumerate(signatures)), key=lambda e: e[1].frequency_hz
    )
    pairs = []
    for n, first in enumerate(ranked):
        for second in ranked[n + 1 :]:
            if second[1].frequency_hz - first[1].frequency_hz >= _CLOSE_FREQUENCY_HZ:
                break
            if abs(first[1].duty - second[1].duty) < _CLOSE_DUTY:
                pairs.append((first, second) if first[0] < second[0] else (second, first))
    return sorted(pairs, key=lambda p: (p[0][0], p[1][0]))


def _first_overlap(leds: list[_Placed]) -> tuple[_Placed, _Placed, float] | None:
    """The first LED (in file order) whose disk overlaps an earlier one at about the same height, with the
    earliest such one and the distance between their centres; None if no disks overlap.

    LEDs are bucketed in square cells at least as wide as the widest disk, so only neighbouring cells are
    compared: the all-pairs loop took 5 s for 4900 LEDs."""
    if not leds:
        return None
    # At least 1 m, so that x / cell stays finite for any finite coordinate.
    cell = max(1.0, max(p.led.diameter_m for p in leds))
    buckets: dict[tuple[int, int], list[int]] = {}
    for j, second in enumerate(leds):
        b = second.led
        cx, cy = math.floor(b.x_m / cell), math.floor(b.y_m / cell)
        earlier = []
        for ix in (cx - 1, cx, cx + 1):
            for iy in (cy - 1, cy, cy + 1):
                for i in buckets.get((ix, iy), ()):
                    a = leds[i].led
                    apart_m = math.hypot(a.x_m - b.x_m, a.y_m - b.y_m)
                    if apart_m < (a.diameter_m + b.diameter_m) / 2 and abs(a.z_m - b.z_m) < 0.05:
                        earlier.append((i, apart_m))
        if earlier:
            i, apart_m = min(earlier)
            return leds[i], second, apart_m
        buckets.setdefault((cx, cy), []).append(j)
    return None


class _Placed(typing.NamedTuple):
    """An LED and where it came from: ``key`` for its position and size, ``signature_key`` for its
    modulation (a grid's signature entry), ``where`` to tell grid LEDs apart in messages."""

    led: Led
    key: str
    signature_key: str
    where: str


def _ever_closed(door: Door) -> bool:
    return door.closes_at_s is not None or door.opens_at_s is not None


def _closed_at_start(door: Door) -> bool:
    return door_scheduled_closed(door, 0.0)


def _wall_ends(w: Wall) -> tuple[Point, Point]:
    return (w.x1_m, w.y1_m), (w.x2_m, w.y2_m)


# -- the world -----------------------------------------------------------------------------------------------
_SECTIONS = (
    "name",
    "robot",
    "camera",
    "laser",
    "rfid",
    "forward_camera",
    "errors",
    "led_defaults",
    "leds",
    "led_grids",
    "walls",
    "polygons",
    "rooms",
    "doors",
    "places",
    "people",
    "route",
    "scene",
)


class _WorldReader:
    def __init__(self, data: dict[str, Any], file: str | None) -> None:
        self.root = _Table(data, "", file)
        self.root.expect(*_SECTIONS)
        self.file = file

    def error(self, key: str, reason: str) -> ConfigError:
        return ConfigError(key, reason, self.file)

    def read(self) -> World:
        root = self.root
        default_name = Path(self.file).stem if self.file else "world"
        name = root.string("name", default_name)
        robot = self._section(RobotSpec, "robot")
        camera = self._section(CameraModel, "camera")
        laser = self._section(LaserModel, "laser")
        rfid = self._section(RfidModel, "rfid")
        forward_camera = self._section(ForwardCameraModel, "forward_camera")
        if forward_camera.mount.roll_rad or forward_camera.mount.pitch_rad:
            raise self.error(
                "forward_camera.mount",
                "the forward camera is level (no roll or pitch); shift cy_px to look upwards",
            )
        errors = self._section(ErrorModel, "errors")
        self._check_robot(robot)
        self._check_camera(camera)
        self._check_laser(laser)
        self._check_rfid(rfid)
        self._check_errors(errors, camera)

        walls = self._walls()
        doors = self._doors()
        places = self._places(walls, robot)
        leds_with_keys = self._leds(robot, camera)
        # People and the robot's route go through doorways, not through doors that close.
        closing = [Wall(d.x1_m, d.y1_m, d.x2_m, d.y2_m) for d in doors if _ever_closed(d)]
        people = self._people(walls + closing)
        route, speed = self._route(walls + closing, robot)
        scene = self._scene(leds_with_keys, robot, camera)
        root.finish()
        self._check_start(robot, walls)
        self._check_start_doors(robot, doors)
        return World(
            name=name,
            walls=tuple(walls),
            doors=tuple(doors),
            places=tuple(places),
            leds=tuple(placed.led for placed in leds_with_keys),
            robot=robot,
            camera=camera,
            laser=laser,
            rfid=rfid,
            forward_camera=forward_camera,
            people=tuple(people),
            route=route,
            route_speed_mps=speed,
            errors=errors,
            scene=scene,
            source=self.file,
        )

    def _section(self, cls: type[Any], name: str) -> Any:
        table = self.root.table(name)
        value = _read_dataclass(cls, table)
        table.finish()
        return value

    # -- per-section checks ----------------------------------------------------------------------------
    def _check_robot(self, robot: RobotSpec) -> None:
        if robot.left_id == robot.right_id:
            raise self.error("robot.right_id", f"must differ from robot.left_id ({robot.left_id})")

    def _check_camera(self, cam: CameraModel) -> None:
        if cam.cx_px is not None and not 0 <= cam.cx_px <= cam.sensor_width_px - 1:
            raise self.error(
                "camera.cx_px", f"must be on the sensor (0..{cam.sensor_width_px - 1}), got {cam.cx_px:g}"
            )
        if cam.cy_px is not None and not 0 <= cam.cy_px <= cam.sensor_height_px - 1:
            raise self.error(
                "camera.cy_px", f"must be on the sensor (0..{cam.sensor_height_px - 1}), got {cam.cy_px:g}"
            )
        period_s = 1.0 / cam.frame_rate_hz
        if cam.exposure_s >= period_s:
            raise self.error(
                "camera.exposure_s",
                f"{cam.exposure_s:g} s does not fit in a frame period "
                f"({period_s:g} s at {cam.frame_rate_hz:g} fps)",
            )
        if cam.led_peak_dn + cam.black_level_dn > 4 * 255:
            log.warning(
                "%s: camera.led_peak_dn %g saturates LEDs far beyond 8 bits", self.file, cam.led_peak_dn
            )
        readout_s = cam.sensor_height_px * cam.t_row_s
        # The dataclass defaults themselves (1536 rows x 32 us at 30 fps) overlap; only warn about a choice.
        chosen = {"sensor_height_px", "t_row_s", "frame_rate_hz"} & set(self.root.data.get("camera", {}))
        if readout_s > period_s and chosen:
            log.warning(
                "%s: camera readout %.1f ms (%d rows x %g us) is longer than the frame period %.1f ms: "
                "a real sensor could not run at %g fps; frames will overlap in time",
                self.file,
                readout_s * 1e3,
                cam.sensor_height_px,
                cam.t_row_s * 1e6,
                period_s * 1e3,
                cam.frame_rate_hz,
            )

    def _check_laser(self, laser: LaserModel) -> None:
        if laser.min_range_mm >= laser.max_range_mm:
            raise self.error("laser.max_range_mm", f"must be above laser.min_range_mm ({laser.min_range_mm})")
        if not laser.first_step <= laser.front_step <= laser.last_step:
            raise self.error(
                "laser.front_step",
                "steps must satisfy first_step <= front_step <= last_step, got "
                f"{laser.first_step} / {laser.front_step} / {laser.last_step}",
            )
        if laser.last_step >= laser.steps_per_rev:
            raise self.error("laser.last_step", f"must be below laser.steps_per_rev ({laser.steps_per_rev})")

    def _check_rfid(self, rfid: RfidModel) -> None:
        from drivers.registry import BACKENDS, DeviceKind

        protocols = sorted(BACKENDS[DeviceKind.RFID])
        if rfid.protocol not in protocols:
            raise self.error(
                "rfid.protocol", f"unknown reader protocol {rfid.protocol!r}; choose one of {protocols}"
            )
        if rfid.antenna_yaws_rad and rfid.protocol != "mercury":
            raise self.error(
                "rfid.antenna_yaws_rad",
                'antennas on ports are a Mercury (UHF) feature; set protocol = "mercury"',
            )

    def _check_errors(self, errors: ErrorModel, cam: CameraModel) -> None:
        cx, cy = cam.principal_point_px
        ex, ey = errors.principal_point_error_px
        if not (0 <= cx - ex <= cam.sensor_width_px - 1 and 0 <= cy - ey <= cam.sensor_height_px - 1):
            raise self.error(
                "errors.principal_point_error_px",
                f"({ex:g}, {ey:g}) px puts the nominal principal point off the sensor",
            )

    # -- walls -------------------------------------------------------------------------------------------
    def _walls(self) -> list[Wall]:
        walls: list[Wall] = []
        for t in self.root.tables("walls", MAX_WALLS):
            t.expect("points", "closed")
            closed = t.boolean("closed", False)
            pts = t.points("points", minimum=3 if closed else 2, maximum=MAX_OUTLINE_POINTS)
            t.finish()
            walls += self._chain(pts, closed, t.key("points"))
            self._check_wall_count(walls, t.key("points"))
        for t in self.root.tables("polygons", MAX_WALLS):
            t.expect("points")
            pts = t.points("points", minimum=3, maximum=MAX_OUTLINE_POINTS)
            t.finish()
            if len(pts) > 3 and pts[0] == pts[-1]:
                pts = pts[:-1]  # a ring written with its closing point repeated
            walls += self._chain(pts, True, t.key("points"))
            self._check_wall_count(walls, t.key("points"))
        for t in self.root.tables("rooms", MAX_WALLS):
            walls += self._room(t)
            self._check_wall_count(walls, t.path)
        return walls

    def _check_wall_count(self, walls: list[Wall], key: str) -> None:
        if len(walls) > MAX_WALLS:
            raise self.error(
                key, f"brings the world to {len(walls)} wall segments, more than the limit of {MAX_WALLS}"
            )

    def _chain(self, pts: tuple[Point, ...], closed: bool, key: str) -> list[Wall]:
        ends = list(pts) + ([pts[0]] if closed else [])
        walls = []
        for i, (a, b) in enumerate(itertools.pairwise(ends)):
            if math.dist(a, b) < 1e-9:
                raise self.error(
                    f"{key}[{(i + 1) % len(pts)}]",
                    f"repeats the point before it {a}: a wall needs two distinct ends",
                )
            walls.append(Wall(a[0], a[1], b[0], b[1]))
        return walls

    def _room(self, t: _Table) -> list[Wall]:
        """A rectangle of walls with door gaps. Sides run west to east (south, north) and south to north
        (west, east); a door's ``offset_m`` is its centre's distance from the side's start."""
        t.expect("x_min_m", "y_min_m", "x_max_m", "y_max_m", "doors")
        x0, y0 = t.number("x_min_m", required=True), t.number("y_min_m", required=True)
        x1, y1 = t.number("x_max_m", required=True), t.number("y_max_m", required=True)
        if x1 <= x0:
            raise t.error("x_max_m", f"must be above x_min_m ({x0:g}), got {x1:g}")
        if y1 <= y0:
            raise t.error("y_max_m", f"must be above y_min_m ({y0:g}), got {y1:g}")
        sides: dict[str, tuple[Point, Point]] = {
            "south": ((x0, y0), (x1, y0)),
            "north": ((x0, y1), (x1, y1)),
            "west": ((x0, y0), (x0, y1)),
            "east": ((x1, y0), (x1, y1)),
        }
        gaps: dict[str, list[tuple[float, float, str]]] = {side: [] for side in _SIDES}
        for d in t.tables("doors", MAX_DOORS):
            d.expect("side", "offset_m", "width_m")
            side = d.string("side")
            if side not in sides:
                raise d.error("side", f"must be one of {list(_SIDES)}, got {side!r}")
            offset = d.number("offset_m", required=True)
            width = d.number("width_m", 0.9)
            d.finish()
            if width <= 0:
                raise d.error("width_m", f"must be > 0, got {width:g}")
            a, b = sides[side]
            length = math.dist(a, b)
            lo, hi = offset - width / 2, offset + width / 2
            if lo < 0 or hi > length:
                raise d.error(
                    "offset_m",
                    f"a {width:g} m door centred at {offset:g} m does not fit in the "
                    f"{length:g} m {side} side",
                )
            for plo, phi, pkey in gaps[side]:
                if lo < phi and plo < hi:
                    raise d.error("offset_m", f"overlaps the door {pkey}")
            gaps[side].append((lo, hi, d.path))
        t.finish()
        walls = []
        for side, (a, b) in sides.items():
            length = math.dist(a, b)
            ux, uy = (b[0] - a[0]) / length, (b[1] - a[1]) / length
            cursor = 0.0
            for lo, hi, _ in [*sorted(gaps[side]), (length, length, "")]:
                if lo - cursor > 1e-9:
                    walls.append(Wall(a[0] + ux * cursor, a[1] + uy * cursor, a[0] + ux * lo, a[1] + uy * lo))
                cursor = hi
        return walls

    # -- doors and places --------------------------------------------------------------------------------
    def _doors(self) -> list[Door]:
        """``[[doors]]``: a segment across a doorway that is a wall while closed, on a schedule."""
        doors: list[Door] = []
        names: dict[str, str] = {}
        for t in self.root.tables("doors", MAX_SCHEDULED_DOORS):
            t.expect("name", "points", "closes_at_s", "opens_at_s")
            name = t.string("name", t.path)
            pts = t.points("points", minimum=2, maximum=2)
            times: dict[str, float | None] = {}
            for key in ("closes_at_s", "opens_at_s"):
                value = t.number(key) if t.has(key) else None
                if value is not None and not (math.isfinite(value) and value >= 0.0):
                    raise t.error(key, f"must be a finite number of seconds >= 0, got {value:g}")
                times[key] = value
            t.finish()
            if math.dist(pts[0], pts[1]) < 1e-6:
                raise t.error("points", "the door's two ends must differ")
            closes, opens = times["closes_at_s"], times["opens_at_s"]
            if closes is not None and opens is not None and closes == opens:
                raise t.error("opens_at_s", f"must differ from closes_at_s ({closes:g} s)")
            if name in names:
                raise t.error("name", f"{name!r} is already the name of {names[name]}")
            names[name] = t.path
            (x1, y1), (x2, y2) = pts
            doors.append(Door(name, x1, y1, x2, y2, closes, opens))
        return doors

    def _places(self, walls: list[Wall], robot: RobotSpec) -> list[Place]:
        """``[[places]]``: named points missions go to; the robot must fit there."""
        places: list[Place] = []
        names: dict[str, str] = {}
        for t in self.root.tables("places", MAX_PLACES):
            t.expect("name", "x_m", "y_m", "yaw_rad", "yaw_deg")
            name = t.string("name")
            x, y = t.number("x_m", required=True), t.number("y_m", required=True)
            if t.has("yaw_rad") and t.has("yaw_deg"):
                raise t.error("yaw_deg", "give either yaw_rad or yaw_deg, not both")
            yaw = None
            if t.has("yaw_rad"):
                yaw = t.number("yaw_rad")
            elif t.has("yaw_deg"):
                yaw = math.radians(t.number("yaw_deg"))
            t.finish()
            if not (math.isfinite(x) and math.isfinite(y) and (yaw is None or math.isfinite(yaw))):
                raise t.error("x_m", "the position and heading must be finite numbers")
            if name in names:
                raise t.error("name", f"{name!r} is already the name of {names[name]}")
            names[name] = t.path
            for w in walls:
                gap = _point_segment_distance((x, y), *_wall_ends(w))
                if gap < robot.radius_m:
                    raise t.error(
                        "x_m",
                        f"the robot ({robot.radius_m:g} m radius) at ({x:g}, {y:g}) would overlap the wall "
                        f"({w.x1_m:g}, {w.y1_m:g})-({w.x2_m:g}, {w.y2_m:g})",
                    )
            places.append(Place(name, x, y, yaw))
        return places

    # -- LEDs --------------------------------------------------------------------------------------------
    def _leds(self, robot: RobotSpec, cam: CameraModel) -> list[_Placed]:
        defaults_table = self.root.table("led_defaults")
        defaults_table.expect("z_m", "diameter_m", "frequency_hz", "duty", "survey_sigma_m", *_LED_EXTRAS)
        base = Led("", 0.0, 0.0, 0.0)
        defaults = {
            "z_m": defaults_table.number("z_m") if defaults_table.has("z_m") else None,
            "diameter_m": defaults_table.number("diameter_m", base.diameter_m),
            "frequency_hz": defaults_table.number("frequency_hz", base.frequency_hz),
            "duty": defaults_table.number("duty", base.duty),
        }
        survey_sigma = self._survey_sigma(defaults_table, None)
        extras = self._led_extras(defaults_table, _DEFAULT_EXTRAS)
        defaults_table.finish()
        for name in ("diameter_m", "frequency_hz", "duty"):
            rule = _RULES[f"Led.{name}"]
            if not rule[0](defaults[name]):
                raise defaults_table.error(name, f"{rule[1]}, got {defaults[name]:g}")

        leds: list[_Placed] = []
        for t in self.root.tables("leds", MAX_LEDS):
            t.expect(
                "id",
                "x_m",
                "y_m",
                "z_m",
                "diameter_m",
                "frequency_hz",
                "duty",
                "survey_sigma_m",
                "dead",
                "mapped",
                *_LED_EXTRAS,
            )
            own = self._led_extras(t, extras)
            led = Led(
                id=t.string("id", allow_int=True),
                x_m=t.number("x_m", required=True),
                y_m=t.number("y_m", required=True),
                z_m=self._led_number(t, "z_m", defaults),
                diameter_m=self._led_number(t, "diameter_m", defaults),
                frequency_hz=self._led_number(t, "frequency_hz", defaults),
                duty=self._led_number(t, "duty", defaults),
                survey_sigma_m=self._survey_sigma(t, survey_sigma),
                dead=t.boolean("dead", False),
                mapped=t.boolean("mapped", True),
                brightness=own["brightness"],
                frequency_drift_hz_per_s=own["frequency_drift_hz_per_s"],
                frequency_walk_hz_per_sqrt_s=own["frequency_walk_hz_per_sqrt_s"],
            )
            t.finish()
            leds.append(_Placed(led, t.path, t.path, t.path))
        for t in self.root.tables("led_grids", MAX_LEDS):
            leds += self._led_grid(t, defaults, len(leds), survey_sigma, extras)
        self._check_leds(leds, robot, cam)
        return leds

    def _led_extras(self, t: _Table, defaults: Mapping[str, float]) -> dict[str, float]:
        """An LED's brightness and frequency drift (:data:`_LED_EXTRAS`), ``defaults`` where not given."""
        out = {}
        for name, (check, reason) in _LED_EXTRAS.items():
            value = t.number(name, defaults[name])
            if not check(value):
                raise t.error(name, f"{reason}, got {value:g}")
            out[name] = value
        return out

    def _led_number(self, t: _Table, name: str, defaults: Mapping[str, float | None]) -> float:
        default = defaults[name]
        if not t.has(name) and default is None:
            raise t.error(name, "missing (give it here or in [led_defaults])")
        value = t.number(name, default)
        rule = _RULES.get(f"Led.{name}")
        if rule is not None and not rule[0](value):
            raise t.error(name, f"{rule[1]}, got {value:g}")
        return value

    def _survey_sigma(self, t: _Table, default: float | None) -> float | None:
        """An LED's stated survey sigma (``survey_sigma_m``), ``default`` when the table gives none."""
        if not t.has("survey_sigma_m"):
            return default
        value = t.number("survey_sigma_m")
        if not 0.0 <= value <= _MAX_SURVEY_SIGMA_M:
            raise t.error("survey_sigma_m", f"must be in [0, {_MAX_SURVEY_SIGMA_M:g}] m, got {value:g}")
        return value

    def _led_grid(
        self,
        t: _Table,
        defaults: Mapping[str, float | None],
        placed: int,
        survey_sigma: float | None,
        extras: Mapping[str, float],
    ) -> list[_Placed]:
        """LEDs on a rectangular grid; signature k goes to LED (ix, iy) with k = (ix + row_shift iy) mod n.
        Neighbours along a row always differ (n > 1); the default row_shift keeps repeats farthest apart.
        ``placed``: LEDs the world already has, which count against :data:`MAX_LEDS` with this grid's."""
        t.expect(
            "x0_m",
            "y0_m",
            "nx",
            "ny",
            "dx_m",
            "dy_m",
            "z_m",
            "diameter_m",
            "signatures",
            "row_shift",
            "survey_sigma_m",
            *_LED_EXTRAS,
        )
        x0, y0 = t.number("x0_m", required=True), t.number("y0_m", required=True)
        nx, ny = t.integer("nx"), t.integer("ny")
        for name, n in (("nx", nx), ("ny", ny)):
            if not 1 <= n <= MAX_LEDS:
                raise t.error(
                    name, f"must be >= 1 and at most {MAX_LEDS} (the limit on LEDs in a world), got {n}"
                )
        if placed + nx * ny > MAX_LEDS:
            # Name the larger factor: the likelier slip.
            raise t.error(
                "ny" if ny >= nx else "nx",
                f"a {nx} x {ny} grid is {nx * ny} LEDs; with the {placed} placed before it the world "
                f"would hold more than the limit of {MAX_LEDS}",
            )
        dx = t.number("dx_m", 0.0 if nx == 1 else None)
        dy = t.number("dy_m", 0.0 if ny == 1 else None)
        z = self._led_number(t, "z_m", defaults)
        diameter = self._led_number(t, "diameter_m", defaults)
        sigma = self._survey_sigma(t, survey_sigma)
        grid_extras = self._led_extras(t, extras)
        signatures = []
        for s in t.tables("signatures", MAX_LEDS):
            s.expect("id", "frequency_hz", "duty")
            sig = (
                s.string("id", allow_int=True),
                self._led_number(s, "frequency_hz", defaults),
                self._led_number(s, "duty", defaults),
            )
            s.finish()
            signatures.append(sig)
        if not signatures:
            raise t.error("signatures", "missing (at least one {id, frequency_hz, duty} is required)")
        n = len(signatures)
        row_shift = t.integer("row_shift", _best_row_shift(n, dx, dy))
        if not 0 <= row_shift < max(n, 1):
            raise t.error("row_shift", f"must be in 0..{n - 1}, got {row_shift}")
        t.finish()
        out = []
        for iy in range(ny):
            for ix in range(nx):
                k = (ix + row_shift * iy) % n
                sid, freq, duty = signatures[k]
                led = Led(
                    sid,
                    x0 + ix * dx,
                    y0 + iy * dy,
                    z,
                    diameter,
                    freq,
                    duty,
                    sigma,
                    brightness=grid_extras["brightness"],
                    frequency_drift_hz_per_s=grid_extras["frequency_drift_hz_per_s"],
                    frequency_walk_hz_per_sqrt_s=grid_extras["frequency_walk_hz_per_sqrt_s"],
                )
                out.append(_Placed(led, t.path, f"{t.path}.signatures[{k}]", f"{t.path} (ix={ix}, iy={iy})"))
        return out

    def _check_leds(self, leds: list[_Placed], robot: RobotSpec, cam: CameraModel) -> None:
        nyquist_sensor_hz = 1.0 / (2.0 * cam.t_row_s)
        k = cam.sensor_height_px / cam.output_height_px
        nyquist_output_hz = nyquist_sensor_hz / k if k > 1 else nyquist_sensor_hz
        by_id: dict[str, tuple[Led, str]] = {}
        by_signature: dict[tuple[float, float], tuple[Led, str]] = {}
        for led, key, sig_key, _ in leds:
            if led.z_m <= robot.camera_mount.z_m:
                raise self.error(
                    f"{key}.z_m",
                    f"{led.z_m:g} m is not above the camera "
                    f"(robot.camera_mount.z_m = {robot.camera_mount.z_m:g} m)",
                )
            if led.frequency_hz > nyquist_sensor_hz:
                raise self.error(
                    f"{sig_key}.frequency_hz",
                    f"{led.frequency_hz:g} Hz is above the rolling-shutter "
                    f"Nyquist limit 1/(2 t_row) = {nyquist_sensor_hz:.0f} Hz: the stripes alias",
                )
            if led.frequency_hz > nyquist_output_hz:
                log.warning(
                    "%s: %s.frequency_hz %g Hz is above %.0f Hz, where the stripes alias after the "
                    "%.2fx nearest-neighbour downsampling",
                    self.file,
                    sig_key,
                    led.frequency_hz,
                    nyquist_output_hz,
                    k,
                )
            x = math.pi * led.frequency_hz * cam.exposure_s
            contrast = abs(math.sin(x) / x) if x > 0 else 1.0
            if contrast < _MIN_STRIPE_CONTRAST:
                log.warning(
                    "%s: %s.frequency_hz %g Hz keeps only %.0f%% stripe contrast with a %g us exposure",
                    self.file,
                    sig_key,
                    led.frequency_hz,
                    100 * contrast,
                    cam.exposure_s * 1e6,
                )
            signature = (led.frequency_hz, led.duty)
            if led.id in by_id:
                other, other_key = by_id[led.id]
                if (other.frequency_hz, other.duty) != signature:
                    raise self.error(
                        sig_key,
                        f"LED id {led.id!r} is {other.frequency_hz:g} Hz / duty {other.duty:g} "
                        f"at {other_key} but {led.frequency_hz:g} Hz / duty {led.duty:g} here: "
                        "an id is its modulation, so one id needs one signature",
                    )
            else:
                by_id[led.id] = (led, sig_key)
                if signature in by_signature:
                    other, other_key = by_signature[signature]
                    raise self.error(
                        sig_key,
                        f"ids {other.id!r} ({other_key}) and {led.id!r} share the signature "
                        f"{led.frequency_hz:g} Hz / duty {led.duty:g}: the decoder could not tell "
                        "them apart",
                    )
                by_signature[signature] = (led, sig_key)
        for (_, a, _), (_, b, bkey) in _close_signature_pairs(list(by_signature.values())):
            log.warning(
                "%s: LED ids %r and %r (%s) have close signatures (%g/%g Hz, duty %g/%g)",
                self.file,
                a.id,
                b.id,
                bkey,
                a.frequency_hz,
                b.frequency_hz,
                a.duty,
                b.duty,
            )
        overlap = _first_overlap(leds)
        if overlap is not None:
            first, second, apart_m = overlap
            raise self.error(
                second.key,
                f"the LED at {second.where} overlaps the one at {first.where} "
                f"(centres {apart_m:.3f} m apart)",
            )

    # -- the rest of the scene ---------------------------------------------------------------------------
    def _scene(self, leds: list[_Placed], robot: RobotSpec, cam: CameraModel) -> Scene:
        t = self.root.table("scene")
        t.expect("ambient_dn", "stray_lights", "occluders")
        ambient = t.number("ambient_dn", 0.0)
        if not 0.0 <= ambient < 255.0 - cam.black_level_dn:
            raise t.error(
                "ambient_dn",
                f"must be in [0, {255.0 - cam.black_level_dn:g}) DN (above black level, below white), "
                f"got {ambient:g}",
            )
        stray = [self._stray_light(s, robot, cam) for s in t.tables("stray_lights", MAX_STRAY_LIGHTS)]
        occluders = [self._occluder(o, leds) for o in t.tables("occluders", MAX_LEDS)]
        t.finish()
        return Scene(ambient, tuple(stray), tuple(occluders))

    def _stray_light(self, t: _Table, robot: RobotSpec, cam: CameraModel) -> StrayLight:
        light: StrayLight = _read_dataclass(StrayLight, t)
        t.finish()
        if light.shape not in _SHAPES:
            raise t.error("shape", f"must be one of {list(_SHAPES)}, got {light.shape!r}")
        if light.z_m <= robot.camera_mount.z_m:
            raise t.error(
                "z_m",
                f"{light.z_m:g} m is not above the camera "
                f"(robot.camera_mount.z_m = {robot.camera_mount.z_m:g} m)",
            )
        for name in ("diameter_m", "width_m", "length_m"):
            if getattr(light, name) <= 0:
                raise t.error(name, f"must be > 0, got {getattr(light, name):g}")
        if not 0 < light.brightness <= _MAX_BRIGHTNESS:
            raise t.error(
                "brightness",
                f"must be > 0 and at most {_MAX_BRIGHTNESS:g} (relative to camera.led_peak_dn), "
                f"got {light.brightness:g}",
            )
        if light.flicker_hz < 0:
            raise t.error("flicker_hz", f"must be >= 0 (0: steady), got {light.flicker_hz:g}")
        if light.flicker_hz > 1.0 / (2.0 * cam.t_row_s):
            raise t.error(
                "flicker_hz",
                f"{light.flicker_hz:g} Hz is above the rolling-shutter Nyquist limit "
                f"1/(2 t_row) = {1.0 / (2.0 * cam.t_row_s):.0f} Hz",
            )
        if not 0 < light.flicker_duty < 1:
            raise t.error("flicker_duty", f"must be strictly between 0 and 1, got {light.flicker_duty:g}")
        return light

    def _occluder(self, t: _Table, leds: list[_Placed]) -> Occluder:
        t.expect("at", "fraction", "angle_rad", "angle_deg", "period_s", "hidden_s", "phase_s")
        at = _as_point(t.take("at"), t.key("at"), self.file) if t.has("at") else None
        if at is None:
            raise t.error("at", "missing (the [x, y] in metres of the LED it hides is required)")
        near = [(math.hypot(p.led.x_m - at[0], p.led.y_m - at[1]), i, p) for i, p in enumerate(leds)]
        if not near or min(near)[0] > _OCCLUDER_REACH_M:
            raise t.error("at", f"no LED within {_OCCLUDER_REACH_M:g} m of {at}")
        _, index, _ = min(near, key=lambda e: (e[0], e[1]))
        fraction = t.number("fraction", 1.0)
        if not 0 < fraction <= 1:
            raise t.error("fraction", f"must be > 0 and at most 1 (the whole disk), got {fraction:g}")
        if t.has("angle_rad") and t.has("angle_deg"):
            raise t.error("angle_deg", "give either angle_rad or angle_deg, not both")
        angle = math.radians(t.number("angle_deg")) if t.has("angle_deg") else t.number("angle_rad", 0.0)
        period = t.number("period_s", 0.0)
        if period < 0:
            raise t.error("period_s", f"must be >= 0 (0: always hidden), got {period:g}")
        hidden = t.number("hidden_s", period / 2.0)
        if period > 0 and not 0 < hidden <= period:
            raise t.error("hidden_s", f"must be > 0 and at most period_s ({period:g} s), got {hidden:g}")
        phase = t.number("phase_s", 0.0)
        t.finish()
        return Occluder(index, fraction, angle, period, hidden, phase)

    # -- things that move --------------------------------------------------------------------------------
    def _check_path(
        self, pts: tuple[Point, ...], walls: list[Wall], key: str, what: str, loop: bool = True
    ) -> None:
        """A path (looped, or walked once) must not go through a wall (people and the robot use the doors)."""
        if len(pts) < 2:
            return
        if loop and len(pts) > 2:
            legs = list(zip(pts, pts[1:] + pts[:1], strict=True))
        else:
            legs = list(itertools.pairwise(pts))
        boxes = _wall_boxes(walls)
        for i, (a, b) in enumerate(legs):
            for n in _walls_near(a, b, boxes, 0.0):
                q1, q2 = _wall_ends(walls[n])
                if _segments_cross(a, b, q1, q2):
                    raise self.error(
                        f"{key}[{i}]",
                        f"{what} from {a} to {b} goes through the wall "
                        f"({q1[0]:g}, {q1[1]:g})-({q2[0]:g}, {q2[1]:g})",
                    )

    def _people(self, walls: list[Wall]) -> list[Person]:
        people = []
        names: dict[str, str] = {}
        for t in self.root.tables("people", MAX_PEOPLE):
            t.expect(
                "name",
                "tag_id",
                "path",
                "speed_mps",
                "radius_m",
                "yields",
                "reaction_s",
                "loop",
                "start_s",
                "clothing",
            )
            base = Person("", "", ())
            clothing_table = t.table("clothing")
            clothing = _read_dataclass(Clothing, clothing_table)
            clothing_table.finish()
            person = Person(
                name=t.string("name"),
                tag_id=t.string("tag_id", allow_int=True),
                path=t.points("path", minimum=1, maximum=MAX_PATH_POINTS),
                speed_mps=self._checked(t, "Person", "speed_mps", base.speed_mps),
                radius_m=self._checked(t, "Person", "radius_m", base.radius_m),
                yields=t.boolean("yields", base.yields),
                reaction_s=self._checked(t, "Person", "reaction_s", base.reaction_s),
                loop=t.boolean("loop", base.loop),
                start_s=self._checked(t, "Person", "start_s", base.start_s),
                clothing=clothing,
            )
            t.finish()
            if person.name in names:
                raise t.error("name", f"{person.name!r} is already the name of {names[person.name]}")
            names[person.name] = t.path
            self._check_path(person.path, walls, t.key("path"), "the walk", person.loop)
            people.append(person)
        return people

    def _checked(self, t: _Table, cls: str, name: str, default: float) -> float:
        value = t.number(name, default)
        rule = _RULES[f"{cls}.{name}"]
        if not rule[0](value):
            raise t.error(name, f"{rule[1]}, got {value:g}")
        return value

    def _route(self, walls: list[Wall], robot: RobotSpec) -> tuple[tuple[Point, ...], float]:
        t = self.root.table("route")
        t.expect("waypoints", "speed_mps")
        waypoints = t.points("waypoints", minimum=1, maximum=MAX_PATH_POINTS, required=False)
        speed = t.number("speed_mps", World("").route_speed_mps)
        t.finish()
        if speed <= 0:
            raise t.error("speed_mps", f"must be > 0, got {speed:g}")
        self._check_path(waypoints, walls, "route.waypoints", "the route leg")
        if len(waypoints) >= 2:
            legs = list(zip(waypoints, waypoints[1:] + waypoints[:1], strict=True))
            boxes = _wall_boxes(walls)
            for i, (a, b) in enumerate(legs):
                for n in _walls_near(a, b, boxes, robot.radius_m):
                    gap = _segment_distance(a, b, *_wall_ends(walls[n]))
                    if gap < robot.radius_m:
                        log.warning(
                            "%s: route leg %d passes %.2f m from a wall, closer than the robot's radius "
                            "%.2f m",
                            self.file,
                            i,
                            gap,
                            robot.radius_m,
                        )
                        break
        return waypoints, speed

    def _check_start_doors(self, robot: RobotSpec, doors: list[Door]) -> None:
        start = (robot.start.x_m, robot.start.y_m)
        for i, d in enumerate(doors):
            gap = _point_segment_distance(start, (d.x1_m, d.y1_m), (d.x2_m, d.y2_m))
            if _closed_at_start(d) and gap < robot.radius_m:
                raise self.error(
                    "robot.start",
                    f"the robot ({robot.radius_m:g} m radius) at {start} overlaps the door doors[{i}] "
                    f"({d.name}), closed at the start",
                )

    def _check_start(self, robot: RobotSpec, walls: list[Wall]) -> None:
        start = (robot.start.x_m, robot.start.y_m)
        for w in walls:
            gap = _point_segment_distance(start, *_wall_ends(w))
            if gap < robot.radius_m:
                raise self.error(
                    "robot.start",
                    f"the robot ({robot.radius_m:g} m radius) at {start} overlaps the "
                    f"wall ({w.x1_m:g}, {w.y1_m:g})-({w.x2_m:g}, {w.y2_m:g})",
                )
