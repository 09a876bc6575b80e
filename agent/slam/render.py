"""Pictures of maps and trajectories as arrays (no files here: ``agent.slam.mapio`` writes them).

Map images follow ROS ``map_server`` conventions: row 0 is the top (largest y), occupied cells black (0),
free cells white (254), unknown grey (205), so a PGM of this image loads in ROS tools and viewers.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

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


def trajectory_picture(
    image: OccupancyImage, paths: list[tuple[FloatArray, tuple[int, int, int]]], scale: int = 2
) -> Uint8Array:
    """A BGR picture of the map with each path (N, >=2 world xy, BGR colour) drawn over it, ``scale``
    pixels per cell; paths that leave the map are clipped by the picture's edges."""
    base = cv2.cvtColor(image.pixels, cv2.COLOR_GRAY2BGR)
    picture = cv2.resize(base, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    for xy, colour in paths:
        if xy.shape[0] < 2:
            continue
        px = image.world_to_pixel(xy[:, :2]) * scale
        pts = np.round(px * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(picture, [pts], False, colour, 1, cv2.LINE_AA, 4)
        start = tuple(int(v) for v in np.round(px[0]).astype(np.int64))
        cv2.circle(picture, start, 3 * scale, colour, -1)
    return np.asarray(picture, dtype=np.uint8)
