"""The forward camera's renderer and simulated backend: people appear where the pinhole model puts them, in
their clothing, hidden by walls and by nearer people; the ground-truth boxes say so; frames stay in memory."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from drivers.camera.base import CameraSettings
from drivers.camera.sim_forward import SimForwardCamera
from drivers.errors import ConfigError, DeviceTimeout
from drivers.sim.forward_render import ForwardRenderer, PersonState
from drivers.sim.raycast import walls_array
from drivers.sim.simulation import Simulation
from drivers.sim.world import Clothing, ForwardCameraModel, Person, Pose2D, Wall, World
from drivers.sim.worldfile import parse_world

RED = (200.0, 30.0, 30.0)
GREEN = (30.0, 160.0, 40.0)
ROOM = (Wall(-2, -4, 8, -4), Wall(8, -4, 8, 4), Wall(8, 4, -2, 4), Wall(-2, 4, -2, -4))
QUIET = ForwardCameraModel(noise_dn=0.0, light_variation=0.0)


class Clock:
    """The simulation's clock, set by the test."""

    def __init__(self, t: float) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def person(name: str, shirt: tuple[float, float, float], pattern: str = "plain") -> Person:
    return Person(name, name.upper(), ((0.0, 0.0),), clothing=Clothing(shirt_rgb=shirt, pattern=pattern))


def state(p: Person, x: float, y: float, heading: float = math.pi) -> PersonState:
    return PersonState(p, x, y, heading, 0.0)


def bgr(rgb: tuple[float, float, float]) -> np.ndarray:
    return np.array(rgb[::-1])


def torso_pixel(model: ForwardCameraModel, x: float, y: float, height_m: float = 1.72) -> tuple[int, int]:
    """Where the pinhole model puts the middle of the torso of someone at (x, y) seen from the origin."""
    f = model.focal_length_px
    cx, cy = model.principal_point_px
    depth, left = x - model.mount.x_m, y - model.mount.y_m
    u = cx - f * left / depth
    v = cy - f * (0.64 * height_m - model.mount.z_m) / depth
    return round(u), round(v)


def test_a_person_appears_at_the_projected_place_in_their_shirt_colour() -> None:
    renderer = ForwardRenderer(QUIET, walls_array(ROOM))
    user = person("user", RED)
    image, truth = renderer.render(Pose2D(0.0, 0.0, 0.0), [state(user, 3.0, 0.6)], 0.0)
    assert image.shape == (480, 640, 3) and image.dtype == np.uint8
    u, v = torso_pixel(QUIET, 3.0, 0.6)
    patch = image[v - 3 : v + 4, u - 3 : u + 4].reshape(-1, 3).astype(float)
    np.testing.assert_allclose(patch.mean(axis=0), bgr(RED), atol=2.0)
    seen = truth.person("user")
    assert seen is not None and seen.visible == pytest.approx(1.0)
    assert seen.visible_box is not None and seen.box is not None
    assert seen.box.x <= u <= seen.box.x + seen.box.w and seen.box.y <= v <= seen.box.y + seen.box.h
    assert abs(seen.box.centre[0] - u) <= 2.0
    assert seen.bearing_rad == pytest.approx(math.atan2(0.6, 2.9))
    # Nothing red outside their box.
    reddish = (image[:, :, 2] > 150) & (image[:, :, 1] < 80)
    outside = reddish.copy()
    b = seen.box
    outside[b.y : b.y + b.h, b.x : b.x + b.w] = False
    assert not outside.any()


def test_turning_the_robot_moves_the_person_across_the_image() -> None:
    renderer = ForwardRenderer(QUIET, walls_array(ROOM))
    user = person("user", RED)
    _, ahead = renderer.render(Pose2D(0.0, 0.0, 0.0), [state(user, 3.0, 0.0)], 0.0)
    _, turned = renderer.render(Pose2D(0.0, 0.0, math.radians(15.0)), [state(user, 3.0, 0.0)], 0.0)
    a, t = ahead.person("user"), turned.person("user")
    assert a is not None and t is not None and a.box is not None and t.box is not None
    assert t.box.centre[0] > a.box.centre[0] + 100  # turned left: they are now on the right
    assert t.bearing_rad < 0.0


def test_a_passer_by_hides_the_user_and_a_wall_hides_everyone_behind_it() -> None:
    walls = (*ROOM, Wall(4.0, -0.2, 4.0, 3.0))  # a partition across the left of the view
    renderer = ForwardRenderer(QUIET, walls_array(walls))
    user, passer = person("user", RED, "stripes"), person("passer", GREEN, "checks")
    image, truth = renderer.render(
        Pose2D(0.0, 0.0, 0.0),
        [state(user, 3.0, -0.7), state(passer, 1.8, -0.45), state(person("hidden", RED), 5.0, 1.5)],
        0.0,
    )
    u_seen = truth.person("user")
    p_seen = truth.person("passer")
    hidden = truth.person("hidden")
    assert u_seen is not None and p_seen is not None and hidden is not None
    assert p_seen.visible == pytest.approx(1.0)
    assert 0.0 < u_seen.visible < 0.6  # partly behind the nearer passer-by
    assert hidden.box is not None and hidden.visible == 0.0 and hidden.visible_box is None
    # The passer-by's torso is their green (checks: green and the pattern's white), not the user's red.
    u, v = torso_pixel(QUIET, 1.8, -0.45)
    patch = image[v - 10 : v + 10, u - 10 : u + 10].reshape(-1, 3).astype(int)
    greenish = (patch[:, 1] > 140) & (patch[:, 2] < 60)
    assert greenish.mean() > 0.3 and not ((patch[:, 2] > 150) & (patch[:, 1] < 80)).any()


def test_light_changes_and_noise_differ_between_frames() -> None:
    model = ForwardCameraModel(noise_dn=4.0, light_variation=0.3, light_period_s=4.0)
    renderer = ForwardRenderer(model, walls_array(ROOM), seed=1)
    scene = [state(person("user", RED), 3.0, 0.0)]
    dim, t_dim = renderer.render(Pose2D(0.0, 0.0, 0.0), scene, 3.0)  # sin(3 pi / 2) = -1
    bright, t_bright = renderer.render(Pose2D(0.0, 0.0, 0.0), scene, 1.0)
    assert t_dim.light_gain == pytest.approx(0.7) and t_bright.light_gain == pytest.approx(1.3)
    assert bright.mean() > dim.mean() * 1.3
    again, _ = renderer.render(Pose2D(0.0, 0.0, 0.0), scene, 1.0)
    residual = again.astype(int) - bright.astype(int)
    assert 2.0 < residual[again < 250].std() < 8.0  # fresh sensor noise (4 DN per frame)


def test_the_simulated_forward_camera_lends_colour_frames_with_truth() -> None:
    world = World(
        "forward",
        walls=ROOM,
        forward_camera=dataclasses.replace(QUIET, width_px=320, height_px=240, frame_rate_hz=10.0),
        people=(dataclasses.replace(person("user", RED), path=((3.0, 0.0), (4.0, 0.0))),),
    )
    now = [100.0]
    sim = Simulation(world, clock=lambda: now[0])
    with SimForwardCamera(sim, seed=2) as camera:
        assert camera.settings().pixel_format == "BGR8"
        now[0] += 0.25
        with camera.fetch(timeout_s=0.5) as frame:
            assert frame.image.shape == (240, 320, 3)
            sequence = frame.sequence
            assert frame.host_time_ns == round((100.0 + sequence * 0.1) * 1e9)
        truth = camera.truth(sequence)
        assert truth.person("user") is not None
        assert camera.health().counters["dropped"] == sequence  # it fell behind: the newest frame
        camera.stall()
        with pytest.raises(DeviceTimeout):
            camera.grab(timeout_s=0.05)
        camera.stall(False)
        now[0] += 0.1
        assert camera.grab(timeout_s=0.5).sequence == sequence + 1
    grey = SimForwardCamera(sim, settings=CameraSettings(pixel_format="Mono8"))
    with grey:
        now[0] += 0.1
        assert grey.grab(timeout_s=0.5).image.shape == (240, 320)


def test_world_files_give_clothing_walk_once_paths_and_the_forward_camera() -> None:
    world = parse_world(
        """
[forward_camera]
width_px = 320
hfov_deg = 60.0
mount = { x_m = 0.2, z_m = 1.1 }
[[people]]
name = "user"
tag_id = "E2000011"
path = [[1.0, 0.0], [5.0, 0.0]]
loop = false
start_s = 2.0
clothing = { shirt_rgb = [200, 30, 30], pattern = "stripes", pattern_period_m = 0.12 }
"""
    )
    assert world.forward_camera.width_px == 320
    assert world.forward_camera.hfov_rad == pytest.approx(math.radians(60.0))
    user = world.people[0]
    assert user.clothing.shirt_rgb == (200.0, 30.0, 30.0) and user.clothing.pattern == "stripes"
    assert not user.loop and user.start_s == 2.0
    now = [0.0]
    sim = Simulation(world, clock=lambda: now[0])
    now[0] = 1.5
    assert sim.person_position(user) == (1.0, 0.0)  # waiting for the cue
    now[0] = 30.0
    x, y, heading, walked = sim.person_pose(user)
    assert (x, y) == (5.0, 0.0) and heading == pytest.approx(0.0) and walked == pytest.approx(4.0)
    with pytest.raises(ConfigError, match=r"people\[0\].clothing.pattern"):
        parse_world('[[people]]\nname = "a"\ntag_id = "1"\npath = [[0, 0]]\nclothing = {pattern = "dots"}\n')
    with pytest.raises(ConfigError, match=r"forward_camera.mount"):
        parse_world("[forward_camera]\nmount = { pitch_deg = 5.0 }\n")


def test_genicam_buffers_give_bgr8_frames_from_bgr8_or_rgb8_lines_with_padding() -> None:
    from types import SimpleNamespace

    from drivers.camera.genicam import GenicamCamera
    from drivers.errors import DeviceError

    def buffer(fmt: str, lines: np.ndarray, width: int, padding: int) -> SimpleNamespace:
        component = SimpleNamespace(
            data_format=fmt, width=width, height=lines.shape[0], data=lines.ravel(), x_padding=padding
        )
        return SimpleNamespace(payload=SimpleNamespace(components=[component]))

    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    padded = np.concatenate([rgb.reshape(2, 9), np.full((2, 2), 255, np.uint8)], axis=1)
    cam = GenicamCamera("x.cti", settings=CameraSettings(pixel_format="BGR8"))
    np.testing.assert_array_equal(cam._image(buffer("RGB8", padded, 3, 2)), rgb[:, :, ::-1])
    np.testing.assert_array_equal(cam._image(buffer("BGR8", padded, 3, 2)), rgb)
    with pytest.raises(DeviceError, match="sent Mono8, not BGR8"):
        cam._image(buffer("Mono8", padded, 9, 2))


def test_the_render_process_draws_the_same_frames() -> None:
    world = World(
        "forward",
        walls=ROOM,
        forward_camera=dataclasses.replace(ForwardCameraModel(), width_px=160, height_px=120),
        people=(dataclasses.replace(person("user", RED, "checks"), path=((3.0, 0.0), (4.0, 0.0))),),
    )
    frames = []
    for render_process in (False, True):
        clock = Clock(50.0)
        sim = Simulation(world, clock=clock)
        with SimForwardCamera(sim, seed=4, render_process=render_process) as camera:
            clock.t += 0.35
            frame = camera.grab(timeout_s=5.0)
            frames.append((frame.image, camera.truth(frame.sequence)))
    np.testing.assert_array_equal(frames[0][0], frames[1][0])
    assert frames[0][1] == frames[1][1]
