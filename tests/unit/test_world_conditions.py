"""What real ceilings do, in world files (issue 19): each condition parses from TOML, is checked with an
error naming its key, and shows in the rendered frame. And every shipped world loads."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from drivers.errors import ConfigError
from drivers.sim.render import RenderedFrame, RollingShutterRenderer
from drivers.sim.world import CameraModel, Mount, Pose2D, World
from drivers.sim.worldfile import load_world, map_indices, nominal_camera, parse_world, survey, surveyed_leds

REPO = Path(__file__).resolve().parents[2]
WORLDS = sorted((REPO / "examples" / "worlds").glob("*.toml"))
MOUNT = Mount(0.0, 0.0, 0.2)
# No noise, for measuring: no read noise, a full well so deep that shot noise is < 1e-3 DN.
QUIET = CameraModel(read_noise_dn=0.0, full_well_e=1e12, black_level_dn=10.0, radial_falloff=0.0)
# An exposure much longer than the PWM period: every row sees the duty's share, a flat disk.
FLAT = dataclasses.replace(QUIET, exposure_s=2e-3, led_peak_dn=100.0)
HEAD = "[led_defaults]\nz_m = 1.5\n"


def led_text(lid: str, x: float, f: float, extra: str = "", duty: float = 0.5) -> str:
    return f'[[leds]]\nid = "{lid}"\nx_m = {x}\ny_m = 0.0\nfrequency_hz = {f}\nduty = {duty}\n{extra}'


def still(x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> Callable[[float], Pose2D]:
    return lambda t: Pose2D(x, y, yaw)


def render(world: World, camera: CameraModel, t0: float = 5.0, seed: int = 0) -> RenderedFrame:
    renderer = RollingShutterRenderer(camera, world.leds, MOUNT, seed=seed, scene=world.scene)
    return renderer.render(still(), t0)


def light_sum(image: npt.NDArray[np.uint8], centre: tuple[float, float], half: int, black: float) -> float:
    u, v = round(centre[0]), round(centre[1])
    patch = image[max(v - half, 0) : v + half, max(u - half, 0) : u + half].astype(np.float64) - black
    return float(np.clip(patch, 0.0, None).sum())


def output_px(x_m: float, y_m: float, z_m: float, camera: CameraModel) -> tuple[float, float]:
    """Where a point of the ceiling lands in the output image, the robot at the origin facing +x."""
    renderer = RollingShutterRenderer(camera, (), MOUNT)
    u, v, _ = renderer.project(np.array([x_m]), np.array([y_m]), np.array([z_m]), 0.0, 0.0, 0.0)
    return renderer.sensor_to_output(float(u[0]), float(v[0]))


# -- every shipped world ---------------------------------------------------------------------------------
@pytest.mark.parametrize("path", WORLDS, ids=[p.stem for p in WORLDS])
def test_every_shipped_world_loads_and_renders(path: Path) -> None:
    world = load_world(path)
    assert world.leds and world.name
    assert len(surveyed_leds(world)) == sum(led.mapped for led in world.leds)
    lit = [led for led in world.leds if not led.dead]
    x, y = lit[0].x_m, lit[0].y_m
    frame = RollingShutterRenderer.for_world(world).render(still(x, y), 10.0)
    assert frame.image.shape == (world.camera.output_height_px, world.camera.output_width_px)
    assert any(t.in_image for t in frame.truth.leds)


# -- LED brightness ----------------------------------------------------------------------------------------
def test_led_brightness_scales_its_light() -> None:
    world = parse_world(HEAD + led_text("A", -0.3, 2000.0) + led_text("B", 0.3, 3000.0, "brightness = 0.4\n"))
    assert [led.brightness for led in world.leds] == [1.0, 0.4]
    frame = render(world, FLAT)
    a, b = (light_sum(frame.image, t.centre_px, 30, FLAT.black_level_dn) for t in frame.truth.leds)
    assert b / a == pytest.approx(0.4, rel=0.03)


def test_led_defaults_and_grids_take_brightness_and_drift() -> None:
    world = parse_world(
        "[led_defaults]\nz_m = 1.5\nbrightness = 0.7\nfrequency_drift_hz_per_s = 0.5\n"
        + led_text("A", 0.0, 2000.0)
        + "[[led_grids]]\nx0_m = 1.0\ny0_m = 0.0\nnx = 2\nny = 1\ndx_m = 0.5\n"
        "frequency_walk_hz_per_sqrt_s = 2.0\nsignatures = [{ id = 'B', frequency_hz = 3000.0 }, "
        "{ id = 'C', frequency_hz = 4000.0 }]\n"
    )
    assert {led.brightness for led in world.leds} == {0.7}
    assert {led.frequency_drift_hz_per_s for led in world.leds} == {0.5}
    assert [led.frequency_walk_hz_per_sqrt_s for led in world.leds] == [0.0, 2.0, 2.0]


# -- dead and unmapped LEDs --------------------------------------------------------------------------------
def test_a_dead_led_is_in_the_map_but_dark() -> None:
    world = parse_world(HEAD + led_text("A", -0.3, 2000.0) + led_text("B", 0.3, 3000.0, "dead = true\n"))
    assert [led.id for led in surveyed_leds(world)] == ["A", "B"]  # the map does not know it failed
    frame = render(world, FLAT)
    assert [t.id for t in frame.truth.leds] == ["A"]
    where = output_px(0.3, 0.0, 1.5, FLAT)
    assert light_sum(frame.image, where, 30, FLAT.black_level_dn) == 0.0


def test_an_unmapped_led_is_lit_but_not_in_the_map() -> None:
    world = parse_world(
        HEAD
        + led_text("A", -0.3, 2000.0)
        + led_text("B", 0.3, 3000.0, "mapped = false\n")
        + led_text("C", 0.6, 4000.0)
    )
    assert [led.id for led in surveyed_leds(world)] == ["A", "C"]
    assert map_indices(world) == (0, None, 1)
    assert survey(world)[1] is None
    frame = render(world, FLAT)
    assert [t.id for t in frame.truth.leds] == ["A", "B", "C"]
    b = frame.truth.leds[1]
    assert light_sum(frame.image, b.centre_px, 20, FLAT.black_level_dn) > 1000.0


def test_marking_an_led_unmapped_leaves_the_others_survey_where_it_was() -> None:
    text = "[errors]\nled_survey_error_m = 0.01\nseed = 4\n" + HEAD
    both = parse_world(text + led_text("A", -0.3, 2000.0) + led_text("B", 0.3, 3000.0))
    one = parse_world(text + led_text("A", -0.3, 2000.0, "mapped = false\n") + led_text("B", 0.3, 3000.0))
    assert surveyed_leds(one) == surveyed_leds(both)[1:]


# -- frequency drift -------------------------------------------------------------------------------------
def stripe_frequency_hz(frame: RenderedFrame, camera: CameraModel) -> float:
    """The stripes' frequency through the LED's centre column, from the spacing of their rising edges."""
    (truth,) = frame.truth.leds
    u, v = (round(c) for c in truth.centre_px)
    span = int(truth.radius_px * 0.8)
    profile = frame.image[v - span : v + span, u - 1 : u + 2].astype(np.float64).mean(axis=1)
    level = (profile.max() + profile.min()) / 2
    above = profile > level
    idx = np.flatnonzero(~above[:-1] & above[1:])
    edges = idx + (level - profile[idx]) / (profile[idx + 1] - profile[idx])
    assert len(edges) >= 8
    period_rows = float(np.polyfit(np.arange(len(edges)), edges, 1)[0])
    k = camera.sensor_height_px / camera.output_height_px
    return 1.0 / (period_rows * k * camera.t_row_s)


BIG = '[[leds]]\nid = "A"\nx_m = 0.0\ny_m = 0.0\ndiameter_m = 0.6\nfrequency_hz = 2000.0\nduty = 0.5\n'


def test_a_drifting_led_changes_its_stripe_period_over_time() -> None:
    world = parse_world(HEAD + BIG + "frequency_drift_hz_per_s = 2.0\n")
    renderer = RollingShutterRenderer(QUIET, world.leds, MOUNT)
    first = stripe_frequency_hz(renderer.render(still(), 100.0), QUIET)
    later = stripe_frequency_hz(renderer.render(still(), 400.0), QUIET)  # 300 s on: +600 Hz
    assert first == pytest.approx(2000.0, rel=0.01)
    assert later == pytest.approx(2600.0, rel=0.01)


def test_a_random_walk_moves_the_frequency_by_about_its_sigma_and_repeats_with_the_seed() -> None:
    world = parse_world(HEAD + BIG + "frequency_walk_hz_per_sqrt_s = 20.0\n")
    offsets = []
    for seed in range(6):
        renderer = RollingShutterRenderer(QUIET, world.leds, MOUNT, seed=seed)
        renderer.render(still(), 100.0)
        offsets.append(stripe_frequency_hz(renderer.render(still(), 200.0), QUIET) - 2000.0)
    again = RollingShutterRenderer(QUIET, world.leds, MOUNT, seed=5)
    again.render(still(), 100.0)
    assert stripe_frequency_hz(again.render(still(), 200.0), QUIET) - 2000.0 == pytest.approx(offsets[5])
    # sigma = 20 Hz x sqrt(100 s) = 200 Hz: six draws are neither all within 20 Hz nor beyond 1000 Hz.
    assert max(abs(o) for o in offsets) > 20.0
    assert max(abs(o) for o in offsets) < 1000.0


# -- ambient light and stray lights ----------------------------------------------------------------------
def test_ambient_light_raises_the_background_and_its_noise() -> None:
    camera = CameraModel(read_noise_dn=1.0, black_level_dn=10.0)
    dark = render(parse_world(HEAD + led_text("A", 0.0, 2000.0)), camera)
    lit = render(parse_world(HEAD + led_text("A", 0.0, 2000.0) + "[scene]\nambient_dn = 30.0\n"), camera)
    corner_dark = dark.image[:100, :100].astype(np.float64)
    corner_lit = lit.image[:100, :100].astype(np.float64)
    assert corner_dark.mean() == pytest.approx(10.0, abs=0.2)
    assert corner_lit.mean() == pytest.approx(40.0, abs=0.3)
    # Shot noise of 30 DN at ~0.025 DN per electron: sqrt(1 + 30 x 0.0245) = 1.3 DN against 1.0.
    assert corner_lit.std() > 1.15 * corner_dark.std()


STRAY = """[[scene.stray_lights]]
x_m = {x}
y_m = 0.0
z_m = 1.5
{extra}
"""


def test_a_stray_lamp_is_drawn_but_is_no_led_of_the_world() -> None:
    world = parse_world(HEAD + led_text("A", -0.4, 2000.0) + STRAY.format(x=0.3, extra="diameter_m = 0.2"))
    (lamp,) = world.scene.stray_lights
    assert lamp.shape == "disk" and lamp.flicker_hz == 0.0
    frame = render(world, FLAT)
    assert [t.id for t in frame.truth.leds] == ["A"]
    where = output_px(0.3, 0.0, 1.5, FLAT)
    u, v = round(where[0]), round(where[1])
    # Steady: the same level on every row of the disk (no stripes), brightness 1 like a full-on LED.
    column = frame.image[v - 20 : v + 20, u].astype(np.float64)
    assert column.std() < 3.0 and column.mean() > FLAT.black_level_dn + 0.8 * FLAT.led_peak_dn


def test_a_flickering_stray_light_has_stripes_and_a_rectangle_has_its_area() -> None:
    world = parse_world(
        HEAD
        + led_text("A", -0.4, 2000.0)
        + STRAY.format(x=0.5, extra="diameter_m = 0.2\nflicker_hz = 1000.0\nflicker_duty = 0.5")
        + STRAY.format(x=0.0, extra='shape = "rectangle"\nwidth_m = 0.4\nlength_m = 0.1\nbrightness = 0.5')
    )
    frame = render(world, QUIET)
    where = output_px(0.5, 0.0, 1.5, QUIET)
    u, v = round(where[0]), round(where[1])
    column = frame.image[v - 20 : v + 20, u].astype(np.float64)
    assert column.max() - column.min() > 0.6 * QUIET.led_peak_dn  # on and off rows (vignetted)
    # The window: 0.4 m along x (the image's u with the robot facing +x) by 0.1 m, 1.3 m above the lens,
    # f = 488 px at 800x600: about 150 x 37.5 px lit, at half the LEDs' light.
    lit = frame.image > QUIET.black_level_dn + 0.25 * QUIET.led_peak_dn
    rows, cols = np.nonzero(lit[:, 300:500])  # the window's columns only (the LED and lamp lie outside)
    assert cols.max() - cols.min() + 1 == pytest.approx(0.4 * 488.3 / 1.3, abs=3)
    assert rows.max() - rows.min() + 1 == pytest.approx(0.1 * 488.3 / 1.3, abs=3)
    level = frame.image[300, 400] - QUIET.black_level_dn
    assert level == pytest.approx(0.5 * QUIET.led_peak_dn, rel=0.05)


# -- occluders -------------------------------------------------------------------------------------------
def test_an_occluder_hides_its_led_only_in_its_window() -> None:
    world = parse_world(
        HEAD
        + led_text("A", -0.3, 2000.0)
        + led_text("B", 0.3, 3000.0)
        + "[[scene.occluders]]\nat = [0.31, 0.01]\nperiod_s = 4.0\nhidden_s = 1.0\nphase_s = 0.5\n"
    )
    (occluder,) = world.scene.occluders
    assert occluder.led_index == 1 and occluder.fraction == 1.0
    renderer = RollingShutterRenderer(FLAT, world.leds, MOUNT, scene=world.scene)
    hidden = renderer.render(still(), 8.7)  # (8.7 - 0.5) mod 4 = 0.2 < 1: hidden
    shown = renderer.render(still(), 9.7)  # 1.2: not
    b_hidden, b_shown = (f.truth.leds[1] for f in (hidden, shown))
    assert light_sum(hidden.image, b_hidden.centre_px, 25, FLAT.black_level_dn) < 10.0
    assert light_sum(shown.image, b_shown.centre_px, 25, FLAT.black_level_dn) > 1000.0
    a = light_sum(hidden.image, hidden.truth.leds[0].centre_px, 25, FLAT.black_level_dn)
    assert a == pytest.approx(light_sum(shown.image, shown.truth.leds[0].centre_px, 25, FLAT.black_level_dn))


def test_a_partial_occluder_covers_its_fraction() -> None:
    world = parse_world(
        HEAD + led_text("A", 0.0, 2000.0) + "[[scene.occluders]]\nat = [0.0, 0.0]\nfraction = 0.5\n"
    )
    bare = render(parse_world(HEAD + led_text("A", 0.0, 2000.0)), FLAT)
    half = render(world, FLAT)
    c = bare.truth.leds[0].centre_px
    ratio = light_sum(half.image, c, 30, FLAT.black_level_dn) / light_sum(
        bare.image, c, 30, FLAT.black_level_dn
    )
    assert ratio == pytest.approx(0.5, abs=0.05)


# -- JPEG --------------------------------------------------------------------------------------------------
def test_jpeg_quality_compresses_every_frame() -> None:
    world = parse_world(HEAD + led_text("A", 0.0, 3000.0))
    camera = CameraModel()
    raw = render(world, camera, seed=2).image
    jpeg = render(world, dataclasses.replace(camera, jpeg_quality=30), seed=2).image
    ok, encoded = cv2.imencode(".jpg", raw, [cv2.IMWRITE_JPEG_QUALITY, 30])
    assert ok
    assert np.array_equal(jpeg, cv2.imdecode(encoded, cv2.IMREAD_GRAYSCALE))
    assert not np.array_equal(jpeg, raw)


# -- camera errors: true vs configured ---------------------------------------------------------------------
def test_row_time_focal_and_distortion_errors_bend_the_agents_camera_not_the_truth() -> None:
    world = parse_world(
        "[camera]\nt_row_s = 32e-6\nfocal_length_m = 4e-3\ndistortion = [-0.1, 0.0, 0.0, 0.0, 0.0]\n"
        "[errors]\nt_row_error_fraction = 0.03\nfocal_length_error_fraction = -0.02\n"
        "distortion_error = [-0.02, 0.01, 0.0, 0.0, 0.0]\n"
    )
    nominal = nominal_camera(world)
    assert world.camera.t_row_s == 32e-6  # the truth, which the renderer uses
    assert nominal.t_row_s * 1.03 == pytest.approx(32e-6)
    assert nominal.focal_length_m * 0.98 == pytest.approx(4e-3)
    assert nominal.distortion == pytest.approx((-0.08, -0.01, 0.0, 0.0, 0.0))
    plain = nominal_camera(parse_world(""))
    assert (plain.t_row_s, plain.focal_length_m, plain.distortion) == (32e-6, 4e-3, (0.0,) * 5)


def test_the_stripes_follow_the_true_row_time_not_the_configured_one() -> None:
    world = parse_world("[errors]\nt_row_error_fraction = 0.03\n" + HEAD + BIG)
    frame = RollingShutterRenderer(QUIET, world.leds, MOUNT).render(still(), 3.0)
    true_f = stripe_frequency_hz(frame, QUIET)
    assert true_f == pytest.approx(2000.0, rel=0.01)
    # Read with the configured row time (3 % shorter than the true one), the same stripes say 3 % more.
    configured = dataclasses.replace(QUIET, t_row_s=nominal_camera(world).t_row_s)
    assert stripe_frequency_hz(frame, configured) == pytest.approx(2000.0 * 1.03, rel=0.01)


# -- mistakes name their key -----------------------------------------------------------------------------
BAD = [
    (HEAD + led_text("A", 0.0, 2000.0, "brightness = 0.0\n"), "leds[0].brightness", "> 0"),
    (HEAD + led_text("A", 0.0, 2000.0, 'dead = "yes"\n'), "leds[0].dead", "true or false"),
    (HEAD + led_text("A", 0.0, 2000.0, "mapped = 1\n"), "leds[0].mapped", "true or false"),
    (
        HEAD + led_text("A", 0.0, 2000.0, "frequency_walk_hz_per_sqrt_s = -1.0\n"),
        "leds[0].frequency_walk_hz_per_sqrt_s",
        "[0, 1000]",
    ),
    (
        "[led_defaults]\nz_m = 1.5\nfrequency_drift_hz_per_s = 5000.0\n",
        "led_defaults.frequency_drift_hz_per_s",
        "1000",
    ),
    ("[camera]\njpeg_quality = 101\n", "camera.jpeg_quality", "1..100"),
    ("[camera]\njpeg_quality = 50.0\n", "camera.jpeg_quality", "integer"),
    ("[errors]\nt_row_error_fraction = 0.8\n", "errors.t_row_error_fraction", "fraction"),
    ('[errors]\nfocal_length_error_fraction = "1%"\n', "errors.focal_length_error_fraction", "number"),
    ("[errors]\ndistortion_error = [0.1, 0.0]\n", "errors.distortion_error", "5 numbers"),
    ("[scene]\nambient_dn = -1.0\n", "scene.ambient_dn", "DN"),
    ("[scene]\nambiant_dn = 1.0\n", "scene.ambiant_dn", "did you mean 'ambient_dn'"),
    ("[[scene.stray_lights]]\nx_m = 0.0\ny_m = 0.0\n", "scene.stray_lights[0].z_m", "missing"),
    (
        '[[scene.stray_lights]]\nx_m = 0.0\ny_m = 0.0\nz_m = 1.5\nshape = "star"\n',
        "scene.stray_lights[0].shape",
        "disk",
    ),
    (
        "[[scene.stray_lights]]\nx_m = 0.0\ny_m = 0.0\nz_m = 0.1\n",
        "scene.stray_lights[0].z_m",
        "not above the camera",
    ),
    (
        "[[scene.stray_lights]]\nx_m = 0.0\ny_m = 0.0\nz_m = 1.5\nflicker_hz = 20000.0\n",
        "scene.stray_lights[0].flicker_hz",
        "Nyquist",
    ),
    (
        "[[scene.stray_lights]]\nx_m = 0.0\ny_m = 0.0\nz_m = 1.5\nflicker_duty = 1.0\n",
        "scene.stray_lights[0].flicker_duty",
        "between 0 and 1",
    ),
    (
        "[[scene.stray_lights]]\nx_m = 0.0\ny_m = 0.0\nz_m = 1.5\nwidth_m = 0.0\n",
        "scene.stray_lights[0].width_m",
        "> 0",
    ),
    (
        HEAD + led_text("A", 0.0, 2000.0) + "[[scene.occluders]]\nat = [3.0, 0.0]\n",
        "scene.occluders[0].at",
        "no LED within",
    ),
    (
        HEAD + led_text("A", 0.0, 2000.0) + "[[scene.occluders]]\nfraction = 0.5\n",
        "scene.occluders[0].at",
        "missing",
    ),
    (
        HEAD + led_text("A", 0.0, 2000.0) + "[[scene.occluders]]\nat = [0.0, 0.0]\nfraction = 1.5\n",
        "scene.occluders[0].fraction",
        "at most 1",
    ),
    (
        HEAD
        + led_text("A", 0.0, 2000.0)
        + "[[scene.occluders]]\nat = [0.0, 0.0]\nperiod_s = 2.0\nhidden_s = 3.0\n",
        "scene.occluders[0].hidden_s",
        "period_s",
    ),
]


@pytest.mark.parametrize(("text", "key", "reason"), BAD, ids=[b[1] for b in BAD])
def test_a_bad_condition_names_its_key(text: str, key: str, reason: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_world(text, source="w.toml")
    assert info.value.key == key, str(info.value)
    assert reason in info.value.reason, str(info.value)


def test_the_new_worlds_say_only_what_is_meant(caplog: pytest.LogCaptureFixture) -> None:
    """The acceptance worlds load without warnings, except the close signatures of sig100 (its point)."""
    with caplog.at_level(logging.WARNING):
        for path in WORLDS:
            load_world(path)
    warned = {r.getMessage().split(":")[0] for r in caplog.records}
    assert all(w.endswith(("sig100.toml", "sig100_row3.toml")) for w in warned), warned


def test_the_simulated_camera_renders_the_worlds_scene() -> None:
    """``vlp-agent sim``'s camera: the stray lights, ambient light and occluders of the world file."""
    from drivers.camera.sim import SimCamera
    from drivers.sim.simulation import Simulation

    world = load_world(REPO / "examples" / "worlds" / "stray_light.toml")
    camera = SimCamera(Simulation(world))
    camera.open()
    try:
        renderer = camera.renderer
        assert isinstance(renderer, RollingShutterRenderer)
        assert renderer.scene is world.scene and len(renderer.scene.stray_lights) == 3
    finally:
        camera.close()
