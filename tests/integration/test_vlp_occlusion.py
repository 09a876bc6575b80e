"""An LED half covered for a second (Environment 1, its realistic errors, 20 fps): its track and id are kept,
it is left out of the fix while covered, and the pose from the other LEDs stays within 2 cm."""

from __future__ import annotations

import math

import pytest

from agent.sim_view import agent_view
from agent.vlp.model import VlpFix
from agent.vlp.pipeline import VlpPipeline
from drivers.sim.render import LedCover, RollingShutterRenderer
from drivers.sim.world import Pose2D
from drivers.sim.worldfile import load_world
from tests.conftest import REPO


@pytest.mark.parametrize("cover_angle_rad", [0.0, 1.2, -2.5])
@pytest.mark.parametrize("speed_mps", [0.0, 0.1])
def test_half_covered_led_keeps_track_and_id(cover_angle_rad: float, speed_mps: float) -> None:
    world = load_world(REPO / "examples" / "worlds" / "env1.toml")
    view = agent_view(world)
    renderer = RollingShutterRenderer.for_world(world, seed=11)
    pipeline = VlpPipeline(view.intrinsics, view.led_map, view.mount)
    fps = world.camera.frame_rate_hz
    covered = next(i for i, led in enumerate(world.leds) if led.id == "L2")
    before, during = range(0, 10), range(10, 10 + round(fps))

    def pose_at(t: float) -> Pose2D:
        return Pose2D(-0.05 + speed_mps * (t - 10.0), 0.02, 0.35)

    history = []
    for k in range(40):
        covers = [LedCover(covered, cover_angle_rad, 0.5)] if k in during else []
        frame = renderer.render(pose_at, 10.0 + k / fps, covers=covers)
        result = pipeline.process(frame.image, frame.truth.t_mid_s)
        assert isinstance(result, VlpFix), (k, result)
        truth = frame.truth.base_pose
        error = math.hypot(result.x_m - truth.x_m, result.y_m - truth.y_m)
        # On the first frame the ids are provisional (settled after two frames): L2 is the one matched to it.
        l2 = [
            o
            for o in result.leds
            if o.id == "L2"
            or (o.id is None and o.map_index is not None and view.led_map.leds[o.map_index].id == "L2")
        ]
        assert len(l2) == 1, (k, result.leds)
        history.append((k, error, l2[0], (result.x_m - truth.x_m, result.y_m - truth.y_m)))
    track_ids = {obs.track_id for _, _, obs, _ in history}
    assert len(track_ids) == 1, "the covered LED lost its track"
    for k, error, obs, _ in history:
        assert error < 0.02, (k, error)
        if k in during:
            assert obs.visibility == "partial" and not obs.used
        if k in before or k >= during.stop + 1:
            assert obs.visibility == "full" and obs.used
    # The fix error vector moves by less than 2 cm when the LED is dropped (a few millimetres in fact).
    steady = [d for k, _, _, d in history if k in before]
    covered_fixes = [d for k, _, _, d in history if k in during]
    shift = math.dist(steady[-1], covered_fixes[0])
    assert shift < 0.02
