"""The VLP pipeline end to end on rendered frames: fixes against ground truth, bad frames that never raise,
one-LED degraded fixes, the calibration's effect, per-stage timings."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest

from agent.sim_view import agent_view
from agent.vlp.calibration import ResidualCorrection, VlpCalibration
from agent.vlp.model import NoFix, PosePrior, VlpFix
from agent.vlp.pipeline import VlpPipeline
from drivers.sim.render import LedCover, RollingShutterRenderer
from drivers.sim.world import ErrorModel, Pose2D
from drivers.sim.worldfile import load_world
from tests.conftest import REPO

ENV1 = REPO / "examples" / "worlds" / "env1.toml"


@pytest.fixture(scope="module")
def perfect_env1():  # type: ignore[no-untyped-def]
    """Environment 1 without its errors: the agent's view is the truth."""
    world = load_world(ENV1)
    return dataclasses.replace(world, errors=ErrorModel())


def frames(world, pose: Pose2D, count: int, seed: int = 1):  # type: ignore[no-untyped-def]
    renderer = RollingShutterRenderer.for_world(world, seed=seed)
    for k in range(count):
        yield renderer.render(lambda t: pose, 10.0 + k / world.camera.frame_rate_hz)


def test_fixes_of_a_perfectly_known_world_are_sub_millimetre(perfect_env1) -> None:  # type: ignore[no-untyped-def]
    view = agent_view(perfect_env1)
    pipeline = VlpPipeline(view.intrinsics, view.led_map, view.mount)
    pose = Pose2D(0.06, -0.03, 0.2)
    for frame in frames(perfect_env1, pose, 6):
        result = pipeline.process(frame.image, frame.truth.t_mid_s)
        assert isinstance(result, VlpFix), result
        assert math.hypot(result.x_m - pose.x_m, result.y_m - pose.y_m) < 1e-3
        assert math.remainder(result.yaw_rad - pose.yaw_rad, 2 * math.pi) == pytest.approx(0.0, abs=2e-3)
        assert set(result.ids) == {"L1", "L2", "L3", "L4"}
        assert not result.degraded
        # The covariance says about a millimetre, not a centimetre or a micrometre.
        assert 1e-4 < result.sigma_xy_m < 5e-3
        t = result.timings
        assert t.total_ms > 0 and t.total_ms >= t.track_ms + t.decode_ms + t.solve_ms


def test_the_calibration_moves_the_principal_point_and_corrects_the_residual() -> None:
    world = load_world(ENV1)
    view = agent_view(world)
    renderer = RollingShutterRenderer.for_world(world, seed=2)
    true_pp = (renderer.output_intrinsics.cx_px, renderer.output_intrinsics.cy_px)
    residual = ResidualCorrection((0.0, 0.0), 1.0, 0, (0.001,), (-0.002,))
    calibration = VlpCalibration((800, 600), true_pp, residual=residual)
    nominal = VlpPipeline(view.intrinsics, view.led_map, view.mount)
    calibrated = VlpPipeline(view.intrinsics, view.led_map, view.mount, calibration=calibration)
    assert calibrated.intrinsics.cx_px == true_pp[0]
    pose = Pose2D(-0.1, 0.15, -2.0)
    frame = renderer.render(lambda t: pose, 3.0)
    a = nominal.process(frame.image, frame.truth.t_mid_s)
    b = calibrated.process(frame.image, frame.truth.t_mid_s)
    assert isinstance(a, VlpFix) and isinstance(b, VlpFix)
    # The principal point error is 3.6 px: about a centimetre off before, millimetres after (the tilt and the
    # LED survey remain); the residual correction shifts the fix by exactly (-1, +2) mm.
    assert math.hypot(a.x_m - pose.x_m, a.y_m - pose.y_m) > 0.007
    assert math.hypot(b.x_m + 0.001 - pose.x_m, b.y_m - 0.002 - pose.y_m) < 0.006


@pytest.mark.parametrize(
    ("image", "reason"),
    [
        (None, "not an image"),
        ("frame", "not an image"),
        (np.zeros((600, 800), np.float32), "wrong pixel type"),
        (np.zeros((600, 800, 3), np.uint8), "wrong shape"),
        (np.zeros((480, 640), np.uint8), "wrong size"),
        (np.zeros((600, 800), np.uint8), "dark frame"),
        (np.full((600, 800), 255, np.uint8), "saturated"),
        (np.clip(np.random.default_rng(0).normal(16, 1.5, (600, 800)), 0, 255).astype(np.uint8), "no LED"),
    ],
    ids=["none", "str", "float", "rgb", "size", "black", "saturated", "noise"],
)
def test_bad_frames_give_no_fix_with_a_reason(perfect_env1, image: object, reason: str) -> None:  # type: ignore[no-untyped-def]
    view = agent_view(perfect_env1)
    pipeline = VlpPipeline(view.intrinsics, view.led_map, view.mount)
    result = pipeline.process(image, 1.0)
    assert isinstance(result, NoFix)
    assert reason in result.reason


def test_one_led_gives_no_fix_without_a_yaw_and_a_degraded_one_with_it(perfect_env1) -> None:  # type: ignore[no-untyped-def]
    world = dataclasses.replace(perfect_env1, leds=perfect_env1.leds[:1])
    view = agent_view(world)
    pipeline = VlpPipeline(view.intrinsics, view.led_map, view.mount)
    pose = Pose2D(-0.3, 0.3, 0.5)
    (frame,) = frames(world, pose, 1)
    alone = pipeline.process(frame.image, frame.truth.t_mid_s)
    assert isinstance(alone, NoFix) and "one LED" in alone.reason
    prior = PosePrior(pose.x_m + 0.1, pose.y_m - 0.1, pose.yaw_rad + 0.01, 0.3, 0.02)
    pipeline.reset()
    helped = pipeline.process(frame.image, frame.truth.t_mid_s, prior=prior)
    assert isinstance(helped, VlpFix)
    assert helped.degraded and "single-led" in helped.flags
    # Off by the prior's yaw error times the LED's horizontal distance (0.01 rad * 0.25 m), not by its 14 cm.
    assert math.hypot(helped.x_m - pose.x_m, helped.y_m - pose.y_m) < 0.005
    assert helped.covariance[2][2] == pytest.approx(0.02**2)


def test_a_frame_that_breaks_the_tracker_still_does_not_raise(perfect_env1) -> None:  # type: ignore[no-untyped-def]
    view = agent_view(perfect_env1)
    pipeline = VlpPipeline(view.intrinsics, view.led_map, view.mount)
    pose = Pose2D(0.0, 0.0, 0.3)
    good = list(frames(perfect_env1, pose, 3))
    for frame in good[:2]:
        assert isinstance(pipeline.process(frame.image, frame.truth.t_mid_s), VlpFix)
    # The LEDs vanish mid-track (lights off), then come back.
    dark = np.full((600, 800), 16, np.uint8)
    for k in range(3):
        result = pipeline.process(dark, 1.0 + k)
        assert isinstance(result, NoFix)
    back = pipeline.process(good[2].image, 5.0)
    assert isinstance(back, VlpFix)


def test_lens_distortion_is_undone(perfect_env1) -> None:  # type: ignore[no-untyped-def]
    """A barrel-distorted lens (k1 = -0.12), the robot off the LEDs' centre (so the distortion does not
    cancel between them): with the distortion known the fix is sub-millimetre; taken for a pinhole it is
    several millimetres off."""
    camera = dataclasses.replace(perfect_env1.camera, distortion=(-0.12, 0.03, 0.0005, -0.0008, 0.0))
    world = dataclasses.replace(perfect_env1, camera=camera)
    view = agent_view(world)
    pinhole = dataclasses.replace(view.intrinsics, distortion=(0.0, 0.0, 0.0, 0.0, 0.0))
    pose = Pose2D(0.25, -0.3, -0.5)
    (frame,) = frames(world, pose, 1)
    known = VlpPipeline(view.intrinsics, view.led_map, view.mount).process(frame.image, frame.truth.t_mid_s)
    naive = VlpPipeline(pinhole, view.led_map, view.mount).process(frame.image, frame.truth.t_mid_s)
    assert isinstance(known, VlpFix) and isinstance(naive, VlpFix)
    assert math.hypot(known.x_m - pose.x_m, known.y_m - pose.y_m) < 1e-3
    assert math.hypot(naive.x_m - pose.x_m, naive.y_m - pose.y_m) > 5e-3


def test_losing_all_but_one_led_carries_on_from_the_last_fix(perfect_env1) -> None:  # type: ignore[no-untyped-def]
    """Two LEDs, then one is covered: single-LED fixes from the pipeline's own last yaw, flagged. The first
    two-LED fix rests on ids one frame named (two LEDs cannot check them): flagged too."""
    world = dataclasses.replace(perfect_env1, leds=perfect_env1.leds[:2])
    view = agent_view(world)
    pipeline = VlpPipeline(view.intrinsics, view.led_map, view.mount)
    renderer = RollingShutterRenderer.for_world(world, seed=5)
    pose = Pose2D(-0.46, 0.04, 1.57)
    for k in range(10):
        covers = [LedCover(0, 0.0, 1.0)] if k >= 5 else []
        frame = renderer.render(lambda t: pose, 10.0 + k / 20.0, covers=covers)
        result = pipeline.process(frame.image, frame.truth.t_mid_s)
        assert isinstance(result, VlpFix), (k, result)
        assert math.hypot(result.x_m - pose.x_m, result.y_m - pose.y_m) < 3e-3
        assert result.degraded == (k == 0 or k >= 5)
        assert ("id-unconfirmed" in result.flags) == (k == 0)
        assert ("single-led" in result.flags) == (k >= 5)
        # Two LEDs, one LED: a fault cannot be told from the pose, nothing is ruled out.
        assert result.protection_level_m == math.inf


def test_settled_ids_are_verified_every_few_frames_and_a_disagreement_every_frame(perfect_env1) -> None:  # type: ignore[no-untyped-def]
    view = agent_view(perfect_env1)
    pipeline = VlpPipeline(view.intrinsics, view.led_map, view.mount)
    decoded_per_frame = []
    stream = frames(perfect_env1, Pose2D(0.02, 0.01, 0.4), 17)
    for _, frame in zip(range(16), stream, strict=False):
        result = pipeline.process(frame.image, frame.truth.t_mid_s)
        assert isinstance(result, VlpFix), result
        assert set(result.ids) == {"L1", "L2", "L3", "L4"}
        # Decoded on this frame: the frame's own classification and stripe features are reported.
        decoded = [o for o in result.leds if o.frame_id is not None]
        # (On the first frame no id is settled yet: one frame's read is provisional.)
        assert all(o.frame_id == (o.id or o.frame_id) and math.isfinite(o.frequency_hz) for o in decoded)
        assert all(o.id is not None for o in result.leds) or len(decoded_per_frame) == 0
        assert all(o.frame_id is None and math.isnan(o.frequency_hz) for o in result.leds if o not in decoded)
        decoded_per_frame.append(len(decoded))
    # The first frames decode every LED; once settled and confirmed, all four together every third frame
    # (one decode batch for all), none in between.
    assert decoded_per_frame[0] == 4
    steady = decoded_per_frame[4:]
    assert set(steady) == {0, 4}
    verifying = [k for k, n in enumerate(steady) if n == 4]
    assert all(b - a == 3 for a, b in itertools.pairwise(verifying)), steady
    assert len(verifying) >= 3
    # Stripes that disagree with the settled id: that LED is decoded on every frame until they agree,
    # also on the frames after a verifying one, when the others are not (as the next frame is).
    assert (len(steady) - verifying[-1]) % 3 != 0
    track = pipeline.tracks[0]
    assert track.frame is not None
    track.frame = dataclasses.replace(track.frame, id="L9")
    for frame in stream:
        result = pipeline.process(frame.image, frame.truth.t_mid_s)
        assert any(o.track_id == track.track_id and o.frame_id is not None for o in result.leds)


def test_a_misread_id_on_two_leds_is_not_passed_as_nominal(perfect_env1) -> None:  # type: ignore[no-untyped-def]
    """Two LEDs (L1, L2: 0.915 m apart) whose ids settled and were confirmed; then one is taken for L3 (0.925
    m from L1: the distances agree, the fix lands about a metre away, its chi^2 is clean). The pipeline's
    own last fix says it cannot be there: the fix is flagged, never nominal."""
    world = dataclasses.replace(perfect_env1, leds=perfect_env1.leds[:2])
    view = agent_view(perfect_env1)
    pipeline = VlpPipeline(view.intrinsics, view.led_map, view.mount)
    renderer = RollingShutterRenderer.for_world(world, seed=5)
    pose = Pose2D(-0.46, 0.04, 1.57)
    for k in range(4):
        frame = renderer.render(lambda t: pose, 10.0 + k / 20.0)
        good = pipeline.process(frame.image, frame.truth.t_mid_s)
    assert isinstance(good, VlpFix) and not good.degraded
    l2 = next(t for t in pipeline.tracks if pipeline.signatures[t.id_index or 0].id == "L2")
    # A confident, confirmed misread: the tally all for L3.
    l3 = [s.id for s in pipeline.signatures].index("L3")
    l2.tally = np.where(np.arange(l2.tally.size) == l3, 0.0, -60.0)
    l2.id_index = l3
    l2.confirmations = 5
    frame = renderer.render(lambda t: pose, 10.0 + 4 / 20.0)
    result = pipeline.process(frame.image, frame.truth.t_mid_s)
    assert isinstance(result, VlpFix)
    assert math.hypot(result.x_m - pose.x_m, result.y_m - pose.y_m) > 0.5
    assert result.degraded
    # The last fix contradicts it.
    assert "prior-mismatch" in result.flags


def test_fixes_carry_their_integrity(perfect_env1) -> None:  # type: ignore[no-untyped-def]
    """Four LEDs: chi^2 within its limit, a finite protection level over the error (and above the
    covariance's own sigma), the association's work (one assignment, no search)."""
    view = agent_view(perfect_env1)
    pipeline = VlpPipeline(view.intrinsics, view.led_map, view.mount)
    pose = Pose2D(0.06, -0.03, 0.2)
    for frame in frames(perfect_env1, pose, 3):
        result = pipeline.process(frame.image, frame.truth.t_mid_s)
        assert isinstance(result, VlpFix) and not result.degraded
        assert result.chi2 <= result.chi2_threshold < math.inf
        error = math.hypot(result.x_m - pose.x_m, result.y_m - pose.y_m)
        assert 3.0 * result.sigma_xy_m < result.protection_level_m < 0.1
        assert error < result.protection_level_m
        assert result.work.hypotheses == 1 and not result.work.truncated


def test_close_signatures_are_those_the_duty_does_not_tell_apart() -> None:
    """Rivals for the ``close-signature`` flag: within 200 Hz and 0.1 duty (as the world file warns)."""
    from agent.vlp.pipeline import _close_rivals

    freq = np.array([2000.0, 2100.0, 2200.0, 2300.0])
    assert _close_rivals(freq, np.full(4, 0.5)) == ((1,), (0, 2), (1, 3), (2,))  # 200 Hz apart is not close
    # Environment 1's signatures (1 kHz apart), and close frequencies the duty tells apart: no rivals.
    assert (
        _close_rivals(np.array([1500.0, 2500.0, 3500.0, 4500.0]), np.array([0.3, 0.6, 0.4, 0.5])) == ((),) * 4
    )
    assert _close_rivals(np.array([2000.0, 2100.0]), np.array([0.3, 0.5])) == ((), ())


def test_a_two_led_fix_over_close_signatures_is_degraded() -> None:
    """sig100 (four signatures 100 Hz apart at duty 0.5): a fix from two LEDs, which nothing in its own
    geometry can check, is flagged ``close-signature``; one from three or four is not."""
    world = load_world(REPO / "examples" / "worlds" / "sig100.toml")
    view = agent_view(world)
    renderer = RollingShutterRenderer.for_world(world, seed=2)
    seen: dict[int, set[bool]] = {}
    # Near L1 and L3 (the north pair) two LEDs are in view; at the centre all four.
    for pose in (Pose2D(0.0, 0.75, 0.0), Pose2D(0.0, 0.0, 0.0)):
        pipe = VlpPipeline(view.intrinsics, view.led_map, view.mount)
        for k in range(8):
            rendered = renderer.render(lambda t, p=pose: p, 10.0 * (pose.y_m + 1) + k / 20)
            result = pipe.process(rendered.image, rendered.truth.t_mid_s)
            if isinstance(result, VlpFix):
                seen.setdefault(len(result.ids), set()).add("close-signature" in result.flags)
    assert seen.get(2) == {True}
    assert seen.get(4) == {False}
