"""Camera calibration for VLP: the rotation centre and a residual correction, and their file format.

Two procedures, after ``reference/vlp.md`` §1.6 (the group's error calibration, arXiv 2010.00529):

* **Rotation centre (principal point).** While the robot turns in place, every LED's image moves on a circle
  around the image of the vertical through the lens. Its centre is the principal point plus what the camera's
  tilt on its mount adds (f tan(tilt)), so fitting circles to the tracked centres (Kasa least squares,
  (u - a)^2 + (v - b)^2 = r^2, linear in a, b and c = r^2 - a^2 - b^2) and averaging them gives the centre
  that makes the level-camera model exact: it absorbs the principal-point error and the tilt together.
  A lens off the rotation axis by m (base frame) moves every circle by -f R(-yaw_m) m / h, which is undone.
* **Residual correction.** Fixes taken at known points leave a position-dependent error e(x, y) = fix - truth
  (LED survey errors, what the centre does not absorb). A low-degree polynomial in (x, y) fitted to the
  errors by least squares is subtracted from every later fix.

Both are stored in a small TOML file (format in docs/vlp.md) read with :func:`parse_calibration`; this module
does no I/O: the caller reads and writes the text.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from agent.vlp.detect import fit_circle
from agent.vlp.model import CameraIntrinsics, CameraMount
from drivers.errors import ConfigError

FloatArray = npt.NDArray[np.float64]

__all__ = [
    "ResidualCorrection",
    "RotationCentre",
    "VlpCalibration",
    "fit_residual_correction",
    "fit_rotation_centre",
    "format_calibration",
    "mount_tilt_from_shift",
    "parse_calibration",
]

# A track must sweep at least this much of its circle to constrain the centre.
_MIN_ARC_RAD = math.radians(60.0)
# The tilt is told from a principal-point error by how the circle centres move with the radius (below); the
# circles' tan^2(alpha) must span at least this much, over at least this many circles.
_MIN_TILT_LEVER = 0.15
_MIN_TILT_CIRCLES = 3
# chi^2 (2 dof) the tilt's slope must reach to be kept: 1e-3 false alarm.
_TILT_CHI2 = 13.8
# Bounds on the counts and sizes a calibration file gives (docs/vlp.md). The image side is the config's
# limit (agent.config.MAX_IMAGE_SIDE_PX; tests/unit/test_vlp_calibration.py holds the two equal). The points
# a residual correction was fitted to are only recorded, but a count beyond this is a corrupt file.
MAX_IMAGE_SIDE_PX = 8192
MAX_RESIDUAL_POINTS = 1_000_000
# A camera tilted more than this on its mount is not looking at the ceiling as the model assumes.
_MAX_MOUNT_TILT_RAD = 0.35


@dataclass(frozen=True, slots=True)
class RotationCentre:
    """The principal point found from a turn in place (output px), its standard error, and the circles.

    ``tilt_px``: where the camera's tilt puts the image of the vertical, relative to the principal point
    (f tan(tilt) per axis, output px), when the circles' radii were spread enough to tell it from a
    principal-point error; (cx_px, cy_px) is then the principal point itself. None: (cx_px, cy_px) is the
    rotation centre, the principal point plus the tilt's shift (the level-camera model with the tilt
    absorbed)."""

    cx_px: float
    cy_px: float
    sigma_px: float
    circles: tuple[tuple[float, float, float, float], ...]  # (a, b, r, rms) per track used
    tilt_px: tuple[float, float] | None = None


def _arc_rad(points: FloatArray, a: float, b: float) -> float:
    """How much of the circle around (a, b) the points cover (2 pi minus the largest angular gap)."""
    ang = np.sort(np.arctan2(points[:, 1] - b, points[:, 0] - a))
    if ang.size < 2:
        return 0.0
    gaps = np.diff(np.concatenate((ang, [ang[0] + 2.0 * math.pi])))
    return float(2.0 * math.pi - gaps.max())


def fit_rotation_centre(
    tracks: Sequence[FloatArray],
    heights_m: Sequence[float],
    intrinsics: CameraIntrinsics,
    mount: CameraMount | None = None,
    *,
    min_points: int = 12,
) -> RotationCentre | str:
    """The principal point from LED image tracks recorded while turning in place, or the reason there is
    none.

    ``tracks[i]`` is an (n, 2) array of one LED's image centres (output px) over the turn, ``heights_m[i]``
    that LED's height above the lens. Each circle centre, moved back by the lens offset
    (+f R(-yaw_m) m_xy / h), estimates the principal point; they are averaged weighted by their arc and
    point count. A turn that saw no LED long enough (a sparse ceiling, a turn away from the LEDs) is not an
    error of the program but an answer: the refusal says what the tracks lacked, and the caller keeps the
    nominal principal point.
    """
    mount = mount if mount is not None else CameraMount()
    cos_m, sin_m = math.cos(mount.yaw_rad), math.sin(mount.yaw_rad)
    # The lens offset in the camera's level frame, R(-yaw_m) m.
    mx = cos_m * mount.x_m + sin_m * mount.y_m
    my = -sin_m * mount.x_m + cos_m * mount.y_m
    centres: list[tuple[float, float, float]] = []
    circles: list[tuple[float, float, float, float]] = []
    used_points: list[int] = []
    short = narrow = 0
    widest_rad = 0.0
    for pts, h in zip(tracks, heights_m, strict=True):
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        if pts.shape[0] < min_points:
            short += 1
            continue
        a, b, r = fit_circle(pts[:, 0], pts[:, 1])
        arc = _arc_rad(pts, a, b) if r > 0 else 0.0
        widest_rad = max(widest_rad, arc)
        if arc < _MIN_ARC_RAD:
            narrow += 1
            continue
        rms = float(np.sqrt(np.mean((np.hypot(pts[:, 0] - a, pts[:, 1] - b) - r) ** 2)))
        # The circle is centred on the principal point minus f R(-yaw_m) m / h.
        cx = a + intrinsics.fx_px * mx / h
        cy = b + intrinsics.fy_px * my / h
        weight = pts.shape[0] * (arc / (2.0 * math.pi)) ** 2 / max(rms, 0.05) ** 2
        centres.append((cx, cy, weight))
        circles.append((a, b, r, rms))
        used_points.append(pts.shape[0])
    if not centres:
        if not tracks:
            return "no LED of the map was tracked during the turn: turn in place under two or more LEDs"
        return (
            f"no LED track covers {math.degrees(_MIN_ARC_RAD):.0f} degrees of its circle ({len(tracks)} "
            f"tracks: {short} with fewer than {min_points} points, {narrow} sweeping at most "
            f"{math.degrees(widest_rad):.0f} degrees): turn in place under two or more LEDs"
        )
    c = np.array(centres)
    w = c[:, 2] / c[:, 2].sum()
    cx, cy = float(w @ c[:, 0]), float(w @ c[:, 1])
    if len(centres) > 1:
        spread = float(np.sqrt(w @ ((c[:, 0] - cx) ** 2 + (c[:, 1] - cy) ** 2) / (len(centres) - 1)))
    else:
        # One circle: its centre's standard error from its own scatter over its points (the track used,
        # which need not be the first one given).
        spread = circles[0][3] / math.sqrt(used_points[0])
    tilt = _tilt_from_circles(c, np.array([r for _, _, r, _ in circles]), intrinsics)
    if tilt is None:
        return RotationCentre(cx, cy, spread, tuple(circles))
    (px, py), (tx, ty), sigma = tilt
    return RotationCentre(px, py, sigma, tuple(circles), (tx, ty))


def _tilt_from_circles(
    centres: FloatArray, radii_px: FloatArray, intrinsics: CameraIntrinsics
) -> tuple[tuple[float, float], tuple[float, float], float] | None:
    """The principal point and the tilt's shift t = f tan(tilt) from circles of different radii.

    A camera tilted by a small angle tau sees a ray at alpha from the vertical at f tan(alpha + tau), so an
    LED circle of radius r = f tan(alpha) is centred on c = p + t (1 + tan^2 alpha) = p + t (1 + (r/f)^2)
    (first order in tau): a principal-point error moves every circle alike, a tilt moves the wide ones
    more. Weighted least squares of the centres on (1, (r/f)^2) per axis gives p + t and t. ``centres[:, 2]``
    are the circles' weights n (arc share)^2 / rms^2, half the inverse variance of a centre (a circle's centre
    is known to rms sqrt(2 / n) from n points all round it). None when the radii do not span
    ``_MIN_TILT_LEVER`` in (r/f)^2, there are fewer than ``_MIN_TILT_CIRCLES``, or the slope t is not
    significant (chi^2 of its two components under ``_TILT_CHI2``): then the single-parameter centre, more
    precise, is the better estimate.
    """
    if len(radii_px) < _MIN_TILT_CIRCLES:
        return None
    lever = np.column_stack(((radii_px / intrinsics.fx_px) ** 2, (radii_px / intrinsics.fy_px) ** 2))
    if float(np.min(lever.max(axis=0) - lever.min(axis=0))) < _MIN_TILT_LEVER:
        return None
    w = 0.5 * centres[:, 2]
    out: list[tuple[float, float]] = []
    chi2_slope = 0.0
    var_p = 0.0
    for axis in (0, 1):
        a = np.column_stack((np.ones(len(w)), lever[:, axis]))
        cov = np.linalg.inv(a.T @ (a * w[:, None]))
        intercept, slope = cov @ (a.T @ (w * centres[:, axis]))
        # The principal point p = intercept - slope, its variance from the fit's covariance.
        var_p += float(cov[0, 0] - 2.0 * cov[0, 1] + cov[1, 1])
        chi2_slope += float(slope) ** 2 / float(cov[1, 1])
        out.append((float(intercept - slope), float(slope)))
    if chi2_slope < _TILT_CHI2:
        return None
    return (out[0][0], out[1][0]), (out[0][1], out[1][1]), math.sqrt(0.5 * var_p)


def mount_tilt_from_shift(tilt_px: tuple[float, float], intrinsics: CameraIntrinsics) -> tuple[float, float]:
    """The camera's (roll, pitch) on its mount that puts the vertical at ``tilt_px`` from the principal point.

    With R_level = Ry(pitch) Rx(roll) (agent.vlp.geometry), the vertical seen by the camera is
    R_level^T e_z = (-sin p, cos p sin r, cos p cos r), at normalised (-tan p / cos r, tan r)."""
    roll = math.atan(tilt_px[1] / intrinsics.fy_px)
    pitch = -math.atan(tilt_px[0] / intrinsics.fx_px * math.cos(roll))
    return roll, pitch


def _monomials(x: FloatArray, y: FloatArray, degree: int) -> FloatArray:
    """[1, x, y, x^2, x y, y^2, ...] up to ``degree``, as columns."""
    cols = [x**i * y ** (d - i) for d in range(degree + 1) for i in range(d, -1, -1)]
    return np.column_stack(cols)


@dataclass(frozen=True, slots=True)
class ResidualCorrection:
    """e(x, y) = sum_k c_k m_k((x - x0) / s, (y - y0) / s), monomials m_k = 1, x, y, x^2, x y, y^2, ...;
    a fix (x, y) is corrected to (x, y) - e(x, y)."""

    origin_m: tuple[float, float]
    scale_m: float
    degree: int
    x_coefficients: tuple[float, ...]
    y_coefficients: tuple[float, ...]
    points: int = 0
    rms_before_m: float = math.nan
    rms_after_m: float = math.nan

    def __post_init__(self) -> None:
        n = (self.degree + 1) * (self.degree + 2) // 2
        if self.degree < 0 or len(self.x_coefficients) != n or len(self.y_coefficients) != n:
            raise ValueError(f"degree {self.degree} needs {n} coefficients per axis")
        if not self.scale_m > 0:
            raise ValueError("scale_m must be > 0")

    def error_at(self, x_m: float, y_m: float) -> tuple[float, float]:
        m = _monomials(
            np.array([(x_m - self.origin_m[0]) / self.scale_m]),
            np.array([(y_m - self.origin_m[1]) / self.scale_m]),
            self.degree,
        )[0]
        return float(m @ np.asarray(self.x_coefficients)), float(m @ np.asarray(self.y_coefficients))

    def apply(self, x_m: float, y_m: float) -> tuple[float, float]:
        ex, ey = self.error_at(x_m, y_m)
        return x_m - ex, y_m - ey


def fit_residual_correction(
    fixes_xy: FloatArray, truth_xy: FloatArray, *, degree: int = 1, ridge: float = 1e-6
) -> ResidualCorrection:
    """Least-squares polynomial (``degree``) through the errors fix - truth at known points (one row per
    fix; several fixes per point average their noise). A small ridge keeps it defined with few points."""
    fixes_xy = np.asarray(fixes_xy, dtype=np.float64).reshape(-1, 2)
    truth_xy = np.asarray(truth_xy, dtype=np.float64).reshape(-1, 2)
    n_coef = (degree + 1) * (degree + 2) // 2
    if fixes_xy.shape[0] < n_coef:
        raise ValueError(f"a degree-{degree} correction needs at least {n_coef} fixes")
    origin = truth_xy.mean(axis=0)
    scale = float(max(np.abs(truth_xy - origin).max(), 1e-3))
    err = fixes_xy - truth_xy
    a = _monomials((fixes_xy[:, 0] - origin[0]) / scale, (fixes_xy[:, 1] - origin[1]) / scale, degree)
    normal = a.T @ a + ridge * np.eye(n_coef)
    cx = np.linalg.solve(normal, a.T @ err[:, 0])
    cy = np.linalg.solve(normal, a.T @ err[:, 1])
    after = err - np.column_stack((a @ cx, a @ cy))
    return ResidualCorrection(
        (float(origin[0]), float(origin[1])),
        scale,
        degree,
        tuple(float(v) for v in cx),
        tuple(float(v) for v in cy),
        int(fixes_xy.shape[0]),
        float(np.sqrt(np.mean(np.sum(err**2, axis=1)))),
        float(np.sqrt(np.mean(np.sum(after**2, axis=1)))),
    )


def validated_residual_correction(
    fixes_xy: FloatArray, truth_xy: FloatArray, *, degree: int = 1, min_spread_m: float = 0.1
) -> ResidualCorrection | str:
    """A residual correction that cannot make the fixes worse, or the reason there is none.

    1. **Spread.** The known points (the distinct true positions) must determine the field: at least as
       many as it has coefficients, and, for degree >= 1, spread in both directions (the smaller principal
       spread of the points at least ``min_spread_m``): points clustered at one place or along a line give
       a slope from noise, which extrapolates to errors far larger than the ones it was fitted to.
    2. **Held-out fixes.** The fixes at each point are split in two halves; the correction fitted to one
       half is applied to the other (both ways), and kept only when the held-out rms error falls (a field
       fitted to noise alone makes the other half worse).
    """
    fixes_xy = np.asarray(fixes_xy, dtype=np.float64).reshape(-1, 2)
    truth_xy = np.asarray(truth_xy, dtype=np.float64).reshape(-1, 2)
    n_coef = (degree + 1) * (degree + 2) // 2
    keys = np.round(truth_xy * 1e3).astype(np.int64)
    points, label = np.unique(keys, axis=0, return_inverse=True)
    label = label.ravel()
    if len(points) < max(n_coef, 2) or fixes_xy.shape[0] < n_coef:
        return (
            f"{len(points)} known points ({fixes_xy.shape[0]} fixes): a degree-{degree} correction needs "
            f"{n_coef}"
        )
    centred = points / 1e3 - points.mean(axis=0) / 1e3
    spread = float(np.sqrt(max(np.linalg.eigvalsh(centred.T @ centred / len(points))[0], 0.0)))
    if degree >= 1 and spread < min_spread_m:
        return f"the known points are not spread out (smaller spread {spread:.3f} m < {min_spread_m} m)"
    # Two folds: every other fix at each known point (so both folds see every point); each fold's correction
    # is judged on the other's fixes.
    rank = np.zeros(len(label), dtype=np.int64)
    for k in range(len(points)):
        at = np.flatnonzero(label == k)
        rank[at] = np.arange(at.size)
    fold = rank % 2 == 0
    if min(np.count_nonzero(fold), np.count_nonzero(~fold)) < n_coef:
        return f"too few fixes to hold half of them out ({fixes_xy.shape[0]})"
    before = after = 0.0
    for train in (fold, ~fold):
        fitted = fit_residual_correction(fixes_xy[train], truth_xy[train], degree=degree)
        for (fx, fy), (tx, ty) in zip(fixes_xy[~train], truth_xy[~train], strict=True):
            cx, cy = fitted.apply(float(fx), float(fy))
            before += (fx - tx) ** 2 + (fy - ty) ** 2
            after += (cx - tx) ** 2 + (cy - ty) ** 2
    n = fixes_xy.shape[0]
    rms_before, rms_after = math.sqrt(before / n), math.sqrt(after / n)
    if not rms_after < rms_before:
        return (
            f"the correction does not improve held-out fixes (rms {1e3 * rms_before:.2f} -> "
            f"{1e3 * rms_after:.2f} mm)"
        )
    return fit_residual_correction(fixes_xy, truth_xy, degree=degree)


@dataclass(frozen=True, slots=True)
class VlpCalibration:
    """What the calibration found: the principal point at the given image size (None: keep the nominal
    one), the camera's tilt on its mount (roll, pitch; None: the mount's own, the tilt then absorbed in the
    principal point) and a residual correction (None: none)."""

    image_size_px: tuple[int, int]
    principal_point_px: tuple[float, float] | None = None
    principal_point_sigma_px: float = math.nan
    residual: ResidualCorrection | None = None
    mount_tilt_rad: tuple[float, float] | None = None

    def mount(self, nominal: CameraMount) -> CameraMount:
        """``nominal`` with the calibrated roll and pitch (the whole tilt the turn saw, not an addition)."""
        if self.mount_tilt_rad is None:
            return nominal
        return dataclasses.replace(nominal, roll_rad=self.mount_tilt_rad[0], pitch_rad=self.mount_tilt_rad[1])

    def intrinsics(self, nominal: CameraIntrinsics) -> CameraIntrinsics:
        """``nominal`` with the calibrated principal point (images must have the calibrated size)."""
        if (nominal.width_px, nominal.height_px) != self.image_size_px:
            raise ValueError(
                f"calibration is for {self.image_size_px[0]}x{self.image_size_px[1]} images, the camera "
                f"gives {nominal.width_px}x{nominal.height_px}"
            )
        if self.principal_point_px is None:
            return nominal
        return nominal.with_principal_point(*self.principal_point_px)


def _fmt(v: float) -> str:
    return repr(float(v))


def format_calibration(cal: VlpCalibration, comment: str = "") -> str:
    """The calibration as TOML text: the format :func:`parse_calibration` reads (docs/vlp.md)."""
    lines = ["# vlp-agent VLP calibration (docs/vlp.md)"]
    lines += [f"# {line}" for line in comment.splitlines()]
    lines += ["", "[camera]"]
    lines.append(f"image_size_px = [{cal.image_size_px[0]}, {cal.image_size_px[1]}]")
    if cal.principal_point_px is not None:
        cx, cy = cal.principal_point_px
        lines.append(f"principal_point_px = [{_fmt(cx)}, {_fmt(cy)}]")
        if math.isfinite(cal.principal_point_sigma_px):
            lines.append(f"principal_point_sigma_px = {_fmt(cal.principal_point_sigma_px)}")
    if cal.mount_tilt_rad is not None:
        lines.append(f"mount_tilt_rad = [{_fmt(cal.mount_tilt_rad[0])}, {_fmt(cal.mount_tilt_rad[1])}]")
    res = cal.residual
    if res is not None:
        lines += ["", "[residual]"]
        lines.append(f"origin_m = [{_fmt(res.origin_m[0])}, {_fmt(res.origin_m[1])}]")
        lines.append(f"scale_m = {_fmt(res.scale_m)}")
        lines.append(f"degree = {res.degree}")
        lines.append("x_coefficients = [" + ", ".join(_fmt(v) for v in res.x_coefficients) + "]")
        lines.append("y_coefficients = [" + ", ".join(_fmt(v) for v in res.y_coefficients) + "]")
        lines.append(f"points = {res.points}")
        for name in ("rms_before_m", "rms_after_m"):
            value = getattr(res, name)
            if math.isfinite(value):
                lines.append(f"{name} = {_fmt(value)}")
    return "\n".join(lines) + "\n"


def _number(table: Mapping[str, Any], key: str, path: str, source: str | None) -> float:
    value = table.get(key)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(float(value)):
        raise ConfigError(f"{path}.{key}", f"must be a finite number, got {value!r}", source)
    return float(value)


def _numbers(table: Mapping[str, Any], key: str, path: str, source: str | None, n: int | None) -> list[float]:
    value = table.get(key)
    if not isinstance(value, list) or (n is not None and len(value) != n):
        want = f"{n} numbers" if n is not None else "numbers"
        raise ConfigError(f"{path}.{key}", f"must be an array of {want}, got {value!r}", source)
    out = []
    for i, v in enumerate(value):
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(float(v)):
            raise ConfigError(f"{path}.{key}[{i}]", f"must be a finite number, got {v!r}", source)
        out.append(float(v))
    return out


def parse_calibration(data: str | Mapping[str, Any], source: str | None = None) -> VlpCalibration:
    """A calibration from TOML text (or a parsed table). Raises ConfigError naming the key on mistakes."""
    if isinstance(data, str):
        try:
            table: Mapping[str, Any] = tomllib.loads(data)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError("", f"not valid TOML: {exc}", source) from exc
    else:
        table = data
    unknown = set(table) - {"camera", "residual"}
    if unknown:
        raise ConfigError(sorted(unknown)[0], "unknown section (expected [camera] and [residual])", source)
    camera = table.get("camera")
    if not isinstance(camera, dict):
        raise ConfigError("camera", "missing [camera] section", source)
    known_camera = {"image_size_px", "principal_point_px", "principal_point_sigma_px", "mount_tilt_rad"}
    for key in camera:
        if key not in known_camera:
            raise ConfigError(f"camera.{key}", "unknown key", source)
    size = _numbers(camera, "image_size_px", "camera", source, 2)
    if any(not 0 < v <= MAX_IMAGE_SIDE_PX or v != int(v) for v in size):
        raise ConfigError(
            "camera.image_size_px", f"must be two integers 1..{MAX_IMAGE_SIDE_PX}, got {size}", source
        )
    principal = None
    if "principal_point_px" in camera:
        cx, cy = _numbers(camera, "principal_point_px", "camera", source, 2)
        principal = (cx, cy)
    tilt = None
    if "mount_tilt_rad" in camera:
        roll, pitch = _numbers(camera, "mount_tilt_rad", "camera", source, 2)
        if max(abs(roll), abs(pitch)) > _MAX_MOUNT_TILT_RAD:
            raise ConfigError(
                "camera.mount_tilt_rad",
                f"must be within +-0.35 rad (20 degrees), got {[roll, pitch]}",
                source,
            )
        tilt = (roll, pitch)
    sigma = math.nan
    if "principal_point_sigma_px" in camera:
        sigma = _number(camera, "principal_point_sigma_px", "camera", source)
    residual = None
    if "residual" in table:
        res = table["residual"]
        if not isinstance(res, dict):
            raise ConfigError("residual", "must be a table", source)
        known = {
            "origin_m",
            "scale_m",
            "degree",
            "x_coefficients",
            "y_coefficients",
            "points",
            "rms_before_m",
            "rms_after_m",
        }
        for key in res:
            if key not in known:
                raise ConfigError(f"residual.{key}", "unknown key", source)
        degree = res.get("degree")
        if isinstance(degree, bool) or not isinstance(degree, int) or not 0 <= degree <= 4:
            raise ConfigError("residual.degree", f"must be an integer 0..4, got {degree!r}", source)
        n = (degree + 1) * (degree + 2) // 2
        ox, oy = _numbers(res, "origin_m", "residual", source, 2)
        scale = _number(res, "scale_m", "residual", source)
        if scale <= 0:
            raise ConfigError("residual.scale_m", f"must be > 0, got {scale}", source)
        xs = _numbers(res, "x_coefficients", "residual", source, n)
        ys = _numbers(res, "y_coefficients", "residual", source, n)
        points = res.get("points", 0)
        if isinstance(points, bool) or not isinstance(points, int) or not 0 <= points <= MAX_RESIDUAL_POINTS:
            raise ConfigError(
                "residual.points", f"must be an integer 0..{MAX_RESIDUAL_POINTS}, got {points!r}", source
            )
        before = _number(res, "rms_before_m", "residual", source) if "rms_before_m" in res else math.nan
        after = _number(res, "rms_after_m", "residual", source) if "rms_after_m" in res else math.nan
        residual = ResidualCorrection((ox, oy), scale, degree, tuple(xs), tuple(ys), points, before, after)
    return VlpCalibration((int(size[0]), int(size[1])), principal, sigma, residual, tilt)
