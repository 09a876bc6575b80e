"""The detector-anchored scale (``agent.following.anchor``): learning the detector-to-box ratios at the
start box, matching, the Kalman blend of the log size; the tracker's ``rescale``; ``eval track``'s
``--param anchor_...``; and, with ../shared, HOG's walker on OTB Woman's first frame found at a fixed image
scale and the anchor learnt and measuring on her first frames."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from agent.commands.eval_track import anchor_config, split_params, track_target
from agent.following.anchor import ScaleAnchor, ScaleAnchorConfig, box_iou
from agent.following.meanshift import MeanShiftTracker, TrackerConfig
from drivers.errors import ConfigError

# A walker's box and a HOG box around it: the box 0.8 of its height and 0.4 of its width, centred.
BOX = np.array([100.0, 50.0, 20.0, 80.0])
HOG = np.array([85.0, 40.0, 50.0, 100.0])


def _anchor(**kw: float) -> ScaleAnchor:
    anchor = ScaleAnchor(ScaleAnchorConfig(every=5, **kw))  # type: ignore[arg-type]
    assert anchor.start(BOX, [HOG])
    return anchor


def test_learns_the_ratio_and_offset_at_the_start_box() -> None:
    anchor = _anchor()
    np.testing.assert_allclose(anchor.ratio, [0.4, 0.8])
    np.testing.assert_allclose(anchor.offset, [0.0, 0.0])
    np.testing.assert_allclose(anchor.implied(HOG), BOX)
    # The same detection 10 % larger about the same centre implies a box 10 % larger.
    bigger = np.array([82.5, 35.0, 55.0, 110.0])
    np.testing.assert_allclose(anchor.implied(bigger)[2:], BOX[2:] * 1.1)
    assert anchor.upscale == pytest.approx(130.0 / 80.0)


@pytest.mark.parametrize(
    "detections",
    [
        [],
        [np.array([200.0, 40.0, 50.0, 100.0])],  # someone beside: the start box's centre is not in it
        [np.array([60.0, 0.0, 100.0, 200.0])],  # twice the nominal height (0.8 of it is the walker's)
    ],
)
def test_not_learnt_without_a_detection_of_the_start_box_and_then_unused(detections: list) -> None:
    anchor = ScaleAnchor(ScaleAnchorConfig(every=5))
    assert not anchor.start(BOX, detections)
    assert not anchor.learnt
    assert anchor.observe(BOX, [HOG]) is None


def test_a_matching_detection_pulls_the_log_size_by_the_kalman_gain() -> None:
    cfg = ScaleAnchorConfig(every=5, process_sigma=0.01, measurement_sigma=0.04)
    anchor = ScaleAnchor(cfg)
    anchor.start(BOX, [HOG])
    for _ in range(10):
        anchor.predict()
    track = np.array([102.0, 55.0, 18.0, 72.0])  # the track shrank to 0.9
    m = anchor.observe(track, [HOG])
    assert m is not None
    p, r = 10 * 0.01**2, 0.04**2
    assert m.gain == pytest.approx(p / (p + r))
    assert m.factor == pytest.approx(math.exp(m.gain * math.log(80.0 / 72.0)))
    np.testing.assert_allclose(m.centre, track[:2] + track[2:] / 2)  # size only by default
    # Right after a measurement the variance is small: the next pull is weaker.
    anchor.predict()
    m2 = anchor.observe(track, [HOG])
    assert m2 is not None and m2.gain < m.gain
    assert anchor.measurements == 2


def test_repeated_measurements_hold_the_size_against_a_drift() -> None:
    anchor = _anchor()
    size = 1.0
    for _ in range(60):  # the track shrinks 1 % a frame; a detection every 5th frame
        for _ in range(5):
            size *= 0.99
            anchor.predict()
        track = np.concatenate([BOX[:2] + BOX[2:] * (1 - size) / 2, BOX[2:] * size])
        m = anchor.observe(track, [HOG])
        assert m is not None
        size *= m.factor
    # Without the anchor 0.99^300 = 0.05; with it the size settles a few per cent under the truth.
    assert 0.85 < size <= 1.0


@pytest.mark.parametrize(
    ("detection", "why"),
    [
        (np.array([130.0, 40.0, 50.0, 100.0]), "off-centre: a passer-by beside the target"),
        (np.array([70.0, 10.0, 80.0, 160.0]), "a passer-by nearer the camera: 1.6 times the height"),
        (np.array([98.0, 66.0, 24.0, 48.0]), "a much smaller person"),
    ],
)
def test_a_detection_that_is_not_the_target_is_not_matched(detection: np.ndarray, why: str) -> None:
    assert _anchor().observe(BOX, [detection]) is None, why


def test_the_best_matching_detection_wins_and_centre_gain_moves_the_centre() -> None:
    anchor = _anchor(centre_gain=1.0)
    for _ in range(20):
        anchor.predict()
    shifted = HOG + np.array([4.0, 2.0, 0.0, 0.0])
    stranger = np.array([118.0, 40.0, 50.0, 100.0])  # IoU with the track lower
    m = anchor.observe(BOX, [stranger, shifted])
    assert m is not None
    np.testing.assert_allclose(m.implied, anchor.implied(shifted))
    np.testing.assert_allclose(m.centre, BOX[:2] + BOX[2:] / 2 + [4.0, 2.0])
    assert box_iou(BOX, BOX) == pytest.approx(1.0)


def test_config_is_checked() -> None:
    with pytest.raises(ValueError, match="every"):
        ScaleAnchorConfig(every=-1)
    with pytest.raises(ValueError, match="detector"):
        ScaleAnchorConfig(detector="yolo")
    with pytest.raises(ValueError, match="centre_gain"):
        ScaleAnchorConfig(centre_gain=2.0)


def test_rescale_keeps_the_aspect_within_the_scale_limits() -> None:
    frame = np.full((120, 160, 3), 90, np.uint8)
    frame[30:90, 60:90] = (20, 40, 200)
    tracker = MeanShiftTracker(TrackerConfig(max_scale=1.5))
    tracker.start(frame, (60.0, 30.0, 30.0, 60.0))
    tracker.rescale(1.2)
    np.testing.assert_allclose(tracker.box, [57.0, 24.0, 36.0, 72.0])
    tracker.rescale(2.0, centre=np.array([80.0, 60.0]))  # clipped at 1.5 times the start size
    np.testing.assert_allclose(tracker.box, [57.5, 15.0, 45.0, 90.0])
    with pytest.raises(ValueError, match="finite"):
        tracker.rescale(0.0)


def test_eval_track_params_split_and_parse() -> None:
    tracker, anchor = split_params(["scale_gain=0.1", "anchor_every=5", "anchor_centre_gain=0.5"])
    assert tracker == ["scale_gain=0.1"]
    cfg = anchor_config(anchor)
    assert (cfg.every, cfg.centre_gain, cfg.detector) == (5, 0.5, "hog")
    assert anchor_config(["anchor_detector=upperbody"]).detector == "upperbody"
    with pytest.raises(ConfigError, match="anchor_every"):
        anchor_config(["anchor_evry=5"])
    with pytest.raises(ConfigError, match="not a int"):
        anchor_config(["anchor_every=often"])
    with pytest.raises(ConfigError, match="detector"):
        anchor_config(["anchor_detector=yolo"])


def test_hog_finds_woman_at_a_fixed_scale_and_the_anchor_measures(shared_data: Path) -> None:
    import cv2

    from agent.following.otb import load_sequence
    from agent.following.prelocate import HeadShoulderLocator, PreLocatorConfig

    sequence = load_sequence(shared_data / "person/Woman")
    target = sequence.targets[0]
    box = target.boxes[0]  # 21 x 95 px: HOG's walker is 96 px tall, so scaled up to 130
    frame = np.asarray(cv2.imread(str(sequence.frames[0])), dtype=np.uint8)
    locator = HeadShoulderLocator(PreLocatorConfig(scale_step=1.05))
    found = locator.locate_around(frame, box, ScaleAnchor.upscale_for(ScaleAnchorConfig(), box))
    centre = box[:2] + box[2:] / 2
    held = [d.box for d in found if d.box[0] <= centre[0] <= d.box[0] + d.box[2]]
    assert held and 0.7 <= box[3] / held[0][3] <= 0.9
    # Tracked with the anchor over 40 frames: learnt at the first box, measuring after.
    boxes, timing = track_target(list(sequence.frames[:40]), box, TrackerConfig(), ScaleAnchorConfig(every=5))
    assert timing["anchor_learnt"] == 1.0 and timing["anchor_measurements"] >= 1
    truth = target.boxes[:40]
    errors = np.hypot(*(boxes[:, :2] + boxes[:, 2:] / 2 - truth[:, :2] - truth[:, 2:] / 2).T)
    assert float(np.median(errors)) < 20.0
