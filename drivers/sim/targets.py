"""Planar calibration targets (chessboard, ChArUco) seen by the simulated camera.

The same camera as the LED renderer (``drivers/sim/render.py``), applied to a printed board instead of a
ceiling LED: OpenCV's pinhole + (k1, k2, p1, p2, k3) distortion model at sensor resolution, the lens blur
and the pixel's own box, cos^4 vignetting, shot noise in electrons (Poisson, drawn as its Gaussian twin: a
pixel of a lit board collects hundreds of electrons), full well, Gaussian read noise, black level, 8-bit
rounding, and only the sensor rows and columns that ``cv2.resize(..., INTER_NEAREST)``
keeps (:func:`drivers.sim.render.nearest_indices`). A board view is static: the board does not move during
the readout, so the rolling shutter plays no part.

How a pixel gets its value: the viewing ray of every kept sensor pixel (undistorted once per camera) meets the
board plane through the plane's homography; the board's print is a binary raster whose cell edges are the
print's edges (squares, marker bits), so a nearest-cell lookup is exact at any point. The point-spread
function is the one the LED renderer uses: a Gaussian whose variance is the lens blur's plus the pixel
box's (1/12 px^2). Mapped onto the board with the local Jacobian of the pixel -> board map it is a Gaussian
there too, so a pixel whose footprint crosses edges of one direction only (the sides of squares, away from
their corners) gets its value in closed form, the sum over cells of
R_k [Phi((x_k+1 - X)/s_X) - Phi((x_k - X)/s_X)]; a pixel near a corner, where the print varies both ways,
is the mean over a 20 x 20 stratified sample of the Gaussian with its own random jitter (unbiased: what is
left is a little extra noise near corners, no shift of the corner). Elsewhere one lookup at the pixel centre
is exact.

Frames: the board frame has its origin at the top-left corner of the printed sheet (margin included), x to the
right along a row of squares, y down, z into the board (OpenCV's convention for calibration objects). The
camera frame is OpenCV's and the renderer's: x along image u, y along image v (down), z along the optical
axis. A pose (R, t) maps board points into the camera: p_camera = R p_board + t.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol

import cv2
import numpy as np
import numpy.typing as npt

from drivers.sim.render import OutputIntrinsics, RollingShutterRenderer, nearest_indices
from drivers.sim.world import CameraModel

FloatArray = npt.NDArray[np.float64]
Float32Array = npt.NDArray[np.float32]
ImageU8 = npt.NDArray[np.uint8]

__all__ = [
    "HAS_ARUCO",
    "CharucoTarget",
    "Chessboard",
    "RenderedTarget",
    "Target",
    "TargetLighting",
    "TargetRenderer",
]

#: Whether this OpenCV build has the ArUco module (ChArUco boards need it).
HAS_ARUCO = hasattr(cv2, "aruco") and hasattr(cv2.aruco, "CharucoBoard")

# Raster cells per square: fine enough that every edge of the print (square sides, marker bits, margins
# given in whole cells) falls on a cell boundary.
_CELLS_PER_SQUARE = 16
# The PSF's reach in standard deviations (its tail beyond is < 1e-4), the most raster cells a blurred edge
# profile may span before the pixel is sampled instead, and the strata per axis of that sampling.
_REACH_SIGMAS = 4.0
_PROFILE_CELLS = 24
_STRATA = 20
# The edge-distance maps are kept on a grid this much finer than the raster's cells (tighter bounds).
_DIST_SPLIT = 4
# Reflectance of the room behind the board (what a pixel sees that misses the sheet), and of the sheet's back.
_SCENE_REFLECTANCE = 0.35
_BACK_REFLECTANCE = 0.6


class Target(Protocol):
    """A printed planar target: its raster, its corner points in the board frame, its name."""

    @property
    def kind(self) -> str: ...

    @property
    def square_m(self) -> float: ...

    @property
    def size_m(self) -> tuple[float, float]:
        """Width and height of the printed sheet, margin included."""
        ...

    def object_points(self) -> Float32Array:
        """(N, 3) corner positions in the board frame (z = 0), in the detector's corner order."""
        ...

    def raster(self) -> tuple[npt.NDArray[np.float32], float]:
        """Reflectance per cell (0..1) covering the sheet, and the cell size in metres."""
        ...


@dataclass(frozen=True, slots=True)
class Chessboard:
    """A chessboard of ``inner_cols`` x ``inner_rows`` inner corners (``findChessboardCorners`` pattern size),
    squares of ``square_m``, a white margin of ``margin_squares`` squares (rounded to a raster cell) and the
    top-left square black. Corner (i, j) is at (margin + (i + 1) s, margin + (j + 1) s), row by row."""

    inner_cols: int = 9
    inner_rows: int = 6
    square_m: float = 0.03
    margin_squares: float = 0.75
    black_reflectance: float = 0.06
    white_reflectance: float = 0.85

    def __post_init__(self) -> None:
        if self.inner_cols < 2 or self.inner_rows < 2:
            raise ValueError(f"a chessboard needs at least 2x2 inner corners, got {self.pattern_size}")
        if not self.square_m > 0 or self.margin_squares < 0:
            raise ValueError("square_m must be > 0 and margin_squares >= 0")

    @property
    def kind(self) -> str:
        return "chessboard"

    @property
    def pattern_size(self) -> tuple[int, int]:
        return self.inner_cols, self.inner_rows

    @property
    def margin_cells(self) -> int:
        return round(self.margin_squares * _CELLS_PER_SQUARE)

    @property
    def margin_m(self) -> float:
        return self.margin_cells * self.square_m / _CELLS_PER_SQUARE

    @property
    def size_m(self) -> tuple[float, float]:
        m = 2.0 * self.margin_m
        return (self.inner_cols + 1) * self.square_m + m, (self.inner_rows + 1) * self.square_m + m

    def object_points(self) -> Float32Array:
        i, j = np.meshgrid(np.arange(self.inner_cols), np.arange(self.inner_rows))
        pts = np.zeros((self.inner_cols * self.inner_rows, 3), dtype=np.float32)
        pts[:, 0] = self.margin_m + (i.ravel() + 1) * self.square_m
        pts[:, 1] = self.margin_m + (j.ravel() + 1) * self.square_m
        return pts

    def raster(self) -> tuple[npt.NDArray[np.float32], float]:
        n = _CELLS_PER_SQUARE
        sq_rows, sq_cols = self.inner_rows + 1, self.inner_cols + 1
        parity = (np.add.outer(np.arange(sq_rows), np.arange(sq_cols)) % 2).astype(bool)
        squares = np.where(parity, self.white_reflectance, self.black_reflectance).astype(np.float32)
        cells = np.kron(squares, np.ones((n, n), dtype=np.float32))
        m = self.margin_cells
        sheet = np.pad(cells, m, constant_values=self.white_reflectance)
        return sheet, self.square_m / n


@dataclass(frozen=True, slots=True)
class CharucoTarget:
    """A ChArUco board as ``cv2.aruco.CharucoBoard`` makes it: ``squares_x`` x ``squares_y`` squares of
    ``square_m``, ArUco markers of ``marker_m`` from ``dictionary`` in the white squares, the top-left square
    black. ``marker_m`` must put the marker bits and the marker's inset on the raster's cells (for example
    40 mm squares with 30 mm markers from a 4x4 dictionary: 5 mm bits, 5 mm inset). Corners are numbered as
    OpenCV numbers them: (i + 1, j + 1) squares from the board's corner, row by row."""

    squares_x: int = 8
    squares_y: int = 6
    square_m: float = 0.04
    marker_m: float = 0.03
    dictionary: str = "DICT_4X4_50"
    margin_squares: float = 0.75
    black_reflectance: float = 0.06
    white_reflectance: float = 0.85
    _board: Any = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not HAS_ARUCO:
            raise RuntimeError("this OpenCV build has no cv2.aruco: ChArUco boards are unavailable")
        if self.squares_x < 3 or self.squares_y < 3:
            raise ValueError("a ChArUco board needs at least 3x3 squares")
        if not 0 < self.marker_m < self.square_m:
            raise ValueError("marker_m must be between 0 and square_m")
        if not hasattr(cv2.aruco, self.dictionary):
            raise ValueError(f"unknown ArUco dictionary {self.dictionary!r}")
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        board = cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_m, self.marker_m, dictionary
        )
        object.__setattr__(self, "_board", board)
        bits = dictionary.markerSize + 2
        cell = self.square_m / _CELLS_PER_SQUARE
        for what, length in (
            ("marker bit", self.marker_m / bits),
            ("marker inset", (self.square_m - self.marker_m) / 2),
        ):
            if abs(length / cell - round(length / cell)) > 1e-6:
                raise ValueError(
                    f"the {what} ({1000 * length:.3f} mm) is not a whole number of {1000 * cell:.3f} mm "
                    "raster "
                    f"cells; choose marker_m so that it is"
                )

    @property
    def kind(self) -> str:
        return "charuco"

    @property
    def board(self) -> Any:
        """The ``cv2.aruco.CharucoBoard`` (for a detector)."""
        return self._board

    @property
    def margin_cells(self) -> int:
        return round(self.margin_squares * _CELLS_PER_SQUARE)

    @property
    def margin_m(self) -> float:
        return self.margin_cells * self.square_m / _CELLS_PER_SQUARE

    @property
    def size_m(self) -> tuple[float, float]:
        m = 2.0 * self.margin_m
        return self.squares_x * self.square_m + m, self.squares_y * self.square_m + m

    def object_points(self) -> Float32Array:
        corners = np.asarray(self._board.getChessboardCorners(), dtype=np.float32).reshape(-1, 3)
        corners[:, :2] += self.margin_m
        return corners

    def raster(self) -> tuple[npt.NDArray[np.float32], float]:
        n = _CELLS_PER_SQUARE
        size = (self.squares_x * n, self.squares_y * n)
        image = self._board.generateImage(size, marginSize=0, borderBits=1)
        white = np.asarray(image) > 127
        cells = np.where(white, self.white_reflectance, self.black_reflectance).astype(np.float32)
        sheet = np.pad(cells, self.margin_cells, constant_values=self.white_reflectance)
        return sheet, self.square_m / n


@dataclass(frozen=True, slots=True)
class TargetLighting:
    """How bright the board looks: a white square at the image centre is ``white_dn`` above black at 0 dB
    (the exposure a calibration would be run with, far longer than the LED exposure)."""

    white_dn: float = 190.0
    gain_db: float = 0.0


@dataclass(frozen=True, slots=True)
class RenderedTarget:
    """One view: the 8-bit image and the truth. ``corners_px`` are the true corner positions in output
    pixels (the ideal projection through the output intrinsics' affine map, not through the nearest-neighbour
    selection); ``corners_visible`` marks corners inside the image on the board's printed side."""

    image: ImageU8
    corners_px: FloatArray
    corners_visible: npt.NDArray[np.bool_]
    rotation: FloatArray
    translation_m: FloatArray
    front_facing: bool


def _phi(z: npt.NDArray[np.floating]) -> FloatArray:
    """The standard normal CDF, 0.5 erfc(-z / sqrt 2), by Abramowitz & Stegun 7.1.26 (absolute error
    < 1.5e-7; scipy is not a dependency of the drivers)."""
    x = np.abs(z) * (1.0 / math.sqrt(2.0))
    t = 1.0 / (1.0 + 0.3275911 * x)
    poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))))
    upper = 0.5 * poly * np.exp(-x * x)
    out: FloatArray = np.where(z >= 0.0, 1.0 - upper, upper)
    return out


# The inverse normal CDF on a uniform grid of probabilities, for drawing sub-pixel samples by direct lookup.
_QUANTILE_STEPS = 8192
_QUANTILES = np.interp(
    (np.arange(_QUANTILE_STEPS) + 0.5) / _QUANTILE_STEPS,
    _phi(np.linspace(-6.0, 6.0, 12001)),
    np.linspace(-6.0, 6.0, 12001),
).astype(np.float32)


def _normal_quantile(p: npt.NDArray[np.floating]) -> npt.NDArray[np.float32]:
    """Phi^-1(p) for p in [0, 1), to within one table step (1/8192 in probability)."""
    index = (p * _QUANTILE_STEPS).astype(np.intp)
    np.clip(index, 0, _QUANTILE_STEPS - 1, out=index)
    out: npt.NDArray[np.float32] = _QUANTILES[index]
    return out


class TargetRenderer:
    """Renders views of one target through one camera.

    Args:
        camera: the true camera (principal point, distortion, noise, output size).
        target: the printed board.
        lighting: how bright the board is.
        seed: seeds the sensor noise, so a sequence of views is repeatable.
    """

    def __init__(
        self, camera: CameraModel, target: Target, lighting: TargetLighting | None = None, *, seed: int = 0
    ) -> None:
        self.camera = camera
        self.target = target
        self.lighting = TargetLighting() if lighting is None else lighting
        self._rng = np.random.default_rng(seed)
        # The LED renderer of the same camera defines the output geometry (its affine sensor <-> output map).
        self._geometry = RollingShutterRenderer(camera, ())
        sw, sh = camera.sensor_width_px, camera.sensor_height_px
        self._cols = nearest_indices(sw, camera.output_width_px).astype(np.float64)
        self._rows = nearest_indices(sh, camera.output_height_px).astype(np.float64)
        f = camera.focal_length_px
        cx, cy = camera.principal_point_px
        self._k_sensor = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
        self._dist = np.asarray(camera.distortion, dtype=np.float64)
        self._xn, self._yn = self._normalised_grid()
        self._vignette = (1.0 / (1.0 + self._xn**2 + self._yn**2) ** 2).astype(np.float32)
        self._raster, self._cell_m = target.raster()
        padded = np.pad(self._raster, 1, constant_values=_SCENE_REFLECTANCE)
        self._padded_shape = padded.shape
        self._padded = padded.ravel()
        self._dist_x_m, self._dist_y_m = self._edge_distances(padded)
        # The PSF: lens blur and the pixel's box as one Gaussian, as the LED renderer has it.
        self._sigma_px = math.sqrt(camera.blur_sigma_px**2 + 1.0 / 12.0)
        # How far the PSF reaches (sensor px): beyond this its tail is below 1e-4.
        self._footprint_px = _REACH_SIGMAS * self._sigma_px
        full_well = camera.full_well_e
        self._dn_per_e = (255.0 - camera.black_level_dn) / full_well * 10.0 ** (self.lighting.gain_db / 20.0)
        self._white_e = self.lighting.white_dn / ((255.0 - camera.black_level_dn) / full_well)

    # -- what it knows ---------------------------------------------------------------------------------
    @property
    def output_intrinsics(self) -> OutputIntrinsics:
        """The true pinhole intrinsics at output resolution (what a perfect calibration finds)."""
        return self._geometry.output_intrinsics

    @property
    def distortion(self) -> tuple[float, float, float, float, float]:
        """The true distortion: OpenCV's (k1, k2, p1, p2, k3), the same in output pixels' normalised
        coordinates as in the sensor's."""
        return self.camera.distortion

    def project(
        self, points_board: FloatArray, rotation: FloatArray, translation_m: FloatArray
    ) -> FloatArray:
        """Output-pixel positions of board points (N, 3) seen with the pose (R, t)."""
        rvec, _ = cv2.Rodrigues(np.asarray(rotation, dtype=np.float64))
        sensor, _ = cv2.projectPoints(
            np.asarray(points_board, dtype=np.float64).reshape(-1, 1, 3),
            rvec,
            np.asarray(translation_m, dtype=np.float64).reshape(3, 1),
            self._k_sensor,
            self._dist,
        )
        sensor = np.asarray(sensor, dtype=np.float64).reshape(-1, 2)
        out = np.empty_like(sensor)
        for n, (u, v) in enumerate(sensor):
            out[n] = self._geometry.sensor_to_output(float(u), float(v))
        return out

    # -- set-up ----------------------------------------------------------------------------------------
    def _normalised_grid(self) -> tuple[FloatArray, FloatArray]:
        """Undistorted normalised coordinates (x/z, y/z) of every kept sensor pixel's centre."""
        cols, rows = self._cols, self._rows
        if np.any(self._dist != 0.0):
            grid = np.stack(np.meshgrid(cols, rows), axis=-1).reshape(-1, 1, 2)
            criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)
            eye = np.eye(3)
            norm = np.asarray(
                cv2.undistortPointsIter(grid, self._k_sensor, self._dist, eye, eye, criteria),
                dtype=np.float64,
            )
            return norm[:, 0, 0].reshape(rows.size, cols.size), norm[:, 0, 1].reshape(rows.size, cols.size)
        f = self.camera.focal_length_px
        cx, cy = self.camera.principal_point_px
        xn, yn = np.meshgrid((cols - cx) / f, (rows - cy) / f)
        return xn, yn

    def _edge_distances(self, padded: npt.NDArray[np.float32]) -> tuple[FloatArray, FloatArray]:
        """On the padded raster split 4 x 4 finer, a lower bound on the distance (m) from any point of each
        fine cell to the nearest edge running along y (where the print changes with x), and to the nearest one
        running along x."""
        fine = np.kron(padded, np.ones((_DIST_SPLIT, _DIST_SPLIT), dtype=np.float32))
        out = []
        for axis in (1, 0):
            change = np.zeros(fine.shape, dtype=bool)
            diff = np.diff(fine, axis=axis) != 0
            if axis == 1:
                change[:, :-1] |= diff
                change[:, 1:] |= diff
            else:
                change[:-1, :] |= diff
                change[1:, :] |= diff
            cells = np.asarray(
                cv2.distanceTransform((~change).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE),
                dtype=np.float64,
            )
            # From a fine cell's centre, the edge beside a changing cell is up to 1.5 cells nearer, and any
            # point of the cell another 0.71.
            out.append(np.maximum(cells - 2.25, 0.0) * self._cell_m / _DIST_SPLIT)
        return out[0], out[1]

    def _fine_cells(self, bx: npt.NDArray[np.floating], by: npt.NDArray[np.floating]) -> npt.NDArray[np.intp]:
        """Flat index of each board point's cell in the 4 x 4 finer padded grid (points off it: its edge)."""
        rows, cols = self._padded_shape
        rows, cols = rows * _DIST_SPLIT, cols * _DIST_SPLIT
        inv = _DIST_SPLIT / self._cell_m
        with np.errstate(invalid="ignore"):
            r = np.clip(np.nan_to_num(np.floor(by * inv) + _DIST_SPLIT, nan=0.0), 0, rows - 1).astype(np.intp)
            c = np.clip(np.nan_to_num(np.floor(bx * inv) + _DIST_SPLIT, nan=0.0), 0, cols - 1).astype(np.intp)
        out: npt.NDArray[np.intp] = r * cols + c
        return out

    # -- one view --------------------------------------------------------------------------------------
    def render(self, rotation: FloatArray, translation_m: FloatArray) -> RenderedTarget:
        """The view of the board with pose (R, t): p_camera = R p_board + t."""
        rot = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
        t = np.asarray(translation_m, dtype=np.float64).reshape(3)
        # Board normal (z into the board) pointing away from the camera: the printed side faces it.
        front = float(rot[:, 2] @ t) > 0.0
        reflectance = self._reflectance(rot, t, front)
        image = self._expose(reflectance)
        obj = self.target.object_points().astype(np.float64)
        corners = self.project(obj, rot, t)
        depth = (obj @ rot.T + t)[:, 2]
        cam = self.camera
        visible = (
            front
            & (depth > 0)
            & (corners[:, 0] >= 0)
            & (corners[:, 0] <= cam.output_width_px - 1)
            & (corners[:, 1] >= 0)
            & (corners[:, 1] <= cam.output_height_px - 1)
        )
        return RenderedTarget(image, corners, visible, rot, t, front)

    def _window(self, rot: FloatArray, t: FloatArray) -> tuple[slice, slice]:
        """The output rows and columns the sheet can cover: its outline projected, plus the blur margin.
        The whole frame when part of the sheet is behind the camera."""
        cam = self.camera
        width, height = self.target.size_m
        s = np.linspace(0.0, 1.0, 17)
        outline = np.concatenate(
            [
                np.column_stack([s * width, np.zeros_like(s)]),
                np.column_stack([s * width, np.full_like(s, height)]),
                np.column_stack([np.zeros_like(s), s * height]),
                np.column_stack([np.full_like(s, width), s * height]),
            ]
        )
        points = np.column_stack([outline, np.zeros(len(outline))])
        depth = (points @ rot.T + t)[:, 2]
        full = (slice(0, cam.output_height_px), slice(0, cam.output_width_px))
        if np.any(depth <= 1e-3):
            return full
        uv = self.project(points, rot, t)
        if not np.all(np.isfinite(uv)):
            return full
        pad = 3.0 + self._footprint_px
        c0 = int(np.clip(np.floor(uv[:, 0].min() - pad), 0, cam.output_width_px))
        c1 = int(np.clip(np.ceil(uv[:, 0].max() + pad) + 1, 0, cam.output_width_px))
        r0 = int(np.clip(np.floor(uv[:, 1].min() - pad), 0, cam.output_height_px))
        r1 = int(np.clip(np.ceil(uv[:, 1].max() + pad) + 1, 0, cam.output_height_px))
        return slice(r0, r1), slice(c0, c1)

    def _board_coordinates(
        self, rot: FloatArray, t: FloatArray, window: tuple[slice, slice]
    ) -> tuple[FloatArray, FloatArray]:
        """Board (X, Y) where each pixel's ray in ``window`` meets the board plane (NaN: it does not).

        The plane z_board = 0 images through H = [r1 r2 t]: z_c (x_n, y_n, 1) = H (X, Y, 1), so
        (X, Y, 1) / z_c = H^-1 (x_n, y_n, 1), and the plane is in front where 1 / z_c > 0."""
        h = np.column_stack([rot[:, 0], rot[:, 1], t])
        hinv = np.linalg.inv(h)
        xn, yn = self._xn[window], self._yn[window]
        w0 = hinv[0, 0] * xn + hinv[0, 1] * yn + hinv[0, 2]
        w1 = hinv[1, 0] * xn + hinv[1, 1] * yn + hinv[1, 2]
        w2 = hinv[2, 0] * xn + hinv[2, 1] * yn + hinv[2, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            bx = np.where(w2 > 0, w0 / w2, np.nan)
            by = np.where(w2 > 0, w1 / w2, np.nan)
        return bx, by

    def _cells(self, bx: npt.NDArray[np.floating], by: npt.NDArray[np.floating]) -> npt.NDArray[np.intp]:
        """Flat index into the padded raster of the cell holding each board point (m); points off the sheet,
        NaN included, land on the padded raster's outer ring, which is the scene."""
        rows, cols = self._raster.shape
        inv = 1.0 / self._cell_m

        def cell(coordinate: npt.NDArray[np.floating], n: int) -> npt.NDArray[np.intp]:
            # fmax/fmin drop NaN: a point off the plane, like one off the sheet, lands on the outer ring.
            c = coordinate * inv
            np.floor(c, out=c)
            np.fmax(c, -1.0, out=c)
            np.fmin(c, float(n), out=c)
            c += 1.0
            return c.astype(np.intp)

        index = cell(by, rows)
        index *= cols + 2
        index += cell(bx, cols)
        return index

    def _lookup(self, bx: npt.NDArray[np.floating], by: npt.NDArray[np.floating]) -> npt.NDArray[np.float32]:
        """Reflectance at board points (m)."""
        out: npt.NDArray[np.float32] = np.take(self._padded, self._cells(bx, by))
        return out

    def _profile(
        self, centre: FloatArray, other: FloatArray, spread: FloatArray, along_x: bool
    ) -> npt.NDArray[np.float32]:
        """Exact Gaussian-blurred value where the print changes along one board axis only: the PSF's
        marginal on that axis, N(centre, spread^2), integrated cell by cell over the row (or column) through
        ``other``."""
        cell = self._cell_m
        first = np.floor((centre - _REACH_SIGMAS * spread) / cell)
        k = np.arange(_PROFILE_CELLS + 1, dtype=np.float64)
        bounds = (first[:, None] + k[None, :]) * cell  # cell edges, (P, M + 1)
        cdf = _phi((bounds - centre[:, None]) / spread[:, None])
        mass = np.diff(cdf, axis=1)
        mass[:, 0] += cdf[:, 0]  # the far tails go to the end cells
        mass[:, -1] += 1.0 - cdf[:, -1]
        mid = (bounds[:, :-1] + bounds[:, 1:]) / 2.0
        line = np.broadcast_to(other[:, None], mid.shape)
        values = self._lookup(mid, line) if along_x else self._lookup(line, mid)
        out: npt.NDArray[np.float32] = (mass * values).sum(axis=1).astype(np.float32)
        return out

    def _reflectance(self, rot: FloatArray, t: FloatArray, front: bool) -> npt.NDArray[np.float32]:
        cam = self.camera
        value = np.full((cam.output_height_px, cam.output_width_px), _SCENE_REFLECTANCE, dtype=np.float32)
        window = self._window(rot, t)
        rows, cols = window
        if rows.stop - rows.start < 3 or cols.stop - cols.start < 3:
            return value
        bx, by = self._board_coordinates(rot, t, window)
        patch = self._lookup(bx, by)
        if not front:
            # The blank back of the sheet: no pattern to find, only its outline against the room.
            value[window] = np.where(patch != _SCENE_REFLECTANCE, _BACK_REFLECTANCE, _SCENE_REFLECTANCE)
            return value
        # Jacobian of board coordinates per sensor pixel, from the kept grid (non-uniform spacing).
        dbx_dv, dbx_du = np.gradient(bx, self._rows[rows], self._cols[cols])
        dby_dv, dby_du = np.gradient(by, self._rows[rows], self._cols[cols])
        sigma = self._sigma_px
        # The PSF on the board: X = X0 + J d, d ~ N(0, sigma^2 I): std(X) = sigma |J_x|, std(Y) = sigma |J_y|.
        spread_x = sigma * np.hypot(dbx_du, dbx_dv)
        spread_y = sigma * np.hypot(dby_du, dby_dv)
        reach = _REACH_SIGMAS * np.hypot(spread_x, spread_y)
        fine = self._fine_cells(bx, by)
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(reach) & np.isfinite(bx) & np.isfinite(by)
            near_x = valid & (np.take(self._dist_x_m.ravel(), fine) < reach)
            near_y = valid & (np.take(self._dist_y_m.ravel(), fine) < reach)
            fits_x = 2.0 * _REACH_SIGMAS * spread_x / self._cell_m + 2.0 <= _PROFILE_CELLS
            fits_y = 2.0 * _REACH_SIGMAS * spread_y / self._cell_m + 2.0 <= _PROFILE_CELLS
        flat = patch.reshape(-1)
        only_x = np.flatnonzero(near_x & ~near_y & fits_x)
        only_y = np.flatnonzero(near_y & ~near_x & fits_y)
        both = np.flatnonzero((near_x & near_y) | (near_x & ~near_y & ~fits_x) | (near_y & ~near_x & ~fits_y))
        if only_x.size:
            flat[only_x] = self._profile(
                bx.flat[only_x], by.flat[only_x], spread_x.flat[only_x], along_x=True
            )
        if only_y.size:
            flat[only_y] = self._profile(
                by.flat[only_y], bx.flat[only_y], spread_y.flat[only_y], along_x=False
            )
        if both.size:
            jac = (dbx_du.flat[both], dbx_dv.flat[both], dby_du.flat[both], dby_dv.flat[both])
            flat[both] = self._sampled(bx.flat[both], by.flat[both], jac)
        value[window] = patch
        return value

    def _sampled(
        self, bx: FloatArray, by: FloatArray, jac: tuple[FloatArray, FloatArray, FloatArray, FloatArray]
    ) -> npt.NDArray[np.float32]:
        """Mean reflectance under the PSF by stratified sampling: one Gaussian draw per stratum of a
        20 x 20 grid in probability space, jittered afresh for every pixel."""
        side = _STRATA
        base = (np.arange(side, dtype=np.float32) / side)[None, :]
        out = np.empty(bx.size, dtype=np.float32)
        chunk = max(1, 1_000_000 // (side * side))
        for start in range(0, bx.size, chunk):
            stop = min(start + chunk, bx.size)
            n = stop - start
            pu = (base + self._rng.random((n, side), dtype=np.float32) / side)[:, :, None]
            pv = (base + self._rng.random((n, side), dtype=np.float32) / side)[:, None, :]
            du = (self._sigma_px * _normal_quantile(np.broadcast_to(pu, (n, side, side)))).reshape(n, -1)
            dv = (self._sigma_px * _normal_quantile(np.broadcast_to(pv, (n, side, side)))).reshape(n, -1)
            a, b, c, d = (j[start:stop, None] for j in jac)
            sx = bx[start:stop, None] + a * du + b * dv
            sy = by[start:stop, None] + c * du + d * dv
            out[start:stop] = self._lookup(sx, sy).mean(axis=1)
        return out

    def _expose(self, reflectance: npt.NDArray[np.float32]) -> ImageU8:
        """Reflectance -> electrons -> DN, as the LED renderer's sensor: shot noise, full well, read noise,
        black level, 8-bit."""
        cam = self.camera
        signal = (self._white_e / self.target_white) * reflectance * self._vignette
        # Shot noise: Poisson in electrons. Every pixel here collects hundreds of electrons or more (the room
        # and the black squares included), where the Gaussian with the same variance matches it to far below
        # a DN, and draws several times faster.
        electrons = signal + np.sqrt(signal) * self._rng.standard_normal(signal.shape, dtype=np.float32)
        np.maximum(electrons, 0.0, out=electrons)
        np.minimum(electrons, cam.full_well_e, out=electrons)
        dn = cam.black_level_dn + self._dn_per_e * electrons
        if cam.read_noise_dn > 0:
            dn += cam.read_noise_dn * self._rng.standard_normal(dn.shape)
        image: ImageU8 = np.clip(np.rint(dn), 0, 255).astype(np.uint8)
        return image

    @property
    def target_white(self) -> float:
        """The reflectance that ``lighting.white_dn`` refers to: the print's white."""
        raster = self._raster
        return float(raster.max()) if raster.size else 1.0
