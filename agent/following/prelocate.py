"""Head-shoulder pre-location: where in a frame the people are, to start the tracker and to re-acquire it.

Two detectors that OpenCV 4.x carries inside the wheel, so nothing is downloaded (``reference/eco.md``
§2.3; OpenCV 5.0 dropped both from the main modules, hence the project's ``opencv-python-headless<5`` pin):

* ``hog``: Dalal and Triggs' HOG people detector, ``cv2.HOGDescriptor_getDefaultPeopleDetector()`` (a
  64 x 128 window, whole standing people). The head and shoulders are taken as the top of its box
  (:data:`HOG_HEAD_SHOULDER`).
* ``upperbody``: the Haar cascade ``haarcascade_upperbody.xml`` in ``cv2.data.haarcascades`` (Kruppa,
  Castrillón and Schiele: head and shoulders, 22 x 18 window): what a robot close behind its user sees.

The search is restricted to a band of image columns (the coarse layer's bearing sector turned into
columns) and run on the band shrunk to ``max_width_px``: both detectors' cost grows with the pixels
searched (eco.md: HOG 43 ms on a whole 640 x 480 frame, 4.8 ms at 320 x 240), and the band keeps a passer-by
outside the user's sector out of the candidates. ``benchmarks/tracker_speed.py`` measures it.
"""

from __future__ import annotations

import enum
import functools
import logging
import math
import time
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from drivers.errors import BackendUnavailable

__all__ = ["Detection", "HeadShoulderLocator", "LocatorKind", "PreLocatorConfig"]

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
ImageU8 = npt.NDArray[np.uint8]

# The head and shoulders inside a HOG person box (x, y, w, h as fractions of it): the default detector's
# window is 64 x 128 with the person about 40 x 96 in its middle, the head from about 1/8 down.
HOG_HEAD_SHOULDER = (0.25, 0.08, 0.5, 0.3)


class LocatorKind(enum.StrEnum):
    HOG = "hog"
    UPPER_BODY = "upperbody"
    OMEGA = "omega"  # our own: oriented chamfer matching of a head-and-shoulders outline (no model)


@dataclass(frozen=True)
class PreLocatorConfig:
    kind: LocatorKind = LocatorKind.HOG
    max_width_px: int = 320  # the band is shrunk to at most this width before the search
    scale_step: float = 1.1  # image-pyramid step
    hog_hit_threshold: float = 0.0  # SVM margin a HOG window needs
    cascade_min_neighbours: int = 3
    # Smallest head-and-shoulders the cascade looks for, in pixels of the (shrunk) band: its own window is
    # 22 x 18, and the small scales are most of its cost; a user a metre or three ahead is far larger.
    cascade_min_width_px: int = 44
    # omega: the frame is searched shrunk to at most omega_width_px wide, for outlines from
    # omega_min_width_px (shrunk pixels) to 0.8 of its height, omega_scale_step apart; a match's mean
    # distance from its outline to the nearest edge of the same orientation, over the outline's width,
    # must stay under omega_max_score.
    omega_width_px: int = 160
    omega_min_width_px: int = 16
    omega_scale_step: float = 1.15
    omega_max_score: float = 0.05
    # A head is a plain blob: a match whose head (the inner 60 % of the outline's head ellipse) holds more
    # than this share of edge pixels is a pattern (a checked shirt), not a head.
    omega_max_head_edges: float = 0.08


@dataclass(frozen=True)
class Detection:
    """A person found: the detector's box, the head-shoulder box to start the tracker on (both x, y, w, h
    in frame pixels) and the detector's score (HOG: SVM margin; cascade: number of merged hits)."""

    box: FloatArray
    head_shoulder: FloatArray
    score: float


class HeadShoulderLocator:
    """Finds head-and-shoulder boxes in a BGR frame. ``last_ms`` is the last call's time."""

    def __init__(self, config: PreLocatorConfig | None = None) -> None:
        import cv2

        self.config = config or PreLocatorConfig()
        self.last_ms = 0.0
        if self.config.kind is LocatorKind.OMEGA:
            pass
        elif self.config.kind is LocatorKind.HOG:
            if not hasattr(cv2, "HOGDescriptor"):
                raise BackendUnavailable(
                    "this OpenCV has no HOGDescriptor (OpenCV 5 dropped it): install opencv-python-headless<5"
                )
            self._hog = cv2.HOGDescriptor()
            self._hog.setSVMDetector(
                np.asarray(cv2.HOGDescriptor.getDefaultPeopleDetector(), dtype=np.float32)
            )
        else:
            path = _cascade_path("haarcascade_upperbody.xml")
            self._cascade = cv2.CascadeClassifier(path)
            if self._cascade.empty():
                raise BackendUnavailable(f"{path}: the upper-body cascade did not load")

    def locate(self, frame: ImageU8, band: tuple[int, int] | None = None) -> list[Detection]:
        """People in ``frame`` whose box centre lies in the column band ``[band[0], band[1])`` (the whole
        width when None), best first."""
        import cv2

        _check_frame(frame)
        t0 = time.perf_counter()
        _height, width = frame.shape[:2]
        c0, c1 = (0, width) if band is None else (max(0, int(band[0])), min(width, int(band[1])))
        if c1 - c0 < 8:
            self.last_ms = (time.perf_counter() - t0) * 1e3
            return []
        crop: ImageU8 = frame[:, c0:c1]
        if self.config.kind is LocatorKind.OMEGA:
            detections = _omega(crop, c0, width, self.config)
            self.last_ms = (time.perf_counter() - t0) * 1e3
            return detections
        shrink = min(1.0, self.config.max_width_px / crop.shape[1])
        if shrink < 1.0:
            crop = np.asarray(cv2.resize(crop, None, fx=shrink, fy=shrink, interpolation=cv2.INTER_AREA))
        detections = []
        for found_rect, score in self._detect(crop):
            box = found_rect / shrink + np.array([c0, 0.0, 0.0, 0.0])
            centre_x = box[0] + box[2] / 2.0
            if not c0 <= centre_x < c1:
                continue
            detections.append(self._detection(box, score))
        detections.sort(key=lambda d: -d.score)
        self.last_ms = (time.perf_counter() - t0) * 1e3
        log.debug("%d people in columns %d-%d in %.1f ms", len(detections), c0, c1, self.last_ms)
        return detections

    def locate_around(
        self,
        frame: ImageU8,
        box: FloatArray | tuple[float, float, float, float],
        scale: float,
        half_width: float = 1.5,
        half_height: float = 1.1,
    ) -> list[Detection]:
        """People near a tracked ``box`` (x, y, w, h): the window of +-``half_width`` box widths and
        +-``half_height`` box heights about its centre, resized by ``scale`` and searched (``omega``
        searches it as it is). HOG's window is 64 x 128 with the person about 96 px tall in it and its
        pyramid only shrinks the image: a walker in OTB (51-114 px tall) must be scaled up to be seen at
        all (to 130 px: Woman's walker found on 45 % of her frames; to 110 px: 15 %). And the size HOG
        reports follows the image scale it searches at (on Woman, a window scaled from a box 0.7 of the
        walker's height gave boxes 1.02 times hers, from her own height 0.80): a caller measuring a size
        keeps ``scale`` fixed (``agent.following.anchor``). Best first."""
        import cv2

        frame = np.asarray(frame)
        _check_frame(frame)
        t0 = time.perf_counter()
        x, y, w, h = (float(v) for v in box)
        if not (w > 0.0 and h > 0.0):
            raise ValueError(f"box {box} has no area")
        if not (math.isfinite(scale) and scale > 0.0):
            raise ValueError(f"scale must be finite and > 0, got {scale}")
        if self.config.kind is LocatorKind.OMEGA:
            scale = 1.0
        cx, cy = x + w / 2.0, y + h / 2.0
        # At least the detector's window (64 x 128, with its padding) once scaled.
        hw, hh = max(half_width * w, 48.0 / scale), max(half_height * h, 80.0 / scale)
        rows, cols = frame.shape[:2]
        x0, y0 = max(0, math.floor(cx - hw)), max(0, math.floor(cy - hh))
        x1, y1 = min(cols, math.ceil(cx + hw)), min(rows, math.ceil(cy + hh))
        detections: list[Detection] = []
        if x1 - x0 >= 8 and y1 - y0 >= 8:
            crop: ImageU8 = frame[y0:y1, x0:x1]
            if scale != 1.0:
                interpolation = cv2.INTER_LINEAR if scale > 1.0 else cv2.INTER_AREA
                crop = np.asarray(cv2.resize(crop, None, fx=scale, fy=scale, interpolation=interpolation))
            if self.config.kind is LocatorKind.OMEGA:
                detections = _omega(crop, x0, cols, self.config)
                for d in detections:
                    d.box[1] += y0
                    d.head_shoulder[1] += y0
            elif crop.shape[0] >= 128 and crop.shape[1] >= 64:
                origin = np.array([x0, y0, 0.0, 0.0])
                for found_rect, score in self._detect(crop):
                    detections.append(self._detection(found_rect / scale + origin, score))
        detections.sort(key=lambda d: -d.score)
        self.last_ms = (time.perf_counter() - t0) * 1e3
        return detections

    def _detection(self, box: FloatArray, score: float) -> Detection:
        if self.config.kind is LocatorKind.HOG:
            fx, fy, fw, fh = HOG_HEAD_SHOULDER
            head = np.array([box[0] + fx * box[2], box[1] + fy * box[3], fw * box[2], fh * box[3]])
        else:
            head = box.copy()
        return Detection(box, head, score)

    def _detect(self, crop: ImageU8) -> list[tuple[FloatArray, float]]:
        """The detector's boxes (x, y, w, h in ``crop``'s pixels) and scores."""
        import cv2

        found: list[tuple[FloatArray, float]] = []
        if self.config.kind is LocatorKind.HOG:
            hog_rects, hog_weights = self._hog.detectMultiScale(
                crop,
                hitThreshold=self.config.hog_hit_threshold,
                winStride=(8, 8),
                padding=(8, 8),
                scale=self.config.scale_step,
            )
            for hog_rect, hog_weight in zip(hog_rects, np.ravel(hog_weights), strict=False):
                found.append((np.asarray(hog_rect, dtype=np.float64), float(hog_weight)))
        else:
            gray = cv2.cvtColor(crop, cv2.COLOR_BGR2GRAY)
            rects, _, weights = self._cascade.detectMultiScale3(
                gray,
                scaleFactor=self.config.scale_step,
                minNeighbors=self.config.cascade_min_neighbours,
                minSize=(self.config.cascade_min_width_px, round(self.config.cascade_min_width_px * 18 / 22)),
                outputRejectLevels=True,
            )
            for rect, weight in zip(rects, np.ravel(weights), strict=False):
                found.append((np.asarray(rect, dtype=np.float64), float(weight)))
        return found


def _check_frame(frame: ImageU8) -> None:
    if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
        raise ValueError(f"want a BGR uint8 (H, W, 3) frame, got {frame.dtype} {frame.shape}")


def _cascade_path(name: str) -> str:
    import cv2

    folder = getattr(getattr(cv2, "data", None), "haarcascades", "")
    if not folder:
        raise BackendUnavailable(
            "this OpenCV ships no Haar cascades (cv2.data): install opencv-python-headless<5"
        )
    return str(folder) + name


# The head-and-shoulders outline in its box (u right, v down, both 0..1; the box is 0.48 m wide and the top
# quarter of a person's height tall, as the renderer's and the tracker's head_box): the head's ellipse
# without its bottom, the neck's sides, the shoulders sloping out, the arms' outer edges.
_OMEGA_ASPECT = 0.86  # height / width


@functools.lru_cache(maxsize=64)
def _omega_outline(width: int) -> tuple[list[npt.NDArray[np.float32]], int]:
    """Binary templates of the outline at ``width`` pixels, one per edge orientation (0, 45, 90, 135
    degrees of the gradient), each normalised by the outline's point count; and its height."""
    import cv2

    height = max(4, round(width * _OMEGA_ASPECT))
    pts: list[tuple[float, float, float]] = []  # u, v, tangent angle
    for th in np.linspace(-math.pi - 0.35, 0.35, 60):
        pts.append((0.5 + 0.177 * math.cos(th), 0.29 + 0.28 * math.sin(th), th + math.pi / 2.0))
    for side in (-1.0, 1.0):
        for v in np.linspace(0.57, 0.645, 5):
            pts.append((0.5 + side * 0.104, float(v), math.pi / 2.0))
        for k in np.linspace(0.0, 1.0, 20):
            pts.append((0.5 + side * (0.25 + 0.25 * k), 0.645 + 0.215 * k, math.atan2(0.215, side * 0.25)))
        for v in np.linspace(0.86, 1.0, 6):
            pts.append((0.5 + side * 0.49, float(v), math.pi / 2.0))
    templates = [np.zeros((height, width), np.float32) for _ in range(4)]
    for u, v, tangent in pts:
        x = min(width - 1, max(0, round(u * (width - 1))))
        y = min(height - 1, max(0, round(v * (height - 1))))
        # The gradient is normal to the outline; its orientation bin (mod 180 degrees).
        b = round(((tangent + math.pi / 2.0) % math.pi) / (math.pi / 4.0)) % 4
        templates[b][y, x] = 1.0
    total = float(sum(float(t.sum()) for t in templates))
    out = [
        np.asarray(cv2.GaussianBlur(t, (3, 3), 0), dtype=np.float32) / np.float32(total) for t in templates
    ]
    return out, height


def _omega(crop: ImageU8, c0: int, frame_width: int, config: PreLocatorConfig) -> list[Detection]:
    """Head-and-shoulder outlines in a band by oriented chamfer matching: the band's edges split by
    gradient orientation into four maps, each map's distance transform correlated with the outline's
    points of that orientation, so stripes (edges of one orientation everywhere) do not match a head; and a
    match whose head is full of edges (checks, which have both orientations) is dropped."""
    import cv2

    # Shrunk as the whole frame would be: a narrow band costs less, not more.
    shrink = min(1.0, config.omega_width_px / frame_width)
    small = (
        crop if shrink >= 1.0 else cv2.resize(crop, None, fx=shrink, fy=shrink, interpolation=cv2.INTER_AREA)
    )
    gray = cv2.cvtColor(np.asarray(small), cv2.COLOR_BGR2GRAY)
    gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3)
    edges = cv2.Canny(gray, 40, 100) > 0
    angle = (np.arctan2(gy, gx) % math.pi) / (math.pi / 4.0)
    bins = np.round(angle).astype(np.int32) % 4
    cap = 8.0
    dts = []
    for b in range(4):
        # An edge counts for its own orientation and half for the neighbouring ones.
        mask = np.where(edges & (bins == b), 0, 255).astype(np.uint8)
        dts.append(np.minimum(cv2.distanceTransform(mask, cv2.DIST_L2, 3), cap))
    h, w = gray.shape
    edge_sum = cv2.integral(edges.astype(np.uint8))  # (h + 1, w + 1)
    found: list[tuple[float, int, int, int, int]] = []
    width = config.omega_min_width_px
    while width <= w and width * _OMEGA_ASPECT <= 0.8 * h:
        templates, height = _omega_outline(width)
        score = np.zeros((h - height + 1, w - width + 1), np.float32)
        for b in range(4):
            if templates[b].any():
                score += cv2.matchTemplate(dts[b], templates[b], cv2.TM_CCORR)
        rel = score / width
        # Local minima under the threshold.
        local = rel <= cv2.erode(rel, np.ones((3, 3), np.uint8))
        ys, xs = np.nonzero(local & (rel < config.omega_max_score))
        # The head's inner rectangle: centre (0.5, 0.29) of the box, 0.6 of its radii (0.177, 0.28).
        hx0, hx1 = (
            round(width * (0.5 - 0.106)),
            max(round(width * (0.5 + 0.106)), round(width * (0.5 - 0.106)) + 1),
        )
        hy0, hy1 = (
            round(height * (0.29 - 0.168)),
            max(round(height * (0.29 + 0.168)), round(height * (0.29 - 0.168)) + 1),
        )
        inside = (
            edge_sum[ys + hy1, xs + hx1]
            - edge_sum[ys + hy0, xs + hx1]
            - edge_sum[ys + hy1, xs + hx0]
            + edge_sum[ys + hy0, xs + hx0]
        ) / float((hx1 - hx0) * (hy1 - hy0))
        plain = inside <= config.omega_max_head_edges
        ys, xs = ys[plain], xs[plain]
        for y, x in zip(ys, xs, strict=True):
            found.append((float(rel[y, x]), int(x), int(y), width, height))
        width = max(width + 1, round(width * config.omega_scale_step))
    found.sort()
    kept: list[tuple[float, int, int, int, int]] = []
    for f in found:  # non-maximum suppression: a box's centre must not lie in a better one
        cx, cy = f[1] + f[3] / 2.0, f[2] + f[4] / 2.0
        if all(not (k[1] <= cx < k[1] + k[3] and k[2] <= cy < k[2] + k[4]) for k in kept):
            kept.append(f)
        if len(kept) >= 8:
            break
    out = []
    for rel_score, bx, by, bw, bh in kept:
        box = np.array([bx / shrink + c0, by / shrink, bw / shrink, bh / shrink])
        out.append(Detection(box, box.copy(), 1.0 - rel_score / config.omega_max_score))
    return out
