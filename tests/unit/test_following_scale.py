"""The discriminative scale-space filter (agent.following.scale) on synthetic frames whose target grows or
shrinks by known factors: the estimated size must follow the truth within a few per cent; and the mean
shift tracker with ``scale_search=ladder``."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from agent.following.meanshift import Features, MeanShiftTracker, ScaleSearch, TrackerConfig
from agent.following.otb import centre_errors
from agent.following.scale import ScaleFilter, ScaleFilterConfig
from agent.following.synthetic import CrossingScene, crossing_sequence


def _scene() -> tuple[np.ndarray, np.ndarray]:
    image, box = next(crossing_sequence(CrossingScene(frames=1, passer=False, seed=7)))
    return image, box


def _zoomed(image: np.ndarray, centre: np.ndarray, s: float, seed: int) -> np.ndarray:
    """The frame blown up by ``s`` about ``centre``, with fresh sensor noise."""
    m = np.array([[s, 0.0, centre[0] * (1.0 - s)], [0.0, s, centre[1] * (1.0 - s)]])
    warped = cv2.warpAffine(image, m, (image.shape[1], image.shape[0]), flags=cv2.INTER_LINEAR)
    noise = np.random.default_rng(seed).normal(0.0, 3.0, warped.shape)
    return np.clip(warped + noise, 0, 255).astype(np.uint8)


def _follow(scales: list[float]) -> list[float]:
    """Run the filter over frames zoomed by ``scales`` (the first 1); the estimated size over the true
    one, per frame."""
    image, box = _scene()
    centre = box[:2] + box[2:] / 2.0
    size0 = box[2:].astype(np.float64)
    sf = ScaleFilter()
    sf.start(_zoomed(image, centre, scales[0], 0), centre, size0 * scales[0])
    size = size0 * scales[0]
    ratios = []
    for i, s in enumerate(scales[1:], start=1):
        frame = _zoomed(image, centre, s, i)
        factor, _ = sf.estimate(frame, centre, size)
        size = size * factor
        sf.learn(frame, centre, size)
        ratios.append(float(size[1] / (size0[1] * s)))
    return ratios


@pytest.mark.parametrize("rate", [1.01, 1.0 / 1.01])
def test_follows_a_target_growing_or_shrinking_one_percent_a_frame(rate: float) -> None:
    # 30 frames: to 1.35 times the size, or to 0.74 of it.
    ratios = _follow([rate**i for i in range(31)])
    assert max(abs(r - 1.0) for r in ratios) < 0.03


def test_follows_a_jump_within_the_ladder() -> None:
    # 8 % in one frame (two rungs of 1.04), then still: the filter takes it at once.
    ratios = _follow([1.0] * 5 + [1.08] * 10)
    assert abs(ratios[4] - 1.0) < 0.03
    assert max(abs(r - 1.0) for r in ratios) < 0.03


def test_holds_a_target_that_keeps_its_size() -> None:
    ratios = _follow([1.0] * 40)
    assert max(abs(r - 1.0) for r in ratios) < 0.02


def test_bad_config_and_order() -> None:
    with pytest.raises(ValueError):
        ScaleFilterConfig(scales=16)
    with pytest.raises(ValueError):
        ScaleFilterConfig(step=1.0)
    with pytest.raises(ValueError):
        ScaleFilterConfig(learning_rate=0.0)
    with pytest.raises(ValueError):
        TrackerConfig(scale_rungs=2)
    image, box = _scene()
    with pytest.raises(RuntimeError):
        ScaleFilter().estimate(image, box[:2], box[2:])
    with pytest.raises(ValueError):
        ScaleFilter().start(image, box[:2], np.array([1.0, 5.0]))


@pytest.mark.parametrize("features", [Features.FULL, Features.COLOUR])
def test_tracker_with_the_ladder_follows_a_growing_target(features: Features) -> None:
    # Over six scenes, not one: on a single scene the ladder's result is a knife edge (seed 3 passed a
    # 10 px / 7 % test by luck and failed it after a change to the kernel's rounding; seeds 0-5 ended 1-30 %
    # off before that change and after it alike). A fixed size ends 28 % short.
    last = []
    for seed in range(6):
        frames = list(crossing_sequence(CrossingScene(frames=40, passer=False, seed=seed)))
        tracker = MeanShiftTracker(TrackerConfig(features=features, scale_search=ScaleSearch.LADDER))
        boxes, truth = [], []
        for i, (image, box) in enumerate(frames):
            # Blown up about the target's centre, 1 % a frame: to 1.39 times by the last frame.
            s = 1.0 + 0.01 * i
            cx, cy = box[0] + box[2] / 2, box[1] + box[3] / 2
            m = np.array([[s, 0, cx * (1 - s)], [0, s, cy * (1 - s)]])
            warped = cv2.warpAffine(image, m, (image.shape[1], image.shape[0]), flags=cv2.INTER_LINEAR)
            truth.append([cx - s * box[2] / 2, cy - s * box[3] / 2, s * box[2], s * box[3]])
            if i == 0:
                tracker.start(warped, truth[0])
                boxes.append(truth[0])
            else:
                boxes.append(tracker.update(warped).box)
        b, t = np.array(boxes), np.array(truth)
        # On the target throughout: the mean shift's centre has some vertical play over the stripes.
        assert np.all(centre_errors(b, t) < 0.25 * t[:, 3]), seed
        last.append(float(np.mean(np.abs(b[-10:, 3] / t[-10:, 3] - 1.0))))
    # The size keeps up with the growth in the typical scene, where a fixed size would end 28 % short (no
    # closer than the contrast test's walk, about 10 % short: the ladder read off centre takes part of the
    # centre's play for a change of scale, which is why it is not the default).
    assert float(np.median(last)) < 0.15, last
    assert sum(e < 0.2 for e in last) >= 4, last
