"""Calibration boards: what the user printed, and finding its corners in an image.

A chessboard is found whole with OpenCV's sector-based detector (``findChessboardCornersSB``, sub-pixel
accurate without a separate refinement); a ChArUco board (when ``cv2.aruco`` is there) may be partly out of
the picture, each corner being identified by its neighbouring markers. The board geometry is the one the
simulated camera renders (``drivers.sim.targets``), so the same object points serve both.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from calibration.report import CalibrationError
from drivers.sim.targets import HAS_ARUCO, CharucoTarget, Chessboard, Target

__all__ = ["HAS_ARUCO", "BoardDetector", "BoardSpec", "Detection"]

log = logging.getLogger(__name__)

Float32Array = npt.NDArray[np.float32]
ImageU8 = npt.NDArray[np.uint8]

# cornerSubPix half-window as a share of the corner spacing.
_REFINE_SHARE = 0.35
# A ChArUco view needs at least this many corners, not all on one line, to say anything about the camera.
_MIN_CHARUCO_CORNERS = 8


@dataclass(frozen=True, slots=True)
class BoardSpec:
    """The printed board. Chessboard: ``cols`` x ``rows`` inner corners. ChArUco: ``cols`` x ``rows``
    squares, markers of ``marker_m`` (default three quarters of a square) from ``dictionary``."""

    kind: str = "chessboard"
    cols: int = 9
    rows: int = 6
    square_m: float = 0.03
    marker_m: float = 0.0
    dictionary: str = "DICT_4X4_50"

    def __post_init__(self) -> None:
        if self.kind not in ("chessboard", "charuco"):
            raise CalibrationError(f"board must be 'chessboard' or 'charuco', not {self.kind!r}")
        if self.kind == "charuco" and not HAS_ARUCO:
            raise CalibrationError(
                "ChArUco boards need OpenCV's aruco module, which this OpenCV build lacks; use a chessboard "
                "or install opencv-contrib-python-headless"
            )
        if not self.square_m > 0:
            raise CalibrationError(f"the square size must be positive, got {self.square_m} m")
        if self.cols < 2 or self.rows < 2:
            raise CalibrationError(
                f"a board needs at least 2 x 2 corners or squares, got {self.cols} x {self.rows}"
            )

    @property
    def marker_length_m(self) -> float:
        return self.marker_m if self.marker_m > 0 else 0.75 * self.square_m

    def target(self) -> Target:
        """The board's geometry (and print, for the simulated camera)."""
        try:
            if self.kind == "chessboard":
                return Chessboard(self.cols, self.rows, self.square_m)
            return CharucoTarget(self.cols, self.rows, self.square_m, self.marker_length_m, self.dictionary)
        except (ValueError, RuntimeError) as exc:
            raise CalibrationError(f"cannot use this board: {exc}") from exc

    def describe(self) -> str:
        mm = f"{1000 * self.square_m:g} mm squares"
        if self.kind == "chessboard":
            return f"a {self.cols} x {self.rows} chessboard (inner corners), {mm}"
        return (
            f"a {self.cols} x {self.rows} ChArUco board ({self.dictionary}), {mm}, "
            f"{1000 * self.marker_length_m:g} mm markers"
        )


@dataclass(frozen=True, slots=True)
class Detection:
    """A board found in one image: corners (N, 2) in pixels, their board points (N, 3) and ids."""

    image_points: Float32Array
    object_points: Float32Array
    corner_ids: npt.NDArray[np.int32]

    @property
    def count(self) -> int:
        return int(self.image_points.shape[0])


class BoardDetector:
    """Finds one board's corners in 8-bit grey images."""

    def __init__(self, spec: BoardSpec, *, equalize_first: bool = True) -> None:
        self.spec = spec
        # findChessboardCornersSB is tried with histogram equalisation and without, in this order. Over a
        # frame that is mostly something else (the forward camera's room: a bright wall around a small board)
        # the equalisation stretches the wall's noise and the board is lost: that camera tries without first.
        plain = int(cv2.CALIB_CB_ACCURACY)
        equalized = int(cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_ACCURACY)
        self._chessboard_flags = (equalized, plain) if equalize_first else (plain, equalized)
        self.target = spec.target()
        self._object_points = self.target.object_points()
        self._charuco: object = None
        if spec.kind == "charuco":
            assert isinstance(self.target, CharucoTarget)
            self._charuco = cv2.aruco.CharucoDetector(self.target.board)

    @property
    def corner_count(self) -> int:
        return int(self._object_points.shape[0])

    def detect(self, image: ImageU8) -> Detection | None:
        """The board's corners, or None when the board is not there (or too little of it)."""
        if image.ndim == 3:
            image = np.asarray(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
        if image.dtype != np.uint8 or image.ndim != 2:
            raise CalibrationError(f"images must be 8-bit grey or colour, got {image.dtype} {image.shape}")
        if self.spec.kind == "chessboard":
            return self._chessboard(image)
        return self._charuco_corners(image)

    def _chessboard(self, image: ImageU8) -> Detection | None:
        size = (self.spec.cols, self.spec.rows)
        found, corners = False, None
        for flags in self._chessboard_flags:
            found, corners = cv2.findChessboardCornersSB(image, size, flags=flags)
            if found and corners is not None:
                break
        if not found or corners is None:
            return None
        pts = np.asarray(corners, dtype=np.float32).reshape(-1, 2)
        if pts.shape[0] != self.corner_count:
            return None
        pts = self._refine(image, pts)
        ids = np.arange(self.corner_count, dtype=np.int32)
        return Detection(pts, self._object_points, ids)

    def _refine(self, image: ImageU8, pts: Float32Array) -> Float32Array:
        """Refine the corners with ``cornerSubPix`` over a window of about a third of a square.

        The sector detector's own sub-pixel step is biased on tilted boards (it leans along the
        foreshortening: on rendered views of known geometry it put the focal length 0.3-0.45 % long), and the
        gradient-based refinement is not."""
        grid = pts.reshape(self.spec.rows, self.spec.cols, 2)
        spacing = np.concatenate(
            [
                np.linalg.norm(np.diff(grid, axis=1), axis=2).ravel(),
                np.linalg.norm(np.diff(grid, axis=0), axis=2).ravel(),
            ]
        )
        half = int(np.clip(round(_REFINE_SHARE * float(np.median(spacing))), 2, 15))
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
        refined = cv2.cornerSubPix(image, pts.reshape(-1, 1, 2).copy(), (half, half), (-1, -1), criteria)
        out: Float32Array = np.asarray(refined, dtype=np.float32).reshape(-1, 2)
        # A corner that wandered off (a half-window onto another corner) keeps the detector's position.
        moved = np.linalg.norm(out - pts, axis=1) > 0.5 * half
        out[moved] = pts[moved]
        return out

    def _charuco_corners(self, image: ImageU8) -> Detection | None:
        corners, ids, _, _ = self._charuco.detectBoard(image)  # type: ignore[attr-defined]
        if corners is None or ids is None or len(ids) < _MIN_CHARUCO_CORNERS:
            return None
        pts = np.asarray(corners, dtype=np.float32).reshape(-1, 2)
        idx = np.asarray(ids, dtype=np.int32).reshape(-1)
        # Corners on one line (a single row of squares) do not constrain a homography.
        centred = pts - pts.mean(axis=0)
        singular = np.linalg.svd(centred, compute_uv=False)
        if singular.size < 2 or singular[1] < 0.05 * singular[0]:
            return None
        return Detection(pts, self._object_points[idx], idx)
