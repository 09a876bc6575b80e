"""The small frozen types that go in and out of the VLP pipeline.

Units are in the names. Image coordinates are output pixels (the images the pipeline is given), u to the
right and v down, pixel centres on integers. The world frame is x east, y north, z up (the LED survey's
frame); yaw is counter-clockwise from +x. The camera frame is right-handed with z up along the optical axis,
image u along camera x and v along camera y (``reference/vlp.md`` §1.5).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from agent.vlp.integrity import ProtectionInputs

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "AssociationWork",
    "CameraIntrinsics",
    "CameraMount",
    "LedMap",
    "LedObservation",
    "MapLed",
    "Motion",
    "NoFix",
    "PosePrior",
    "Signature",
    "StageTimings",
    "Tilt",
    "VlpFix",
    "VlpResult",
]


def _nearest_neighbour_line(src_size: int, dst_size: int) -> tuple[float, float]:
    """Source coordinate = a * destination coordinate + b, the least-squares line through the indices that
    ``cv2.resize(..., INTER_NEAREST)`` keeps (OpenCV ``resizeNN``: index = min(floor(x * src/dst), src - 1),
    with the scale computed as 1 / (dst / src) in double precision)."""
    if dst_size == src_size:
        return 1.0, 0.0
    ifx = 1.0 / (dst_size / src_size)
    x = np.arange(dst_size, dtype=np.float64)
    chosen = np.minimum(np.floor(x * ifx), src_size - 1)
    a, b = np.polyfit(x, chosen, 1)
    return float(a), float(b)


@dataclass(frozen=True, slots=True)
class CameraIntrinsics:
    """Pinhole intrinsics of the images the pipeline receives, and the rolling-shutter timing.

    ``fx_px``..``cy_px`` are at output resolution. An image resized from the sensor with nearest neighbour
    keeps sensor row ``sensor_rows_per_row * v + sensor_row_offset`` in output row v, so a stripe period
    of P output rows lasts P * ``sensor_rows_per_row`` * ``t_row_s`` (the effective row time). Distortion
    is OpenCV's (k1, k2, p1, p2, k3) on normalised coordinates, so it does not depend on the resolution.
    """

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    t_row_s: float
    sensor_rows_per_row: float = 1.0
    sensor_row_offset: float = 0.0
    sensor_height_px: int = 0
    exposure_s: float = 20e-6
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.width_px <= 0 or self.height_px <= 0:
            raise ValueError(f"image size must be positive, got {self.width_px}x{self.height_px}")
        if not (self.fx_px > 0 and self.fy_px > 0):
            raise ValueError(f"focal lengths must be positive, got {self.fx_px}, {self.fy_px}")
        if not self.t_row_s > 0:
            raise ValueError(f"t_row_s must be positive, got {self.t_row_s}")
        if not self.sensor_rows_per_row > 0:
            raise ValueError(f"sensor_rows_per_row must be positive, got {self.sensor_rows_per_row}")

    @classmethod
    def from_sensor(
        cls,
        *,
        sensor_width_px: int,
        sensor_height_px: int,
        output_width_px: int,
        output_height_px: int,
        focal_length_px: float,
        cx_sensor_px: float,
        cy_sensor_px: float,
        t_row_s: float,
        exposure_s: float = 20e-6,
        distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0),
    ) -> CameraIntrinsics:
        """Output-resolution intrinsics of a sensor whose frames are resized with nearest neighbour.

        Sensor column = a_x u + b_x (rows alike), so fx = f / a_x and cx = (cx_sensor - b_x) / a_x.
        """
        ax, bx = _nearest_neighbour_line(sensor_width_px, output_width_px)
        ay, by = _nearest_neighbour_line(sensor_height_px, output_height_px)
        return cls(
            width_px=output_width_px,
            height_px=output_height_px,
            fx_px=focal_length_px / ax,
            fy_px=focal_length_px / ay,
            cx_px=(cx_sensor_px - bx) / ax,
            cy_px=(cy_sensor_px - by) / ay,
            t_row_s=t_row_s,
            sensor_rows_per_row=ay,
            sensor_row_offset=by,
            sensor_height_px=sensor_height_px,
            exposure_s=exposure_s,
            distortion=distortion,
        )

    @classmethod
    def from_output(
        cls,
        *,
        width_px: int,
        height_px: int,
        fx_px: float,
        fy_px: float,
        cx_px: float,
        cy_px: float,
        t_row_s: float,
        sensor_height_px: int = 0,
        exposure_s: float = 20e-6,
        distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0),
    ) -> CameraIntrinsics:
        """Intrinsics calibrated at output resolution (a camera_info file, a config) of frames resized
        with nearest neighbour from ``sensor_height_px`` rows (0: not resized): the sensor row of each
        output row is worked out as in :meth:`from_sensor`."""
        a_y, b_y = (
            _nearest_neighbour_line(sensor_height_px, height_px) if sensor_height_px > 0 else (1.0, 0.0)
        )
        return cls(
            width_px=width_px,
            height_px=height_px,
            fx_px=fx_px,
            fy_px=fy_px,
            cx_px=cx_px,
            cy_px=cy_px,
            t_row_s=t_row_s,
            sensor_rows_per_row=a_y,
            sensor_row_offset=b_y,
            sensor_height_px=sensor_height_px,
            exposure_s=exposure_s,
            distortion=distortion,
        )

    @property
    def t_row_eff_s(self) -> float:
        """Time between consecutive output rows: t_row * sensor rows per output row."""
        return self.t_row_s * self.sensor_rows_per_row

    @property
    def readout_rows(self) -> int:
        return self.sensor_height_px if self.sensor_height_px > 0 else self.height_px

    def row_time_from_mid_s(self, v_px: float) -> float:
        """When output row ``v_px`` was exposed, relative to the middle of the readout (the frame's time):
        t = ((a v + b) - (rows - 1) / 2) t_row."""
        sensor_row = self.sensor_rows_per_row * v_px + self.sensor_row_offset
        return (sensor_row - (self.readout_rows - 1) / 2.0) * self.t_row_s

    def with_principal_point(self, cx_px: float, cy_px: float) -> CameraIntrinsics:
        return CameraIntrinsics(
            self.width_px,
            self.height_px,
            self.fx_px,
            self.fy_px,
            cx_px,
            cy_px,
            self.t_row_s,
            self.sensor_rows_per_row,
            self.sensor_row_offset,
            self.sensor_height_px,
            self.exposure_s,
            self.distortion,
        )


@dataclass(frozen=True, slots=True)
class CameraMount:
    """Where the camera's lens sits on the robot base (x forward, y left, z up) and how it is turned.

    Roll and pitch are the known mounting tilt (the tilt compensation adds the IMU's base tilt to them).
    """

    x_m: float = 0.0
    y_m: float = 0.0
    z_m: float = 0.2
    yaw_rad: float = 0.0
    roll_rad: float = 0.0
    pitch_rad: float = 0.0


@dataclass(frozen=True, slots=True)
class Signature:
    """An LED's identity as the camera sees it: its PWM frequency and duty cycle."""

    id: str
    frequency_hz: float
    duty: float


@dataclass(frozen=True, slots=True)
class MapLed:
    """One surveyed ceiling LED: a horizontal disk facing down. ``survey_sigma_m``: the standard deviation
    of its surveyed x and y, when the survey states one (None: the solver's ``map_sigma_m``)."""

    id: str
    x_m: float
    y_m: float
    z_m: float
    frequency_hz: float
    duty: float
    diameter_m: float = 0.086
    survey_sigma_m: float | None = None

    @classmethod
    def of(cls, led: SurveyedLed) -> MapLed:
        """The map's LED from any record of one (an LED map file's entry, a world file's LED)."""
        return cls(
            led.id, led.x_m, led.y_m, led.z_m, led.frequency_hz, led.duty, led.diameter_m, led.survey_sigma_m
        )


class SurveyedLed(Protocol):
    """What a record of a surveyed LED carries: :class:`MapLed`'s fields, read-only."""

    @property
    def id(self) -> str: ...
    @property
    def x_m(self) -> float: ...
    @property
    def y_m(self) -> float: ...
    @property
    def z_m(self) -> float: ...
    @property
    def frequency_hz(self) -> float: ...
    @property
    def duty(self) -> float: ...
    @property
    def diameter_m(self) -> float: ...
    @property
    def survey_sigma_m(self) -> float | None: ...


@dataclass(frozen=True)
class LedMap:
    """The surveyed LED map. Ids may repeat across a large building (the same signature on LEDs far
    apart); one id always has one signature. ``signatures`` lists each id once, in first-seen order.
    ``survey_sigma_m``: each LED's survey standard deviation (NaN where it states none), or None when no LED
    states one."""

    leds: tuple[MapLed, ...]
    signatures: tuple[Signature, ...] = field(init=False)
    indices_by_id: dict[str, tuple[int, ...]] = field(init=False, compare=False)
    xyz_m: FloatArray = field(init=False, compare=False, repr=False)
    survey_sigma_m: FloatArray | None = field(init=False, compare=False, repr=False)

    def __post_init__(self) -> None:
        by_id: dict[str, list[int]] = {}
        sigs: dict[str, Signature] = {}
        for i, led in enumerate(self.leds):
            if not (led.frequency_hz > 0 and 0 < led.duty < 1 and led.diameter_m > 0):
                raise ValueError(f"LED {led.id!r} has an impossible signature or size: {led}")
            if led.survey_sigma_m is not None and not 0.0 <= led.survey_sigma_m < math.inf:
                raise ValueError(f"LED {led.id!r} has an impossible survey sigma: {led.survey_sigma_m}")
            known = sigs.get(led.id)
            if known is None:
                sigs[led.id] = Signature(led.id, led.frequency_hz, led.duty)
            elif (known.frequency_hz, known.duty) != (led.frequency_hz, led.duty):
                raise ValueError(f"LED id {led.id!r} appears with two signatures")
            by_id.setdefault(led.id, []).append(i)
        xyz = np.array([[led.x_m, led.y_m, led.z_m] for led in self.leds], dtype=np.float64).reshape(-1, 3)
        object.__setattr__(self, "signatures", tuple(sigs.values()))
        object.__setattr__(self, "indices_by_id", {k: tuple(v) for k, v in by_id.items()})
        object.__setattr__(self, "xyz_m", xyz)
        stated = [led.survey_sigma_m for led in self.leds]
        sigma = (
            np.array([math.nan if v is None else v for v in stated], dtype=np.float64)
            if any(v is not None for v in stated)
            else None
        )
        object.__setattr__(self, "survey_sigma_m", sigma)

    def map_sigmas_m(self, default_m: float) -> list[float] | None:
        """Each LED's survey sigma, ``default_m`` where it states none; None when none states one (every LED
        then has the default)."""
        if self.survey_sigma_m is None:
            return None
        return [default_m if math.isnan(v) else float(v) for v in self.survey_sigma_m.tolist()]

    def __len__(self) -> int:
        return len(self.leds)

    def candidates(self, led_id: str) -> tuple[int, ...]:
        """Indices of the map LEDs that carry ``led_id`` (several in a building that repeats ids)."""
        return self.indices_by_id.get(led_id, ())

    @property
    def ids_unique(self) -> bool:
        return all(len(v) == 1 for v in self.indices_by_id.values())


@dataclass(frozen=True, slots=True)
class Tilt:
    """The robot base's roll and pitch (from the IMU), radians, right-handed about base x and y."""

    roll_rad: float = 0.0
    pitch_rad: float = 0.0


@dataclass(frozen=True, slots=True)
class PosePrior:
    """Where the robot base roughly is (odometry, the last fix, a map prior): mean and standard deviations.

    Used to tell apart LEDs that share an id, to reject fixes that jump impossibly far, and for a single-LED
    degraded fix (which needs the yaw)."""

    x_m: float
    y_m: float
    yaw_rad: float
    sigma_xy_m: float = 0.5
    sigma_yaw_rad: float = math.radians(20.0)


@dataclass(frozen=True, slots=True)
class Motion:
    """The base's velocity in the world frame during the frame (for the rolling-shutter correction)."""

    vx_mps: float = 0.0
    vy_mps: float = 0.0
    yaw_rate_radps: float = 0.0


@dataclass(frozen=True, slots=True)
class StageTimings:
    """Wall time spent per stage of one frame, milliseconds."""

    acquire_ms: float = 0.0
    track_ms: float = 0.0
    decode_ms: float = 0.0
    solve_ms: float = 0.0
    total_ms: float = 0.0


@dataclass(frozen=True, slots=True)
class AssociationWork:
    """What telling repeated ids apart cost on one frame: ``checks`` candidate tests (a prior gate, a pair's
    distance, a predicted LED's place: each a few float operations), ``hypotheses`` id-to-LED assignments
    solved by Gauss-Newton, ``truncated`` when the work budget ran out before every candidate was tried."""

    checks: int = 0
    hypotheses: int = 0
    truncated: bool = False


NO_WORK = AssociationWork()


@dataclass(frozen=True, slots=True)
class LedObservation:
    """One LED seen in one frame.

    ``frame_id`` is what this frame's stripes alone say (``None``: undecidable), with ``frame_confidence``;
    ``id`` is the track's settled identity after voting over frames (``None`` until it settles).
    ``visibility`` is ``"full"``, ``"partial"`` (partly occluded: kept, not used for the fix) or
    ``"occluded"`` (coasting on the Kalman prediction). ``map_index`` is the map LED the solver matched.
    ``frame_reason``: why this frame's stripes named no id when they were decoded (the decoder's refusal:
    ``"unresolved: ..."``, ``"low-contrast: ..."``, ``"blob-too-short: ..."``, ``"stripe-too-short: ..."``,
    ``"too-few-stripes: ..."``, ``"poor-fit: ..."``; ``agent.vlp.decode.Classification``).
    """

    track_id: int
    centre_px: tuple[float, float]
    radius_px: float
    visibility: str
    bhattacharyya: float
    frame_id: str | None
    frame_confidence: float
    id: str | None
    id_confidence: float
    frequency_hz: float
    duty: float
    area_px: int
    map_index: int | None = None
    used: bool = False
    frame_reason: str | None = None


@dataclass(frozen=True, slots=True)
class VlpFix:
    """A pose of the robot base at ``time_s`` (the frame's mid-readout time).

    ``covariance`` is over (x_m, y_m, yaw_rad), row-major 3x3. ``residual_rms`` is the solver's RMS
    residual in standard deviations (about 1 when the noise is as modelled). ``degraded`` says the fix is
    weaker than a
    normal one, with the reasons in ``flags`` (e.g. ``"single-led"``, ``"inconsistent"``,
    ``"id-unconfirmed"``). ``work``: what the id association cost. Integrity: ``chi2`` is the fit's
    whitened residual sum (every fitted term, the LED-height correction's prior included), tested against
    ``chi2_threshold`` (a fix past it is degraded, flag ``"inconsistent"``); ``protection_level_m`` bounds the
    base position error that a fault in one LED could cause without the test seeing it, at the solver's
    risks (inf when nothing can be ruled out: two LEDs, one LED), computed on reading from ``protection``.
    """

    time_s: float
    x_m: float
    y_m: float
    yaw_rad: float
    covariance: tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
    ids: tuple[str, ...]
    leds: tuple[LedObservation, ...]
    residual_rms: float
    degraded: bool
    flags: tuple[str, ...]
    timings: StageTimings
    work: AssociationWork = NO_WORK
    chi2: float = math.nan
    chi2_threshold: float = math.inf
    protection: ProtectionInputs | None = None

    @property
    def protection_level_m(self) -> float:
        """The protection level, metres (computed from ``protection`` on reading; inf without it)."""
        return self.protection.protection_level_m if self.protection is not None else math.inf

    @property
    def sigma_xy_m(self) -> float:
        """sqrt of the larger eigenvalue of the position covariance: the worst direction's deviation."""
        c = self.covariance
        a, b, d = c[0][0], c[0][1], c[1][1]
        return math.sqrt(max(0.5 * (a + d) + math.sqrt(0.25 * (a - d) ** 2 + b * b), 0.0))


@dataclass(frozen=True, slots=True)
class NoFix:
    """No pose from this frame, and why (``reason`` is one short sentence)."""

    time_s: float
    reason: str
    leds: tuple[LedObservation, ...]
    timings: StageTimings
    work: AssociationWork = NO_WORK


VlpResult = VlpFix | NoFix
