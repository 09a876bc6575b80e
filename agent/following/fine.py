"""The fine layer as one object: the pre-locator starts the tracker inside the coarse layer's band and
helps it re-acquire; the tracker does the rest.

Per frame the caller gives the band of image columns where the coarse layer (RFID) puts the user, or None
for the whole width. With no target yet, the pre-locator searches the band and the tracker starts on the
best head-shoulder box (``SEARCHING`` until one is found). While the tracker reports the target occluded,
the pre-locator runs in the band every ``prelocate_every`` frames and its boxes go to the tracker as
re-acquisition hints; the tracker keeps its model, so a passer-by found by the detector is accepted only
if it matches the user's colours and texture. After ``lost_after_frames`` occluded frames the state is
``LOST`` (the follower stops); the search goes on.
"""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from agent.following.meanshift import MeanShiftTracker, Silhouette, TrackerConfig, TrackState
from agent.following.prelocate import Detection

__all__ = ["FineLayer", "FineLayerConfig", "FineResult", "FineState", "Locator"]

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
    tracker: TrackerConfig = field(default_factory=lambda: TrackerConfig(silhouette=Silhouette.OMEGA))
    prelocate_every: int = 5  # occluded frames between pre-locator runs
    lost_after_frames: int = 30


@dataclass(frozen=True)
class FineResult:
    state: FineState
    box: FloatArray | None  # x, y, w, h of the head and shoulders; None while searching
    rho: float
    prelocated: bool  # the pre-locator ran this frame


class FineLayer:
    def __init__(self, locator: Locator, config: FineLayerConfig | None = None) -> None:
        self.config = config or FineLayerConfig()
        self._locator = locator
        self._tracker: MeanShiftTracker | None = None

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
        if result.state is TrackState.TRACKING:
            state = FineState.TRACKING
        elif result.frames_lost >= cfg.lost_after_frames:
            state = FineState.LOST
        else:
            state = FineState.OCCLUDED
        return FineResult(state, result.box, result.rho, prelocated)

    def reset(self) -> None:
        """Forget the target (another user, or the coarse layer says the tracked one is not the tag's)."""
        self._tracker = None
