"""The fine layer as one object: the pre-locator starts the tracker inside the coarse layer's band and
helps it re-acquire; the tracker does the rest.

Per frame the caller gives the band of image columns where the coarse layer (RFID) puts the user, or None
for the whole width. With no target yet, the pre-locator searches the band and the tracker starts on the
best head-shoulder box (``SEARCHING`` until one is found). While the tracker reports the target occluded,
the pre-locator runs in the band every ``prelocate_every`` frames and its boxes go to the tracker as
re-acquisition hints; the tracker keeps its model, so a passer-by found by the detector is accepted only
if it matches the user's colours and texture. After ``lost_after_frames`` occluded frames the state is
``LOST`` (the follower stops); the search goes on. While tracking, the pre-locator runs every
``correct_every`` frames: a detection of the target's size overlapping the box pulls the tracker onto it
(its scale lags behind a user the robot closes in on), and the running offset between the detections and
the mean shift's mode is added to the reported box.
"""

from __future__ import annotations

import enum
import logging
import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from agent.following.anchor import box_iou
from agent.following.meanshift import ColourSpace, MeanShiftTracker, Silhouette, TrackerConfig, TrackState
from agent.following.prelocate import Detection

__all__ = ["FineLayer", "FineLayerConfig", "FineResult", "FineState", "Locator", "camera_band"]

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
ImageU8 = npt.NDArray[np.uint8]


class Locator(Protocol):
    """What the fine layer needs of a pre-locator (``agent.following.prelocate.HeadShoulderLocator``)."""

    def locate(self, frame: ImageU8, band: tuple[int, int] | None = None) -> list[Detection]: ...


class FineState(enum.StrEnum):
    SEARCHING = "searching"  # no target yet: the pre-locator looks in the band
    TRACKING = "tracking"
    OCCLUDED = "occluded"  # coasting, searching with the tracker and the pre-locator
    LOST = "lost"  # occluded too long: the follower should stop; the search goes on


@dataclass(frozen=True)
class FineLayerConfig:
    # Head-and-shoulder boxes; hue-saturation colour: a robot's camera sees the light change.
    tracker: TrackerConfig = field(
        default_factory=lambda: TrackerConfig(silhouette=Silhouette.OMEGA, colour_space=ColourSpace.HSV)
    )
    prelocate_every: int = 3  # occluded frames between pre-locator runs
    # While tracking, the pre-locator runs every this many frames (0: never) and a detection overlapping
    # the box (IoU >= correct_iou) pulls its centre and size halfway: the scale test lags behind a user
    # the robot closes in on.
    correct_every: int = 3
    correct_iou: float = 0.3
    correct_gain: float = 1.0
    correct_size: float = 0.25  # a detection's width within this share of the box's
    # The reported box is the tracker's plus the running mean (rate offset_rate) of how far, in box
    # sizes, the detections lay from where the mean shift had converged: the colour model's mode need not
    # be the head box's centre (on the rendered user it settles 10-20 px high), and the detector says
    # where the box is. 0: the tracker's box as it is.
    offset_rate: float = 0.3
    lost_after_frames: int = 30


@dataclass(frozen=True)
class FineResult:
    state: FineState
    box: FloatArray | None  # x, y, w, h of the head and shoulders; None while searching
    rho: float
    prelocated: bool  # the pre-locator ran this frame


def camera_band(
    probability: float,
    bearing_rad: float,
    focal_px: float,
    cx_px: float,
    width_px: int,
    half_width_rad: float = math.radians(25.0),
    min_probability: float = 0.2,
) -> tuple[int, int] | None:
    """The columns where the coarse layer puts the user: ``probability`` and ``bearing_rad`` of its window in
    the camera's view (``CoarseFilter.within(0, half_fov)``), turned into the columns of bearing +-
    ``half_width_rad`` (a level pinhole camera: u = cx - f tan(bearing)). None (the whole width) while the
    window holds less than ``min_probability``: the RFID layer cannot say where, so it does not narrow.

    The half-width is wide on purpose: within the camera's view the coarse layer's bearing is right to a
    few degrees at the median but tens at the tail (docs/following.md), and the band only has to keep
    people on the far side of the view out of the pre-locator's candidates."""
    if not (probability >= min_probability) or not math.isfinite(bearing_rad):
        return None
    lo = cx_px - focal_px * math.tan(min(bearing_rad + half_width_rad, 1.5))
    hi = cx_px - focal_px * math.tan(max(bearing_rad - half_width_rad, -1.5))
    c0, c1 = max(0, math.floor(lo)), min(width_px, math.ceil(hi))
    return (c0, c1) if c1 - c0 >= 8 else None


class FineLayer:
    def __init__(self, locator: Locator, config: FineLayerConfig | None = None) -> None:
        self.config = config or FineLayerConfig()
        self._locator = locator
        self._tracker: MeanShiftTracker | None = None
        self._frames = 0
        self._offset = np.zeros(2)  # detection minus mean-shift mode, in box sizes

    def update(self, frame: ImageU8, band: tuple[int, int] | None = None) -> FineResult:
        cfg = self.config
        if self._tracker is None:
            detections = self._locator.locate(frame, band)
            if not detections:
                return FineResult(FineState.SEARCHING, None, 0.0, True)
            tracker = MeanShiftTracker(cfg.tracker)
            tracker.start(frame, detections[0].head_shoulder)
            self._tracker = tracker
            log.info("target started on a pre-located box %s", np.round(detections[0].head_shoulder))
            return FineResult(FineState.TRACKING, tracker.box, 1.0, True)
        tracker = self._tracker
        hints: list[FloatArray] = []
        prelocated = False
        if tracker.state is TrackState.OCCLUDED and (tracker.frames_lost + 1) % cfg.prelocate_every == 0:
            hints = [d.head_shoulder for d in self._locator.locate(frame, band)]
            prelocated = True
        result = tracker.update(frame, hints)
        self._frames += 1
        if (
            result.state is TrackState.TRACKING
            and cfg.correct_every > 0
            and self._frames % cfg.correct_every == 0
            and not prelocated
        ):
            prelocated = True
            found = [d.head_shoulder for d in self._locator.locate(frame, band)]
            # The same person: overlapping, and of about the same size (a passer-by crossing nearer the
            # camera is larger).
            width = float(result.box[2])
            alike = [b for b in found if abs(float(b[2]) - width) <= cfg.correct_size * width]
            best = max(alike, key=lambda b: box_iou(b, result.box), default=None)
            if best is not None and box_iou(best, result.box) >= cfg.correct_iou:
                size = result.box[2:]
                seen = (best[:2] + best[2:] / 2.0 - result.box[:2] - size / 2.0) / size
                self._offset += cfg.offset_rate * (seen - self._offset)
                tracker.correct(best, cfg.correct_gain)
                return FineResult(FineState.TRACKING, tracker.box, result.rho, prelocated)
        if result.state is TrackState.TRACKING:
            state = FineState.TRACKING
        elif result.frames_lost >= cfg.lost_after_frames:
            state = FineState.LOST
        else:
            state = FineState.OCCLUDED
        box = result.box
        if state is FineState.TRACKING:
            box = result.box + np.concatenate([self._offset * result.box[2:], np.zeros(2)])
        return FineResult(state, box, result.rho, prelocated)

    def reset(self) -> None:
        """Forget the target (another user, or the coarse layer says the tracked one is not the tag's)."""
        self._tracker = None
        self._offset = np.zeros(2)
