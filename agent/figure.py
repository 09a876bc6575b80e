"""Pictures for people, drawn with OpenCV (no plotting library on the robot): one palette, axes with ticks,
a scale bar, a legend box and a title, shared by every PNG the product writes (``sim``, ``eval slam``,
``eval vlp``, the calibration reports) so that a colour means the same thing in all of them.

The palette: truth green, drawn thick underneath; the fused pose red, thinner; the SLAM estimate blue,
thinnest; wheel odometry purple; VLP fixes teal; before calibration grey; LEDs amber; walls and occupied
cells black. Estimates are drawn thinner on top of the truth, so all stay visible where they agree.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum

import cv2
import numpy as np
import numpy.typing as npt

__all__ = [
    "FUSED",
    "LED",
    "ODOMETRY",
    "SLAM",
    "TRUTH",
    "UNCALIBRATED",
    "VLP_FIX",
    "Axes",
    "Entry",
    "Mark",
    "draw_path",
    "legend",
    "legend_size",
    "nice_ticks",
    "scale_bar",
    "text",
    "title",
]

ImageBgr = npt.NDArray[np.uint8]
Colour = tuple[int, int, int]

# BGR. Distinct in hue and in lightness, so they survive a grey-scale print too.
TRUTH: Colour = (60, 170, 60)
FUSED: Colour = (40, 40, 215)
SLAM: Colour = (200, 100, 0)
ODOMETRY: Colour = (170, 60, 170)
VLP_FIX: Colour = (150, 140, 0)
UNCALIBRATED: Colour = (160, 160, 160)
LED: Colour = (0, 190, 255)
BLACK: Colour = (0, 0, 0)
WHITE: Colour = (255, 255, 255)
GREY: Colour = (120, 120, 120)

# Nested widths: where the paths agree, each still shows as a band around the next.
TRUTH_WIDTH_PX = 8
FUSED_WIDTH_PX = 4
ESTIMATE_WIDTH_PX = 2
SWATCH_PX = (28, 10)  # a legend entry's sample: solid, so a test (or an eye) finds the exact colour
FONT = cv2.FONT_HERSHEY_SIMPLEX


class Mark(Enum):
    """How a legend entry is drawn: a solid bar (a path or an area) or a marker (points)."""

    BAR = "bar"
    DOT = "dot"
    CROSS = "cross"
    RING = "ring"


@dataclass(frozen=True, slots=True)
class Entry:
    label: str
    colour: Colour
    mark: Mark = Mark.BAR


def text(
    img: ImageBgr,
    s: str,
    org: tuple[int, int],
    scale: float = 0.5,
    colour: Colour = BLACK,
    thickness: int = 1,
) -> None:
    cv2.putText(img, s, (int(org[0]), int(org[1])), FONT, scale, colour, thickness, cv2.LINE_AA)


def text_width(s: str, scale: float = 0.5, thickness: int = 1) -> int:
    return int(cv2.getTextSize(s, FONT, scale, thickness)[0][0])


def title(img: ImageBgr, s: str, org: tuple[int, int] = (16, 30)) -> None:
    text(img, s, org, 0.7, BLACK, 2)


def nice_step(span: float, count: int = 6) -> float:
    """A 1, 2 or 5 times a power of ten step giving about ``count`` ticks over ``span``."""
    raw = max(abs(span), 1e-12) / max(count, 1)
    power = 10.0 ** math.floor(math.log10(raw))
    for m in (1.0, 2.0, 5.0, 10.0):
        if m * power >= raw:
            return m * power
    return 10.0 * power


def nice_ticks(lo: float, hi: float, count: int = 6) -> list[float]:
    """Round values between ``lo`` and ``hi`` (inclusive), about ``count`` of them."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo] if math.isfinite(lo) else []
    step = nice_step(hi - lo, count)
    first = math.ceil(lo / step - 1e-9)
    last = math.floor(hi / step + 1e-9)
    return [round(k * step, 12) for k in range(first, last + 1)]


def tick_label(value: float, step: float) -> str:
    digits = max(0, -math.floor(math.log10(step) + 1e-9)) if step > 0 else 0
    s = f"{value:.{digits}f}"
    return "0" if s in ("-0", "-0.0", "-0.00", "-0.000") else s


@dataclass(frozen=True, slots=True)
class Axes:
    """A plot box: ``rect`` in pixels (left, top, right, bottom) showing ``bounds`` (xmin, xmax, ymin, ymax)
    of the data. ``flip_y``: y grows downwards (image coordinates, e.g. pixels of a camera)."""

    rect: tuple[int, int, int, int]
    bounds: tuple[float, float, float, float]
    flip_y: bool = False

    @classmethod
    def fit(
        cls,
        bounds: tuple[float, float, float, float],
        rect: tuple[int, int, int, int],
        *,
        equal: bool = True,
        flip_y: bool = False,
    ) -> Axes:
        """The box inside ``rect`` showing ``bounds``; with ``equal`` a metre is as long across as up, the
        bounds widened (centred) to fill the box."""
        xmin, xmax, ymin, ymax = bounds
        if xmax <= xmin:
            xmin, xmax = xmin - 0.5, xmax + 0.5
        if ymax <= ymin:
            ymin, ymax = ymin - 0.5, ymax + 0.5
        if equal:
            left, top, right, bottom = rect
            scale = min((right - left) / (xmax - xmin), (bottom - top) / (ymax - ymin))
            half_w, half_h = (right - left) / scale / 2, (bottom - top) / scale / 2
            mx, my = (xmin + xmax) / 2, (ymin + ymax) / 2
            xmin, xmax, ymin, ymax = mx - half_w, mx + half_w, my - half_h, my + half_h
        return cls(rect, (xmin, xmax, ymin, ymax), flip_y)

    @property
    def px_per_unit(self) -> float:
        left, _, right, _ = self.rect
        return (right - left) / (self.bounds[1] - self.bounds[0])

    def to_px(self, x: float, y: float) -> tuple[int, int]:
        p = self.px(np.array([[x, y]], dtype=np.float64))[0]
        return round(float(p[0])), round(float(p[1]))

    def px(self, xy: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """(N, 2) data points -> (N, 2) pixel coordinates (continuous)."""
        left, top, right, bottom = self.rect
        xmin, xmax, ymin, ymax = self.bounds
        u = left + (xy[:, 0] - xmin) * (right - left) / (xmax - xmin)
        fy = (xy[:, 1] - ymin) / (ymax - ymin)
        v = top + fy * (bottom - top) if self.flip_y else bottom - fy * (bottom - top)
        return np.stack([u, v], axis=1)

    def draw(
        self,
        img: ImageBgr,
        xlabel: str = "x (m)",
        ylabel: str = "y (m)",
        *,
        grid: bool = False,
        frame: bool = True,
        count: int = 6,
    ) -> None:
        """The box's frame, ticks with values along the bottom and left edges, and the axis names."""
        left, top, right, bottom = self.rect
        xmin, xmax, ymin, ymax = self.bounds
        if frame:
            cv2.rectangle(img, (left, top), (right, bottom), BLACK, 1)
        xs = nice_ticks(xmin, xmax, count)
        ys = nice_ticks(ymin, ymax, count)
        xstep = xs[1] - xs[0] if len(xs) > 1 else 1.0
        ystep = ys[1] - ys[0] if len(ys) > 1 else 1.0
        for x in xs:
            u = self.to_px(x, ymin)[0]
            if grid:
                cv2.line(img, (u, top), (u, bottom), (225, 225, 225), 1)
            cv2.line(img, (u, bottom), (u, bottom + 6), BLACK, 1)
            label = tick_label(x, xstep)
            text(img, label, (u - text_width(label, 0.45) // 2, bottom + 22), 0.45)
        for y in ys:
            v = self.to_px(xmin, y)[1]
            if grid:
                cv2.line(img, (left, v), (right, v), (225, 225, 225), 1)
            cv2.line(img, (left - 6, v), (left, v), BLACK, 1)
            label = tick_label(y, ystep)
            text(img, label, (left - 10 - text_width(label, 0.45), v + 5), 0.45)
        if xlabel:
            text(img, xlabel, ((left + right) // 2 - text_width(xlabel) // 2, bottom + 44))
        if ylabel:
            text(img, ylabel, (max(2, left - 10 - text_width(ylabel)), max(top - 10, 14)))


def legend_size(entries: Sequence[Entry], scale: float = 0.5) -> tuple[int, int]:
    """Width and height in pixels of :func:`legend`'s box."""
    width = max((text_width(e.label, scale) for e in entries), default=0)
    return SWATCH_PX[0] + width + 30, 24 * len(entries) + 12


def legend(img: ImageBgr, entries: Sequence[Entry], top_left: tuple[int, int], scale: float = 0.5) -> None:
    """A framed white box, one row per entry: its colour's sample and its label."""
    if not entries:
        return
    w, h = legend_size(entries, scale)
    x0, y0 = top_left
    cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), WHITE, -1)
    cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), BLACK, 1)
    sw, sh = SWATCH_PX
    for i, e in enumerate(entries):
        cy = y0 + 18 + 24 * i
        cx = x0 + 10 + sw // 2
        # Every mark keeps a solid swatch of the exact colour, so a reader can match it to the picture.
        if e.mark is Mark.BAR:
            cv2.rectangle(img, (x0 + 10, cy - sh // 2), (x0 + 10 + sw - 1, cy + sh // 2 - 1), e.colour, -1)
        else:
            cv2.rectangle(
                img, (cx - sh // 2, cy - sh // 2), (cx + sh // 2 - 1, cy + sh // 2 - 1), e.colour, -1
            )
            if e.mark is Mark.CROSS:
                cv2.drawMarker(img, (cx, cy), e.colour, cv2.MARKER_CROSS, 20, 2)
            elif e.mark is Mark.RING:
                cv2.circle(img, (cx, cy), 8, BLACK, 1, cv2.LINE_AA)
        text(img, e.label, (x0 + sw + 20, cy + 5), scale)


def scale_bar(img: ImageBgr, px_per_m: float, left_bottom: tuple[int, int], target_px: int = 160) -> int:
    """A bar of a round number of metres (1, 2 or 5 times a power of ten), at most ``target_px`` long, with
    its length written above it; returns its length in pixels."""
    limit_m = target_px / px_per_m
    power = 10.0 ** math.floor(math.log10(limit_m))
    metres = max(m * power for m in (1.0, 2.0, 5.0) if m * power <= limit_m * (1 + 1e-9))
    length = round(float(metres * px_per_m))
    x0, y0 = left_bottom
    cv2.rectangle(img, (x0, y0 - 8), (x0 + length, y0), BLACK, -1)
    half = length // 2
    cv2.rectangle(img, (x0 + half, y0 - 7), (x0 + length - 1, y0 - 1), WHITE, -1)
    label = f"{metres:g} m"
    text(img, label, (x0 + length // 2 - text_width(label) // 2, y0 - 14))
    return length


def draw_path(
    img: ImageBgr,
    axes: Axes,
    xy: npt.NDArray[np.float64],
    colour: Colour,
    width: int = ESTIMATE_WIDTH_PX,
    *,
    start: bool = True,
) -> None:
    """A path (N, >=2 data xy) as a line; ``start`` marks its first point with a ring."""
    p = np.asarray(xy, dtype=np.float64).reshape(-1, xy.shape[-1] if xy.ndim == 2 else 2)[:, :2]
    p = p[np.all(np.isfinite(p), axis=1)]
    if p.shape[0] == 0:
        return
    px = axes.px(p)
    if p.shape[0] >= 2:
        pts = np.round(px * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(img, [pts], False, colour, width, cv2.LINE_AA, 4)
    if start:
        c = (round(float(px[0, 0])), round(float(px[0, 1])))
        # Hollow, so that no solid blob of a path's colour competes with its legend sample.
        cv2.circle(img, c, width + 5, WHITE, -1, cv2.LINE_AA)
        cv2.circle(img, c, width + 5, colour, 3, cv2.LINE_AA)
        cv2.circle(img, c, width + 7, BLACK, 1, cv2.LINE_AA)
