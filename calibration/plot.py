"""Report figures drawn with OpenCV (no plotting library on the robot): bar charts, scatter plots, text,
with the axes, legend and palette of :mod:`agent.figure`.

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

from agent import figure

__all__ = ["Series", "bar_chart", "grid", "png", "scatter", "text_panel"]

ImageBgr = npt.NDArray[np.uint8]
Colour = tuple[int, int, int]

WHITE: Colour = (255, 255, 255)
BLACK: Colour = (0, 0, 0)
GREY: Colour = (170, 170, 170)
GREEN: Colour = (60, 160, 60)
RED: Colour = (40, 40, 210)
BLUE: Colour = (200, 110, 30)
ORANGE: Colour = figure.LED
# The meanings shared with every other picture of the product (agent.figure's palette).
TRUTH: Colour = figure.TRUTH
VLP_FIX: Colour = figure.VLP_FIX
UNCALIBRATED: Colour = figure.UNCALIBRATED
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_MARGIN = (60, 20, 40, 40)  # left, right, top, bottom


@dataclass(frozen=True, slots=True)
class Series:
    """Points of one colour in a scatter plot; ``line`` joins them in order; ``labels`` (one per point, or
    none) are written beside the points."""

    points: npt.NDArray[np.float64]
    colour: Colour
    label: str
    radius: int = 2
    line: bool = False
    labels: Sequence[str] = ()


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
    xlabel: str = "",
    threshold: float | None = None,
    size: tuple[int, int] = (640, 400),
) -> ImageBgr:
    """One bar per value (numbered from 1 on the x axis); bars above ``threshold`` are red, a dashed line
    marks it; the y axis has ticks with values, ``ylabel`` names it (with its unit)."""
    w, h = size
    img = np.full((h, w, 3), 255, np.uint8)
    left, right, top, bottom = _MARGIN
    top, bottom = top + 16, bottom + 16
    _text(img, title, (12, 22), 0.55)
    finite = [v for v in values if math.isfinite(v)]
    vmax = max(finite + ([threshold] if threshold is not None else []) + [1e-9]) * 1.15
    pw, ph = w - left - right, h - top - bottom
    axes = figure.Axes((left, top, left + pw, top + ph), (0.0, float(max(len(values), 1)), 0.0, vmax))
    ticks = figure.nice_ticks(0.0, vmax, 5)
    step = ticks[1] - ticks[0] if len(ticks) > 1 else vmax
    cv2.rectangle(img, (left, top), (left + pw, top + ph), GREY, 1)
    for t in ticks:
        y = axes.to_px(0.0, t)[1]
        cv2.line(img, (left - 5, y), (left, y), BLACK, 1)
        cv2.line(img, (left, y), (left + pw, y), (230, 230, 230), 1)
        label = figure.tick_label(t, step)
        _text(img, label, (left - 8 - figure.text_width(label, 0.4), y + 4), 0.4)
    _text(img, ylabel, (4, top - 8), 0.42)
    n = max(len(values), 1)
    bar = pw / n
    for i, v in enumerate(values):
        if not math.isfinite(v):
            continue
        x0 = left + int(i * bar + 0.15 * bar)
        x1 = max(left + int((i + 1) * bar - 0.15 * bar), x0 + 1)
        y = axes.to_px(0.0, v)[1]
        colour = RED if threshold is not None and v > threshold else BLUE
        cv2.rectangle(img, (x0, y), (x1, top + ph), colour, -1)
        if n <= 40 and (n <= 20 or i % 2 == 0):
            _text(img, str(i + 1), (x0, top + ph + 14), 0.33)
    if xlabel:
        _text(img, xlabel, (left + pw // 2 - figure.text_width(xlabel, 0.45) // 2, top + ph + 36), 0.45)
    if threshold is not None:
        y = axes.to_px(0.0, threshold)[1]
        for x in range(left, left + pw, 12):
            cv2.line(img, (x, y), (min(x + 6, left + pw), y), RED, 1)
        _text(img, f"threshold {_nice(threshold)}", (left + pw - 150, max(y - 5, top + 12)), 0.4, RED)
    return img


def scatter(
    series: Sequence[Series],
    *,
    title: str,
    bounds: tuple[float, float, float, float] | None = None,
    size: tuple[int, int] = (640, 560),
    flip_y: bool = False,
    grid_lines: tuple[Sequence[float], Sequence[float]] | None = None,
    circles: Sequence[tuple[float, float, float, Colour]] = (),
    axis_labels: tuple[str, str] = ("x", "y"),
) -> ImageBgr:
    """Points of each series in a box with equal axis scales, ticks with values on both axes (named by
    ``axis_labels``, units included) and a legend box below. ``bounds`` = (xmin, xmax, ymin, ymax), default
    the data's; ``flip_y``: y grows downwards (image coordinates). ``circles``: (x, y, radius, colour)."""
    w, h = size
    img = np.full((h, w, 3), 255, np.uint8)
    _text(img, title, (12, 22), 0.55)
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
        span = max(xmax - xmin, ymax - ymin, 1e-9) * 1.15
        mx, my = (xmin + xmax) / 2, (ymin + ymax) / 2
        bounds = (mx - span / 2, mx + span / 2, my - span / 2, my + span / 2)
    entries = [figure.Entry(s.label, s.colour, figure.Mark.DOT) for s in series if s.label]
    legend_h = figure.legend_size(entries, 0.45)[1] if entries else 0
    rect = (80, 58, w - 24, h - 56 - legend_h - (10 if entries else 0))
    axes = figure.Axes.fit(bounds, rect, flip_y=flip_y)
    xmin, xmax, ymin, ymax = axes.bounds

    def clip(x: float, y: float) -> tuple[int, int]:
        return axes.to_px(min(max(x, xmin), xmax), min(max(y, ymin), ymax))

    if grid_lines is not None:
        for x in grid_lines[0]:
            cv2.line(img, axes.to_px(x, ymin), axes.to_px(x, ymax), GREY, 1)
        for y in grid_lines[1]:
            cv2.line(img, axes.to_px(xmin, y), axes.to_px(xmax, y), GREY, 1)
    for cx, cy, r, colour in circles:
        cv2.circle(img, axes.to_px(cx, cy), max(round(r * axes.px_per_unit), 1), colour, 1, cv2.LINE_AA)
    for s in series:
        p = s.points.reshape(-1, 2)
        keep = np.all(np.isfinite(p), axis=1)
        p = p[keep]
        if s.line and len(p) > 1:
            poly = np.array([axes.to_px(float(x), float(y)) for x, y in p], np.int32)
            cv2.polylines(img, [poly], False, s.colour, 1, cv2.LINE_AA)
        for x, y in p:
            cv2.circle(img, clip(float(x), float(y)), s.radius, s.colour, -1, cv2.LINE_AA)
        names = [n for n, k in zip(s.labels, keep, strict=False) if k]
        for (x, y), name in zip(p, names, strict=False):
            u, v = clip(float(x), float(y))
            _text(img, name, (u + s.radius + 4, v - s.radius - 2), 0.5)
    axes.draw(img, *axis_labels, count=5)
    figure.legend(img, entries, (rect[0], h - legend_h - 6), 0.45)
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
