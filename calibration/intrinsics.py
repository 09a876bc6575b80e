"""Step ``intrinsics``: the camera's focal length, principal point and distortion from views of a board.

Views come from the camera (live: a view is taken when the board is held still somewhere new), from a folder
of images, or, with ``--sim``, from the simulated camera rendering the board where a simulated helper holds
it (``drivers.sim.targets``: the same camera model as the LED frames). While collecting, the image is split
into 3 x 3 cells and the step says where the board is still missing, and whether it should be tilted more or
brought closer. ``cv2.calibrateCamera`` fits the pinhole + plumb_bob model (k3 fixed unless asked for);
views whose reprojection error is far above the rest are dropped once and the fit redone. The result is a ROS
camera_info YAML file and a PNG with the per-view errors, where the corners were, and the residuals.
"""

from __future__ import annotations

import argparse
import datetime
import logging
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np
import numpy.typing as npt

from calibration import plot
from calibration.boards import HAS_ARUCO, BoardDetector, BoardSpec, Detection
from calibration.camera_info import CameraInfo, format_camera_info
from calibration.context import StepContext
from calibration.report import (
    CalibrationError,
    Check,
    Output,
    StepResult,
    ask_choice,
    ask_int,
    ask_line,
)
from drivers.camera.base import Camera
from drivers.sim.render import nearest_indices

__all__ = [
    "Coverage",
    "FolderSource",
    "Guidance",
    "IntrinsicsFit",
    "LensSolution",
    "View",
    "ViewCollector",
    "add_arguments",
    "add_lens_arguments",
    "calibrate",
    "check_view_counts",
    "first_image_size",
    "interactive",
    "run",
    "solve_lens",
    "truth_of",
]

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
ImageU8 = npt.NDArray[np.uint8]

NAME = "intrinsics"
DEFAULT_FILE = "camera_info.yaml"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")
CELLS = 3
# A cell counts as covered once this many corners have been seen in it.
CELL_MIN_CORNERS = 12
# A new view must move the corners this far (mean, share of the image diagonal) or tilt this much differently.
NOVEL_SHIFT = 0.04
NOVEL_TILT_DEG = 8.0
# A live view is taken when the board moved less than this between two frames (px).
STILL_PX = 1.0
# A view is an outlier when its reprojection rms is above both of these.
OUTLIER_FACTOR = 3.0
OUTLIER_MIN_PX = 0.75


# -- collecting views -----------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class View:
    detection: Detection
    label: str
    tilt_deg: float
    area_fraction: float


@dataclass(frozen=True, slots=True)
class Guidance:
    """Where the board should go next: ``cell`` (column, row) of the emptiest cell, whether to tilt it more,
    whether to bring it closer, and the same as a sentence."""

    cell: tuple[int, int]
    tilt_more: bool
    closer: bool
    text: str


_ROW_NAMES = ("top", "middle", "bottom")
_COL_NAMES = ("left", "centre", "right")


def cell_name(cell: tuple[int, int]) -> str:
    col, row = cell
    if (col, row) == (1, 1):
        return "centre"
    if row == 1:
        return _COL_NAMES[col]
    if col == 1:
        return _ROW_NAMES[row]
    return f"{_ROW_NAMES[row]} {_COL_NAMES[col]}"


class Coverage:
    """Corners seen per cell of a 3 x 3 split of the image, and how varied the views' tilts and sizes are."""

    def __init__(self, width: int, height: int) -> None:
        self.width = width
        self.height = height
        self.counts = np.zeros((CELLS, CELLS), dtype=np.int64)  # [row, col]
        self.tilts: list[float] = []
        self.areas: list[float] = []

    def cell_of(self, points: FloatArray) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
        cols = np.clip((points[:, 0] / self.width * CELLS).astype(np.intp), 0, CELLS - 1)
        rows = np.clip((points[:, 1] / self.height * CELLS).astype(np.intp), 0, CELLS - 1)
        return rows, cols

    def add(self, view: View) -> None:
        rows, cols = self.cell_of(view.detection.image_points.astype(np.float64))
        np.add.at(self.counts, (rows, cols), 1)
        self.tilts.append(view.tilt_deg)
        self.areas.append(view.area_fraction)

    @property
    def covered(self) -> int:
        return int(np.count_nonzero(self.counts >= CELL_MIN_CORNERS))

    def missing(self) -> list[str]:
        return [
            cell_name((c, r))
            for r in range(CELLS)
            for c in range(CELLS)
            if self.counts[r, c] < CELL_MIN_CORNERS
        ]

    @property
    def tilted_views(self) -> int:
        return sum(1 for t in self.tilts if t >= 20.0)

    def guidance(self) -> Guidance:
        row, col = np.unravel_index(int(np.argmin(self.counts)), self.counts.shape)
        cell = (int(col), int(row))
        n = len(self.tilts)
        tilt_more = n >= 3 and self.tilted_views < max(n // 2, 1)
        closer = n >= 3 and float(np.median(self.areas)) < 0.12
        parts = [f"hold the board at the {cell_name(cell)} of the picture"]
        if tilt_more:
            parts.append("tilted 20-45 degrees towards or away from the camera")
        if closer:
            parts.append("closer, so it fills more of the picture")
        return Guidance(cell, tilt_more, closer, ", ".join(parts))


def view_geometry(detection: Detection, width: int, height: int, f_guess_px: float) -> tuple[float, float]:
    """(tilt of the board to the image plane in degrees, share of the image its corners span), from a pose
    fitted with a guessed camera: good enough to steer the collection, not part of the calibration."""
    k = np.array([[f_guess_px, 0.0, width / 2.0], [0.0, f_guess_px, height / 2.0], [0.0, 0.0, 1.0]])
    ok, rvec, _ = cv2.solvePnP(
        detection.object_points.reshape(-1, 1, 3),
        detection.image_points.reshape(-1, 1, 2),
        k,
        None,
        flags=cv2.SOLVEPNP_IPPE,
    )
    tilt = math.nan
    if ok:
        rot, _ = cv2.Rodrigues(rvec)
        tilt = math.degrees(math.acos(min(1.0, abs(float(rot[2, 2])))))
    hull = cv2.convexHull(detection.image_points.reshape(-1, 1, 2))
    area = float(cv2.contourArea(hull)) / float(width * height)
    return tilt, area


class ViewCollector:
    """Decides which detections become calibration views: the board found, still (live sources), and
    somewhere or somehow new compared with every view taken so far."""

    def __init__(
        self,
        detector: BoardDetector,
        width: int,
        height: int,
        f_guess_px: float,
        resize: NearestResize | None = None,
    ) -> None:
        self.detector = detector
        self.resize = resize
        self.width = width
        self.height = height
        self.f_guess_px = f_guess_px
        self.views: list[View] = []
        self.coverage = Coverage(width, height)
        self.images_seen = 0
        self.boards_seen = 0
        self.rejected: dict[str, int] = {}
        self._previous: Detection | None = None

    def _reject(self, reason: str) -> tuple[None, str]:
        self.rejected[reason] = self.rejected.get(reason, 0) + 1
        return None, reason

    def consider(self, image: ImageU8, label: str, *, need_still: bool = False) -> tuple[View | None, str]:
        """Take ``image`` as a view or say why not."""
        self.images_seen += 1
        if image.shape[:2] != (self.height, self.width):
            return self._reject(
                f"size {image.shape[1]}x{image.shape[0]} differs from the first image's "
                f"{self.width}x{self.height}"
            )
        detection = self.detector.detect(image)
        if detection is not None and self.resize is not None:
            detection = Detection(
                self.resize.correct(detection.image_points), detection.object_points, detection.corner_ids
            )
        previous, self._previous = self._previous, detection
        if detection is None:
            return self._reject("no board")
        self.boards_seen += 1
        if need_still and (previous is None or not _same_place(previous, detection, STILL_PX)):
            return self._reject("moving")
        tilt, area = view_geometry(detection, self.width, self.height, self.f_guess_px)
        diagonal = math.hypot(self.width, self.height)
        for n, view in enumerate(self.views):
            shift = _mean_shift(view.detection, detection)
            tilt_change = abs(tilt - view.tilt_deg) if math.isfinite(tilt) else 0.0
            if shift < NOVEL_SHIFT * diagonal and tilt_change < NOVEL_TILT_DEG:
                return self._reject(f"too like view {n + 1}")
        view = View(detection, label, tilt, area)
        self.views.append(view)
        self.coverage.add(view)
        return view, "taken"


def _mean_shift(a: Detection, b: Detection) -> float:
    """Mean distance between the corners two detections share (inf when they share fewer than 4)."""
    common, ia, ib = np.intersect1d(a.corner_ids, b.corner_ids, return_indices=True)
    if common.size < 4:
        return math.inf
    return float(np.linalg.norm(a.image_points[ia] - b.image_points[ib], axis=1).mean())


def _same_place(a: Detection, b: Detection, tolerance_px: float) -> bool:
    return _mean_shift(a, b) <= tolerance_px


# -- frames resized with nearest neighbour ---------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class NearestResize:
    """Frames made from a larger sensor by ``cv2.resize(..., INTER_NEAREST)``, as the camera node does.

    Output pixel k shows sensor column s(k) = floor(k * src / dst): the samples are not evenly spaced, and a
    corner located on the output grid as if they were is off by up to 0.2 px in a pattern fixed to the
    image, which views cannot average away. A position measured on the output grid is moved to the
    sensor by interpolating s between the neighbouring samples, then to the output frame of the
    camera model (sensor = a k + b, the least-squares line, as ``agent.vlp.model`` and the simulated camera
    define it)."""

    sensor_width_px: int
    sensor_height_px: int
    output_width_px: int
    output_height_px: int

    def correct(self, points: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        out = np.empty_like(points)
        for axis, src, dst in (
            (0, self.sensor_width_px, self.output_width_px),
            (1, self.sensor_height_px, self.output_height_px),
        ):
            chosen = nearest_indices(src, dst).astype(np.float64)
            k = np.arange(dst, dtype=np.float64)
            a, b = np.polyfit(k, chosen, 1)
            sensor = np.interp(points[:, axis].astype(np.float64), k, chosen, left=np.nan, right=np.nan)
            # Beyond the outermost samples the line continues the spacing of its neighbours.
            edge = np.isnan(sensor)
            sensor[edge] = a * points[edge, axis] + b
            out[:, axis] = (sensor - b) / a
        return out


# -- sources of images --------------------------------------------------------------------------------
class ViewSource(Protocol):
    """Images to look for the board in. ``live``: a stream (the board must be held still to be taken)."""

    live: bool

    def images(self, guidance: Callable[[], Guidance]) -> Iterator[tuple[ImageU8, str]]: ...


class FolderSource:
    """Every image file in a folder, in name order."""

    live = False

    def __init__(self, folder: Path) -> None:
        if not folder.is_dir():
            raise CalibrationError(f"no such folder: {folder}")
        self.folder = folder
        self.paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.paths:
            raise CalibrationError(f"no images in {folder} (looked for {', '.join(IMAGE_SUFFIXES)})")
        self.unreadable: list[str] = []

    def images(self, guidance: Callable[[], Guidance]) -> Iterator[tuple[ImageU8, str]]:
        for path in self.paths:
            image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if image is None:
                log.warning("cannot read %s as an image; skipped", path)
                self.unreadable.append(path.name)
                continue
            yield np.asarray(image, dtype=np.uint8), path.name


class CameraSource:
    """Frames from the robot's camera until ``timeout_s``."""

    live = True

    def __init__(self, camera: Camera, timeout_s: float) -> None:
        self.camera = camera
        self.timeout_s = timeout_s

    def images(self, guidance: Callable[[], Guidance]) -> Iterator[tuple[ImageU8, str]]:
        deadline = time.monotonic() + self.timeout_s
        while time.monotonic() < deadline:
            frame = self.camera.grab(timeout_s=2.0)
            yield frame.image, f"frame {frame.sequence}"


# -- the fit ------------------------------------------------------------------------------------------
@dataclass
class IntrinsicsFit:
    width: int
    height: int
    k: FloatArray
    d: FloatArray
    rms_px: float
    views: list[View]
    per_view_rms_px: list[float]
    residuals_px: list[FloatArray]
    std_intrinsics: FloatArray
    dropped: list[tuple[str, float]] = field(default_factory=list)

    @property
    def fx(self) -> float:
        return float(self.k[0, 0])

    @property
    def fy(self) -> float:
        return float(self.k[1, 1])

    @property
    def cx(self) -> float:
        return float(self.k[0, 2])

    @property
    def cy(self) -> float:
        return float(self.k[1, 2])


def _flags(k_coefficients: int) -> int:
    if k_coefficients == 2:
        return int(cv2.CALIB_FIX_K3)
    if k_coefficients == 3:
        return 0
    raise CalibrationError(f"--k-coefficients must be 2 or 3, not {k_coefficients}")


def _fit_once(views: list[View], width: int, height: int, flags: int) -> IntrinsicsFit:
    obj = [v.detection.object_points.reshape(-1, 1, 3).astype(np.float32) for v in views]
    img = [v.detection.image_points.reshape(-1, 1, 2).astype(np.float32) for v in views]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    try:
        rms, k, d, rvecs, tvecs, std_int, _, per_view = cv2.calibrateCameraExtended(
            obj, img, (width, height), np.eye(3), np.zeros(5), flags=flags, criteria=criteria
        )
    except cv2.error as exc:
        raise CalibrationError(f"the fit failed ({exc.err}); take more varied views") from exc
    residuals = []
    for o, i, rv, tv in zip(obj, img, rvecs, tvecs, strict=True):
        proj, _ = cv2.projectPoints(o, rv, tv, k, d)
        residuals.append((i.reshape(-1, 2) - proj.reshape(-1, 2)).astype(np.float64))
    return IntrinsicsFit(
        width,
        height,
        np.asarray(k, dtype=np.float64),
        np.asarray(d, dtype=np.float64).ravel(),
        float(rms),
        list(views),
        [float(v) for v in np.asarray(per_view).ravel()],
        residuals,
        np.asarray(std_int, dtype=np.float64).ravel(),
    )


def calibrate(
    views: list[View], width: int, height: int, *, k_coefficients: int = 2, drop_outliers: bool = True
) -> IntrinsicsFit:
    """``cv2.calibrateCamera`` over the views; views far worse than the rest (rms above both
    3 x the median and 0.75 px) are dropped once and the fit redone."""
    flags = _flags(k_coefficients)
    fit = _fit_once(views, width, height, flags)
    if not drop_outliers or len(views) < 6:
        return fit
    median = float(np.median(fit.per_view_rms_px))
    limit = max(OUTLIER_FACTOR * median, OUTLIER_MIN_PX)
    bad = [i for i, e in enumerate(fit.per_view_rms_px) if e > limit]
    if not bad or len(views) - len(bad) < 6:
        return fit
    kept = [v for i, v in enumerate(views) if i not in bad]
    refit = _fit_once(kept, width, height, flags)
    refit.dropped = [(views[i].label, fit.per_view_rms_px[i]) for i in bad]
    log.info("dropped %d outlier views: %s", len(bad), refit.dropped)
    return refit


# -- the step -----------------------------------------------------------------------------------------
def add_board_arguments(p: argparse.ArgumentParser, square_mm: float = 30.0) -> None:
    kinds = ["chessboard", "charuco"] if HAS_ARUCO else ["chessboard"]
    p.add_argument(
        "--board", choices=kinds, default="chessboard", help="the printed board (default: chessboard)"
    )
    p.add_argument(
        "--cols",
        type=int,
        default=None,
        help="chessboard: inner corners across (9); ChArUco: squares across (8)",
    )
    p.add_argument(
        "--rows", type=int, default=None, help="chessboard: inner corners down (6); ChArUco: squares down (6)"
    )
    p.add_argument(
        "--square-mm", type=float, default=square_mm, help=f"square size in mm (default: {square_mm:g})"
    )
    p.add_argument(
        "--marker-mm", type=float, default=0.0, help="ChArUco marker size in mm (default: 3/4 square)"
    )
    p.add_argument(
        "--dictionary", default="DICT_4X4_50", help="ChArUco ArUco dictionary (default: DICT_4X4_50)"
    )


def board_spec(options: argparse.Namespace) -> BoardSpec:
    charuco = options.board == "charuco"
    cols = options.cols if options.cols is not None else (8 if charuco else 9)
    rows = options.rows if options.rows is not None else 6
    return BoardSpec(
        options.board, cols, rows, options.square_mm / 1000.0, options.marker_mm / 1000.0, options.dictionary
    )


def add_lens_arguments(p: argparse.ArgumentParser) -> None:
    """The options every board calibration of a lens takes (this step's and ``forward-camera``'s)."""
    add_board_arguments(p)
    p.add_argument("--images", metavar="DIR", help="calibrate from the images in DIR instead of the camera")
    p.add_argument("--views", type=int, default=40, help="views to collect (default: 40)")
    p.add_argument("--min-views", type=int, default=10, help="fewest views to calibrate from (default: 10)")
    p.add_argument(
        "--k-coefficients",
        type=int,
        choices=(2, 3),
        default=2,
        help="radial distortion terms: 2 (k3 fixed) or 3",
    )
    p.add_argument(
        "--max-rms", type=float, default=0.5, help="quality threshold on the rms error, px (default 0.5)"
    )
    p.add_argument(
        "--timeout-s", type=float, default=300.0, help="live camera: stop collecting after this long"
    )
    p.add_argument("--exposure-ms", type=float, default=None, help="live camera: exposure while calibrating")


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_lens_arguments(p)
    p.add_argument(
        "--sensor-size",
        metavar="WxH",
        help="sensor size when frames are resized from it with nearest neighbour (default: the robot "
        "config's "
        "[vlp.rolling_shutter], the simulated camera's)",
    )


def interactive(ctx: StepContext, options: argparse.Namespace) -> argparse.Namespace:
    """The wizard's questions for this step (and ``forward-camera``'s)."""
    console = ctx.console
    if ctx.sim is None:
        source = ask_choice(
            console, "views from the camera or from a folder of images", ["camera", "folder"], "camera"
        )
        if source == "folder":
            options.images = ask_line(console, "folder of images: ").strip() or None
    if HAS_ARUCO:
        options.board = ask_choice(console, "board", ["chessboard", "charuco"], options.board)
    options.views = ask_int(
        console, "views to collect", options.views, minimum=options.min_views, maximum=200
    )
    return options


def _sensor_size(text: str | None) -> tuple[int, int] | None:
    if not text:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise CalibrationError(f"--sensor-size must look like 2048x1536, not {text!r}") from None
    if w <= 0 or h <= 0:
        raise CalibrationError(f"--sensor-size must be positive, got {text!r}")
    return w, h


def _resize(sensor: tuple[int, int] | None, width: int, height: int) -> NearestResize | None:
    if sensor is None or sensor == (width, height):
        return None
    return NearestResize(sensor[0], sensor[1], width, height)


def check_view_counts(options: argparse.Namespace) -> None:
    if options.min_views < 3 or options.views < options.min_views:
        raise CalibrationError(
            f"--views ({options.views}) must be at least --min-views ({options.min_views}) >= 3"
        )


def first_image_size(folder: FolderSource) -> tuple[int, int]:
    """Width and height of the folder's first image (the size every view must have)."""
    first = cv2.imread(str(folder.paths[0]), cv2.IMREAD_GRAYSCALE)
    if first is None:
        raise CalibrationError(f"cannot read {folder.paths[0]} as an image")
    height, width = first.shape[:2]
    return width, height


def run(ctx: StepContext, options: argparse.Namespace) -> StepResult:
    console = ctx.console
    spec = board_spec(options)
    detector = BoardDetector(spec)
    check_view_counts(options)
    output = ctx.output(options.output, DEFAULT_FILE)
    sensor = _sensor_size(options.sensor_size)
    truth: dict[str, float] | None = None
    console.say(f"intrinsics: looking for {spec.describe()}")

    if options.images:
        folder = FolderSource(Path(options.images))
        width, height = first_image_size(folder)
        console.say(f"  {len(folder.paths)} images in {options.images}")
        lens = solve_lens(
            ctx, options, detector, folder, width, height, 0.8 * width, _resize(sensor, width, height)
        )
    elif ctx.sim is not None:
        from calibration.sim import BoardHelper, target_renderer

        world = ctx.sim.load()
        cam = world.camera
        renderer = target_renderer(cam, detector.target, seed=ctx.sim.seed)
        width, height = cam.output_width_px, cam.output_height_px
        truth = truth_of(renderer.output_intrinsics)
        helper = BoardHelper(renderer, seed=ctx.sim.seed)
        console.say(
            f"  simulated camera of world {world.name!r} ({width}x{height}); a helper holds the board"
        )
        held = helper.source(max_images=max(6 * options.views, 60))
        sensor = sensor or (cam.sensor_width_px, cam.sensor_height_px)
        lens = solve_lens(
            ctx, options, detector, held, width, height, 0.8 * width, _resize(sensor, width, height), truth
        )
    else:
        ctx.require_robot("calibrating from the camera")
        from calibration.rig import Rig

        with Rig.for_context(ctx) as rig:
            exposure = None if options.exposure_ms is None else options.exposure_ms / 1000.0
            camera = rig.camera(exposure_s=exposure)
            frame = camera.grab(timeout_s=5.0)
            height, width = frame.image.shape[:2]
            f_guess = rig.nominal.intrinsics_f_px(width)
            sensor = sensor or rig.nominal.sensor_size_px
            console.say("  hold the board still in front of the camera; a view is taken when it is still")
            live = CameraSource(camera, options.timeout_s)
            lens = solve_lens(
                ctx, options, detector, live, width, height, f_guess, _resize(sensor, width, height)
            )
    use = [
        f'set camera_info = "{output}" in the [vlp] table of the robot config',
        "next: `vlp-agent calibrate mount` (camera tilt and yaw on the base) uses this file",
    ]
    return lens.result(NAME, output, "vlp_camera", options.max_rms, use)


# -- the lens from collected views: shared with the forward camera's step (calibration/forward_camera.py) --
def truth_of(intrinsics: Any) -> dict[str, float]:
    """The simulated camera's true fx, fy, cx, cy (a ``drivers.sim.render.OutputIntrinsics``)."""
    return {"fx": intrinsics.fx_px, "fy": intrinsics.fy_px, "cx": intrinsics.cx_px, "cy": intrinsics.cy_px}


@dataclass
class LensSolution:
    """A lens calibrated from board views: the fit, how the views were collected, the quality checks, the
    figures (``values``, for ``--json``) and the report lines; ``truth``: the simulated camera's, if any."""

    fit: IntrinsicsFit
    collector: ViewCollector
    spec: BoardSpec
    checks: list[Check]
    values: dict[str, Any]
    report: list[str]
    truth: dict[str, float] | None

    def camera_info(self, camera_name: str) -> CameraInfo:
        fit = self.fit
        return CameraInfo.from_matrices(
            fit.width, fit.height, fit.k, _five(fit.d), _projection(fit), camera_name=camera_name
        )

    def advice(self, use: list[str]) -> list[str]:
        """What to do about failed checks; when all pass, ``use`` (where the file goes, what comes next)."""
        fit, checks = self.fit, self.checks
        advice: list[str] = []
        by_name = {c.name: c for c in checks}
        if not by_name["reprojection rms"].ok:
            advice.append(
                "the rms error is high: views drawn red in the PNG are blurred or badly detected; retake "
                "them, and check the square size and that the board is flat"
            )
        if not by_name["image cells covered"].ok:
            missing = _coverage(fit).missing()
            advice.append("add views with the board at the " + ", ".join(missing) + " of the picture")
        if not by_name["focal length 1-sigma"].ok or not by_name["principal point 1-sigma"].ok:
            advice.append(
                "the fit is loose: add views with the board tilted 20-45 degrees, and near the corners"
            )
        if all(c.ok for c in checks):
            advice += use
        return advice

    def result(self, step: str, output: Path, camera_name: str, max_rms: float, use: list[str]) -> StepResult:
        """The step's result: the camera_info file at ``output`` and its PNG report beside it."""
        fit = self.fit
        stamp = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
        comment = (
            f"vlp-agent calibrate {step}, {stamp}\n"
            f"{len(fit.views)} views of {self.spec.describe()}; reprojection rms {fit.rms_px:.3f} px"
        )
        figure = _figure(fit, max_rms, self.checks, self.truth, step)
        outputs = [
            Output(output, format_camera_info(self.camera_info(camera_name), comment)),
            Output(output.with_suffix(".png"), plot.png(figure), report=True),
        ]
        return StepResult(step, self.values, self.checks, self.report, self.advice(use), outputs)


def solve_lens(
    ctx: StepContext,
    options: argparse.Namespace,
    detector: BoardDetector,
    source: ViewSource,
    width: int,
    height: int,
    f_guess: float,
    resize: NearestResize | None = None,
    truth: dict[str, float] | None = None,
) -> LensSolution:
    """Collect views from ``source`` (options ``views``, ``min_views``), fit the lens (``k_coefficients``)
    and judge it (``max_rms``; coverage; the fit's 1-sigma). CalibrationError, with what to change, when no
    board was found or too few usable views."""
    fit, collector = _collect_and_fit(ctx, options, detector, source, width, height, f_guess, resize)
    spec = detector.spec
    coverage = _coverage(fit)
    checks = [
        Check("reprojection rms", fit.rms_px, options.max_rms, "px"),
        Check("views used", float(len(fit.views)), float(options.min_views), "", at_least=True),
        Check("image cells covered", float(coverage.covered), 7.0, "of 9", at_least=True),
        Check("focal length 1-sigma", 100.0 * float(fit.std_intrinsics[0]) / fit.fx, 0.5, "%"),
        Check(
            "principal point 1-sigma",
            float(math.hypot(fit.std_intrinsics[2], fit.std_intrinsics[3])),
            1.0,
            "px",
        ),
    ]
    values: dict[str, Any] = {
        "rms_px": round(fit.rms_px, 4),
        "views": len(fit.views),
        "fx": round(fit.fx, 3),
        "fy": round(fit.fy, 3),
        "cx": round(fit.cx, 3),
        "cy": round(fit.cy, 3),
        "distortion": [round(float(v), 6) for v in _five(fit.d)],
        "width": fit.width,
        "height": fit.height,
        "board": spec.describe(),
        "per_view_rms_px": [round(v, 4) for v in fit.per_view_rms_px],
        "dropped_views": [{"view": label, "rms_px": round(e, 3)} for label, e in fit.dropped],
        "images_seen": collector.images_seen,
        "boards_seen": collector.boards_seen,
        "cells_covered": coverage.covered,
        "cells_missing": coverage.missing(),
        "fx_sigma_px": round(float(fit.std_intrinsics[0]), 4),
        "cx_sigma_px": round(float(fit.std_intrinsics[2]), 4),
        "cy_sigma_px": round(float(fit.std_intrinsics[3]), 4),
    }
    report = [
        f"{len(fit.views)} views ({collector.images_seen} images looked at, board in "
        f"{collector.boards_seen})",
        f"fx {fit.fx:.2f}  fy {fit.fy:.2f}  cx {fit.cx:.2f}  cy {fit.cy:.2f} px  ({fit.width}x{fit.height})",
        "distortion (k1 k2 p1 p2 k3) " + " ".join(f"{v:+.5f}" for v in _five(fit.d)),
        f"reprojection rms {fit.rms_px:.3f} px; worst view {max(fit.per_view_rms_px):.3f} px",
        f"coverage: {coverage.covered} of 9 image cells"
        + (f" (missing: {', '.join(coverage.missing())})" if coverage.covered < 9 else ""),
    ]
    if fit.dropped:
        report.append(
            "dropped as outliers: " + ", ".join(f"{label} ({e:.2f} px)" for label, e in fit.dropped)
        )
    if truth is not None:
        fx_err = 100.0 * abs(fit.fx - truth["fx"]) / truth["fx"]
        pp_err = math.hypot(fit.cx - truth["cx"], fit.cy - truth["cy"])
        values.update(
            fx_error_pct=round(fx_err, 4),
            fy_error_pct=round(100.0 * abs(fit.fy - truth["fy"]) / truth["fy"], 4),
            principal_point_error_px=round(pp_err, 4),
            truth={key: round(v, 3) for key, v in truth.items()},
        )
        report.append(
            f"against the simulated truth: fx off by {fx_err:.3f} %, principal point off by {pp_err:.3f} px"
        )
    return LensSolution(fit, collector, spec, checks, values, report, truth)


def _five(d: FloatArray) -> FloatArray:
    out = np.zeros(5)
    out[: min(5, d.size)] = d[:5]
    return out


def _projection(fit: IntrinsicsFit) -> FloatArray:
    """ROS's choice for a monocular camera: P = [K' | 0] with K' the optimal new camera matrix at alpha 0."""
    new_k, _ = cv2.getOptimalNewCameraMatrix(fit.k, _five(fit.d), (fit.width, fit.height), 0.0)
    p = np.zeros((3, 4))
    p[:, :3] = new_k
    return p


def _coverage(fit: IntrinsicsFit) -> Coverage:
    coverage = Coverage(fit.width, fit.height)
    for view in fit.views:
        coverage.add(view)
    return coverage


def _collect_and_fit(
    ctx: StepContext,
    options: argparse.Namespace,
    detector: BoardDetector,
    source: ViewSource,
    width: int,
    height: int,
    f_guess: float,
    resize: NearestResize | None,
) -> tuple[IntrinsicsFit, ViewCollector]:
    console = ctx.console
    collector = ViewCollector(detector, width, height, f_guess, resize)
    guidance = collector.coverage.guidance
    last_reason = ""
    for image, label in source.images(guidance):
        view, reason = collector.consider(image, label, need_still=source.live)
        coverage = collector.coverage
        if view is not None:
            last_reason = f"took {label}"
        elif reason != "moving":
            last_reason = f"{label}: {reason}"
        console.status(
            f"views {len(collector.views)}/{options.views}  cells {coverage.covered}/9  "
            f"| next: {coverage.guidance().text} | {last_reason}"
        )
        if len(collector.views) >= options.views and coverage.covered >= 7:
            break
        if len(collector.views) >= 2 * options.views:
            break
    console.status("")
    if collector.boards_seen == 0:
        raise CalibrationError(
            f"no board found in any of the {collector.images_seen} images: looked for "
            f"{detector.spec.describe()}. "
            "Check --cols/--rows (a chessboard counts inner corners), the square size, focus and lighting."
        )
    if len(collector.views) < options.min_views:
        reasons = ", ".join(
            f"{n} {why}" for why, n in sorted(collector.rejected.items(), key=lambda kv: -kv[1])
        )
        raise CalibrationError(
            f"too few views: {len(collector.views)} usable, at least {options.min_views} needed "
            f"(the board was found in {collector.boards_seen} of {collector.images_seen} images; rejected: "
            f"{reasons or 'none'}). Add views with the board in other places and at other tilts."
        )
    console.say(f"  {len(collector.views)} views; fitting")
    fit = calibrate(collector.views, width, height, k_coefficients=options.k_coefficients)
    return fit, collector


def _figure(
    fit: IntrinsicsFit, max_rms: float, checks: list[Check], truth: dict[str, float] | None, title: str
) -> Any:
    bars = plot.bar_chart(
        fit.per_view_rms_px,
        title="reprojection rms per view",
        ylabel="rms (px)",
        xlabel="view",
        threshold=max(max_rms, 1e-3),
    )
    corners = np.vstack([v.detection.image_points for v in fit.views]).astype(np.float64)
    errors = np.concatenate([np.linalg.norm(r, axis=1) for r in fit.residuals_px])
    good = corners[errors <= max_rms]
    bad = corners[errors > max_rms]
    xs = [fit.width * i / CELLS for i in range(1, CELLS)]
    ys = [fit.height * i / CELLS for i in range(1, CELLS)]
    cover = plot.scatter(
        [
            plot.Series(good, plot.GREEN, f"corner error <= {max_rms:g} px", 1),
            plot.Series(bad, plot.RED, f"> {max_rms:g} px", 2),
        ],
        title=f"coverage: {_coverage(fit).covered} of 9 cells",
        bounds=(0.0, float(fit.width), 0.0, float(fit.height)),
        flip_y=True,
        grid_lines=(xs, ys),
        axis_labels=("u (px)", "v (px)"),
    )
    residuals = np.vstack(fit.residuals_px)
    resid = plot.scatter(
        [plot.Series(residuals, plot.BLUE, "a corner's residual", 1)],
        title="residuals; the circle: their rms",
        axis_labels=("dx (px)", "dy (px)"),
        circles=[(0.0, 0.0, fit.rms_px, plot.RED)],
    )
    lines = [
        f"fx {fit.fx:.2f}  fy {fit.fy:.2f} px",
        f"cx {fit.cx:.2f}  cy {fit.cy:.2f} px",
        "k1 k2 p1 p2 k3: " + " ".join(f"{v:+.4f}" for v in _five(fit.d)),
        f"rms {fit.rms_px:.3f} px over {len(fit.views)} views",
    ]
    if truth is not None:
        lines.append(f"truth fx {truth['fx']:.2f} cx {truth['cx']:.2f} cy {truth['cy']:.2f}")
    lines += [c.describe() for c in checks]
    text = plot.text_panel(lines, title=title)
    return plot.grid([bars, cover, resid, text], columns=2)
