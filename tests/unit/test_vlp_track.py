"""Tracking: the constant-velocity Kalman filter, the Bhattacharyya coefficient, CamShift following moving
LEDs, covers (partial: kept, not trusted; full: coasting, then dropped), and id voting that does not flip."""

from __future__ import annotations

import math

import numpy as np
import pytest

from agent.vlp.decode import Classification
from agent.vlp.detect import DetectorConfig, find_blobs
from agent.vlp.track import (
    FULL,
    OCCLUDED,
    PARTIAL,
    KalmanCV,
    LedTrack,
    LedTracker,
    TrackerConfig,
    bhattacharyya,
)
from drivers.sim.render import LedCover, RollingShutterRenderer
from drivers.sim.world import CameraModel, Led, Mount, Pose2D

LEDS = (
    Led("L1", -0.465, 0.495, 1.5, frequency_hz=1500.0, duty=0.3),
    Led("L2", -0.460, -0.420, 1.5, frequency_hz=2500.0, duty=0.6),
    Led("L3", 0.460, 0.490, 1.5, frequency_hz=3500.0, duty=0.4),
)
DETECTOR = DetectorConfig(min_diameter_px=16.0, bridge_px=8.0)


def test_kalman_filter_learns_a_constant_velocity() -> None:
    kf = KalmanCV(100.0, 50.0, 1.0, 400.0)
    for k in range(1, 40):
        kf.predict(0.05, 3000.0)
        kf.update((100.0 + 120.0 * 0.05 * k, 50.0 - 40.0 * 0.05 * k), 0.15)
    assert kf.velocity == pytest.approx((120.0, -40.0), abs=0.5)
    before = kf.position_sigma_px
    kf.predict(0.05, 3000.0)
    # x = F x: the prediction one frame ahead, and P grows by F P F^T + Q.
    assert kf.position == pytest.approx((100.0 + 120.0 * 2.0, 50.0 - 40.0 * 2.0), abs=0.05)
    assert kf.position_sigma_px > before


def test_bhattacharyya_coefficient() -> None:
    p = np.array([0.2, 0.3, 0.5])
    assert bhattacharyya(p, p) == pytest.approx(1.0)
    assert bhattacharyya(np.array([1.0, 0.0]), np.array([0.0, 1.0])) == 0.0
    assert bhattacharyya(np.array([0.5, 0.5]), np.array([1.0, 0.0])) == pytest.approx(math.sqrt(0.5))


def run(poses, covers=None, frames=30, seed=1):  # type: ignore[no-untyped-def]
    """Track LEDs over ``frames`` frames at 20 fps (full search on the first only); yields each frame's
    truth and the tracker."""
    renderer = RollingShutterRenderer(CameraModel(frame_rate_hz=20.0), LEDS, Mount(0.0, 0.0, 0.2), seed=seed)
    tracker = LedTracker(DETECTOR, TrackerConfig())
    for k in range(frames):
        t0 = 10.0 + k / 20.0
        frame = renderer.render(poses, t0, covers=covers(k) if covers else ())
        t = frame.truth.t_mid_s
        if k == 0:
            tracker.add(frame.image, [b for b in find_blobs(frame.image, DETECTOR)], t, 4)
        else:
            tracker.step(frame.image, t)
        yield frame, tracker


def track_of(tracker: LedTracker, centre: tuple[float, float]):  # type: ignore[no-untyped-def]
    return min(tracker.tracks, key=lambda t: math.dist(t.kf.position, centre))


def test_tracks_follow_leds_across_a_turn_touching_only_their_windows() -> None:
    ids: dict[str, int] = {}
    errors = []
    for frame, tracker in run(lambda t: Pose2D(0.02 * (t - 10.0), 0.0, 0.6 * (t - 10.0))):
        for truth in frame.truth.leds:
            track = track_of(tracker, truth.centre_px)
            ids.setdefault(truth.id, track.track_id)
            assert track.track_id == ids[truth.id]
            assert track.centre_ok
            errors.append(math.dist(track.blob.centre_px, truth.centre_px))
    assert len(ids) == 3
    # L1's disk is crossed by only two bright stripes (1.5 kHz, duty 0.3): its centre is the least sure.
    assert max(errors) < 0.5
    assert float(np.mean(errors)) < 0.15


def test_a_half_covered_led_is_kept_but_not_trusted_and_recovers() -> None:
    def covers(k: int) -> list[LedCover]:
        return [LedCover(1, 0.0, 0.5)] if 10 <= k < 30 else []

    states = []
    for frame, tracker in run(lambda t: Pose2D(0.02, -0.01, 0.4), covers, frames=40):
        truth = next(t for t in frame.truth.leds if t.id == "L2")
        track = track_of(tracker, truth.centre_px)
        states.append((track.track_id, track.visibility, track.centre_ok))
        # The other LEDs are untouched.
        others = [track_of(tracker, t.centre_px) for t in frame.truth.leds if t.id != "L2"]
        assert all(o.visibility == FULL for o in others)
    assert len({s[0] for s in states}) == 1  # one track throughout
    assert all(s[1] == FULL and s[2] for s in states[:10])
    assert all(s[1] == PARTIAL and not s[2] for s in states[10:30])
    assert all(s[1] == FULL and s[2] for s in states[31:])


def test_a_fully_covered_led_coasts_then_is_dropped() -> None:
    config = TrackerConfig()

    def covers(k: int) -> list[LedCover]:
        return [LedCover(0, 0.0, 1.0)] if k >= 5 else []

    seen = []
    for frame, tracker in run(
        lambda t: Pose2D(0.0, 0.0, 0.2), covers, frames=5 + config.max_coast_frames + 3
    ):
        del frame
        seen.append({t.track_id: t.visibility for t in tracker.tracks})
    covered = set(seen[0]) - set(seen[-1])
    assert len(covered) == 1
    (lost,) = covered
    assert all(s[lost] == OCCLUDED for s in seen[5 : 5 + config.max_coast_frames])


def test_a_settled_id_does_not_flip_on_a_few_bad_frames() -> None:
    frame, tracker = next(iter(run(lambda t: Pose2D(0.0, 0.0, 0.0), frames=1)))
    del frame
    track = tracker.tracks[0]
    config = TrackerConfig()
    says_a = Classification("A", 1.0, (0.0, -40.0, -60.0, -80.0))
    says_b = Classification("B", 1.0, (-40.0, 0.0, -60.0, -80.0))
    for _ in range(20):
        track.vote(says_a, config)
    assert track.id_index == 0
    for _ in range(3):
        track.vote(says_b, config)
        assert track.id_index == 0
    # A track that really changed LED is followed after a few more frames (the tally is bounded).
    for _ in range(10):
        track.vote(says_b, config)
    assert track.id_index == 1


def test_an_id_settles_by_evidence_over_frames_not_one() -> None:
    """One confident frame makes the id provisional only (the solver may use it where three LEDs check it);
    it settles once settle_frames decided frames in a row named it; an undecided frame neither breaks nor
    extends the run; a settled id is confirmed while the last decided frames named it, and a frame naming
    another id withdraws that (and does not settle the other)."""
    frame, tracker = next(iter(run(lambda t: Pose2D(0.0, 0.0, 0.0), frames=1)))
    del frame
    track = tracker.tracks[0]
    config = TrackerConfig(settle_frames=2, confirm_frames=2)
    says_a = Classification("A", 1.0, (0.0, -40.0, -60.0, -80.0))
    says_b = Classification("B", 1.0, (-40.0, 0.0, -60.0, -80.0))
    weakly_b = Classification("B", 0.9, (-1.0, 0.0, -60.0, -80.0))
    undecided = Classification(None, 0.0, (0.0, -0.5, -1.0, -1.0))
    track.vote(says_a, config)
    assert track.id_index is None and track.provisional_index(config) == 0
    assert not track.confirmed(config)
    track.vote(undecided, config)
    assert track.id_index is None
    track.vote(says_a, config)
    assert track.id_index == 0 and track.confirmed(config)
    track.vote(weakly_b, config)
    assert track.id_index == 0 and not track.confirmed(config)
    track.vote(says_a, config)
    track.vote(says_a, config)
    assert track.confirmed(config)
    # A fresh track read wrong once, then right: the wrong read never settles.
    fresh = tracker.tracks[0]
    fresh.tally[:] = 0.0
    fresh.votes, fresh.id_index, fresh.confirmations = 0, None, 0
    fresh._streak = (-1, 0)
    fresh.vote(says_b, config)
    assert fresh.id_index is None and fresh.provisional_index(config) == 1
    fresh.vote(says_a, config)
    assert fresh.id_index is None
    # One frame settles with settle_frames = 1 (the former rule).
    fresh.vote(says_a, TrackerConfig(settle_frames=1))
    assert fresh.id_index is None or fresh.id_index == 0


def test_a_track_started_from_a_poor_first_look_becomes_fully_visible() -> None:
    # The first look at L2 is half covered (an LED entering at the image edge looks like this): the target
    # histogram and the radius taken from it are wrong. Once the LED shows whole, the track must take its
    # model again and count it as fully visible, or it is never decoded and never identified.
    def covers(k: int) -> list[LedCover]:
        return [LedCover(1, 0.0, 0.5)] if k == 0 else []

    states = []
    for frame, tracker in run(lambda t: Pose2D(0.02, -0.01, 0.4), covers, frames=12):
        truth = next(t for t in frame.truth.leds if t.id == "L2")
        track = track_of(tracker, truth.centre_px)
        states.append((track.visibility, track.centre_ok, abs(track.radius_px - truth.radius_px)))
    assert all(s[0] == FULL and s[1] for s in states[4:]), states
    assert states[-1][2] < 0.5


def test_two_tracks_on_one_led_are_merged() -> None:
    frames = run(lambda t: Pose2D(0.0, 0.0, 0.2), frames=3)
    _, tracker = next(frames)
    first = tracker.tracks[0]
    ghost = LedTrack(999, first.blob, first.time_s, 4, tracker.config)  # a second track on the same LED
    ghost.kf.update(first.blob.centre_px, 0.15)
    tracker.tracks.append(ghost)
    _, tracker = next(frames)
    assert len(tracker.tracks) == 3
    assert all(t.track_id != 999 for t in tracker.tracks)  # the younger one went
