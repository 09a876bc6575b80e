"""Likelihood-field scan matching, batched over particles.

The likelihood field (Thrun, Burgard, Fox, *Probabilistic Robotics* §6.4) scores a scan at a pose by the
distance d_i from each endpoint to the nearest obstacle cell: p(z | x, m) = prod_i p_hit(d_i), with
p_hit a zero-mean Gaussian of ``sigma_m``, endpoints farther than ``outlier_m`` counting as a constant
(unexplained reading). The distance d(x, y) is a Euclidean distance transform of the obstacle cells,
sampled bilinearly, so it has a gradient and the best pose can be found by Gauss-Newton on
sum_i w_i d_i(x)^2 instead of GMapping's greedy hill climb on a kernel score.

Everything here works on a *stack* of distance windows (one per distinct map) and a batch of poses (one
per particle, each naming its window), so 30 particles cost a few large numpy operations, not 30 loops.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from agent.slam.pose import wrap_angle

FloatArray = npt.NDArray[np.float64]
Float32Array = npt.NDArray[np.float32]
IntArray = npt.NDArray[np.int64]


UNKNOWN = -1.0  # distance-field value of cells the map has not observed
MEDIAL_REACH_CELLS = 3.0  # within this distance of a wall, distances are taken to its medial point


@dataclass(frozen=True)
class DistanceField:
    """Distance (metres, capped at ``cap_m``) to the nearest obstacle cell, for a stack of windows that
    share one placement. ``distance_m`` is (U, H + 2, W + 2): each window has a one-cell border holding
    ``cap_m``, so that lookups clamped to the array land on "far from everything" with zero gradient;
    ``distance_m[u, 1 + row, 1 + col]`` belongs to the cell whose lower-left corner is
    ``origin_m + (col, row) * resolution_m``. Obstacle cells hold exactly 0, unobserved ones ``UNKNOWN``.

    Sampling is bilinear, except within ``MEDIAL_REACH_CELLS`` of a straight wall, where the distance is
    to the wall's medial line. The nearest obstacle cell is the one d |grad d|⁻¹ grad d back from the
    sample; when its obstacle neighbours run along one axis (above and below it, or left and right, not
    both), the wall runs along that axis, and its medial line passes through the cell centre, moved half
    a cell towards an obstacle neighbour across the wall if it has one on that side only. A wall that
    lies on a cell boundary is hit on both sides of it, so it is two cells thick in the map; bilinear
    distances are 0 all across the pair, a flat-bottomed valley 5 cm wide in which matches drift with
    odometry (the simulated office, whose walls all lie on 5 cm boundaries, lost 2.5 cm per axis to it).
    To the medial line the distance is |x - X| again, X the boundary. Corners, wall ends and clutter keep
    the bilinear value.

    ``medial_window_cells`` W > 0 judges straightness over the square of W cells either way around the
    cell instead (:func:`_wall_lines`; ``MatcherConfig.medial_window_cells``): a boundary wall seen at
    grazing angles is mapped in patches, single cells alternating between the two rows with gaps between
    them, which the four neighbours take for no wall (the bilinear distances to the patches then pull
    endpoints diagonally: the simulated office's first map turned the next scans' matches by 0.1-0.35
    degrees). 0 (the default): the four neighbours.
    """

    distance_m: Float32Array
    origin_m: tuple[float, float]
    resolution_m: float
    cap_m: float
    medial_window_cells: int = 0

    @property
    def medial(self) -> npt.NDArray[np.int8]:
        """Per cell (same layout as distance_m): 0, or for an obstacle cell on a straight wall
        1 + 3 a + k, a = 0 for a wall along y (distance across it in x), 1 along x, k = 0, 1, 2 for a
        medial line half a cell below, at, or above the cell centre. Computed here for the whole stack
        (for inspection); the lookups compute it for the cells they read (:func:`_medial_at`): as a
        stored int8 stack it was a fifth of the field's memory (Intel: ~5.5 MB at the peak RSS). With
        ``medial_window_cells`` every cell is coded (:func:`_square_codes`): a lookup lands on the cell its
        nearest-obstacle estimate gives, which need not be an obstacle there."""
        if self.medial_window_cells > 0:
            return _square_codes(self.distance_m, self.medial_window_cells)
        return _medial_codes(self.distance_m)

    @classmethod
    def from_obstacles(
        cls,
        obstacles: npt.NDArray[np.bool_],
        origin_m: tuple[float, float],
        resolution_m: float,
        cap_m: float,
        known: npt.NDArray[np.bool_] | None = None,
    ) -> DistanceField:
        """Distance transform of the obstacle cells (U, H, W), for each window in the stack
        (``cv2.distanceTransform``, 5x5 chamfer: exact along the axes, within 2 % otherwise).

        Window by window (:meth:`from_windows`), each transform written straight into the field: one call
        for the whole stack needed the stack again as one image, its float output, and a copy into the
        bordered layout (on Intel's 15 m scans, 30 windows of 640 x 640 cells: 50 MB each).

        ``known`` (U, H, W), if given, marks the cells the map has observed. Cells farther than one cell
        from any of them hold ``UNKNOWN`` (negative): an endpoint there says nothing about the map, and
        :meth:`sample_known` reports it as such instead of pulling it towards the nearest mapped wall.
        Without this, a robot driving along a corridor sees its side walls a little beyond where its map
        ends, and those endpoints drag every match backwards. The one-cell margin keeps endpoints that
        range noise puts just behind a wall.
        """
        u, h, w = obstacles.shape
        if known is not None and known.shape != obstacles.shape:
            raise ValueError(f"known {known.shape} must match obstacles {obstacles.shape}")

        def window(k: int) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_] | None]:
            return obstacles[k], None if known is None else known[k]

        return cls.from_windows(u, (h, w), window, origin_m, resolution_m, cap_m)

    @classmethod
    def from_windows(
        cls,
        count: int,
        shape: tuple[int, int],
        window: Callable[[int], tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_] | None]],
        origin_m: tuple[float, float],
        resolution_m: float,
        cap_m: float,
    ) -> DistanceField:
        """:meth:`from_obstacles` for ``count`` windows of ``shape`` (H, W) handed over one at a time:
        ``window(k)`` returns window k's obstacles and known cells (or None). Only the field itself is
        held for the whole stack; each window's inputs and scratch images live while it is transformed
        (on Intel's 15 m scans a stack of 30 windows of 640 x 640 cells is 12 MB per byte per cell, and
        the whole-stack inputs and scratch were six of those)."""
        h, w = shape
        padded = np.empty((count, h + 2, w + 2), dtype=np.float32)
        canvas = np.empty((h + 2, w + 2), dtype=np.uint8)
        kernel = np.ones((3, 3), np.uint8)
        unknown = np.float32(UNKNOWN / resolution_m)
        fill: Float32Array | None = None  # UNKNOWN, copied where no known cell is near (cv2.copyTo)
        for k in range(count):
            obstacles, known = window(k)
            if obstacles.shape != shape or (known is not None and known.shape != shape):
                raise ValueError(f"window {k}: obstacles and known must be {shape}")
            out = padded[k]
            if known is None:
                canvas[...] = 1  # the border is free: it gets the cap below
                np.logical_not(obstacles, out=canvas[1:-1, 1:-1], casting="unsafe")  # DT: distance to 0s
                cv2.distanceTransform(canvas, cv2.DIST_L2, 5, dst=out)
                continue
            # Only the box of the known cells and the obstacles, one cell wider, can hold anything but
            # UNKNOWN: the transform and the dilation run there (the same values as over the whole
            # window: the 5x5 chamfer distance between two cells is a path of mask moves inside their
            # bounding box, so cropping the image to a box holding every obstacle changes no cell of it;
            # a unit test checks this against the whole window).
            r0, r1, c0, c1 = _known_box(obstacles, known)
            if r0 >= r1:
                out[...] = unknown
                continue
            region = out[1 + r0 : 1 + r1, 1 + c0 : 1 + c1]
            box = canvas[: r1 - r0, : c1 - c0]
            np.logical_not(obstacles[r0:r1, c0:c1], out=box, casting="unsafe")  # DT: distance to the 0s
            cv2.distanceTransform(box, cv2.DIST_L2, 5, dst=region)
            near_known = cv2.dilate(known[r0:r1, c0:c1].view(np.uint8), kernel)
            # np.copyto(region, unknown, where=near_known == 0), in half the time.
            if fill is None:
                fill = np.full(shape, unknown, dtype=np.float32)
            far = cv2.compare(near_known, 0, cv2.CMP_EQ)  # type: ignore[call-overload]  # (scalar operand)
            cv2.copyTo(fill[: r1 - r0, : c1 - c0], far, region)
            _fill_outside(out, r0, r1, c0, c1, unknown)
        return cls._finished(padded, origin_m, resolution_m, cap_m)

    @classmethod
    def from_log_odds(
        cls,
        count: int,
        shape: tuple[int, int],
        window: Callable[[int], npt.NDArray[np.int8]],
        occupied: int,
        origin_m: tuple[float, float],
        resolution_m: float,
        cap_m: float,
    ) -> DistanceField:
        """:meth:`from_windows` for windows of stored log-odds counts (``agent.slam.grid``): ``window(k)``
        returns window k (H, W) as int8 counts (a view will do), whose obstacles are the cells above
        ``occupied`` and whose known cells are the nonzero ones. The same field, bit for bit, from fewer
        passes: ``occupied`` >= 0 makes every obstacle a known cell, so the box is the known cells' alone;
        the transform's input and the unknown cells come from the counts by one comparison each, and
        "no known cell within one" is the unknown mask eroded rather than the known one dilated and
        inverted."""
        if occupied < 0:
            raise ValueError(f"occupied must be >= 0 (every obstacle a known cell), got {occupied}")
        h, w = shape
        padded = np.empty((count, h + 2, w + 2), dtype=np.float32)
        scratch = np.empty((3, h, w), dtype=np.uint8)  # the masks, reused from window to window
        kernel = np.ones((3, 3), np.uint8)
        unknown = np.float32(UNKNOWN / resolution_m)
        fill: Float32Array | None = None
        for k in range(count):
            counts = window(k)
            if counts.shape != shape:
                raise ValueError(f"window {k}: counts must be {shape}, got {counts.shape}")
            out = padded[k]
            x, y, box_w, box_h = cv2.boundingRect(counts.view(np.uint8))  # the nonzero (known) cells
            if box_w == 0 or box_h == 0:
                out[...] = unknown
                continue
            r0, r1 = max(y - 1, 0), min(y + box_h + 1, h)
            c0, c1 = max(x - 1, 0), min(x + box_w + 1, w)
            box = counts[r0:r1, c0:c1]
            region = out[1 + r0 : 1 + r1, 1 + c0 : 1 + c1]
            # DT: distance to the 0s, the obstacles (255 elsewhere, as 1 was).
            free, unknown_cells, far = (a[: r1 - r0, : c1 - c0] for a in scratch)
            cv2.compare(box, occupied, cv2.CMP_LE, dst=free)  # type: ignore[call-overload]  # (scalar)
            cv2.distanceTransform(free, cv2.DIST_L2, 5, dst=region)
            # No known cell in the 3 x 3 neighbourhood: the unknown cells eroded (outside the box, and the
            # window, counts as unknown: erode's default border, as dilate's was for the known cells).
            cv2.compare(box, 0, cv2.CMP_EQ, dst=unknown_cells)  # type: ignore[call-overload]
            cv2.erode(unknown_cells, kernel, dst=far)
            if fill is None:
                fill = np.full(shape, unknown, dtype=np.float32)
            cv2.copyTo(fill[: r1 - r0, : c1 - c0], far, region)
            _fill_outside(out, r0, r1, c0, c1, unknown)
        return cls._finished(padded, origin_m, resolution_m, cap_m)

    @classmethod
    def _finished(
        cls, padded: Float32Array, origin_m: tuple[float, float], resolution_m: float, cap_m: float
    ) -> DistanceField:
        """The field from a stack of transforms in cells (UNKNOWN cells already filled): what is the
        same for every window, once for the stack (the per-window calls were a fixed cost each, as much
        as the transform itself on exp1's 30 windows of 130 x 130 cells)."""
        np.multiply(padded, np.float32(resolution_m), out=padded)
        # min(d, cap) as OpenCV's truncating threshold (in place, the cap rounded to float32 as
        # np.minimum's float32 scalar is: the same values, ~7x faster than np.minimum's NaN-aware loop).
        flat_rows = padded.reshape(-1, padded.shape[2])
        cv2.threshold(flat_rows, cap_m, 0.0, cv2.THRESH_TRUNC, dst=flat_rows)
        padded[:, 0, :] = padded[:, -1, :] = cap_m
        padded[:, :, 0] = padded[:, :, -1] = cap_m
        return cls(padded, origin_m, resolution_m, cap_m)

    def sample(
        self, window_index: IntArray, x_m: FloatArray, y_m: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Bilinear d and its gradient (dd/dx, dd/dy) at world points (P, N), x and y apart, in windows (P,).

        Points outside the window, or next to an unknown cell, get d = cap and zero gradient.
        """
        d, ddx, ddy, _known = self.sample_known(window_index, x_m, y_m)
        return d, ddx, ddy

    def sample_known(
        self, window_index: IntArray, x_m: FloatArray, y_m: FloatArray, medial: bool = True
    ) -> tuple[FloatArray, FloatArray, FloatArray, npt.NDArray[np.bool_]]:
        """:meth:`sample`, and whether each point lies among known cells (all four bilinear neighbours).
        ``medial=False`` skips the medial-line distances near walls (plain bilinear: cheaper, for coarse
        stages that do not need sub-cell precision)."""
        d, ddx, ddy, known, _g = self._sample(window_index, x_m, y_m, medial)
        return d, ddx, ddy, known

    def _sample(
        self, window_index: IntArray, x_m: FloatArray, y_m: FloatArray, medial: bool
    ) -> tuple[FloatArray, FloatArray, FloatArray, npt.NDArray[np.bool_], FloatArray | None]:
        """:meth:`sample_known`, and |gradient| (``np.hypot(ddx, ddy)``, bit for bit) where the medial
        lookups computed it on the way (None otherwise): :func:`residuals` needs it, and hypot is the
        dearest elementwise operation of a match."""
        _u, hp, wp = self.distance_m.shape
        inv_res = 1.0 / self.resolution_m
        # Cell centres sit at integer coordinates c = (x - x0) / res - 1/2, plus 1 for the border.
        cx = x_m * inv_res + (0.5 - self.origin_m[0] * inv_res)
        cy = y_m * inv_res + (0.5 - self.origin_m[1] * inv_res)
        _clip(cx, 0.0, wp - 1.001, out=cx)
        _clip(cy, 0.0, hp - 1.001, out=cy)
        # The cell and the fraction: cx >= 0 after the clip, so floor(cx) is the integer astype truncates
        # to and cx - floor(cx) is cx - ix, without subtracting an int64 array from a float one.
        fx = np.floor(cx)
        fy = np.floor(cy)
        ix = fx.astype(np.int64)
        iy = fy.astype(np.int64)
        np.subtract(cx, fx, out=fx)
        np.subtract(cy, fy, out=fy)
        flat = self.distance_m.reshape(-1)
        window_base = np.asarray(window_index, dtype=np.int64)[:, None] * hp
        base = (window_base + iy) * wp + ix
        # The neighbours through views of the table that start 1, wp, wp + 1 cells on (flat[k:][base] is
        # flat[base + k]): no index array per neighbour.
        f00 = flat[base]
        f01 = flat[1:][base]
        f10 = flat[wp:][base]
        f11 = flat[wp + 1 :][base]
        # d = (1-fy)[f00 + fx (f01 - f00)] + fy[f10 + fx (f11 - f10)]
        d_top = f01 - f00
        d_bottom = f11 - f10
        top = f00 + fx * d_top
        bottom = f10 + fx * d_bottom
        vertical = bottom - top
        d = top + fy * vertical
        ddx = (d_top + fy * (d_bottom - d_top)) * inv_res
        ddy = vertical * inv_res
        # All four neighbours >= 0 (known): no sign bit among them. The field holds no -0.0 (distances
        # are +0 or above, UNKNOWN below 0), so this is min(f00, f01, f10, f11) >= 0 without numpy's
        # NaN-aware float minimum.
        signs = f00.view(np.int32) | f01.view(np.int32)
        signs |= f10.view(np.int32)
        signs |= f11.view(np.int32)
        known = signs >= 0
        if not known.all():
            d = np.where(known, d, self.cap_m)
            ddx = np.where(known, ddx, 0.0)
            ddy = np.where(known, ddy, 0.0)
        if not medial:
            return d, ddx, ddy, known, None
        # Near straight walls: the distance to the wall's medial line (see the class docstring).
        near = known & (d < MEDIAL_REACH_CELLS * self.resolution_m)
        if not near.any():
            return d, ddx, ddy, known, None
        g = np.hypot(ddx, ddy)
        step = np.zeros_like(g)
        np.divide(d * inv_res, g, out=step, where=g > 1e-9)
        jx = np.rint(cx - step * ddx)
        jy = np.rint(cy - step * ddy)
        jx = _clip(jx, 1, wp - 2, out=jx).astype(np.int64)
        jy = _clip(jy, 1, hp - 2, out=jy).astype(np.int64)
        cell = (window_base + jy) * wp + jx
        if self.medial_window_cells > 0:
            # The square's test (its cells each) for the samples near a wall only.
            wall = np.zeros(near.shape, dtype=bool)
            along_y = np.zeros(near.shape, dtype=bool)
            shift = np.zeros(near.shape)
            wall[near], along_y[near], shift[near] = _square_walls(
                flat, cell[near], wp, hp, self.medial_window_cells
            )
        else:
            wall, along_y, shift = _medial_walls(flat, cell, wp)
            wall &= near
        # The medial line across the wall: cell centre (j - 1/2) res + origin, plus the shift.
        # (The operands chosen per point first, then one expression: the same operations on the same
        # operands as computing both sides and choosing, in fewer passes.)
        offset = np.where(along_y, x_m, y_m) - (
            (np.where(along_y, jx, jy) - 0.5 + shift) * self.resolution_m
            + np.where(along_y, self.origin_m[0], self.origin_m[1])
        )
        sign = np.where(offset >= 0.0, 1.0, -1.0)
        # d, ddx, ddy and g are this call's own arrays: replaced in place on the walls.
        np.copyto(d, np.abs(offset), where=wall)
        np.copyto(ddx, np.where(along_y, sign, 0.0), where=wall)
        np.copyto(ddy, np.where(along_y, 0.0, sign), where=wall)
        g[wall] = 1.0  # hypot(+-1, 0)
        return d, ddx, ddy, known, g


def _known_box(obstacles: npt.NDArray[np.bool_], known: npt.NDArray[np.bool_]) -> tuple[int, int, int, int]:
    """Rows [r0, r1) and columns [c0, c1) of the smallest box holding every known cell and obstacle,
    one cell wider on each side (within the window); r0 >= r1 when there are none."""
    h, w = known.shape
    boxes = [cv2.boundingRect(known.view(np.uint8)), cv2.boundingRect(obstacles.view(np.uint8))]
    boxes = [b for b in boxes if b[2] > 0 and b[3] > 0]
    if not boxes:
        return 0, 0, 0, 0
    c0 = max(min(b[0] for b in boxes) - 1, 0)
    r0 = max(min(b[1] for b in boxes) - 1, 0)
    c1 = min(max(b[0] + b[2] for b in boxes) + 1, w)
    r1 = min(max(b[1] + b[3] for b in boxes) + 1, h)
    return r0, r1, c0, c1


def _medial_walls(
    flat: Float32Array, cells: IntArray, wp: int
) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_], FloatArray]:
    """:func:`_medial_at` as the lookups use it: whether each cell lies on a straight wall (code > 0),
    whether along y (code 1-3), and its medial line's shift across the wall in cells ((k - 1) / 2:
    -0.5, 0, 0.5; meaningful on walls only). The same neighbour tests, without building the codes."""
    # Through views of the table (flat[k:][low] is flat[low + k]): one index array for the five cells.
    low = cells - wp
    below, above = flat[low] == 0.0, flat[2 * wp :][low] == 0.0
    left, right = flat[wp - 1 :][low] == 0.0, flat[wp + 1 :][low] == 0.0
    across_x = left & right
    across_y = below & above
    along_y = across_y & ~across_x
    along_x = across_x & ~across_y
    wall = along_y | along_x
    wall &= flat[wp:][low] == 0.0
    high = np.where(along_y, right, above).view(np.int8)
    low = np.where(along_y, left, below).view(np.int8)
    shift: FloatArray = (high - low) * 0.5
    return wall, along_y, shift


def _wall_lines(
    flat: Float32Array, cells: IntArray, wp: int, hp: int, reach: int
) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_], npt.NDArray[np.int8]]:
    """For cells (flat indices into a padded stack, windows of ``hp`` rows of ``wp``): whether each lies
    on a straight wall, whether the wall runs along y, and where its medial line lies across it (-1, 0,
    1: half a cell below/left of, at, above/right of the cell centre).

    Judged over the square of ``reach`` W cells either way (within the cell's window): for a
    wall along x, the cell's row holds obstacles in the square (the cell itself may be a gap between
    patches: where the distance field's gradient is flat, between patches, the cell it points back to
    often is), the square's obstacles lie in the cell's row and the rows next to it only (none 2..W rows
    away, which rejects corners and clutter), and some lie at either side along x within those three
    rows (which rejects wall ends); along y the same with rows and columns exchanged; a cell that passes
    both is no wall. Where one of the two rows next to it holds obstacles and the other none, the wall
    is two cells thick (it lies on a cell boundary) and its medial line is that boundary, half a cell
    towards them; otherwise the line is the cell centre. The rows' gaps are allowed: a wall seen at
    grazing angles is mapped in patches (a beam every 5-10 cm along it, each hit in either row of a
    boundary wall)."""
    span = 2 * reach + 1
    steps = np.arange(-reach, reach + 1)
    cells = np.asarray(cells, dtype=np.int64).reshape(-1)
    col = cells % wp
    row = (cells // wp) % hp
    # The square's cells (span, span, M) and whether each lies inside the cell's window.
    offsets = (steps[:, None] * wp + steps[None, :]).reshape(-1)
    index = cells[None, :] + offsets[:, None]
    np.clip(index, 0, flat.shape[0] - 1, out=index)
    occupied = (flat[index] == 0.0).reshape(span, span, -1)
    row_ok = (row[None, :] + steps[:, None] >= 0) & (row[None, :] + steps[:, None] < hp)
    col_ok = (col[None, :] + steps[:, None] >= 0) & (col[None, :] + steps[:, None] < wp)
    occupied &= row_ok[:, None, :]
    occupied &= col_ok[None, :, :]
    rows = occupied.any(axis=1)  # (span, M): any obstacle in the row dy (over the square's columns)
    cols = occupied.any(axis=0)  # (span, M): any in the column dx
    far_rows = rows[: reach - 1].any(axis=0) | rows[reach + 2 :].any(axis=0)
    far_cols = cols[: reach - 1].any(axis=0) | cols[reach + 2 :].any(axis=0)
    band_x = occupied[reach - 1 : reach + 2]  # the three rows (3, span, M)
    band_y = occupied[:, reach - 1 : reach + 2]  # the three columns (span, 3, M)
    both_sides_x = band_x[:, :reach].any(axis=(0, 1)) & band_x[:, reach + 1 :].any(axis=(0, 1))
    both_sides_y = band_y[:reach].any(axis=(0, 1)) & band_y[reach + 1 :].any(axis=(0, 1))
    along_x = rows[reach] & ~far_rows & both_sides_x
    along_y = cols[reach] & ~far_cols & both_sides_y
    crossed = along_x & along_y
    along_x &= ~crossed
    along_y &= ~crossed
    high = np.where(along_y, cols[reach + 1], rows[reach + 1]).view(np.int8)
    low = np.where(along_y, cols[reach - 1], rows[reach - 1]).view(np.int8)
    return along_x | along_y, along_y, high - low


def _square_walls(
    flat: Float32Array, cells: IntArray, wp: int, hp: int, reach: int
) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.bool_], FloatArray]:
    """:func:`_wall_lines` as the lookups use it (as :func:`_medial_walls`): whether each cell lies on a
    straight wall, whether along y, and its medial line's shift across the wall in cells (-0.5, 0, 0.5)."""
    shape = np.shape(cells)
    wall, along_y, side = _wall_lines(flat, cells, wp, hp, reach)
    shift: FloatArray = side.astype(np.float64) * 0.5
    return wall.reshape(shape), along_y.reshape(shape), shift.reshape(shape)


def _square_at(flat: Float32Array, cells: IntArray, wp: int, hp: int, reach: int) -> IntArray:
    """``DistanceField.medial`` with ``medial_window_cells`` ``reach`` at flat indices ``cells`` of a padded
    stack (``flat``, windows of ``hp`` rows of ``wp``)."""
    wall, along_y, side = _wall_lines(flat, cells, wp, hp, reach)
    codes = np.where(along_y, 2 + side, 5 + side)
    out: IntArray = np.where(wall, codes, 0).astype(np.int64)
    return out


def _square_codes(padded: Float32Array, reach: int) -> npt.NDArray[np.int8]:
    """``DistanceField.medial`` with ``medial_window_cells`` ``reach``: :func:`_wall_lines` coded for every
    cell of a padded stack."""
    _u, hp, wp = padded.shape
    flat = padded.reshape(-1)
    codes = _square_at(flat, np.arange(flat.size, dtype=np.int64), wp, hp, reach).astype(np.int8)
    return codes.reshape(padded.shape)


_EYE3 = np.eye(3)[None, :, :]
_EYE3.flags.writeable = False


def _clip(a: npt.NDArray[Any], lo: float, hi: float, out: npt.NDArray[Any]) -> npt.NDArray[Any]:
    """``np.clip(a, lo, hi, out=out)`` without its Python-level argument handling (~10 us a call, and
    the lookups clip four arrays per residual evaluation): the same ufunc."""
    result: npt.NDArray[Any] = np.minimum(np.maximum(a, lo, out=out), hi, out=out)
    return result


def _medial_at(flat: Float32Array, cells: IntArray, wp: int) -> IntArray:
    """``DistanceField.medial`` at flat indices ``cells`` of a padded stack (``flat``, rows of ``wp``),
    none of them on the one-cell border: the same tests as :func:`_medial_codes`, for these cells only."""
    left, right = flat[cells - 1] == 0.0, flat[cells + 1] == 0.0
    below, above = flat[cells - wp] == 0.0, flat[cells + wp] == 0.0
    along_y = below & above & ~(left & right)
    along_x = left & right & ~(below & above)
    k_y = 1 + right.astype(np.int8) - left.astype(np.int8)
    k_x = 1 + above.astype(np.int8) - below.astype(np.int8)
    codes = np.where(along_y, 1 + k_y, np.where(along_x, 4 + k_x, 0)).astype(np.int8)
    out: IntArray = np.where(flat[cells] == 0.0, codes, 0).astype(np.int64)
    return out


def _medial_codes(padded: Float32Array, cells: IntArray | None = None) -> npt.NDArray[np.int8]:
    """``DistanceField.medial`` for a padded distance stack whose obstacle cells hold 0 (``cells``: their
    flat indices, if known).

    A cell with obstacle neighbours above and below but not both left and right lies on a wall along y
    (and the other way round); its medial line is at its centre, or half a cell towards its one obstacle
    neighbour across the wall (a wall two cells thick)."""
    _u, _hp, wp = padded.shape
    flat = padded.reshape(-1)
    codes = np.zeros(flat.shape, dtype=np.int8)
    if cells is None:
        cells = np.flatnonzero(flat == 0.0)  # the one-cell border holds the cap: neighbours stay inside
    if cells.size == 0:
        return codes.reshape(padded.shape)
    left, right = flat[cells - 1] == 0.0, flat[cells + 1] == 0.0
    below, above = flat[cells - wp] == 0.0, flat[cells + wp] == 0.0
    along_y = below & above & ~(left & right)
    along_x = left & right & ~(below & above)
    k_y = 1 + right.astype(np.int8) - left.astype(np.int8)  # 0, 1, 2: medial below, at, above the centre
    k_x = 1 + above.astype(np.int8) - below.astype(np.int8)
    codes[cells] = np.where(along_y, 1 + k_y, np.where(along_x, 4 + k_x, 0)).astype(np.int8)
    return codes.reshape(padded.shape)


@dataclass(frozen=True)
class MatcherConfig:
    """Gauss-Newton schedule: for each stage, the residual beyond which an endpoint is ignored (metres)
    and the number of iterations. Wide first (large basin), then narrow (precise)."""

    stages: tuple[tuple[float, int], ...] = ((0.5, 4), (0.25, 4), (0.12, 4))
    damping: float = 1e-6
    # A match is trusted when at least ``min_inliers`` endpoints lie within the last stage's bound, and
    # they are at least ``min_inlier_fraction`` of all endpoints and ``min_known_inlier_fraction`` of the
    # endpoints that fall among mapped cells. ``eval slam`` trusts radish logs' matches on 10 endpoints
    # whatever their share (``agent.commands.eval_slam.log_proposal``; docs/slam.md, "Scan matching").
    min_inliers: int = 20
    min_inlier_fraction: float = 0.1
    min_known_inlier_fraction: float = 0.0
    max_step_m: float = 0.2
    max_step_rad: float = 0.1
    converged_m: float = 5e-4
    converged_rad: float = 5e-4
    # Per-pose convergence: within a stage, a pose whose step fell below ``converged_m`` /
    # ``converged_rad`` leaves the batch, and later iterations cost only the poses still moving (each
    # pose then gets exactly the answer it would get matched alone). Off: the whole batch iterates
    # until every pose has converged (a converged pose takes the extra, tiny, steps too).
    per_pose_convergence: bool = False
    # The robust kernel's inlier test on the residual the match minimises instead of the distance to the
    # nearest obstacle (``residuals(gate_residual=True)``; differs only point to line, with normals).
    # Where it is on, the proposal's likelihood and energies judge endpoints the same way. On for radish
    # logs in ``eval slam`` (``[slam] match_gate_residual``; docs/slam.md, "Scan matching").
    gate_on_residual: bool = False
    # Degeneracy-aware steps: where the scan's translation information has an eigenvalue below this (in
    # endpoints' worth: each inlier adds |J|² ~ 1; with surface normals, sum n nᵀ over the inliers that
    # have one), the scan's residuals do not move the pose along that eigenvector (the prior alone holds
    # it there: a corridor's length).
    # 0: off (the default). ``[slam] match_min_translation_information``; docs/slam.md, "Scan matching".
    min_translation_information: float = 0.0
    # The distance field's straight-wall test (``DistanceField.medial_window_cells``): 0 a wall cell's four
    # neighbours (the default), W > 0 the square of W cells either way around it, which also finds a
    # boundary wall mapped in patches, and misplaces walls that lie elsewhere in their cells.
    # ``[slam] match_medial_window_cells``; off everywhere (docs/slam.md, "Scan matching", *Walls on cell
    # boundaries*).
    medial_window_cells: int = 0
    # ... and only where the other translation direction is observed at least this many times as well
    # (a corridor: walls on both sides, nothing along it; a scan with few surfaces in any direction, a
    # cluttered room, is left to the whole Σ J Jᵀ). 0: any weak direction.
    degenerate_ratio: float = 0.0


@dataclass(frozen=True)
class MatchResult:
    """Per pose of the batch: the matched pose, the Gauss-Newton information matrix sum_i J_i J_iᵀ of the
    last stage (3x3, in (x_m, y_m, yaw_rad)), the fraction of endpoints within the last stage's
    residual bound, their RMS residual, and whether the match is trusted; ``known_inlier_fraction``: the
    inliers' share of the endpoints that fall among mapped cells."""

    poses: FloatArray
    information: FloatArray
    inlier_fraction: FloatArray
    rms_m: FloatArray
    ok: npt.NDArray[np.bool_]
    known_inlier_fraction: FloatArray


def world_points(
    poses: FloatArray, points_xy: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """p' = R(yaw) p and p' + t for every pose (P, 3) and point (N, 2), as x and y arrays (P, N):
    (world x, world y, rotated x, rotated y); the yaw derivative needs the rotated offsets."""
    c = np.cos(poses[:, 2])[:, None]
    s = np.sin(poses[:, 2])[:, None]
    px = points_xy[None, :, 0]
    py = points_xy[None, :, 1]
    rx = c * px - s * py
    ry = s * px + c * py
    return rx + poses[:, 0:1], ry + poses[:, 1:2], rx, ry


@dataclass(frozen=True)
class Residuals:
    """Per pose and endpoint (P, N): the distance d to the nearest obstacle, the residual r the match
    minimises, dr/d(x, y) (``jx``, ``jy``) and the endpoint rotated into the world (``rx``, ``ry``), so
    that dr/dyaw = jy rx - jx ry. ``gate``: what the robust kernels compare with their bounds (an endpoint
    is an inlier of a bound b when gate < b): d, or with ``residuals(gate_residual=True)`` r itself
    where the field holds a nearest wall (d below its cap less a cell), the cap elsewhere."""

    d: FloatArray
    r: FloatArray
    jx: FloatArray
    jy: FloatArray
    rx: FloatArray
    ry: FloatArray
    known: npt.NDArray[np.bool_]
    gate: FloatArray

    def rows(self, index: IntArray) -> Residuals:
        """These residuals for the poses ``index`` (each pose's row depends on that pose alone, so this
        is what :func:`residuals` gives for those poses)."""
        return Residuals(
            self.d[index],
            self.r[index],
            self.jx[index],
            self.jy[index],
            self.rx[index],
            self.ry[index],
            self.known[index],
            self.gate[index],
        )

    def with_rows(self, index: IntArray, other: Residuals) -> Residuals:
        """A copy with the rows ``index`` replaced by ``other``'s rows (in order)."""
        out = self.rows(np.arange(self.d.shape[0]))
        for name in ("d", "r", "jx", "jy", "rx", "ry", "known", "gate"):
            getattr(out, name)[index] = getattr(other, name)
        return out


def residuals(
    field: DistanceField,
    window_index: IntArray,
    points_xy: FloatArray,
    poses: FloatArray,
    normals_xy: FloatArray | None = None,
    along_weight: float = 1.0,
    medial: bool = True,
    gate_residual: bool = False,
) -> Residuals:
    """Point-to-map residuals for endpoints (N, 2) at poses (P, 3).

    Without normals (or where an endpoint's normal is (0, 0)): point to point, r = d, J = grad d.
    With a surface normal n (``normals_xy``, the scan's own, rotated with the pose) and its tangent t:
    v = d ĝ (ĝ = grad d / |grad d|) is the offset from the nearest obstacle to the endpoint, and
    r = sqrt((v . n)^2 + w (v . t)^2), dr/dp = (n (v . n) + w t (v . t)) / r, w = ``along_weight``:
    1 is point to point again, 0 point to line (only the offset across the surface counts). An endpoint
    on a wall that the map holds in patches (cells hit here and there, as far stretches of wall seen at
    grazing angles are) is pulled along the wall towards the mapped patches, which lie nearer the places
    the map was seen from; w < 1 weakens that pull, and with it the slide of a match back along a
    corridor, while keeping some of what wall ends and door frames say along the wall.

    ``gate_residual``: the robust kernels judge an endpoint by r (the residual minimised), not by d,
    wherever the field holds a wall near it (``Residuals.gate``). With d, an endpoint on a wall the map
    holds in patches is an outlier where it lies between the patches (d the distance along the wall to the
    nearest one) and an inlier where it lies on one, so the kernel alone pulls a match along a corridor
    towards poses that put the scan's side walls on the mapped patches, whatever r says.
    """
    wx, wy, rx, ry = world_points(poses, points_xy)
    d, gx, gy, known, g_norm = field._sample(window_index, wx, wy, medial)
    if normals_xy is None or along_weight == 1.0:
        return Residuals(d, d, gx, gy, rx, ry, known, d)
    c = np.cos(poses[:, 2])[:, None]
    s = np.sin(poses[:, 2])[:, None]
    nx = c * normals_xy[None, :, 0] - s * normals_xy[None, :, 1]
    ny = s * normals_xy[None, :, 0] + c * normals_xy[None, :, 1]
    has = ((normals_xy[:, 0] != 0.0) | (normals_xy[:, 1] != 0.0))[None, :]
    if g_norm is None:
        g_norm = np.hypot(gx, gy)
    # (Divisions where the divisor is above the floor, 0 elsewhere: what dividing by the floored divisor
    # under np.where gave, in fewer passes.)
    scale = np.zeros_like(d)
    np.divide(d, g_norm, out=scale, where=g_norm > 1e-6)
    vx, vy = gx * scale, gy * scale
    across = vx * nx + vy * ny
    if along_weight == 0.0:
        # Point to line: the terms along the surface are +-0 (finite v . t times 0), so these are the
        # general expressions' values without computing v . t (up to the sign of a zero Jacobian entry,
        # which no sum, product or comparison downstream can see).
        r_line = np.sqrt(across * across)
        inv_r = np.zeros_like(r_line)
        np.divide(1.0, r_line, out=inv_r, where=r_line > 1e-9)
        jx = nx * across * inv_r
        jy = ny * across * inv_r
    else:
        along = vy * nx - vx * ny  # v . t, t = (-n_y, n_x)
        r_line = np.sqrt(across * across + along_weight * along * along)
        inv_r = np.zeros_like(r_line)
        np.divide(1.0, r_line, out=inv_r, where=r_line > 1e-9)
        jx = (nx * across - along_weight * ny * along) * inv_r
        jy = (ny * across + along_weight * nx * along) * inv_r
    if not has.all():
        r_line, jx, jy = np.where(has, r_line, d), np.where(has, jx, gx), np.where(has, jy, gy)
    gate = d
    if gate_residual:
        gate = np.where(d < field.cap_m - field.resolution_m, r_line, field.cap_m)
    return Residuals(d, r_line, jx, jy, rx, ry, known, gate)


def match(
    field: DistanceField,
    window_index: IntArray,
    points_xy: FloatArray,
    initial_poses: FloatArray,
    config: MatcherConfig,
    prior_information: FloatArray | None = None,
    centre: FloatArray | None = None,
    normals_xy: FloatArray | None = None,
    along_weight: float = 1.0,
) -> MatchResult:
    """See :func:`match_with_residuals` (this is its match alone)."""
    return match_with_residuals(
        field,
        window_index,
        points_xy,
        initial_poses,
        config,
        prior_information,
        centre,
        normals_xy,
        along_weight,
    )[0]


def match_with_residuals(
    field: DistanceField,
    window_index: IntArray,
    points_xy: FloatArray,
    initial_poses: FloatArray,
    config: MatcherConfig,
    prior_information: FloatArray | None = None,
    centre: FloatArray | None = None,
    normals_xy: FloatArray | None = None,
    along_weight: float = 1.0,
) -> tuple[MatchResult, Residuals]:
    """Gauss-Newton on E(x) = sum_i w_i r_i(x)^2 + (x - x0)ᵀ Λ (x - x0) for every pose of the batch;
    returns the match and :func:`residuals` at the matched poses (what the match's verdict was taken
    from: callers that score the same poses reuse them instead of sampling the field again).

    r_i is the endpoint's distance to the nearest obstacle, or with ``normals_xy`` and ``along_weight``
    < 1 its offset from the surface with the part along the surface weighted down (:func:`residuals`);
    J_i = dr_i/dx = [jx, jy, jy p'_x - jx p'_y] (p' = R(yaw) p_i). Each step solves
    (sum w J Jᵀ + Λ + lambda I) delta = -(sum w J r + Λ (x - x0)), clipped to a trust region. w_i is 1 for
    endpoints whose distance d_i is below the stage's bound, 0 otherwise (a hard robust kernel). The prior
    Λ (``prior_information``, (P, 3, 3) or (3, 3); none by default) ties the match to ``centre``
    (default: the initial poses) in directions the scan does not constrain (a corridor, a scan of one
    wall), which is where an unconstrained matcher slides off.

    Rows that are the same problem bit for bit (start, centre, prior and window: the copies of a resampled
    particle, at the update after resampling) are matched once and their answers copied: each row's
    iterations depend on that row alone, and the whole batch stops when every distinct row has converged,
    so the answers are the ones the full batch gives.
    """
    unique = _distinct_rows(window_index, initial_poses, prior_information, centre)
    if unique is not None:
        first, inverse = unique
        count = np.asarray(initial_poses).shape[0]
        windows = np.broadcast_to(np.asarray(window_index, dtype=np.int64), (count,))
        priors = None
        if prior_information is not None:
            priors = np.broadcast_to(prior_information, (count, 3, 3))[first]
        matched, matched_res = match_with_residuals(
            field,
            windows[first],
            points_xy,
            np.asarray(initial_poses, dtype=np.float64)[first],
            config,
            priors,
            None if centre is None else np.asarray(centre, dtype=np.float64)[first],
            normals_xy,
            along_weight,
        )
        return (
            MatchResult(
                matched.poses[inverse],
                matched.information[inverse],
                matched.inlier_fraction[inverse],
                matched.rms_m[inverse],
                matched.ok[inverse],
                matched.known_inlier_fraction[inverse],
            ),
            matched_res.rows(inverse),
        )
    poses = np.array(initial_poses, dtype=np.float64, copy=True)
    x0 = poses.copy() if centre is None else np.asarray(centre, dtype=np.float64)
    prior = (
        np.zeros((x0.shape[0], 3, 3))
        if prior_information is None
        else np.broadcast_to(prior_information, (x0.shape[0], 3, 3))
    )
    n = points_xy.shape[0]
    info = np.zeros((poses.shape[0], 3, 3))
    if config.per_pose_convergence:
        windows = np.broadcast_to(np.asarray(window_index, dtype=np.int64), (poses.shape[0],))
        for stage, (bound_m, iterations) in enumerate(config.stages):
            fine = stage == len(config.stages) - 1
            active = np.arange(poses.shape[0])
            for _ in range(iterations):
                sub = poses[active]
                step, info_active = _gauss_newton_step(
                    field,
                    windows[active],
                    points_xy,
                    sub,
                    x0[active],
                    prior[active],
                    config,
                    bound_m,
                    fine,
                    normals_xy,
                    along_weight,
                )
                sub += step
                sub[:, 2] = wrap_angle(sub[:, 2])
                poses[active] = sub
                info[active] = info_active
                moving = (np.abs(step[:, :2]) >= config.converged_m).any(axis=1) | (
                    np.abs(step[:, 2]) >= config.converged_rad
                )
                active = active[moving]
                if active.size == 0:
                    break
    else:
        for stage, (bound_m, iterations) in enumerate(config.stages):
            # Sub-cell (medial-line) distances only where the match settles: the last stage.
            fine = stage == len(config.stages) - 1
            for _ in range(iterations):
                step, info = _gauss_newton_step(
                    field,
                    window_index,
                    points_xy,
                    poses,
                    x0,
                    prior,
                    config,
                    bound_m,
                    fine,
                    normals_xy,
                    along_weight,
                )
                poses += step
                poses[:, 2] = wrap_angle(poses[:, 2])
                if np.all(np.abs(step[:, :2]) < config.converged_m) and np.all(
                    np.abs(step[:, 2]) < config.converged_rad
                ):
                    break
    res = residuals(
        field, window_index, points_xy, poses, normals_xy, along_weight, gate_residual=config.gate_on_residual
    )
    last_bound = config.stages[-1][0]
    inliers = res.gate < last_bound
    count = inliers.sum(axis=1)
    fraction = count / max(n, 1)
    rms = np.sqrt(np.where(inliers, res.r * res.r, 0.0).sum(axis=1) / np.maximum(count, 1))
    known_fraction = count / np.maximum(res.known.sum(axis=1), 1)
    ok = (
        (count >= config.min_inliers)
        & (fraction >= config.min_inlier_fraction)
        & (known_fraction >= config.min_known_inlier_fraction)
    )
    return MatchResult(poses, info, fraction, rms, ok, known_fraction), res


def _distinct_rows(
    window_index: IntArray,
    initial_poses: FloatArray,
    prior_information: FloatArray | None,
    centre: FloatArray | None,
) -> tuple[IntArray, IntArray] | None:
    """For a batch of matches: each distinct row's first index and every row's distinct row (inverse),
    rows being equal when start, centre, prior and window are equal bit for bit; None when all differ."""
    start = np.asarray(initial_poses, dtype=np.float64)
    count = start.shape[0]
    if count < 2:
        return None
    prior = np.zeros((count, 9))
    if prior_information is not None:
        information = np.asarray(prior_information, dtype=np.float64)
        prior = np.broadcast_to(information, (count, 3, 3)).reshape(count, 9)
    windows = np.ascontiguousarray(np.broadcast_to(np.asarray(window_index, dtype=np.int64), (count,)))
    parts = [
        start,
        start if centre is None else np.asarray(centre, dtype=np.float64),
        prior,
        windows.view(np.float64)[:, None],  # the index's bits: equal exactly when the index is
    ]
    rows = np.ascontiguousarray(np.concatenate(parts, axis=1))
    keys = rows.view(np.dtype((np.void, rows.dtype.itemsize * rows.shape[1]))).reshape(count)
    _keys, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    if first.size == count:
        return None
    return first.astype(np.int64), np.asarray(inverse, dtype=np.int64).reshape(count)


def _gauss_newton_step(
    field: DistanceField,
    window_index: IntArray,
    points_xy: FloatArray,
    poses: FloatArray,
    x0: FloatArray,
    prior: FloatArray,
    config: MatcherConfig,
    bound_m: float,
    fine: bool,
    normals_xy: FloatArray | None,
    along_weight: float,
) -> tuple[FloatArray, FloatArray]:
    """One Gauss-Newton step of :func:`match` for every pose (P, 3): the clipped step (P, 3) and the
    information matrix sum_i w_i J_i J_iᵀ (P, 3, 3) at the poses."""
    n = points_xy.shape[0]
    eye = _EYE3
    res = residuals(
        field, window_index, points_xy, poses, normals_xy, along_weight, fine, config.gate_on_residual
    )
    jac = np.empty((poses.shape[0], n, 3), dtype=np.float32)
    jac[..., 0] = res.jx
    jac[..., 1] = res.jy
    jac[..., 2] = res.jy * res.rx - res.jx * res.ry
    # The hard kernel's weights as float32 1s and 0s: the products jac * w are jac * bool's, without
    # numpy casting the bool operand in buffered chunks (2.7x the time).
    wj = jac * (res.gate < bound_m).astype(np.float32)[..., None]
    info = np.matmul(wj.transpose(0, 2, 1), jac).astype(np.float64)
    if config.min_translation_information > 0.0:
        # Which directions the scan observes, judged by the inliers with a surface normal where the scan
        # has normals (sum n nᵀ: the scan's own geometry; an endpoint without one, pulled along a wall
        # the map holds in patches, adds information along the wall that is no observation of it).
        observed = info[:, :2, :2]
        if normals_xy is not None:
            nx, ny = _inlier_normals(res, normals_xy, poses, bound_m)
            observed = np.stack(
                [
                    np.stack([(nx * nx).sum(axis=1), (nx * ny).sum(axis=1)], axis=-1),
                    np.stack([(nx * ny).sum(axis=1), (ny * ny).sum(axis=1)], axis=-1),
                ],
                axis=-2,
            )
        projection = degenerate_projection(
            observed, config.min_translation_information, config.degenerate_ratio
        )
        if projection is not None:
            # The scan's Jacobians with their part along each weak direction taken out (the residuals and
            # the yaw column kept): the step then moves the pose there by the prior alone.
            jac_xy = np.einsum("pij,pnj->pni", projection, jac[..., :2].astype(np.float64))
            jac = jac.copy()
            jac[..., :2] = jac_xy
            wj = jac * (res.gate < bound_m).astype(np.float32)[..., None]
            raw_info = info
            info = np.matmul(wj.transpose(0, 2, 1), jac).astype(np.float64)
            step_info, info = info, raw_info
        else:
            step_info = info
    else:
        step_info = info
    offset = poses - x0
    offset[:, 2] = wrap_angle(offset[:, 2])
    grad = np.matmul(wj.transpose(0, 2, 1), res.r[..., None])[..., 0] + np.einsum("pij,pj->pi", prior, offset)
    info_total = step_info + prior
    scale = np.maximum(np.trace(info_total, axis1=1, axis2=2) / 3.0, 1e-9)[:, None, None]
    step = -np.linalg.solve(info_total + config.damping * scale * eye + 1e-12 * eye, grad[..., None])[..., 0]
    # Trust region: never jump farther than the stage can justify in one iteration.
    _clip(step[:, :2], -config.max_step_m, config.max_step_m, out=step[:, :2])
    _clip(step[:, 2], -config.max_step_rad, config.max_step_rad, out=step[:, 2])
    return step, info


def _inlier_normals(
    res: Residuals, normals_xy: FloatArray, poses: FloatArray, bound_m: float
) -> tuple[FloatArray, FloatArray]:
    """The world-frame surface normals (x, y components, (P, N) each) of the endpoints that have one and
    are inliers of ``bound_m`` (``res.gate`` below it) at ``poses``; (0, 0) for every other endpoint."""
    has = ((normals_xy[:, 0] != 0.0) | (normals_xy[:, 1] != 0.0))[None, :] & (res.gate < bound_m)
    c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
    nx = np.where(has, c * normals_xy[None, :, 0] - s * normals_xy[None, :, 1], 0.0)
    ny = np.where(has, s * normals_xy[None, :, 0] + c * normals_xy[None, :, 1], 0.0)
    return nx, ny


def line_information(res: Residuals, normals_xy: FloatArray, poses: FloatArray, bound_m: float) -> FloatArray:
    """Point-to-line information of a match (P, 3, 3, world x, y, yaw): sum g gᵀ over the endpoints that
    have a surface normal n (``normals_xy``, the scan's, rotated with the pose) and are inliers of
    ``bound_m``, g = (n_x, n_y, p' x n) with p' = R(yaw) p (``res.rx``, ``res.ry``: the endpoint's offset
    from the robot in the world), the Jacobian of the endpoint's offset across its surface. An endpoint
    without a normal is left out: pulled along a wall the map holds in patches, its point-to-point
    Jacobian says the wall fixes the pose along itself (sum J Jᵀ counts it), which it does not. So a
    corridor's match is loose along the corridor here, and its heading is what the walls' lines give
    (the lever arm of each line's endpoints), as in point-to-line ICP."""
    nx, ny = _inlier_normals(res, normals_xy, poses, bound_m)
    g = np.stack([nx, ny, res.rx * ny - res.ry * nx], axis=-1)
    out: FloatArray = np.matmul(g.transpose(0, 2, 1), g)
    return out


def degenerate_projection(
    information_xy: FloatArray, threshold: float, ratio: float = 0.0
) -> FloatArray | None:
    """Per pose, the 2x2 projection I - sum u uᵀ over the eigenvectors u of the translation information
    (P, 2, 2) whose eigenvalue is below ``threshold`` (and, with ``ratio`` > 0, below 1/``ratio`` of the
    largest); None when no pose has such a direction."""
    values, vectors = np.linalg.eigh(information_xy)
    weak = values < threshold
    if ratio > 0.0:
        weak &= values * ratio <= values[:, -1:]
    if not weak.any():
        return None
    kept = vectors * (~weak)[:, None, :]
    projection: FloatArray = np.einsum("pik,pjk->pij", kept, vectors)
    return projection


def truncated_energy(
    field: DistanceField,
    window_index: IntArray,
    points_xy: FloatArray,
    poses: FloatArray,
    bound_m: float,
    prior_information: FloatArray | None = None,
    centre: FloatArray | None = None,
    normals_xy: FloatArray | None = None,
    along_weight: float = 1.0,
    residuals_at_poses: Residuals | None = None,
    gate_residual: bool = False,
    unknown_as_bound: bool = False,
) -> FloatArray:
    """The objective :func:`match` minimises, with every endpoint's residual truncated at ``bound_m``
    (an endpoint farther than that from every wall counts ``bound_m``²), for poses (P, 3): sum_i
    min(r_i, bound)² + (x - x0)ᵀ Λ (x - x0). Endpoints among unmapped cells count as the mean of the
    others (as :func:`scan_log_likelihood`), or with ``unknown_as_bound`` as ``bound_m``² (as far from
    every wall as counts at all). Comparable between two matches of the same scan in the same window: the
    lower one explains the scan better at the price the prior puts on its move.
    ``residuals_at_poses``: :func:`residuals` at these poses if already computed (the match's own, from
    :func:`match_with_residuals`), not computed again. ``gate_residual``: as :func:`residuals`."""
    res = residuals_at_poses
    if res is None:
        res = residuals(
            field, window_index, points_xy, poses, normals_xy, along_weight, gate_residual=gate_residual
        )
    e2 = np.where(res.gate < bound_m, res.r * res.r, bound_m * bound_m)
    n = points_xy.shape[0]
    if unknown_as_bound:
        total = np.where(res.known, e2, bound_m * bound_m).sum(axis=1)
    else:
        n_known = res.known.sum(axis=1)
        total = np.where(
            n_known > 0,
            np.where(res.known, e2, 0.0).sum(axis=1) * n / np.maximum(n_known, 1),
            n * bound_m * bound_m,
        )
    if prior_information is not None and centre is not None:
        offset = poses - centre
        offset[:, 2] = wrap_angle(offset[:, 2])
        prior = np.broadcast_to(prior_information, (poses.shape[0], 3, 3))
        total = total + np.einsum("pi,pij,pj->p", offset, prior, offset)
    energy: FloatArray = total
    return energy


@dataclass(frozen=True)
class SearchConfig:
    """Correlative search window: translations up to ``xy_range_m`` in steps of ``xy_step_m`` (whole
    cells of the field), rotations up to ``yaw_range_rad`` in steps of ``yaw_step_rad``; residuals are
    truncated at ``truncate_m``."""

    xy_range_m: float = 0.3
    xy_step_m: float = 0.1
    yaw_range_rad: float = 0.2
    yaw_step_rad: float = 0.02
    truncate_m: float = 0.2


def correlative_search(
    field: DistanceField,
    window: int,
    points_xy: FloatArray,
    centre: FloatArray,
    config: SearchConfig,
    prior_information: FloatArray | None = None,
) -> tuple[FloatArray, float]:
    """Exhaustive search of a pose window around ``centre`` in one distance window (Olson's correlative
    matching, with the distance field as the lookup table): the pose minimising
    C(x) = sum_i min(d(T(x) p_i), c)^2 + (x - centre)ᵀ Λ (x - centre).

    Each rotation's points are computed once; translations are whole-cell shifts of their cell indices, so
    a candidate costs one gather per point. Returns the best pose and its cost.
    """
    _u, h, w = field.distance_m.shape  # padded: cell (row, col) is at (1 + row, 1 + col)
    res = field.resolution_m
    cells = max(round(config.xy_step_m / res), 1)
    reach = round(config.xy_range_m / res) // cells
    shifts = np.arange(-reach, reach + 1) * cells
    grid_y, grid_x = np.meshgrid(shifts, shifts, indexing="ij")
    sy, sx = grid_y.ravel(), grid_x.ravel()
    n_yaw = round(config.yaw_range_rad / config.yaw_step_rad)
    yaws = centre[2] + np.arange(-n_yaw, n_yaw + 1) * config.yaw_step_rad
    candidates = np.tile(centre, (yaws.size, 1))
    candidates[:, 2] = yaws
    wx, wy, _, _ = world_points(candidates, points_xy)  # (R, N)
    col = np.floor((wx - field.origin_m[0]) / res).astype(np.int64) + 1
    row = np.floor((wy - field.origin_m[1]) / res).astype(np.int64) + 1
    # Each point's cost min(d, c)² (0 where the cell is unknown) and whether its cell is known, as two
    # tables over the window (each cell's value once, not once per point and pose). A point outside the
    # window costs as the cap: the tables are padded by ``pad`` cells of the cap's values and each
    # point's row and column clamped to within reach + 1 of the window, so that every shift of a point
    # outside lands in the padding.
    #
    # The translations are a grid, shifts (rows) x shifts (columns), t = row shift * S + column shift:
    # the rows and columns are (R, S, N), and only their sums are (R, S, S, N) = (R, T, N).
    s_count = shifts.size
    far = int(shifts[-1]) + 1
    pad = 2 * far - 1
    window_d = field.distance_m[window]
    # (float32 throughout, as the per-point arithmetic on the gathered float32 distances was.)
    # where(known, min(d, c)², 0) as max(min(d, c), 0)²: known cells hold d >= +0 (the field holds no
    # -0.0), unknown ones UNKNOWN < 0; the min and max as OpenCV's truncating and to-zero thresholds
    # (the bound rounded to float32 as numpy's float32 scalar is: the same values, without numpy's
    # NaN-aware minimum, the mask and the where over the window).
    clipped = cv2.threshold(window_d, config.truncate_m, 0.0, cv2.THRESH_TRUNC)[1]
    cv2.threshold(clipped, 0.0, 0.0, cv2.THRESH_TOZERO, dst=clipped)
    cost_table = np.empty((h + 2 * pad, w + 2 * pad), dtype=np.float32)
    outside = np.minimum(np.float32(field.cap_m), np.float32(config.truncate_m))
    cost_table[...] = outside * outside
    np.multiply(clipped, clipped, out=cost_table[pad:-pad, pad:-pad])
    # Known cells as bytes (1 known): summed over the points straight into int64 counts, as the bool
    # gather's sum was, without numpy casting bools in buffered chunks.
    known_table = np.ones((h + 2 * pad, w + 2 * pad), dtype=np.uint8)
    np.greater_equal(window_d, 0.0, out=known_table[pad:-pad, pad:-pad].view(bool))
    width = w + 2 * pad
    rows = np.clip(row, -far, h - 1 + far)[:, None, :] + (shifts + pad)[None, :, None]  # (R, S, N)
    rows *= width
    cols = np.clip(col, -far, w - 1 + far)[:, None, :] + (shifts + pad)[None, :, None]
    index = (rows[:, :, None, :] + cols[:, None, :, :]).reshape(yaws.size, s_count * s_count, -1)
    # Unknown cells: the mean cost of the candidate's other points (see scan_log_likelihood).
    n_points = points_xy.shape[0]
    n_known = np.take(known_table.reshape(-1), index).sum(axis=2, dtype=np.int64)
    cost = cost_table.reshape(-1)[index].sum(axis=2)  # (R, T)
    del index
    cost = np.where(n_known > 0, cost * n_points / np.maximum(n_known, 1), n_points * config.truncate_m**2)
    offsets = np.stack(
        np.broadcast_arrays(sx[None, :] * res, sy[None, :] * res, (yaws - centre[2])[:, None]), axis=-1
    )  # (R, T, 3)
    if prior_information is not None:
        cost = cost + np.einsum("rti,ij,rtj->rt", offsets, prior_information, offsets)
    r, t = np.unravel_index(int(np.argmin(cost)), cost.shape)
    best = centre + offsets[r, t]
    best[2] = float(wrap_angle(best[2]))
    return best, float(cost[r, t])


def scan_log_likelihood(
    field: DistanceField,
    window_index: IntArray,
    points_xy: FloatArray,
    poses: FloatArray,
    sigma_m: float,
    outlier_m: float,
    normals_xy: FloatArray | None = None,
    along_weight: float = 1.0,
    gate_residual: bool = False,
) -> FloatArray:
    """log p(z | x, m) up to a constant, for poses (P, K, 3) in windows (P,):
    -sum_i e_i^2 / (2 sigma^2), e_i = r_i (:func:`residuals`: the distance, or with normals the offset
    from the surface, its part along it weighted down) where d_i < outlier, else outlier (an unexplained
    reading). Endpoints in cells the map has not observed count as the mean e^2 of the pose's other
    endpoints: scoring them as outliers would favour poses that keep the scan inside the mapped part (a
    robot moving on always sees a little beyond its map, so every pose would be pulled back towards
    where it came from), scoring them as perfect would favour poses that push it out. Returns (P, K); the
    caller tempers it (beams are not independent).
    """
    p, k, _ = poses.shape
    res = residuals(
        field,
        np.repeat(np.asarray(window_index, dtype=np.int64), k),
        points_xy,
        poses.reshape(p * k, 3),
        normals_xy,
        along_weight,
        gate_residual=gate_residual,
    )
    e2 = np.where(res.gate < outlier_m, res.r * res.r, outlier_m * outlier_m)
    n_known = res.known.sum(axis=1)
    known_sum = np.where(res.known, e2, 0.0).sum(axis=1)
    total = np.where(
        n_known > 0,
        known_sum * points_xy.shape[0] / np.maximum(n_known, 1),
        points_xy.shape[0] * outlier_m**2,
    )
    ll: FloatArray = -total.reshape(p, k) / (2.0 * sigma_m * sigma_m)
    return ll


def _linearized_sums(
    field: DistanceField,
    window_index: IntArray,
    points_xy: FloatArray,
    centres: FloatArray,
    outlier_m: float,
    normals_xy: FloatArray | None,
    along_weight: float,
    residuals_at_centres: Residuals | None = None,
    gate_residual: bool = False,
) -> tuple[FloatArray, FloatArray, FloatArray, IntArray]:
    """The endpoints' residuals linearised at poses centres (P, 3): A = sum J Jᵀ (P, 3, 3), b = sum J r
    (P, 3) over the endpoints within ``outlier_m``, c = sum r^2 (P,) with each known endpoint beyond it
    counting outlier_m^2, and the number of known endpoints (P,). ``residuals_at_centres``: the
    residuals there, if already computed."""
    res = residuals_at_centres
    if res is None:
        res = residuals(
            field, window_index, points_xy, centres, normals_xy, along_weight, gate_residual=gate_residual
        )
    inlier = res.known & (res.gate < outlier_m)
    w = inlier.astype(np.float64)
    jac = np.stack([res.jx, res.jy, res.jy * res.rx - res.jx * res.ry], axis=-1)  # (P, N, 3)
    wj = jac * w[..., None]
    a = np.einsum("pni,pnj->pij", wj, jac)
    b = np.einsum("pni,pn->pi", wj, res.r)
    outliers = (res.known & ~inlier).sum(axis=1)
    c = (w * res.r * res.r).sum(axis=1) + outliers * outlier_m**2
    n_known = res.known.sum(axis=1)
    return a, b, c, n_known


def linearized_log_likelihood(
    field: DistanceField,
    window_index: IntArray,
    points_xy: FloatArray,
    centres: FloatArray,
    offsets: FloatArray,
    sigma_m: float,
    outlier_m: float,
    normals_xy: FloatArray | None = None,
    along_weight: float = 1.0,
    residuals_at_centres: Residuals | None = None,
    gate_residual: bool = False,
) -> FloatArray:
    """:func:`scan_log_likelihood` at poses centres (P, 3) + offsets (P, K, 3), with each endpoint's
    residual linearised at its centre: e_i(delta) = r_i + J_i delta for the endpoints within ``outlier_m``
    there (the others stay outliers, the unknown ones stay imputed). Then
    sum_i e_i^2 = c + 2 bᵀ delta + deltaᵀ A delta with A = sum J Jᵀ, b = sum J r, c = sum r^2: one residual
    evaluation per particle instead of one per grid point. Meant for offsets well inside the cell size
    (the proposal's grid spans the match's own standard deviation, millimetres).
    """
    a, b, c, n_known = _linearized_sums(
        field,
        window_index,
        points_xy,
        centres,
        outlier_m,
        normals_xy,
        along_weight,
        residuals_at_centres,
        gate_residual,
    )
    n = points_xy.shape[0]
    scale = np.where(n_known > 0, n / np.maximum(n_known, 1), 0.0)
    quadratic = (
        c[:, None]
        + 2.0 * np.einsum("pi,pki->pk", b, offsets)
        + np.einsum("pki,pij,pkj->pk", offsets, a, offsets)
    )
    total = np.where(n_known[:, None] > 0, scale[:, None] * quadratic, n * outlier_m**2)
    ll: FloatArray = -total / (2.0 * sigma_m * sigma_m)
    return ll


def log_likelihood_quadratic(
    field: DistanceField,
    window_index: IntArray,
    points_xy: FloatArray,
    centres: FloatArray,
    sigma_m: float,
    outlier_m: float,
    normals_xy: FloatArray | None = None,
    along_weight: float = 1.0,
    gate_residual: bool = False,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`linearized_log_likelihood` as the quadratic itself: log p(z | centre + delta) =
    l0 + gᵀ delta - 1/2 deltaᵀ H delta for poses centres (P, 3); returns l0 (P,), g (P, 3), H (P, 3, 3)
    (l0 = -s c / 2 sigma^2, g = -s b / sigma^2, H = s A / sigma^2 with A, b, c and the imputation scale s
    = N / N_known as there)."""
    a, b, c, n_known = _linearized_sums(
        field, window_index, points_xy, centres, outlier_m, normals_xy, along_weight, None, gate_residual
    )
    n = points_xy.shape[0]
    scale = np.where(n_known > 0, n / np.maximum(n_known, 1), 0.0) / (sigma_m * sigma_m)
    # No known endpoint at all: every endpoint counts as an outlier, flat in delta.
    l0: FloatArray = np.where(n_known > 0, -0.5 * scale * c, -n * outlier_m**2 / (2.0 * sigma_m * sigma_m))
    grad: FloatArray = -scale[:, None] * b
    hess: FloatArray = scale[:, None, None] * a
    return l0, grad, hess


def _fill_outside(out: Float32Array, r0: int, r1: int, c0: int, c1: int, value: np.float32) -> None:
    """``value`` in the padded window ``out`` outside the box of rows ``r0:r1``, columns ``c0:c1`` of the
    unpadded window (the transform filled the box)."""
    out[: 1 + r0] = value
    out[1 + r1 :] = value
    out[1 + r0 : 1 + r1, : 1 + c0] = value
    out[1 + r0 : 1 + r1, 1 + c1 :] = value
