"""Report figures drawn with OpenCV (no plotting library on the robot): bar charts, scatter plots, text.

Each function returns a BGR image; :func:`png` encodes one for saving. Figures are small and plain: they are
for a person checking a calibration, not for publication.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

__all__ = ["Series", "bar_chart", "grid", "png", "scatter", "text_panel"]

ImageBgr = npt.NDArray[np.uint8]
Colour = tuple[int, int, int]

WHITE: Colour = (255, 255, 255)
BLACK: Colour = (0, 0, 0)
GREY: Colour = (170, 170, 170)
GREEN: Colour = (60, 160, 60)
RED: Colour = (40, 40, 210)
BLUE: Colour = (200, 110, 30)
ORANGE: Colour = (0, 140, 255)
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_MARGIN = (60, 20, 40, 40)  # left, right, top, bottom


@dataclass(frozen=True, slots=True)
class Series:
    """Points of one colour in a scatter plot; ``line`` joins them in order."""

    points: npt.NDArray[np.float64]
    colour: Colour
    label: str
    radius: int = 2
    line: bool = False


def _text(
    img: ImageBgr, text: str, org: tuple[int, int], scale: float = 0.45, colour: Colour = BLACK
) -> None:
    cv2.putText(img, text, org, _FONT, scale, colour, 1, cv2.LINE_AA)


def _nice(value: float) -> str:
    return f"{value:.3g}"


def bar_chart(
    values: Sequence[float],
    *,
    title: str,
    ylabel: str,
    threshold: float | None = None,
    size: tuple[int, int] = (640, 360),
) -> ImageBgr:
    """One bar per value (index on the x axis); bars above ``threshold`` are red, a dashed line marks it."""
    w, h = size
    img = np.full((h, w, 3), 255, np.uint8)
    left, right, top, bottom = _MARGIN
    _text(img, title, (left, 22), 0.5)
    finite = [v for v in values if math.isfinite(v)]
    vmax = max(finite + ([threshold] if threshold is not None else []) + [1e-9]) * 1.15
    pw, ph = w - left - right, h - top - bottom
    cv2.rectangle(img, (left, top), (left + pw, top + ph), GREY, 1)
    for k in range(5):
        y = top + ph - int(ph * k / 4)
        cv2.line(img, (left - 4, y), (left, y), BLACK, 1)
        _text(img, _nice(vmax * k / 4), (4, y + 4), 0.38)
    _text(img, ylabel, (4, top - 6), 0.38)
    n = max(len(values), 1)
    bar = pw / n
    for i, v in enumerate(values):
        if not math.isfinite(v):
            continue
        x0 = left + int(i * bar + 0.15 * bar)
        x1 = max(left + int((i + 1) * bar - 0.15 * bar), x0 + 1)
        y = top + ph - int(ph * v / vmax)
        colour = RED if threshold is not None and v > threshold else BLUE
        cv2.rectangle(img, (x0, y), (x1, top + ph), colour, -1)
        if n <= 40 and (n <= 20 or i % 2 == 0):
            _text(img, str(i + 1), (x0, top + ph + 14), 0.33)
    if threshold is not None:
        y = top + ph - int(ph * threshold / vmax)
        for x in range(left, left + pw, 12):
            cv2.line(img, (x, y), (min(x + 6, left + pw), y), RED, 1)
        _text(img, f"threshold {_nice(threshold)}", (left + pw - 150, max(y - 5, top + 12)), 0.4, RED)
    return img


def scatter(
    series: Sequence[Series],
    *,
    title: str,
    bounds: tuple[float, float, float, float] | None = None,
    size: tuple[int, int] = (640, 480),
    flip_y: bool = False,
    grid_lines: tuple[Sequence[float], Sequence[float]] | None = None,
    circles: Sequence[tuple[float, float, float, Colour]] = (),
    axis_labels: tuple[str, str] = ("", ""),
) -> ImageBgr:
    """Points of each series in a box with equal axis scales. ``bounds`` = (xmin, xmax, ymin, ymax), default
    the data's; ``flip_y``: y grows downwards (image coordinates). ``circles``: (x, y, radius, colour)."""
    w, h = size
    img = np.full((h, w, 3), 255, np.uint8)
    left, right, top, bottom = _MARGIN
    _text(img, title, (left, 22), 0.5)
    pts = [s.points.reshape(-1, 2) for s in series if s.points.size]
    if bounds is None:
        allp = np.vstack(pts) if pts else np.zeros((1, 2))
        allp = allp[np.all(np.isfinite(allp), axis=1)] if allp.size else np.zeros((1, 2))
        if allp.size == 0:
            allp = np.zeros((1, 2))
        if len(allp) >= 50:
            # A few wild points (a mis-detected corner) must not squash the rest: they are drawn at the edge.
            xmin, ymin = np.percentile(allp, 0.5, axis=0)
            xmax, ymax = np.percentile(allp, 99.5, axis=0)
        else:
            xmin, ymin = allp.min(axis=0)
            xmax, ymax = allp.max(axis=0)
        for cx, cy, r, _ in circles:
            xmin, xmax, ymin, ymax = (
                min(xmin, cx - r),
                max(xmax, cx + r),
                min(ymin, cy - r),
                max(ymax, cy + r),
            )
        span = max(xmax - xmin, ymax - ymin, 1e-9) * 1.1
        mx, my = (xmin + xmax) / 2, (ymin + ymax) / 2
        bounds = (mx - span / 2, mx + span / 2, my - span / 2, my + span / 2)
    xmin, xmax, ymin, ymax = bounds
    pw, ph = w - left - right, h - top - bottom
    scale = min(pw / max(xmax - xmin, 1e-12), ph / max(ymax - ymin, 1e-12))
    ox = left + (pw - scale * (xmax - xmin)) / 2
    oy = top + (ph - scale * (ymax - ymin)) / 2

    def to_px(x: float, y: float) -> tuple[int, int]:
        px = ox + (x - xmin) * scale
        py = oy + ((y - ymin) if flip_y else (ymax - y)) * scale
        return round(px), round(py)

    cv2.rectangle(img, to_px(xmin, ymin if flip_y else ymax), to_px(xmax, ymax if flip_y else ymin), GREY, 1)
    if grid_lines is not None:
        for x in grid_lines[0]:
            cv2.line(img, to_px(x, ymin), to_px(x, ymax), GREY, 1)
        for y in grid_lines[1]:
            cv2.line(img, to_px(xmin, y), to_px(xmax, y), GREY, 1)
    for cx, cy, r, colour in circles:
        cv2.circle(img, to_px(cx, cy), max(round(r * scale), 1), colour, 1, cv2.LINE_AA)
    for s in series:
        p = s.points.reshape(-1, 2)
        p = p[np.all(np.isfinite(p), axis=1)]
        if s.line and len(p) > 1:
            cv2.polylines(
                img, [np.array([to_px(x, y) for x, y in p], np.int32)], False, s.colour, 1, cv2.LINE_AA
            )
        for x, y in p:
            cx = min(max(float(x), xmin), xmax)
            cy = min(max(float(y), ymin), ymax)
            cv2.circle(img, to_px(cx, cy), s.radius, s.colour, -1, cv2.LINE_AA)
    legend_y = h - 10
    x = left
    for s in series:
        if not s.label:
            continue
        cv2.circle(img, (x + 5, legend_y - 4), 4, s.colour, -1)
        _text(img, s.label, (x + 14, legend_y), 0.4)
        x += 24 + 8 * len(s.label)
    _text(img, f"{axis_labels[0]} {_nice(xmin)} .. {_nice(xmax)}", (left, top - 6), 0.35)
    if axis_labels[1]:
        _text(img, f"{axis_labels[1]} {_nice(ymin)} .. {_nice(ymax)}", (left + pw // 2, top - 6), 0.35)
    return img


def _wrap(text: str, width_px: int, scale: float) -> list[str]:
    """Words of ``text`` in lines no wider than ``width_px`` in the panel's font."""
    lines: list[str] = []
    current = ""
    for word in text.split(" "):
        trial = f"{current} {word}" if current else word
        if current and cv2.getTextSize(trial, _FONT, scale, 1)[0][0] > width_px:
            lines.append(current)
            current = "    " + word
        else:
            current = trial
    lines.append(current)
    return lines


def text_panel(lines: Sequence[str], size: tuple[int, int] = (640, 360), title: str = "") -> ImageBgr:
    """Lines of text, wrapped to the panel's width; what does not fit in its height is left out."""
    w, h = size
    img = np.full((h, w, 3), 255, np.uint8)
    y = 22
    if title:
        _text(img, title, (12, y), 0.5)
        y += 24
    for line in lines:
        for part in _wrap(line, w - 24, 0.42):
            if y > h - 6:
                return img
            _text(img, part, (12, y), 0.42)
            y += 18
    return img


def grid(panels: Sequence[ImageBgr], columns: int = 2) -> ImageBgr:
    """Panels left to right, top to bottom, padded to the largest."""
    if not panels:
        return np.full((10, 10, 3), 255, np.uint8)
    ph = max(p.shape[0] for p in panels)
    pw = max(p.shape[1] for p in panels)
    rows = math.ceil(len(panels) / columns)
    out = np.full((rows * ph, min(columns, len(panels)) * pw, 3), 255, np.uint8)
    for i, p in enumerate(panels):
        r, c = divmod(i, columns)
        out[r * ph : r * ph + p.shape[0], c * pw : c * pw + p.shape[1]] = p
    return out


def png(image: ImageBgr) -> bytes:
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise ValueError("PNG encoding failed")
    return bytes(data.tobytes())
