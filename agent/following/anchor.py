"""A detector-anchored scale for the fine layer: the pre-locator's person detections hold the tracker's size.

The mean-shift tracker's size is a random walk of 1 % steps (Comaniciu's +-10 % test, scored by contrast:
docs/following.md, "Woman's success AUC gap"), and a pixel's difference in the converged centre sends the
walk one way or the other. A person detector's box, by contrast, has a size that does not drift: the HOG
people detector's window is 64 x 128 with the person about 96 px tall in it, whatever happened on the
frames before. So every ``every`` frames (and on the first frame after a re-acquisition) the caller runs
the detector in a window around the track (:meth:`HeadShoulderLocator.locate_around
<agent.following.prelocate.HeadShoulderLocator.locate_around>`) and gives the detections here.

* **Learnt at the start.** How a detector's box relates to the tracked box depends on who drew the tracked
  box (OTB's annotators draw a walker's box at 0.70-0.85 of HOG's height and 0.41-0.52 of its width, per
  sequence) and on the detector. At :meth:`ScaleAnchor.start` the detection that holds the start box's
  centre and whose height is within ``learn_ratio`` of it gives the ratios (start box / detection, height
  and width) and the centre's offset (in detection sizes). No detection there: the anchor stays unused
  for this target (``learnt`` False): the start box is the only truth the tracker gets.
* **Matched.** A detection maps to the box it implies (its centre moved by the offset, its sides times the
  ratios). It matches the track when the track's centre lies inside the implied box and the implied box's
  centre inside the track's, their IoU is at least ``min_iou``, and its height is within ``max_change``
  (log ratio) of the track's: a passer-by nearer the camera is larger, one beside the target is off-centre.
  The best match (highest IoU) is the measurement.
* **Blended.** The scale is a scalar in log space (HOG's box always has the window's 1:2 aspect, so its
  width says nothing its height does not: the tracker keeps its own aspect). A one-dimensional Kalman
  filter: each tracked frame adds ``process_sigma``^2 to the variance of the track's log size (the scale
  test's walk: at most 1 % a frame), a measurement has variance ``measurement_sigma``^2 (the spread of
  the detector's height ratio on a walker: 3-4 % between quartiles on OTB's Woman and Jogging), the gain
  ``P / (P + R)`` pulls the log size toward the measurement and the variance shrinks by ``1 - gain``.

Pure: numpy in, numpy out; the detector is run by the caller.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ["AnchorMeasurement", "ScaleAnchor", "ScaleAnchorConfig", "box_iou"]

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class ScaleAnchorConfig:
    every: int = 0  # tracked frames between detector runs; 0: the anchor is off
    detector: str = "hog"  # the pre-locator's kind (agent.following.prelocate.LocatorKind)
    detector_scale_step: float = 1.05  # its pyramid's step: a coarser one quantises the size it measures
    # The image is scaled by window_height_px / the start box's height for every search (HOG needs a
    # walker over about 100 px tall; the size it reports follows the image scale, so the scale is fixed).
    window_height_px: float = 130.0
    window_width: float = 1.5  # the search window's half-width, in track widths (at least the detector's)
    window_height: float = 1.1  # its half-height, in track heights
    learn_ratio: float = 0.5  # at the start, a detection's height within 1 -+ this of the start box's / 0.8
    min_iou: float = 0.3  # implied box against the track's
    max_change: float = 0.25  # |log(implied height / track height)| at most log(1 + this)
    process_sigma: float = 0.01  # the track's log size wanders this much a tracked frame
    measurement_sigma: float = 0.04  # a detection's implied log size scatters this much
    centre_gain: float = 0.0  # also pull the centre onto the implied box's by this share (0: size only)

    def __post_init__(self) -> None:
        if self.every < 0:
            raise ValueError(f"anchor every must be >= 0, got {self.every}")
        if self.detector not in ("hog", "upperbody", "omega"):
            raise ValueError(f"anchor detector must be hog, upperbody or omega, got {self.detector!r}")
        if not self.detector_scale_step > 1.0:
            raise ValueError(f"anchor detector_scale_step must be > 1, got {self.detector_scale_step}")
        if not self.window_height_px >= 16.0:
            raise ValueError(f"anchor window_height_px must be >= 16, got {self.window_height_px}")
        if not (self.process_sigma > 0.0 and self.measurement_sigma > 0.0):
            raise ValueError("anchor process_sigma and measurement_sigma must be > 0")
        if not 0.0 <= self.centre_gain <= 1.0:
            raise ValueError(f"anchor centre_gain must be in [0, 1], got {self.centre_gain}")
        if not (0.0 < self.learn_ratio < 1.0 and 0.0 <= self.min_iou < 1.0 and self.max_change > 0.0):
            raise ValueError("anchor learn_ratio in (0, 1), min_iou in [0, 1), max_change > 0 wanted")


@dataclass(frozen=True)
class AnchorMeasurement:
    """What a matched detection says: the box it implies, the factor to multiply the track's size by, and
    the centre to move to (the track's own unless ``centre_gain`` > 0)."""

    implied: FloatArray  # x, y, w, h
    factor: float
    centre: FloatArray
    gain: float


class ScaleAnchor:
    """One target's anchor. :meth:`start` with the start box and the detections around it, then each
    tracked frame :meth:`predict`, and on the frames the detector ran :meth:`observe`."""

    def __init__(self, config: ScaleAnchorConfig) -> None:
        self.config = config
        self.ratio = np.ones(2)  # tracked box / detection, width and height
        self.offset = np.zeros(2)  # tracked box's centre - detection's, in detection sizes
        self.learnt = False
        self.upscale = 1.0  # the detector's image scale, fixed at the start
        self._variance = 0.0  # of the track's log size since the last measurement
        self.measurements = 0

    @staticmethod
    def upscale_for(config: ScaleAnchorConfig, box: FloatArray) -> float:
        """The image scale every search of this target runs at: the start box's height to
        ``window_height_px``."""
        return config.window_height_px / float(box[3])

    def start(self, box: FloatArray, detections: list[FloatArray]) -> bool:
        """Learn the ratios from the start ``box`` and the detector's boxes around it, found at the image
        scale :meth:`upscale_for` gives (kept in ``upscale`` for the later searches); True if learnt."""
        x, y, w, h = (float(v) for v in box)
        self.upscale = self.upscale_for(self.config, np.asarray(box, dtype=np.float64))
        cx, cy = x + w / 2.0, y + h / 2.0
        # A walker's box is about 0.8 of HOG's height; any detection within learn_ratio of that holding
        # the start box's centre is the same person.
        nominal = h / 0.8
        best: FloatArray | None = None
        for d in detections:
            dx, dy, dw, dh = (float(v) for v in d)
            if not (dx <= cx <= dx + dw and dy <= cy <= dy + dh):
                continue
            if abs(dh / nominal - 1.0) > self.config.learn_ratio:
                continue
            if best is None or abs(dh / nominal - 1.0) < abs(float(best[3]) / nominal - 1.0):
                best = np.asarray(d, dtype=np.float64)
        self.learnt = best is not None
        self._variance = 0.0
        self.measurements = 0
        if best is None:
            return False
        size = best[2:]
        self.ratio = np.array([w, h]) / size
        self.offset = (np.array([cx, cy]) - (best[:2] + size / 2.0)) / size
        return True

    def implied(self, detection: FloatArray) -> FloatArray:
        """The tracked box a detection implies (the learnt offset and ratios applied)."""
        size = np.asarray(detection[2:], dtype=np.float64)
        centre = np.asarray(detection[:2], dtype=np.float64) + size / 2.0 + self.offset * size
        implied_size = size * self.ratio
        return np.concatenate([centre - implied_size / 2.0, implied_size])

    def predict(self) -> None:
        """One tracked frame: the track's size has wandered a little more since the last measurement."""
        self._variance += self.config.process_sigma**2

    def observe(self, box: FloatArray, detections: list[FloatArray]) -> AnchorMeasurement | None:
        """The matched detection's pull on the track ``box``, or None (no match, or not learnt)."""
        if not self.learnt:
            return None
        cfg = self.config
        x, y, w, h = (float(v) for v in box)
        centre = np.array([x + w / 2.0, y + h / 2.0])
        best: tuple[float, FloatArray] | None = None
        for d in detections:
            imp = self.implied(np.asarray(d, dtype=np.float64))
            ic = imp[:2] + imp[2:] / 2.0
            if not (imp[0] <= centre[0] <= imp[0] + imp[2] and imp[1] <= centre[1] <= imp[1] + imp[3]):
                continue
            if not (x <= ic[0] <= x + w and y <= ic[1] <= y + h):
                continue
            if abs(math.log(float(imp[3]) / h)) > math.log1p(cfg.max_change):
                continue
            iou = box_iou(imp, box)
            if iou >= cfg.min_iou and (best is None or iou > best[0]):
                best = (iou, imp)
        if best is None:
            return None
        imp = best[1]
        r = cfg.measurement_sigma**2
        # The variance is at least one frame's wander: a detection on consecutive frames is not a truth.
        p = max(self._variance, cfg.process_sigma**2)
        gain = p / (p + r)
        self._variance = (1.0 - gain) * p
        self.measurements += 1
        factor = math.exp(gain * math.log(float(imp[3]) / h))
        ic = imp[:2] + imp[2:] / 2.0
        return AnchorMeasurement(imp, factor, centre + cfg.centre_gain * (ic - centre), gain)


def box_iou(a: FloatArray, b: FloatArray) -> float:
    """Intersection over union of two (x, y, w, h) boxes."""
    ax, ay, aw, ah = (float(v) for v in a)
    bx, by, bw, bh = (float(v) for v in b)
    iw = max(0.0, min(ax + aw, bx + bw) - max(ax, bx))
    ih = max(0.0, min(ay + ah, by + bh) - max(ay, by))
    inter = iw * ih
    union = aw * ah + bw * bh - inter
    return inter / union if union > 0 else 0.0
