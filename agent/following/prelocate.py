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
import logging
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
        if self.config.kind is LocatorKind.HOG:
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

        if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
            raise ValueError(f"want a BGR uint8 (H, W, 3) frame, got {frame.dtype} {frame.shape}")
        t0 = time.perf_counter()
        _height, width = frame.shape[:2]
        c0, c1 = (0, width) if band is None else (max(0, int(band[0])), min(width, int(band[1])))
        if c1 - c0 < 8:
            self.last_ms = (time.perf_counter() - t0) * 1e3
            return []
        crop: ImageU8 = frame[:, c0:c1]
        shrink = min(1.0, self.config.max_width_px / crop.shape[1])
        if shrink < 1.0:
            crop = np.asarray(cv2.resize(crop, None, fx=shrink, fy=shrink, interpolation=cv2.INTER_AREA))
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
        detections = []
        for found_rect, score in found:
            box = found_rect / shrink + np.array([c0, 0.0, 0.0, 0.0])
            centre_x = box[0] + box[2] / 2.0
            if not c0 <= centre_x < c1:
                continue
            if self.config.kind is LocatorKind.HOG:
                fx, fy, fw, fh = HOG_HEAD_SHOULDER
                head = np.array([box[0] + fx * box[2], box[1] + fy * box[3], fw * box[2], fh * box[3]])
            else:
                head = box.copy()
            detections.append(Detection(box, head, score))
        detections.sort(key=lambda d: -d.score)
        self.last_ms = (time.perf_counter() - t0) * 1e3
        log.debug("%d people in columns %d-%d in %.1f ms", len(detections), c0, c1, self.last_ms)
        return detections


def _cascade_path(name: str) -> str:
    import cv2

    folder = getattr(getattr(cv2, "data", None), "haarcascades", "")
    if not folder:
        raise BackendUnavailable(
            "this OpenCV ships no Haar cascades (cv2.data): install opencv-python-headless<5"
        )
    return str(folder) + name
