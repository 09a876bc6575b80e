"""Finding LED blobs in a frame and measuring each one's centre from its disk outline.

The stripes of a rolling-shutter LED cut its disk into bars; a centroid of the bars, or the box around
them, moves with the stripe phase (up to half a stripe, ``reference/vlp.md`` §3.6). So the centre here comes
from the *outline*: on every bright row the left and right edges are located to a fraction of a pixel (the
half-level crossing of that row's own edge step, so the disk's fall-off does not pull it), and a circle is
fitted to those edge points. The projection of a horizontal disk on an image plane parallel to it is a
circle whose centre is the projection of the LED centre; dark rows contribute nothing, so the stripes cannot
bias the fit.

Steps for a whole frame (the reference's Otsu + 20x20 closing + ``bwareaopen``, made cheaper):

1. A coarse copy (``INTER_AREA`` halvings, the SIMD path) and its grey-level histogram give the background
   level and noise; the threshold is background + max(k sigma, a floor, a fraction of the brightest blob).
2. The coarse mask is dilated vertically, which bridges the dark stripes, and its outer contours are the
   candidates.
3. Each candidate is measured at full resolution (:func:`measure_blob`): vertical grey closing (row-gap
   bridging), threshold, the component's contour, edge points, circle fit. Blobs too close to the border
   are flagged (a half-visible LED gives a wrong centre and id), as the reference does within 20 px at
   800x600.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
import numpy.typing as npt

ImageU8 = npt.NDArray[np.uint8]
FloatArray = npt.NDArray[np.float64]

# Columns around a rough edge, from outside to inside: left edges (c - 1, c, c + 1), right (c + 1, c, c - 1);
# and the direction into the disk from each (+1 on the left, -1 on the right).
_AROUND = np.array([[[-1, 0, 1]], [[1, 0, -1]]], dtype=np.intp)
_INWARD = np.array([[1], [-1]], dtype=np.intp)
# Below this many outline points the radius is taken from what is known of the LED when that is given.
_FEW_POINTS = 20
# Circle fits of this many LEDs or more are done as one batch (fewer: one by one).
_BATCH_FITS = 3
# Tukey scale floor: edge points scatter ~0.1-0.3 px about the rim, so a residual of a pixel is an outlier.
_MIN_SCALE_PX = 0.3

# A tracked LED to measure: (its closed window, centre_px, radius_px, background), as measure_tracked's.
TrackedLed = tuple[ImageU8, tuple[float, float], float, float]
# A tracked LED's disk window: (pixels, top-left pixel, box, bridged area, peak).
_TrackedWindow = tuple[ImageU8, tuple[int, int], tuple[int, int, int, int], int, float]

__all__ = [
    "Blob",
    "DetectorConfig",
    "TrackedLed",
    "background_level",
    "close_rows",
    "find_blobs",
    "fit_circle",
    "measure_blob",
    "measure_tracked",
    "measure_tracked_many",
    "refine_circle",
    "search_bands",
]


@dataclass(frozen=True, slots=True)
class DetectorConfig:
    """``min_diameter_px``: the smallest LED disk to find (sets the coarse factor and the minimum area).
    ``bridge_px``: the longest dark gap between stripes that is bridged (default 0.6 x min diameter).
    ``border_fraction``: blobs closer than this fraction of the image width to a border are flagged
    (the reference: 20 px at 800 px). The three threshold terms are explained in the module docstring.
    ``radius_range_px``: the disk radii the map allows; a free circle fit outside it (a disk crossed by few
    bright stripes constrains its radius poorly) is redone with the radius clamped into the range."""

    min_diameter_px: float = 10.0
    max_diameter_px: float = 600.0
    bridge_px: float | None = None
    border_fraction: float = 20.0 / 800.0
    min_contrast_dn: float = 5.0
    noise_sigmas: float = 6.0
    relative_level: float = 0.2
    max_blobs: int = 32
    radius_range_px: tuple[float, float] | None = None

    @property
    def bridge(self) -> int:
        """Height of the vertical closing, rows (odd)."""
        gap = self.bridge_px if self.bridge_px is not None else 0.6 * self.min_diameter_px
        return max(3, math.ceil(gap) | 1)

    @property
    def coarse_factor(self) -> int:
        return max(1, int(self.min_diameter_px // 5))


@dataclass(frozen=True, slots=True)
class Blob:
    """One LED disk in a frame (full-image pixel coordinates, pixel centres on integers).

    ``box`` is (x0, y0, x1, y1), end-exclusive, of the stripe-bridged component; ``area_px`` its pixel count.
    ``outline_rms_px`` is the circle fit's residual (inf when the fit fell back to the box centre);
    ``at_border`` says the blob is too close to the image border to be trusted.
    """

    centre_px: tuple[float, float]
    radius_px: float
    box: tuple[int, int, int, int]
    area_px: int
    peak_dn: float
    background_dn: float
    outline_rms_px: float
    outline_points: int
    inlier_fraction: float
    at_border: bool


def close_rows(roi: ImageU8, kernel: ImageU8) -> ImageU8:
    """Grey closing with a vertical kernel: every dark gap between brighter rows shorter than the kernel
    takes the level of the rows around it (the stripes of an LED bridged into a disk)."""
    # erode(dilate(roi)), which is what MORPH_CLOSE computes, without morphologyEx's dispatch (~4 us a call
    # on a tracking window).
    closed: ImageU8 = np.asarray(cv2.erode(cv2.dilate(roi, kernel), kernel), dtype=np.uint8)
    return closed


def background_level(image: ImageU8) -> tuple[float, float]:
    """(median, noise sigma) of an image that is mostly dark ceiling, from its 256-bin histogram.

    sigma = median - 16th percentile (one sigma of a Gaussian), which the few bright LED pixels do not move.
    """
    hist = cv2.calcHist([image], [0], None, [256], [0, 256]).ravel()
    cdf = np.cumsum(hist)
    total = cdf[-1]
    median = float(np.searchsorted(cdf, 0.5 * total))
    p16 = float(np.searchsorted(cdf, 0.1587 * total))
    return median, max(median - p16, 0.5)


def fit_circle(x: FloatArray, y: FloatArray) -> tuple[float, float, float]:
    """Algebraic (Kasa) circle fit: x^2 + y^2 + D x + E y + F = 0 in least squares, linear in D, E, F;
    centre (-D/2, -E/2), r^2 = (D^2 + E^2)/4 - F.

    With the coordinates centred (sum x = sum y = 0) the normal equations split: F = -mean(z) with
    z = x^2 + y^2, and [[Sxx, Sxy], [Sxy, Syy]] (D, E) = -(Sxz, Syz), solved here in closed form.
    """
    n = x.size
    mx, my = float(x.sum()) / n, float(y.sum()) / n
    xc, yc = x - mx, y - my
    zz = xc * xc + yc * yc
    sxx, syy, sxy = float(xc @ xc), float(yc @ yc), float(xc @ yc)
    return _kasa_solve(mx, my, n, sxx, syy, sxy, -float(xc @ zz), -float(yc @ zz), float(zz.sum()))


def _kasa_solve(
    mx: float, my: float, n: float, sxx: float, syy: float, sxy: float, bx: float, by: float, sz: float
) -> tuple[float, float, float]:
    """The Kasa circle from the centred sums of :func:`fit_circle` (points' mean (mx, my), n points,
    S_xx, S_yy, S_xy, b = -(S_xz, S_yz), S_z): (D, E) by Cramer's rule, F = -S_z / n."""
    det = sxx * syy - sxy * sxy
    if det <= 1e-12:
        return mx, my, 0.0
    d = (bx * syy - by * sxy) / det
    e = (sxx * by - sxy * bx) / det
    f = -sz / n
    cx, cy = -0.5 * d, -0.5 * e
    r2 = cx * cx + cy * cy - f
    return cx + mx, cy + my, math.sqrt(max(r2, 0.0))


def _solve3(
    a11: float, a12: float, a13: float, a22: float, a23: float, a33: float, b1: float, b2: float, b3: float
) -> tuple[float, float, float] | None:
    """The symmetric 3x3 system A s = b by Cramer's rule (None when singular)."""
    c11 = a22 * a33 - a23 * a23
    c12 = a13 * a23 - a12 * a33
    c13 = a12 * a23 - a13 * a22
    det = a11 * c11 + a12 * c12 + a13 * c13
    if abs(det) < 1e-12:
        return None
    c22 = a11 * a33 - a13 * a13
    c23 = a12 * a13 - a11 * a23
    c33 = a11 * a22 - a12 * a12
    return (
        (c11 * b1 + c12 * b2 + c13 * b3) / det,
        (c12 * b1 + c22 * b2 + c23 * b3) / det,
        (c13 * b1 + c23 * b2 + c33 * b3) / det,
    )


def _centre_for_radius(
    x: FloatArray, y: FloatArray, start: tuple[float, float], radius: float, iterations: int = 2
) -> tuple[float, float]:
    """Least-squares centre of a circle of known radius: Gauss-Newton on d_i = |p_i - c| - r (no weights;
    two steps from the algebraic centre)."""
    cx, cy = start
    for _ in range(iterations):
        dx, dy = x - cx, y - cy
        dist = np.maximum(np.hypot(dx, dy), 1e-9)
        resid = dist - radius
        jx, jy = dx / dist, dy / dist
        a11, a12, a22 = float(jx @ jx), float(jx @ jy), float(jy @ jy)
        b1, b2 = float(jx @ resid), float(jy @ resid)
        det = a11 * a22 - a12 * a12
        if abs(det) < 1e-12:
            break
        # J = -(jx, jy): the step is (J^T J)^-1 J^T (-d) = (A)^-1 (jx . d, jy . d).
        cx += (b1 * a22 - b2 * a12) / det
        cy += (a11 * b2 - a12 * b1) / det
    return cx, cy


def refine_circle(
    x: FloatArray,
    y: FloatArray,
    centre: tuple[float, float],
    radius: float,
    *,
    fixed_radius: bool = False,
    iterations: int = 3,
    scales_px: tuple[float, ...] = (3.0, 1.5, 0.6),
) -> tuple[float, float, float, float, float]:
    """Geometric circle fit by Gauss-Newton on the distances d_i = |p_i - c| - r with Tukey biweights
    w = (1 - (d/s)^2)^2 for |d| < s, else 0, the scale s shrinking through ``scales_px`` (graduated
    non-convexity: a start a few pixels off still finds the rim, and points that are not on it, such as an
    occluder's straight edge, drop out). With ``fixed_radius`` only the centre moves (a partly covered LED
    of known size).

    Returns (cx, cy, r, rms of the inliers, inlier fraction).
    """
    cx, cy, r = centre[0], centre[1], radius
    weights = np.ones_like(x)
    resid = np.zeros_like(x)
    for scale in scales_px:
        inv = 1.0 / max(scale, _MIN_SCALE_PX)
        for _ in range(iterations):
            dx, dy = x - cx, y - cy
            dist = np.maximum(np.sqrt(dx * dx + dy * dy), 1e-9)
            resid = dist - r
            u = resid * inv
            weights = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
            if weights.sum() < 3:
                break
            # d d_i / d (cx, cy, r) = (-(x - cx)/dist, -(y - cy)/dist, -1); normal equations J^T W J,
            # solved in closed form (2x2 or 3x3).
            jx, jy = -dx / dist, -dy / dist
            wjx, wjy = weights * jx, weights * jy
            a11, a12, a22 = float(wjx @ jx), float(wjx @ jy), float(wjy @ jy)
            b1, b2 = -float(wjx @ resid), -float(wjy @ resid)
            if fixed_radius:
                det = a11 * a22 - a12 * a12
                if abs(det) < 1e-12:
                    break
                step = ((b1 * a22 - b2 * a12) / det, (a11 * b2 - a12 * b1) / det, 0.0)
            else:
                a13, a23, a33 = -float(wjx.sum()), -float(wjy.sum()), float(weights.sum())
                b3 = float(weights @ resid)
                solved = _solve3(a11, a12, a13, a22, a23, a33, b1, b2, b3)
                if solved is None:
                    break
                step = solved
            cx += step[0]
            cy += step[1]
            r += step[2]
            if max(abs(step[0]), abs(step[1]), abs(step[2])) < 1e-4:
                break
    dx, dy = x - cx, y - cy
    resid = np.sqrt(dx * dx + dy * dy) - r
    inliers = np.abs(resid) < max(scales_px[-1], _MIN_SCALE_PX)
    rms = float(np.sqrt(np.mean(resid[inliers] ** 2))) if inliers.any() else math.inf
    return cx, cy, r, rms, float(inliers.mean())


class _EdgeRows(NamedTuple):
    """Sub-pixel disk edges of several sub-windows found together (:func:`_edge_rows`): for every row used,
    its left edge ``xs[0]``, right edge ``xs[1]`` and the row ``ys`` (each in its own sub-window's
    coordinates); rows ``bounds[i]`` to ``bounds[i + 1]`` are sub-window i's, top to bottom."""

    xs: FloatArray
    ys: FloatArray
    bounds: list[int]

    def points(self, i: int, origin: tuple[int, int]) -> tuple[FloatArray, FloatArray]:
        """Sub-window i's edge points in the image (its top-left pixel at ``origin``): its rows' left edges,
        then their right edges."""
        b0, b1 = self.bounds[i], self.bounds[i + 1]
        if b1 == b0:
            empty = np.empty(0)
            return empty, empty
        y = self.ys[b0:b1]
        xs: FloatArray = self.xs[:, b0:b1].ravel() + origin[0]
        ys: FloatArray = np.concatenate((y, y)) + origin[1]
        return xs, ys


def _edge_points(
    sub: ImageU8, origin: tuple[int, int], background: float, peak: float
) -> tuple[FloatArray, FloatArray]:
    """Sub-pixel left and right edges of the disk on its bright rows (``sub``: the component's rows, its
    columns plus a margin; unclosed pixels), in the image (``sub``'s top-left pixel at ``origin``):
    :func:`_edge_rows` of one sub-window.

    Returns (x, y): the left edges of the rows used, top to bottom, then their right edges.
    """
    return _edge_rows([sub], [background], [peak]).points(0, origin)


def _edge_rows(subs: list[ImageU8], backgrounds: list[float], peaks: list[float]) -> _EdgeRows:
    """The disk edges of every sub-window (each with its blob's background and peak level), all rows of all
    sub-windows in one set of array operations.

    A row is used when its brightest pixel reaches half the blob's peak above the background (dark stripe
    rows and their transitions are skipped) and it is not among the top and bottom 15 % of rows, where the
    rim runs nearly along the row and a horizontal crossing is ill-defined. The edge is where the row
    crosses half-way between the background and the value just inside that edge (not the row's peak: the
    disk's radial fall-off would pull the crossing inwards), interpolated linearly between pixels.

    Rows of different widths are stacked zero-padded on the right: padding is never above a threshold, so
    it changes neither a row's maximum nor its first and last pixel above half of it.
    """
    centrals: list[ImageU8] = []
    params: list[tuple[float, float, int, int]] = []
    offset = 0
    for sub, background, peak in zip(subs, backgrounds, peaks, strict=True):
        h, w = sub.shape
        if h < 3 or w < 6:
            central = sub[:0]
            r_lo = 0
        else:
            # Central rows only: |r - (h - 1)/2| <= 0.425 h.
            r_lo = max(math.ceil(0.5 * (h - 1) - 0.425 * h), 0)
            r_hi = min(math.floor(0.5 * (h - 1) + 0.425 * h), h - 1)
            central = sub[r_lo : r_hi + 1]
        centrals.append(central)
        # Per sub-window: the row level that counts as bright, half the background, the last column an
        # edge may sit on (one inside, so that the three columns read exist), and stacked row -> sub row.
        params.append((background + 0.5 * (peak - background), 0.5 * background, w - 2, offset - r_lo))
        offset += central.shape[0]
    heights = [c.shape[0] for c in centrals]
    starts = [0] * len(heights)
    for i in range(1, len(heights)):
        starts[i] = starts[i - 1] + heights[i - 1]
    if len(centrals) == 1:
        stack = centrals[0]
    else:
        stack = np.zeros((offset, max(c.shape[1] for c in centrals)), dtype=np.uint8)
        for c, s in zip(centrals, starts, strict=True):
            stack[s : s + c.shape[0], : c.shape[1]] = c
    width = stack.shape[1]
    per_row = np.array(params).T.repeat(heights, axis=1)
    plateau = stack.max(axis=1) if offset else np.empty(0)
    rows = (plateau >= per_row[0]).nonzero()[0]
    bounds = rows.searchsorted([*starts, offset]).tolist()
    n = rows.size
    if n == 0:
        return _EdgeRows(np.empty((2, 0)), np.empty(0), bounds)
    block = stack[rows]
    half_bg, last_col, shift = per_row[1:, rows]
    # The first and last pixels above half the row's peak; the crossing is then refined around them.
    above = block > (half_bg + 0.5 * plateau[rows])[:, None]
    cols = np.empty((2, n), dtype=np.intp)
    cols[0] = above.argmax(axis=1)
    cols[1] = above[:, ::-1].argmax(axis=1)
    cols[1] = (width - 1) - cols[1]
    np.minimum(np.maximum(cols, 1, out=cols), last_col.astype(np.intp), out=cols)
    # Per edge, the pixels outside, at and inside it ((c - 1, c, c + 1) on the left, mirrored on the
    # right), read from the rows' pixels by flat index (``block`` is a fresh C-ordered copy).
    flat = (cols + np.arange(0, n * width, width))[:, :, None] + _AROUND
    vals = block.take(flat).astype(np.float64)
    out, edge = vals[:, :, 0], vals[:, :, 1]
    level = half_bg + 0.5 * np.maximum(edge, vals[:, :, 2])
    frac = np.minimum(np.maximum((level - out) / np.maximum(edge - out, 1e-9), 0.0), 1.0)
    # Left: (c - 1) + frac; right: (c + 1) - frac.
    xs: FloatArray = (cols - _INWARD) + _INWARD * frac
    ys: FloatArray = rows - shift
    return _EdgeRows(xs, ys, bounds)


def measure_blob(
    image: ImageU8,
    box: tuple[int, int, int, int],
    background: float,
    noise: float,
    config: DetectorConfig,
    *,
    radius_hint: float | None = None,
    centre_hint: tuple[float, float] | None = None,
    closed: ImageU8 | None = None,
    radius_prior: float | None = None,
) -> Blob | None:
    """Measure the LED inside ``box`` (x0, y0, x1, y1) of ``image``: vertical grey closing (row-gap bridging:
    the dark stripes take the level of the bright ones around them), threshold, the largest blob (or the one
    under ``centre_hint``), outline edge points on the unclosed pixels, and a circle fit.

    With ``radius_hint`` the fit keeps that radius (a partly covered LED of known size): points on the
    cover's edge are then outliers of the known circle and drop out of the robust fit. ``radius_prior``
    (the tracker's smoothed radius) is used the same way only when the outline has fewer than
    ``_FEW_POINTS`` edge points (a disk crossed by one or two bright stripes pins its centre poorly across
    the stripes). ``closed`` may give the box's pixels already closed (the tracker has them). Returns None
    when nothing LED-like is there.
    """
    height, width = image.shape
    x0, y0, x1, y1 = max(box[0], 0), max(box[1], 0), min(box[2], width), min(box[3], height)
    if x1 - x0 < 3 or y1 - y0 < 3:
        return None
    roi = image[y0:y1, x0:x1]
    if closed is None:
        closed = close_rows(roi, np.ones((config.bridge, 1), dtype=np.uint8))
    peak = float(cv2.minMaxLoc(roi)[1])
    if peak - background < config.min_contrast_dn:
        return None
    level = background + max(0.25 * (peak - background), 4.0 * noise, 0.5 * config.min_contrast_dn)
    _, mask = cv2.threshold(closed, level, 1, cv2.THRESH_BINARY)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return None
    chosen = None
    if len(contours) == 1:
        chosen = contours[0]
    elif centre_hint is not None:
        hint = (float(centre_hint[0] - x0), float(centre_hint[1] - y0))
        for c in contours:
            if cv2.pointPolygonTest(c, hint, False) >= 0:
                chosen = c
                break
    if chosen is None:
        chosen = max(contours, key=cv2.contourArea)
    bx, by, bw, bh = cv2.boundingRect(chosen)
    if max(bw, bh) > config.max_diameter_px:
        return None
    area = int(cv2.countNonZero(mask[by : by + bh, bx : bx + bw]))
    if area < 0.25 * math.pi * (0.5 * config.min_diameter_px) ** 2:
        return None
    # The edges are searched a few pixels beyond the component's box: its outermost pixels are above the
    # threshold, the half-level crossing lies outside them.
    sx0, sx1 = max(bx - 3, 0), min(bx + bw + 3, x1 - x0)
    ex, ey = _edge_points(roi[by : by + bh, sx0:sx1], (x0 + sx0, y0 + by), background, peak)
    return _outline_from_points(
        ex,
        ey,
        (x0 + bx, y0 + by, x0 + bx + bw, y0 + by + bh),
        area,
        peak,
        background,
        (width, height),
        config,
        radius_hint=radius_hint,
        centre_hint=centre_hint,
        radius_prior=radius_prior,
    )


def measure_tracked(
    image: ImageU8,
    closed: ImageU8,
    centre_px: tuple[float, float],
    radius_px: float,
    background: float,
    config: DetectorConfig,
    *,
    radius_hint: float | None = None,
) -> Blob | None:
    """:func:`measure_blob` for an LED whose place and size a tracker already knows to a pixel: the disk's
    rows are centre +- radius and its columns the same with the edge margin, so no component search is
    needed. ``closed`` is the tracker's closed window around the LED (for the bridged area only). With
    ``radius_hint`` the fit keeps that radius (a partly covered LED)."""
    window = _tracked_window(image, closed, centre_px, radius_px, background, config)
    if window is None:
        return None
    sub, origin, box, area, peak = window
    ex, ey = _edge_points(sub, origin, background, peak)
    return _outline_from_points(
        ex,
        ey,
        box,
        area,
        peak,
        background,
        (image.shape[1], image.shape[0]),
        config,
        radius_hint=radius_hint,
        centre_hint=centre_px,
        radius_prior=radius_px,
    )


def measure_tracked_many(image: ImageU8, leds: list[TrackedLed], config: DetectorConfig) -> list[Blob | None]:
    """:func:`measure_tracked` (without a radius hint) of several LEDs of one frame, each given as
    (closed window, centre_px, radius_px, background): their edge points and algebraic circle fits are
    computed together (:func:`_edge_rows`, :func:`_kasa_many`); an LED whose fit needs more (few points,
    points off the rim, a radius outside the map's range) goes on alone as in :func:`measure_tracked`."""
    size = (image.shape[1], image.shape[0])
    out: list[Blob | None] = [None] * len(leds)
    found: list[tuple[int, _TrackedWindow]] = []
    for i, (closed, centre, radius, background) in enumerate(leds):
        window = _tracked_window(image, closed, centre, radius, background, config)
        if window is not None:
            found.append((i, window))
    if not found:
        return out
    rows = _edge_rows([w[0] for _, w in found], [leds[i][3] for i, _ in found], [w[4] for _, w in found])
    counts = [rows.bounds[j + 1] - rows.bounds[j] for j in range(len(found))]
    # The free fits together when there are a few (for one or two the batch costs more than it saves);
    # fitted in each sub-window's own coordinates, the centre moved to the image after.
    free = [j for j, c in enumerate(counts) if 2 * c >= _FEW_POINTS]
    fits = dict(zip(free, _kasa_many(rows, free), strict=True)) if len(free) >= _BATCH_FITS else {}
    for j, (i, (_, origin, box, area, peak)) in enumerate(found):
        _, centre, radius, background = leds[i]
        fit = fits.get(j)
        if fit is not None:
            fit = (fit[0] + origin[0], fit[1] + origin[1], *fit[2:])
            if _free_fit_is_final(fit, config):
                out[i] = _make_blob((*fit[:4], 1.0), 2 * counts[j], box, area, peak, background, size, config)
                continue
        ex, ey = rows.points(j, origin)
        if fit is not None:
            ox, oy, bx1, by1 = box
            circle = _robust_free_fit(ex, ey, fit, (0.5 * (ox + bx1 - 1), 0.5 * (oy + by1 - 1)), config)
            out[i] = _make_blob(circle, int(ex.size), box, area, peak, background, size, config)
            continue
        out[i] = _outline_from_points(
            ex,
            ey,
            box,
            area,
            peak,
            background,
            size,
            config,
            radius_hint=None,
            centre_hint=centre,
            radius_prior=radius,
        )
    return out


def _tracked_window(
    image: ImageU8,
    closed: ImageU8,
    centre_px: tuple[float, float],
    radius_px: float,
    background: float,
    config: DetectorConfig,
) -> _TrackedWindow | None:
    """The window of a tracked LED's disk (rows centre +- radius, columns the same plus the edge margin):
    (pixels, their top-left pixel in the image, the disk's box, the bridged area above a quarter of the
    peak in ``closed``, the peak); None when it is too small or not brighter than the background."""
    height, width = image.shape
    u, v = centre_px
    r = radius_px
    y0, y1 = max(round(v - r), 0), min(round(v + r) + 1, height)
    x0, x1 = max(round(u - r) - 3, 0), min(round(u + r) + 4, width)
    if y1 - y0 < 3 or x1 - x0 < 6:
        return None
    sub = image[y0:y1, x0:x1]
    peak = float(cv2.minMaxLoc(sub)[1])
    if peak - background < config.min_contrast_dn:
        return None
    level = background + max(0.25 * (peak - background), 0.5 * config.min_contrast_dn)
    area = int(cv2.countNonZero(cv2.threshold(closed, level, 1, cv2.THRESH_BINARY)[1]))
    box = (max(round(u - r), 0), y0, min(round(u + r) + 1, width), y1)
    return sub, (x0, y0), box, area, peak


def _outline_from_points(
    ex: FloatArray,
    ey: FloatArray,
    box: tuple[int, int, int, int],
    area: int,
    peak: float,
    background: float,
    size: tuple[int, int],
    config: DetectorConfig,
    *,
    radius_hint: float | None,
    centre_hint: tuple[float, float] | None,
    radius_prior: float | None,
) -> Blob | None:
    """The circle through a disk's edge points (image coordinates): free (Kasa, robust when points are off
    the rim, the radius clamped into the map's range), with ``radius_hint`` fixed and robust from
    ``centre_hint`` (a cover), or, with few points, fixed at ``radius_prior`` (unless the free circle fits
    them much better). Fewer than 6 points: the box's centre, with an infinite rms."""
    ox, oy, bx1, by1 = box
    box_centre = (0.5 * (ox + bx1 - 1), 0.5 * (oy + by1 - 1))
    if ex.size >= 6:
        if radius_hint is None and radius_prior is not None and ex.size < _FEW_POINTS:
            # A whole disk crossed by few stripes: the known radius, the centre by least squares from the
            # algebraic one (a cut outline would show as a large rms and be measured again by the caller).
            fx, fy, fr = fit_circle(ex, ey)
            cx, cy = _centre_for_radius(ex, ey, (fx, fy), radius_prior)
            r = radius_prior
            resid = np.hypot(ex - cx, ey - cy) - r
            rms = math.sqrt(float(resid @ resid) / resid.size)
            if math.isfinite(fr) and abs(fr - radius_prior) <= 0.25 * radius_prior:
                # The known radius can be what is off (a track started from a poor first look at the LED):
                # the free circle stands when it fits the points much better.
                free = np.hypot(ex - fx, ey - fy) - fr
                free_rms = math.sqrt(float(free @ free) / free.size)
                if free_rms < 0.5 * rms:
                    cx, cy, r, resid, rms = fx, fy, fr, free, free_rms
            inl = 1.0 if max(float(resid.max()), -float(resid.min())) < max(4.0 * rms, 1.0) else 0.5
        elif radius_hint is not None:
            if centre_hint is not None:
                start = centre_hint
            else:
                fx, fy, _ = fit_circle(ex, ey)
                start = (fx, fy) if math.isfinite(fx) and math.isfinite(fy) else box_centre
            cx, cy, r, rms, inl = refine_circle(ex, ey, start, radius_hint, fixed_radius=True)
        else:
            cx, cy, r = fit_circle(ex, ey)
            resid = np.hypot(ex - cx, ey - cy) - r
            rms = math.sqrt(float(resid @ resid) / resid.size)
            cx, cy, r, rms, inl = _robust_free_fit(
                ex, ey, (cx, cy, r, rms, max(float(resid.max()), -float(resid.min()))), box_centre, config
            )
        points = int(ex.size)
    else:
        cx, cy = box_centre
        r = 0.25 * (bx1 - ox + by1 - oy)
        rms, inl, points = math.inf, 0.0, int(ex.size)
    return _make_blob((cx, cy, r, rms, inl), points, box, area, peak, background, size, config)


def _free_fit_is_final(fit: tuple[float, float, float, float, float], config: DetectorConfig) -> bool:
    """Whether the algebraic fit (cx, cy, r, rms, largest |residual|) stands as it is: no edge point far
    off the rim and the radius within the map's range (else :func:`_robust_free_fit` refines it)."""
    _, _, r, rms, worst = fit
    if worst > max(4.0 * rms, 1.0):
        return False
    if config.radius_range_px is not None:
        lo, hi = config.radius_range_px
        return 0.85 * lo <= r <= 1.15 * hi
    return True


def _robust_free_fit(
    ex: FloatArray,
    ey: FloatArray,
    fit: tuple[float, float, float, float, float],
    box_centre: tuple[float, float],
    config: DetectorConfig,
) -> tuple[float, float, float, float, float]:
    """The free circle from the algebraic fit (cx, cy, r, rms, largest |residual|): (cx, cy, r, rms, inlier
    fraction), refined robustly when an edge point is far off the rim, and at a fixed radius when the radius
    is outside the map's range."""
    cx, cy, r, rms, worst = fit
    inl = 1.0
    # The algebraic fit is the geometric one for a well-covered circle without outliers; only when some
    # edge point is far off the rim (a cover, a reflection) is the robust refinement needed.
    if worst > max(4.0 * rms, 1.0):
        cx, cy, r, rms, inl = refine_circle(ex, ey, (cx, cy), r)
    if config.radius_range_px is not None:
        lo, hi = config.radius_range_px
        if not 0.85 * lo <= r <= 1.15 * hi:
            start = (cx, cy) if math.isfinite(cx) and math.isfinite(cy) else box_centre
            r_known = min(max(r, lo), hi) if math.isfinite(r) else 0.5 * (lo + hi)
            cx, cy, r, rms, inl = refine_circle(ex, ey, start, r_known, fixed_radius=True)
    return cx, cy, r, rms, inl


def _make_blob(
    circle: tuple[float, float, float, float, float],
    points: int,
    box: tuple[int, int, int, int],
    area: int,
    peak: float,
    background: float,
    size: tuple[int, int],
    config: DetectorConfig,
) -> Blob | None:
    """The blob of a fitted circle (cx, cy, r, rms, inlier fraction); None when the circle is not finite;
    flagged when its box is within ``border_fraction`` of the image width of a border."""
    cx, cy, r, rms, inl = circle
    if not (math.isfinite(cx) and math.isfinite(cy) and math.isfinite(r)) or r <= 0:
        return None
    width, height = size
    ox, oy, bx1, by1 = box
    margin = config.border_fraction * width
    at_border = ox < margin or oy < margin or bx1 > width - margin or by1 > height - margin
    return Blob((cx, cy), r, box, area, peak, background, rms, points, inl, bool(at_border))


@functools.lru_cache(maxsize=64)
def _identity(n: int) -> FloatArray:
    """The n x n identity (kept: ``np.eye`` is a Python-level call)."""
    eye: FloatArray = np.eye(n)
    eye.flags.writeable = False
    return eye


def _kasa_many(rows: _EdgeRows, which: list[int]) -> list[tuple[float, float, float, float, float]]:
    """:func:`fit_circle` of the edge points of sub-windows ``which`` (each with at least one row, in its
    own coordinates), with the rms and the largest |residual| of the points about the circle: (cx, cy, r,
    rms, largest). All sub-windows' sums come from products with the rows' membership matrix (rows x
    sub-windows, 1 where the row is the sub-window's), each row's two edge points summed first."""
    counts = [rows.bounds[i + 1] - rows.bounds[i] for i in which]
    if len(which) == len(rows.bounds) - 1:
        x, y = rows.xs, rows.ys
    else:
        keep = np.concatenate([np.arange(rows.bounds[i], rows.bounds[i + 1]) for i in which])
        x, y = rows.xs[:, keep], rows.ys[keep]
    member = _identity(len(which)).repeat(counts, axis=0)
    n = [2.0 * c for c in counts]
    sx, sy = (np.array([x[0] + x[1], y]) @ member).tolist()
    mx = [s / k for s, k in zip(sx, n, strict=True)]
    my = [2.0 * s / k for s, k in zip(sy, n, strict=True)]
    centre = member @ np.array([mx, my]).T
    xc = x - centre[:, 0]
    yc = y - centre[:, 1]
    zz = xc * xc + yc * yc
    zsum = zz.sum(axis=0)
    per_row = np.array(
        [(xc * xc).sum(axis=0), 2.0 * yc * yc, (xc[0] + xc[1]) * yc, (xc * zz).sum(axis=0), yc * zsum, zsum]
    )
    sxx, syy, sxy, sxz, syz, sz = (per_row @ member).tolist()
    fits = [
        _kasa_solve(mx[j], my[j], n[j], sxx[j], syy[j], sxy[j], -sxz[j], -syz[j], sz[j])
        for j in range(len(which))
    ]
    circle = member @ np.array(fits)
    resid = np.hypot(x - circle[:, 0], y - circle[:, 1]) - circle[:, 2]
    sq = ((resid * resid).sum(axis=0) @ member).tolist()
    starts = [0] * len(counts)
    for j in range(1, len(counts)):
        starts[j] = starts[j - 1] + counts[j - 1]
    worst = np.maximum.reduceat(np.abs(resid).max(axis=0), starts).tolist()
    return [(cx, cy, r, math.sqrt(s / k), w) for (cx, cy, r), s, k, w in zip(fits, sq, n, worst, strict=True)]


def find_blobs(
    image: ImageU8,
    config: DetectorConfig = DetectorConfig(),
    *,
    background: tuple[float, float] | None = None,
    known: Sequence[tuple[float, float, float]] = (),
    rows: tuple[int, int] | None = None,
) -> list[Blob]:
    """All LED-like blobs in a frame, brightest first, border ones included but flagged.

    ``background`` (median, sigma) may be passed when already known; otherwise it is estimated from the
    coarse copy. ``known``: LEDs already held (centre u, v and radius in pixels, as a tracker predicts
    them): a candidate region that is one of them (its box holds the centre and is no bigger than that
    disk) is not measured, since only new LEDs are wanted, which makes the periodic search while tracking
    cost the coarse pass alone.

    ``rows`` = (y0, y1) searches that band of rows only (a search spread over frames, see
    :func:`search_bands`): a candidate cut by a band edge inside the image is left to the neighbouring band,
    which holds it whole when the bands overlap by an LED's diameter; what is found is measured, and flagged
    at the border, in the whole image.
    """
    full, y_off = image, 0
    band_top = band_bottom = False
    if rows is not None:
        y0, y1 = max(rows[0], 0), min(rows[1], full.shape[0])
        if y1 - y0 < 8:
            return []
        image, y_off, band_top, band_bottom = full[y0:y1], y0, y0 > 0, y1 < full.shape[0]
    # Halve with INTER_AREA while the LEDs stay >= ~5 coarse pixels across: OpenCV's 2x2 area path is SIMD,
    # other factors are many times slower.
    coarse, s = image, 1
    while 2 * s <= config.coarse_factor and coarse.shape[0] >= 32 and coarse.shape[1] >= 32:
        hc, wc = coarse.shape[0] // 2, coarse.shape[1] // 2
        coarse = np.asarray(
            cv2.resize(coarse[: 2 * hc, : 2 * wc], (wc, hc), interpolation=cv2.INTER_AREA), dtype=np.uint8
        )
        s *= 2
    bg_c, sigma_c = background_level(coarse) if background is None else (background[0], background[1] / s)
    top = float(cv2.minMaxLoc(coarse)[1])
    threshold = bg_c + max(
        config.noise_sigmas * sigma_c, config.min_contrast_dn, config.relative_level * (top - bg_c)
    )
    if threshold >= 255.0 or top <= threshold:
        return []
    _, mask = cv2.threshold(coarse, threshold, 255, cv2.THRESH_BINARY)
    gap = max(1, math.ceil(config.bridge / s))
    mask = cv2.dilate(mask, np.ones((gap + 1, 1), dtype=np.uint8))
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if not contours:
        return []
    rects = sorted((cv2.boundingRect(c) for c in contours), key=lambda r: -r[2] * r[3])
    min_side_c = 0.3 * config.min_diameter_px / s
    # Full-resolution noise: averaging s x s pixels divided it by s.
    noise = sigma_c * s if background is None else background[1]
    bg = bg_c if background is None else background[0]
    blobs: list[Blob] = []
    pad = s + 2
    h_c = coarse.shape[0]
    for x, y, w, h in rects[: 4 * config.max_blobs]:
        if w < min_side_c or h < min_side_c:
            continue
        # Cut by a band edge (or a stripe gap away from it, its rest dark there): the next band has it whole.
        if (band_top and y <= gap) or (band_bottom and y + h >= h_c - gap):
            continue
        box = (x * s - pad, y * s + y_off - pad, (x + w) * s + pad, (y + h) * s + y_off + pad)
        size = max(box[2] - box[0], box[3] - box[1])
        limit = size - 4 * pad
        held = (box[0] <= u < box[2] and box[1] <= v < box[3] and limit <= 3.0 * r for u, v, r in known)
        if any(held):
            continue
        blob = measure_blob(full, box, bg, noise, config)
        if blob is None:
            continue
        if any(
            math.dist(blob.centre_px, b.centre_px) < 0.8 * max(blob.radius_px, b.radius_px) for b in blobs
        ):
            continue
        blobs.append(blob)
        if len(blobs) >= config.max_blobs:
            break
    blobs.sort(key=lambda b: -b.peak_dn)
    return blobs


def search_bands(height: int, bands: int, overlap: int) -> list[tuple[int, int]]:
    """``bands`` bands of rows covering ``height`` rows, each overlapping the next by ``overlap`` rows (at
    least an LED's diameter, so every LED lies whole in one band): the parts of a full-frame search spread
    over ``bands`` frames (:func:`find_blobs` with ``rows``)."""
    if bands <= 1:
        return [(0, height)]
    step = math.ceil(height / bands)
    return [
        (max(k * step - overlap // 2, 0), min((k + 1) * step + overlap - overlap // 2, height))
        for k in range(bands)
    ]
