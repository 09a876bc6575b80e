"""eval follow's pieces: the coarse layer's band in image columns, the omega pre-locator on a drawn head and
shoulders, hue-saturation colour under a change of light, the identity-switch and re-acquisition scoring,
and the command end to end on a short stretch of a scenario world."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from agent.commands.eval_follow import _Frame, _reacquire, _switches
from agent.following.fine import camera_band
from agent.following.meanshift import ColourSpace, MeanShiftTracker, Silhouette, TrackerConfig
from agent.following.prelocate import HeadShoulderLocator, LocatorKind, PreLocatorConfig

ROOT = Path(__file__).resolve().parents[2]


def test_camera_band_centres_on_the_bearing_and_gives_up_when_unsure() -> None:
    f, cx = 457.0, 319.5
    band = camera_band(0.6, 0.0, f, cx, 640)
    assert band is not None and band[0] < 320 < band[1]
    left = camera_band(0.6, math.radians(20.0), f, cx, 640)  # to the left: lower columns
    assert left is not None and left[0] == 0 and left[1] < band[1]
    assert camera_band(0.1, 0.0, f, cx, 640) is None  # the window holds too little
    assert camera_band(0.6, math.nan, f, cx, 640) is None


def _head_and_shoulders(x0: int, y0: int, w: int) -> np.ndarray:
    img = np.full((240, 320, 3), (170, 180, 190), np.uint8)
    h = round(w * 0.86)
    cv2.ellipse(
        img,
        (x0 + w // 2, y0 + round(0.29 * h)),
        (round(0.177 * w), round(0.28 * h)),
        0,
        0,
        360,
        (40, 50, 70),
        -1,
    )
    body = np.array(
        [
            [x0 + w // 2 - w // 4, y0 + round(0.645 * h)],
            [x0 + w // 2 + w // 4, y0 + round(0.645 * h)],
            [x0 + w, y0 + round(0.86 * h)],
            [x0 + w, 240],
            [x0, 240],
            [x0, y0 + round(0.86 * h)],
        ],
        np.int32,
    )
    cv2.fillPoly(img, [body], (40, 40, 190))
    return img


def test_omega_prelocator_finds_a_drawn_head_and_shoulders() -> None:
    locator = HeadShoulderLocator(PreLocatorConfig(kind=LocatorKind.OMEGA))
    found = locator.locate(_head_and_shoulders(100, 40, 110))
    assert found
    x, y, w, _ = found[0].head_shoulder
    assert abs(x + w / 2 - 155) < 15 and abs(y - 40) < 15 and 80 < w < 140
    assert not locator.locate(np.full((240, 320, 3), 128, np.uint8))  # a blank frame holds nobody
    # A checked shirt filling the frame: edges of every orientation everywhere, but no plain head.
    yy, xx = np.mgrid[0:240, 0:320]
    checks = np.where(((yy // 12) + (xx // 12)) % 2 == 0, 40, 200).astype(np.uint8)
    assert not locator.locate(np.dstack([checks] * 3))


def test_hsv_colour_holds_through_a_change_of_light() -> None:
    img = _head_and_shoulders(100, 40, 110)
    brighter = cv2.convertScaleAbs(img, alpha=1.15)
    box = (100.0, 40.0, 110.0, 95.0)
    rhos = {}
    for space in ColourSpace:
        tracker = MeanShiftTracker(TrackerConfig(silhouette=Silhouette.OMEGA, colour_space=space))
        tracker.start(img, box)
        rhos[space] = tracker.update(brighter).rho_colour
    assert rhos[ColourSpace.HSV] > rhos[ColourSpace.BGR] + 0.1


def test_switches_count_runs_on_someone_else() -> None:
    assert _switches(["user", "user", None, "user"], "user") == 0
    assert _switches(["user", "p1", "user"], "user") == 0  # one frame on the occluder: not a switch
    assert _switches(["user", "p1", "p1", "p1", "p1", "user", "p2", "p2", "p2"], "user") == 2
    # Frames on the occluder either side of an occlusion (not tracking: None) are not a run.
    assert _switches(["user", "p1", "p1", None, None, "p1", "user"], "user") == 0


def _frame(t: float, state: str, visible: float, centre_x: float) -> _Frame:
    truth = np.array([100.0, 50.0, 40.0, 40.0])
    return _Frame(t, state, np.array([centre_x - 20.0, 50.0, 40.0, 40.0]), truth, visible, None)


def test_reacquire_times_each_full_occlusion() -> None:
    frames = [
        _frame(0.0, "tracking", 1.0, 120.0),
        _frame(0.1, "occluded", 0.0, 160.0),
        _frame(0.2, "occluded", 0.0, 160.0),
        _frame(0.3, "occluded", 1.0, 160.0),
        _frame(0.4, "tracking", 1.0, 125.0),
        _frame(0.5, "occluded", 0.05, 200.0),
        _frame(0.6, "tracking", 1.0, 200.0),  # tracking, but 80 px off: not back
    ]
    times = _reacquire(frames)
    assert times[0] == pytest.approx(0.2)
    assert times[1] is None


def test_eval_follow_runs_a_short_stretch(capsys: pytest.CaptureFixture[str]) -> None:
    from agent.cli import main

    world = ROOT / "examples" / "worlds" / "track_straight.toml"
    assert main(["eval", "follow", "--world", str(world), "--seconds", "1.0", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    for key in ("precision_20px", "success_auc", "fps", "identity_switches", "reacquire_s_max"):
        assert key in out
    assert out["frames"] == 15 and out["first_tracking_s"] is not None
    assert out["precision_20px"] > 0.5  # the user is 1.3-1.8 m ahead, alone in the band


def test_a_hint_brings_the_target_back_at_its_new_size() -> None:
    # Hidden while the robot closed in: the pre-locator's box, 1.6 times larger, is taken at its size.
    small = _head_and_shoulders(100, 40, 80)
    tracker = MeanShiftTracker(TrackerConfig(silhouette=Silhouette.OMEGA, colour_space=ColourSpace.HSV))
    tracker.start(small, (100.0, 40.0, 80.0, 69.0))
    blank = np.full_like(small, (170, 180, 190))
    assert tracker.update(blank).state.value == "occluded"
    big = _head_and_shoulders(60, 20, 128)
    result = tracker.update(big, [np.array([60.0, 20.0, 128.0, 110.0])])
    assert result.state.value == "tracking"
    assert abs(result.box[2] - 128.0) < 10.0 and abs(result.box[0] + result.box[2] / 2 - 124.0) < 10.0
