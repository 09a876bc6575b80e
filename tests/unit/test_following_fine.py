"""The fine layer: the pre-locator starts the tracker in the band and feeds it while the target is hidden;
and the real HOG detector on a real OTB frame (skipped without ../shared)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from agent.following.fine import FineLayer, FineLayerConfig, FineState
from agent.following.meanshift import Silhouette, TrackerConfig
from agent.following.prelocate import Detection, HeadShoulderLocator, LocatorKind, PreLocatorConfig
from agent.following.synthetic import CrossingScene, crossing_sequence


class ScriptedLocator:
    """A pre-locator whose answers are set by the test (the real one needs real people); it records the
    bands it was asked about."""

    def __init__(self) -> None:
        self.answer: list[Detection] = []
        self.bands: list[tuple[int, int] | None] = []

    def locate(self, frame: np.ndarray, band: tuple[int, int] | None = None) -> list[Detection]:
        self.bands.append(band)
        return list(self.answer)


def test_starts_in_the_band_and_reacquires_with_the_prelocator() -> None:
    frames = list(crossing_sequence(CrossingScene(frames=40, passer=False, seed=2)))
    locator = ScriptedLocator()
    layer = FineLayer(
        locator,
        FineLayerConfig(
            tracker=TrackerConfig(silhouette=Silhouette.ELLIPSE), lost_after_frames=4, correct_every=0
        ),
    )
    # Nobody found yet: searching, in the band asked for.
    assert layer.update(frames[0][0], band=(40, 200)).state is FineState.SEARCHING
    assert locator.bands == [(40, 200)]
    box = frames[1][1]
    locator.answer = [Detection(box, box, 1.0)]
    first = layer.update(frames[1][0], band=(40, 200))
    assert first.state is FineState.TRACKING and first.prelocated
    for image, truth in frames[2:20]:
        result = layer.update(image, band=(40, 200))
        assert result.state is FineState.TRACKING and not result.prelocated
        assert result.box is not None and np.hypot(*(result.box[:2] - truth[:2])) < 6.0
    # The view jumps (the robot turned): occluded, then lost; the pre-locator is asked every
    # prelocate_every frames and its box brings the tracker back.
    locator.answer = []
    states = []
    for image, _ in frames[20:30]:
        states.append(layer.update(np.roll(image, 150, axis=1), band=(0, 320)))
    assert states[0].state is FineState.OCCLUDED
    assert any(s.state is FineState.LOST for s in states)
    assert sum(s.prelocated for s in states) == 3  # every prelocate_every (3) occluded frames
    image, truth = frames[30]
    moved = truth + np.array([150.0, 0.0, 0.0, 0.0])
    locator.answer = [Detection(moved, moved, 1.0)]
    results = [layer.update(np.roll(frames[i][0], 150, axis=1), band=(0, 320)) for i in range(30, 36)]
    back = [r for r in results if r.state is FineState.TRACKING]
    assert back, [r.state for r in results]
    assert (
        back[-1].box is not None
        and np.hypot(*(back[-1].box[:2] - (frames[35][1][:2] + np.array([150.0, 0.0])))) < 8.0
    )


def test_the_prelocator_corrects_the_box_while_tracking_but_not_onto_someone_larger() -> None:
    frames = list(crossing_sequence(CrossingScene(frames=12, passer=False, seed=2)))
    locator = ScriptedLocator()
    layer = FineLayer(locator, FineLayerConfig(tracker=TrackerConfig(silhouette=Silhouette.ELLIPSE)))
    box = frames[0][1]
    locator.answer = [Detection(box, box, 1.0)]
    layer.update(frames[0][0])
    # A detection of twice the size (a passer-by nearer the camera) overlapping the box: ignored.
    big = np.array([box[0] - box[2] / 2, box[1] - box[3] / 2, 2 * box[2], 2 * box[3]])
    locator.answer = [Detection(big, big, 1.0)]
    results = [layer.update(image) for image, _ in frames[1:4]]
    assert results[-1].prelocated and results[-1].box is not None and results[-1].box[2] < 1.3 * box[2]
    # One of the target's size a few pixels off: the box is pulled onto it.
    shifted = frames[6][1] + np.array([4.0, 3.0, 0.0, 0.0])
    locator.answer = [Detection(shifted, shifted, 1.0)]
    results = [layer.update(image) for image, _ in frames[4:7]]
    assert results[-1].prelocated and results[-1].box is not None
    assert np.hypot(*(results[-1].box[:2] - shifted[:2])) < 1.0


def test_hog_finds_the_runners_of_real_jogging(shared_data: Path) -> None:
    # OTB Jogging frame 1, scaled by 1.4 so the runners (about 100 px tall) fill HOG's 64 x 128 window.
    image = cv2.imread(str(shared_data / "person/Jogging/img/0001.jpg"))
    big = cv2.resize(image, None, fx=1.4, fy=1.4)
    truths = []
    for name in ("groundtruth_rect.1.txt", "groundtruth_rect.2.txt"):
        x, y, w, h = (
            float(v) for v in (shared_data / "person/Jogging" / name).read_text().split("\n")[0].split(",")
        )
        truths.append(1.4 * np.array([x - 1 + w / 2, y - 1 + h / 2]))
    locator = HeadShoulderLocator(PreLocatorConfig(kind=LocatorKind.HOG, max_width_px=1000, scale_step=1.05))
    found = locator.locate(big)
    centres = [d.box[:2] + d.box[2:] / 2 for d in found]
    # Each runner has a detection within 25 px of its box centre (about a quarter of its height) ...
    for truth in truths:
        assert min(np.hypot(*(c - truth)) for c in centres) < 25.0
    # ... and a band around the left runner keeps the right one out.
    left = min(truths, key=lambda t: t[0])
    banded = locator.locate(big, band=(int(left[0]) - 40, int(left[0]) + 40))
    assert banded and all(abs(d.box[0] + d.box[2] / 2 - left[0]) < 40 for d in banded)
    assert locator.last_ms > 0.0
    # The upper-body cascade loads from the wheel and runs (what it finds on these small runners is not
    # asserted: it is made for a person close to the camera).
    HeadShoulderLocator(PreLocatorConfig(kind=LocatorKind.UPPER_BODY)).locate(image)
