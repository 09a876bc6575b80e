"""Maps as arrays, and pictures of them for people (no files here: ``agent.slam.mapio`` writes them).

Map images follow ROS ``map_server`` conventions: row 0 is the top (largest y), occupied cells black (0),
free cells white (254), unknown grey (205), so a PGM of this image loads in ROS tools and viewers.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from agent import figure

FloatArray = npt.NDArray[np.float64]
Float32Array = npt.NDArray[np.float32]
Uint8Array = npt.NDArray[np.uint8]

FREE_VALUE = 254
UNKNOWN_VALUE = 205
OCCUPIED_VALUE = 0


@dataclass(frozen=True)
class OccupancyImage:
    """A map as map_server sees it: ``pixels`` (rows top = largest y), cell size, and the world pose of
    the lower-left pixel's lower-left corner (``origin``: x_m, y_m, yaw_rad)."""

    pixels: Uint8Array
    resolution_m: float
    origin: tuple[float, float, float]
    occupied_thresh: float = 0.65
    free_thresh: float = 0.196

    def world_to_pixel(self, xy: FloatArray) -> FloatArray:
        """(N, 2) world points -> (N, 2) pixel coordinates (column, row), continuous, centres at +0.5."""
        h = self.pixels.shape[0]
        col = (xy[:, 0] - self.origin[0]) / self.resolution_m
        row = h - (xy[:, 1] - self.origin[1]) / self.resolution_m
        return np.stack([col, row], axis=1)

    def occupied_mask(self) -> npt.NDArray[np.bool_]:
        """Cells map_server would call occupied: p = (255 - value) / 255 > occupied_thresh."""
        p = (255.0 - self.pixels.astype(np.float64)) / 255.0
        mask: npt.NDArray[np.bool_] = p > self.occupied_thresh
        return mask


def occupancy_image(
    log_odds: Float32Array,
    origin_m: tuple[float, float],
    resolution_m: float,
    occupied_thresh: float = 0.65,
    free_thresh: float = 0.196,
) -> OccupancyImage:
    """Three-valued map image from log-odds (rows = increasing y): occupied where p > occupied_thresh,
    free where p < free_thresh, unknown otherwise."""
    # p = 1 - 1 / (1 + exp(l)) is monotonic in l: compare the log-odds with the thresholds' log-odds
    # instead of converting a whole building's map to probabilities.
    log_odds_free = float(np.log(free_thresh / (1.0 - free_thresh)))
    log_odds_occupied = float(np.log(occupied_thresh / (1.0 - occupied_thresh)))
    pixels = np.full(log_odds.shape, UNKNOWN_VALUE, dtype=np.uint8)
    pixels[log_odds < log_odds_free] = FREE_VALUE
    pixels[log_odds > log_odds_occupied] = OCCUPIED_VALUE
    return OccupancyImage(
        np.ascontiguousarray(pixels[::-1]),
        resolution_m,
        (origin_m[0], origin_m[1], 0.0),
        occupied_thresh,
        free_thresh,
    )


@dataclass(frozen=True)
class MapPath:
    """A path to draw over a map: (N, >=2) world xy, its legend label, its colour (``agent.figure``'s
    palette) and line width; the truth goes thick (``TRUTH_WIDTH_PX``), estimates thin."""

    label: str
    xy: FloatArray
    colour: tuple[int, int, int]
    width: int = figure.ESTIMATE_WIDTH_PX


MIN_MAP_PX = 800
_MARGIN_LEFT, _MARGIN_TOP, _MARGIN_BOTTOM, _GAP, _PANEL_MIN = 80, 66, 62, 24, 250


def map_picture(image: OccupancyImage, paths: Sequence[MapPath] = (), title: str = "") -> Uint8Array:
    """A BGR picture of the map for a person: its cells enlarged (nearest neighbour) so that the longer
    side is at least :data:`MIN_MAP_PX`, axes in metres, each path drawn over it (in order: the truth first,
    underneath), and beside it a legend, a scale bar and the cell size. Paths leaving the map are clipped."""
    h, w = image.pixels.shape
    k = max(1, math.ceil(MIN_MAP_PX / max(h, w, 1)))
    map_w, map_h = w * k, h * k
    entries = [figure.Entry(p.label, p.colour) for p in paths if p.xy.shape[0] >= 1]
    entries += [
        figure.Entry("occupied (wall)", (0, 0, 0)),
        figure.Entry("unknown", (UNKNOWN_VALUE,) * 3),
    ]
    legend_w, legend_h = figure.legend_size(entries)
    panel_w = max(legend_w, _PANEL_MIN)
    width = _MARGIN_LEFT + map_w + _GAP + panel_w + 16
    height = max(_MARGIN_TOP + map_h + _MARGIN_BOTTOM, _MARGIN_TOP + legend_h + 200)
    img = np.full((height, width, 3), 255, np.uint8)

    # The map and the paths on their own canvas, so paths that leave the map stop at its edge.
    base = cv2.cvtColor(image.pixels, cv2.COLOR_GRAY2BGR)
    enlarged = cv2.resize(base, (map_w, map_h), interpolation=cv2.INTER_NEAREST)
    canvas = np.ascontiguousarray(enlarged, dtype=np.uint8)
    x0, y0 = image.origin[0], image.origin[1]
    res = image.resolution_m
    bounds = (x0, x0 + w * res, y0, y0 + h * res)
    local = figure.Axes((0, 0, map_w, map_h), bounds)
    for p in paths:
        figure.draw_path(canvas, local, p.xy[:, :2], p.colour, p.width)
    top = _MARGIN_TOP
    img[top : top + map_h, _MARGIN_LEFT : _MARGIN_LEFT + map_w] = canvas
    axes = figure.Axes((_MARGIN_LEFT, top, _MARGIN_LEFT + map_w, top + map_h), bounds)
    axes.draw(img)
    if title:
        figure.title(img, title, (16, 30))
    px = _MARGIN_LEFT + map_w + _GAP
    figure.legend(img, entries, (px, top))
    y = top + legend_h + 50
    figure.scale_bar(img, k / res, (px + 10, y))
    figure.text(img, "white: free space", (px + 10, y + 34), 0.45)
    figure.text(img, f"1 cell = {res * 100:g} cm", (px + 10, y + 56), 0.45)
    figure.text(img, "ring: where a path starts", (px + 10, y + 78), 0.45)
    return img
